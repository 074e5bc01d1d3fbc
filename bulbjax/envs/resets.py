"""Resets of the worlds that ended, a fixed-size chunk at a time (`MjxPixelEnv._reset_done`).

Domains whose reset simulates (Incline's initial fall, up to 50 of bulb's steps; Rearrange's
30-step settle) would otherwise simulate every world at each env step in which any ends, while
under random actions only ~6% end per step. Here the done worlds' indices are gathered
(`jnp.nonzero` with a static size, padded with `num_envs`), the domain's `_reset_batch` runs on
a batch of K of them (their keys, and `reset_with`'s fixed draws gathered by the same indices),
and the results are scattered back; a `lax.while_loop` repeats this until every done world is
reset, so nothing is clipped when more than K end at once, and runs no chunk when none ends.
Shapes stay static under jit: one compiled reset of K worlds.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def chunk_size(chunk: Any, fraction: float, num_envs: int) -> int:
    """Worlds per reset chunk in `step`: `chunk` (EnvConfig.reset_chunk) if given, else the
    domain's `fraction` of `num_envs`; at most `num_envs`; 0 is the full-batch reset. A value that
    is not None or a non-negative int is a ValueError naming the choices."""
    if chunk is not None and (isinstance(chunk, (bool, np.bool_)) or not isinstance(chunk, (int, np.integer))
                              or chunk < 0):
        raise ValueError(f"reset_chunk must be None (the domain's default), 0 (full-batch resets) or a "
                         f"positive number of worlds, got {chunk!r}")
    chunk = math.ceil(fraction * num_envs) if chunk is None else chunk
    return min(int(chunk), num_envs)


def reset_in_chunks(env: Any, keys: jax.Array, done: jax.Array, data: Any, scheme: jax.Array,
                    params: dict[str, jax.Array]) -> tuple[Any, jax.Array, dict[str, jax.Array]]:
    """`data`, `scheme` `[N]` and `params` of `env`'s N worlds with the worlds in `done` reset
    from their `keys` `[N, 2]` (no forward pass), `env.reset_chunk` worlds per `_reset_batch`."""
    k, n = env.reset_chunk, env.num_envs
    order = jnp.nonzero(done, size=math.ceil(n / k) * k, fill_value=n)[0]  # done worlds, then n
    count = done.sum()

    def chunk(carry):
        c, data, scheme, params = carry
        idx = jax.lax.dynamic_slice(order, (c * k,), (k,))  # >= n: padding, dropped below
        rows = jnp.minimum(idx, n - 1)
        saved = env._fixed
        env._fixed = {name: v[rows] for name, v in saved.items()}
        try:
            fresh, fresh_scheme, fresh_params, _ = env._reset_batch(keys[rows], idx < n, forward=False)
        finally:
            env._fixed = saved
        return (c + 1, scatter_rows(idx, fresh, data, n),
                scheme.at[idx].set(fresh_scheme.astype(scheme.dtype), mode="drop"),
                scatter_rows(idx, fresh_params, params, n))

    init = (jnp.int32(0), data, scheme, params)
    return jax.lax.while_loop(lambda carry: carry[0] * k < count, chunk, init)[1:]


def scatter_rows(idx: jax.Array, part: Any, full: Any, n: int) -> Any:
    """`full` (batched over `n` worlds) with its rows `idx` `[K]` replaced by `part`'s rows (an
    index >= n is dropped); leaves without the world axis (MJX-Warp's shared contact buffers)
    are kept from `full`, as `base._where_tree` keeps them."""
    def put(x, y):
        if y.ndim == 0 or y.shape[0] != n or x.shape != (idx.shape[0], *y.shape[1:]):
            return y
        return y.at[idx].set(x.astype(y.dtype), mode="drop")
    return jax.tree.map(put, part, full)
