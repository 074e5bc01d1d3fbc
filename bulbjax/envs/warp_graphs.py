"""MuJoCo Warp's CUDA-graph cache, sized for a whole experiment epoch.

Every MJX-Warp operation (step, kinematics, forward, render) is a `warp.jax_callable`. On a GPU
(MJX's default `GraphMode.WARP`) its handler replays a CUDA graph that it captured for the same
call site and the same buffer addresses, and captures a new one otherwise; each callable keeps
only `graph_cache_max` captures, 32 by default, least recently used first out. One experiment
epoch has more (call site, addresses) pairs than that per callable: PPO's rollouts, the replay
and window renders and the held-out rollouts, with XLA's loop buffers at their own addresses.
With the default, the six-learner pendulum epoch (3 seeds, H100) re-captured 95 graphs in every
probing epoch and 45 in every other one, and the GPU sat idle while the host recorded them:
2.77 s and 1.78 s per epoch against 1.33 s and 1.09 s with the captures kept
(`benchmarks/warp_ffi_stats.py`, benchmarks/README.md). The addresses are the same from one
epoch to the next, so the set of graphs stops growing after the first epoch of each program.

`install()` (called when an environment is built) makes `GRAPH_CACHE_MAX` the default of
`warp.jax_callable`, through which MJX makes its callables, and raises the limit of callables
made before. A value passed explicitly to `warp.jax_callable` is kept. CPU runs never capture.
"""

from __future__ import annotations

import functools
import inspect
import warnings
from typing import Any

GRAPH_CACHE_MAX = 4096  # captured graphs kept per callable: far above what an epoch needs (~150 in all)

_installed_limit: int | None = None


def _registry() -> dict[Any, Any]:
    from warp._src.jax import ffi

    return ffi._FFI_CALLABLE_REGISTRY


def install(limit: int = GRAPH_CACHE_MAX) -> None:
    """Keep up to `limit` captured graphs per Warp JAX callable (default and existing ones)."""
    global _installed_limit
    import warp

    if limit < 1:
        raise ValueError(f"graph cache limit must be at least 1, got {limit}")
    base = getattr(warp.jax_callable, "__wrapped__", warp.jax_callable)
    if "graph_cache_max" not in inspect.signature(base).parameters:
        warnings.warn("this Warp's jax_callable has no graph_cache_max; MuJoCo Warp's graph cache is left "
                      "at its default (GPU epochs may re-capture CUDA graphs)", stacklevel=2)
        return
    if _installed_limit != limit:

        @functools.wraps(base)
        def jax_callable(*args: Any, **kwargs: Any) -> Any:
            kwargs.setdefault("graph_cache_max", limit)
            return base(*args, **kwargs)

        warp.jax_callable = jax_callable
        _installed_limit = limit
    for c in list(_registry().values()):
        if c.graph_cache_max is not None and c.graph_cache_max < limit:
            c.graph_cache_max = limit


def limits() -> dict[str, int | None]:
    """Each existing Warp JAX callable's capture limit, by FFI target name (for checks)."""
    return {c.name: c.graph_cache_max for c in _registry().values()}


def graph_mode(name: str | None, device: Any) -> Any:
    """`mjx.put_model`'s graph_mode for `EnvConfig.graph_mode` on `device`: None (MJX's default)
    when `name` is None or the device is not a GPU (the CPU never captures graphs), else Warp's
    `JaxCallableGraphMode` member of that name ("none", "jax", "warp", "warp_staged", ...)."""
    if name is None or getattr(device, "platform", "cpu") != "gpu":
        return None
    import warp

    return warp.JaxCallableGraphMode[name.upper()]
