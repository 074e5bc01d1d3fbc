"""Per-world operations on batched pytrees (the world axis first): selects and scatters between
two batches of worlds, per-world checks of finiteness, and the check of the one key `reset`
takes. MJX-Warp's Data holds leaves without
the world axis (contact buffers shared by all worlds, empty arrays): every operation here keeps
those from the batch it writes into."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp


def where_tree(mask: jax.Array, a: Any, b: Any) -> Any:
    """Per-world select between two batched pytrees; leaves without the world axis (empty
    Warp buffers) are taken from `b`."""
    def sel(x, y):
        if x.ndim == 0 or x.shape[0] != mask.shape[0] or x.shape != y.shape:
            return y
        m = mask.reshape(mask.shape + (1,) * (x.ndim - 1))
        return jnp.where(m, x, y)
    return jax.tree.map(sel, a, b)


def scatter_rows(idx: jax.Array, part: Any, full: Any, n: int) -> Any:
    """`full` (batched over `n` worlds) with its rows `idx` `[K]` replaced by `part`'s rows (an
    index >= n is dropped); leaves without the world axis (MJX-Warp's shared contact buffers)
    are kept from `full`, as `where_tree` keeps them."""
    def put(x, y):
        if y.ndim == 0 or y.shape[0] != n or x.shape != (idx.shape[0], *y.shape[1:]):
            return y
        return y.at[idx].set(x.astype(y.dtype), mode="drop")
    return jax.tree.map(put, part, full)


def finite_rows(data: Any) -> jax.Array:
    """`[N]` bool: the worlds whose qpos and qvel are finite."""
    return jnp.isfinite(data.qpos).all(axis=1) & jnp.isfinite(data.qvel).all(axis=1)


def nonfinite(x: jax.Array) -> jax.Array:
    """Per world `[N]` int32: the NaN or inf entries of a batched array `[N, ...]`."""
    return (~jnp.isfinite(x)).reshape(x.shape[0], -1).sum(axis=1).astype(jnp.int32)


def add_counts(counts: dict[str, jax.Array], **step: jax.Array) -> dict[str, jax.Array]:
    """`EnvState.counts` after a step (a state without counts, e.g. built by hand, starts at 0)."""
    return {k: counts.get(k, jnp.zeros_like(v)) + v for k, v in step.items()}


def prng_key(key: Any) -> jax.Array:
    """One PRNG key as a uint32 `[2]` array: `jax.random.PRNGKey(seed)` as it is, a typed
    `jax.random.key(seed)` as its data; anything else (an int seed, a batch of keys) is a
    ValueError naming what was given, instead of JAX's error from inside `split`."""
    dtype, shape = getattr(key, "dtype", None), getattr(key, "shape", None)
    if dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key) and shape == ():
        key = jax.random.key_data(key)
        dtype, shape = key.dtype, key.shape
    if dtype != jnp.uint32 or shape != (2,):
        given = (f"{type(key).__name__} {key!r}" if dtype is None
                 else f"an array of {dtype} {tuple(shape)}")
        raise ValueError("reset takes one PRNG key, e.g. jax.random.PRNGKey(0) (uint32 [2]), "
                         f"not {given}")
    return key
