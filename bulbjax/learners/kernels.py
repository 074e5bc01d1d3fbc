"""Pallas kernels for the learners' memory-bound passes (issue 63).

`column_sum`: the sums over the batch axis of a [B, N] array in float32, one Pallas kernel over
(rows, columns) blocks of it, each block's column sums written and the few block rows added
after. It is the first pass of a conv layer's bias gradient (`networks._bias_sum`, with
`LearnerConfig.bias_grad="pallas"`), where XLA's reduction fusions reach about a third of the
card's bandwidth (docs/performance.md, "Learner updates"); whether this kernel does better is
`benchmarks/diagnostics/relu_bias_grad.py`'s question, so it is an option, not the default.
On a CPU it runs in Pallas's interpret mode (the same function, slowly), as the tests do.
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


def column_sum(x: jax.Array) -> jax.Array:
    """`x [B, N]` summed over its first axis, in float32 ([N]). Blocks of up to `MAX_ROWS` x
    `MAX_COLS` (powers of two dividing B and N); where N has no power-of-two divisor of at least
    `MIN_COLS`, XLA's sum."""
    import jax.experimental.pallas as pl

    b, n = x.shape
    rows, cols = _pow2_divisor(b, MAX_ROWS), _pow2_divisor(n, MAX_COLS)
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
