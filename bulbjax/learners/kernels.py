"""Pallas kernels for the learners' memory-bound passes (issue 63).

`column_sum`: the sums over the batch axis of a [B, N] array in float32, one Pallas kernel over
(rows, columns) blocks of it, each block's column sums written and the few block rows added
after. It is the first pass of a conv layer's bias gradient (`networks._bias_sum`, with
`LearnerConfig.bias_grad="pallas"`), where XLA's reduction fusions reach about a third of the
card's bandwidth (docs/performance.md, "Learner updates"). `masked_column_sum` does a ReLU's
backward mask in the same kernel (`bias_grad="pallas_relu"`: the gradient and the ReLU's output
read once, the masked gradient written once). Alone both are slower than XLA's fusion on an
H200, yet the VAE update is ~3% and 6.4% faster with them: inside the update XLA does not make
the fusion a layer alone gets (the update's kernel list: docs/performance.md, "Learner
updates"). Options until a same-seeds run on a GPU gives the default's numbers.
On a CPU they run in Pallas's interpret mode (the same function, slowly), as the tests do.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

MAX_ROWS, MAX_COLS = 32, 1024  # a block: at most 32 x 1,024 elements (64 KB in bf16)
MIN_COLS = 16  # narrower blocks than this: XLA's sum instead


def _pow2_divisor(n: int, cap: int) -> int:
    """The largest power of two that divides `n` and is at most `cap`."""
    d = 1
    while d * 2 <= cap and n % (d * 2) == 0:
        d *= 2
    return d


def _blocks(b: int, n: int) -> tuple[int, int]:
    """(rows, columns) of a kernel's blocks over a [b, n] array; columns < MIN_COLS: none fits."""
    return _pow2_divisor(b, MAX_ROWS), _pow2_divisor(n, MAX_COLS)


def column_sum(x: jax.Array) -> jax.Array:
    """`x [B, N]` summed over its first axis, in float32 ([N]). Blocks of up to `MAX_ROWS` x
    `MAX_COLS` (powers of two dividing B and N); where N has no power-of-two divisor of at least
    `MIN_COLS`, XLA's sum."""
    import jax.experimental.pallas as pl

    b, n = x.shape
    rows, cols = _blocks(b, n)
    if cols < MIN_COLS:
        return x.sum(0, dtype=jnp.float32)

    def kernel(x_ref, part_ref):
        part_ref[...] = jnp.sum(x_ref[...].astype(jnp.float32), axis=0, keepdims=True)

    part = pl.pallas_call(
        kernel, grid=(b // rows, n // cols),
        in_specs=[pl.BlockSpec((rows, cols), lambda i, j: (i, j))],
        out_specs=pl.BlockSpec((1, cols), lambda i, j: (i, j)),
        out_shape=jax.ShapeDtypeStruct((b // rows, n), jnp.float32),
        interpret=jax.default_backend() == "cpu")(x)
    return part.sum(0)


def masked_column_sum(g: jax.Array, y: jax.Array, rows: int | None = None,
                      cols: int | None = None) -> tuple[jax.Array, jax.Array]:
    """A ReLU's backward pass and its layer's bias-gradient first pass in one kernel: `g [B, N]`
    (the gradient at the ReLU's output) kept where `y [B, N]` (the ReLU's output) is positive,
    and that masked gradient's sums over the first axis in float32 ([N]). Blocks as
    `column_sum`'s (or `rows` x `cols`, powers of two dividing B and N: the diagnostic's sweep);
    without one, XLA's ops."""
    import jax.experimental.pallas as pl

    b, n = g.shape
    auto = _blocks(b, n)
    rows, cols = rows or auto[0], cols or auto[1]
    if cols < MIN_COLS:
        gx = jnp.where(y > 0, g, jnp.zeros_like(g))
        return gx, gx.sum(0, dtype=jnp.float32)

    def kernel(g_ref, y_ref, gx_ref, part_ref):
        gv = g_ref[...]
        m = jnp.where(y_ref[...] > 0, gv, jnp.zeros_like(gv))
        gx_ref[...] = m
        part_ref[...] = jnp.sum(m.astype(jnp.float32), axis=0, keepdims=True)

    block = pl.BlockSpec((rows, cols), lambda i, j: (i, j))
    gx, part = pl.pallas_call(
        kernel, grid=(b // rows, n // cols), in_specs=[block, block],
        out_specs=[block, pl.BlockSpec((1, cols), lambda i, j: (i, j))],
        out_shape=[jax.ShapeDtypeStruct((b, n), g.dtype),
                   jax.ShapeDtypeStruct((b // rows, n), jnp.float32)],
        interpret=jax.default_backend() == "cpu")(g, y)
    return gx, part.sum(0)
