"""`bulbjax/learners/kernels.py`: the Pallas column sum (a conv layer's bias gradient, first pass,
with `bias_grad="pallas"`) equals XLA's float32 sum over the batch axis, for batches that are and
are not powers of two (the sequential learners' 1,008 and 1,176 frames), bf16 inputs, under vmap,
and falls back to XLA's sum where the columns have no power-of-two block. On a CPU it runs in
Pallas's interpret mode."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.learners import kernels


@pytest.mark.parametrize("shape", [(64, 4096), (1008, 192), (1176, 48), (3, 256), (40, 105)])
def test_column_sum_is_the_batch_sum(shape: tuple[int, int]) -> None:
    x = jax.random.normal(jax.random.PRNGKey(0), shape, jnp.bfloat16)
    got = jax.jit(kernels.column_sum)(x)
    want = x.sum(0, dtype=jnp.float32)
    assert got.dtype == jnp.float32 and got.shape == (shape[1],)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-5, atol=1e-4)


def test_blocks_are_powers_of_two_that_divide() -> None:
    assert kernels._pow2_divisor(1008, kernels.MAX_ROWS) == 16
    assert kernels._pow2_divisor(1176, kernels.MAX_ROWS) == 8
    assert kernels._pow2_divisor(1024, kernels.MAX_ROWS) == 32
    assert kernels._pow2_divisor(12288, kernels.MAX_COLS) == 1024
    assert kernels._pow2_divisor(105, kernels.MAX_COLS) == 1  # (40, 105) above: XLA's sum


def test_column_sum_under_vmap() -> None:
    x = jax.random.normal(jax.random.PRNGKey(1), (2, 32, 512), jnp.float32)
    got = jax.vmap(kernels.column_sum)(x)
    np.testing.assert_allclose(np.asarray(got), np.asarray(x.sum(1)), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("shape", [(64, 4096), (1008, 192), (40, 105)])
def test_masked_column_sum_is_the_relu_backward_and_its_batch_sum(shape: tuple[int, int]) -> None:
    """The masked gradient equal to the ReLU's backward pass (exactly), its batch sum XLA's."""
    kg, ky = jax.random.split(jax.random.PRNGKey(2))
    g = jax.random.normal(kg, shape, jnp.bfloat16)
    y = jax.nn.relu(jax.random.normal(ky, shape, jnp.bfloat16))
    gx, sums = jax.jit(kernels.masked_column_sum)(g, y)
    want = jnp.where(y > 0, g, jnp.zeros_like(g))
    np.testing.assert_array_equal(np.asarray(gx, np.float32), np.asarray(want, np.float32))
    np.testing.assert_allclose(np.asarray(sums), np.asarray(want.sum(0, dtype=jnp.float32)),
                               rtol=1e-5, atol=1e-4)
