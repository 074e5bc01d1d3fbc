"""Resets of the worlds that ended in `step`: from a pool of pre-settled initial states
(`reset_from_pool`), or a fixed-size chunk at a time (`MjxPixelEnv._reset_done`).

The pool (EnvConfig.reset_pool, on by default for Incline and Rearrange): `reset` also settles
f * N initial states from fresh keys (`make_pool`, kept in `EnvState.pool`), and `step` gives
each ended world the next unused one, a gather with no simulation; when fewer remain than worlds
ended, the pool is refilled first, in one batched reset under `lax.cond`. With fixed draws
(`reset_with`'s, in `env._fixed` while `step` is traced) or no pool in the state, `step` takes
the chunked path below.

Chunks:
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

from bulbjax.envs.batch import scatter_rows


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


# ----- the pool of pre-settled initial states -------------------------------------------------
# The mjx.Data fields a reset sets that the forward pass does not compute from others (the state,
# controls and applied forces, the mocap poses, the solver's warm start): a pool entry holds these
# (plus the colour scheme and the parameters), `step` writes them into an ended world, and its
# pose pass (`MjxPixelEnv._poses`) and the next `mjx.step`'s own forward pass recompute everything
# else, as after a chunked reset.
POOL_FIELDS = ("time", "qpos", "qvel", "act", "qacc_warmstart", "ctrl", "qfrc_applied", "xfrc_applied",
               "mocap_pos", "mocap_quat")
POOL_SALT = 0x706F6F6C  # the pool's keys at `reset`: the world keys folded with this, then split


def pool_multiple(pool: Any, default: int) -> int:
    """Pool size in `step` as a multiple of num_envs (EnvConfig.reset_pool): `pool` if given,
    else the domain's `default`; 0 is no pool (the chunked resets). A value that is not None or a
    non-negative int is a ValueError naming the choices."""
    if pool is not None and (isinstance(pool, (bool, np.bool_)) or not isinstance(pool, (int, np.integer))
                             or pool < 0):
        raise ValueError(f"reset_pool must be None (the domain's default), 0 (no pool: chunked resets) or a "
                         f"positive int, the pool's size as a multiple of num_envs, got {pool!r}")
    return int(default if pool is None else pool)


def make_pool(env: Any, keys: jax.Array) -> dict[str, Any]:
    """A fresh pool of `env.pool_size` = f * N initial states, settled from `keys` `[f * N, 2]`
    in one `_reset_batch` (with `env._pool_data0`, whose shared contact buffers hold f * N
    worlds; without `reset_with`'s fixed draws: the pool is for the later resets, which draw as
    usual). Laid out world-major, `[N, f, ...]`, so that every leaf has the world axis first
    (EnvState is sharded and reshaped per world); entry j is `[j // f, j % f]`, the cursor `[N]`
    (the same value in every world of a block, `env.pool_segments`) is the block's next unused
    entry, counted within the block's rows."""
    n, f = env.num_envs, env.reset_pool
    saved = env._data0, env._fixed
    env._data0, env._fixed = env._pool_data0, {}
    try:
        data, scheme, params, _ = env._reset_batch(keys, jnp.ones(n * f, bool), forward=False)
    finally:
        env._data0, env._fixed = saved
    rows = lambda x: x.reshape((n, f) + x.shape[1:])  # noqa: E731
    fields = {name: rows(getattr(data, name)) for name in POOL_FIELDS}
    return {"data": fields, "scheme": rows(scheme.astype(jnp.int32)), "params": jax.tree.map(rows, params),
            "cursor": jnp.zeros(n, jnp.int32)}


def pool_keys_at_reset(keys: jax.Array, f: int) -> jax.Array:
    """`[f * N, 2]` keys of the pool made at `reset` from the worlds' reset keys `[N, 2]`."""
    return jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, POOL_SALT), f))(keys).reshape(-1, 2)


def reset_from_pool(env: Any, keys: jax.Array, done: jax.Array, data: Any, scheme: jax.Array,
                    params: dict[str, jax.Array], pool: dict[str, Any]
                    ) -> tuple[Any, jax.Array, dict[str, jax.Array], dict[str, Any]]:
    """`data`, `scheme`, `params` with the worlds in `done` given the next unused pool entries
    (no simulation), and the pool after. The worlds are `env.pool_segments` equal, consecutive
    blocks (the experiment's seeds), each with its own part of the pool (the rows of its worlds)
    and cursor: the i-th ended world of a block, in world order, takes the block's cursor + i.
    A block with fewer entries left than worlds ended is first refilled (`make_pool` from `keys`
    `[N, 2]`, the worlds' reset keys of this step, each split f ways: a block's new entries come
    from its own worlds' keys) and read from its start; the batched refill runs under
    `lax.cond` only when some block needs it, and only the blocks that need it keep its states,
    so a block's resets depend on its own worlds alone. `done` may hold every world."""
    n, f, g = env.num_envs, env.reset_pool, env.pool_segments
    m = n // g  # worlds per block
    done_g = done.reshape(g, m)
    count = done_g.sum(axis=1, dtype=jnp.int32)  # [g]
    low = pool["cursor"].reshape(g, m)[:, 0] + count > m * f  # [g]: blocks that must refill
    worlds_low = jnp.repeat(low, m)  # [n]

    def refill(p: dict[str, Any]) -> dict[str, Any]:
        fresh = make_pool(env, jax.vmap(lambda k: jax.random.split(k, f))(keys).reshape(-1, 2))
        keep = lambda new, old: jnp.where(worlds_low.reshape((n,) + (1,) * (old.ndim - 1)), new, old)  # noqa: E731
        return jax.tree.map(keep, fresh, p)  # the cursor of a refilled block goes to 0

    pool = jax.lax.cond(low.any(), refill, lambda p: p, pool)
    cursor = pool["cursor"].reshape(g, m)[:, 0]  # [g]
    local = cursor[:, None] + jnp.cumsum(done_g, axis=1, dtype=jnp.int32) - 1  # [g, m]
    entry = jnp.where(done, (jnp.arange(g, dtype=jnp.int32)[:, None] * (m * f) + local).reshape(n), 0)
    take = lambda x: x.reshape((n * f,) + x.shape[2:])[entry]  # noqa: E731
    pick = lambda new, old: jnp.where(done.reshape((n,) + (1,) * (old.ndim - 1)), take(new).astype(old.dtype), old)  # noqa: E731
    data = data.replace(**{name: pick(v, getattr(data, name)) for name, v in pool["data"].items()})
    scheme = pick(pool["scheme"], scheme)
    params = {k: pick(pool["params"][k], v) for k, v in params.items()}
    return data, scheme, params, {**pool, "cursor": jnp.repeat(cursor + count, m)}
