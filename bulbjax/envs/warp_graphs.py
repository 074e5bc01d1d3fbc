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
With `$BULBJAX_STABLE_WARP_IDS` set it also numbers Warp's calls by their signature
(`stable_call_ids()`), so that re-traced programs load from JAX's persistent compilation cache.

`wait_at_exit()` (also called when an environment is built) lets a script exit that ends with a
step still running (issue 65): see its docstring.
"""

from __future__ import annotations

import atexit
import functools
import hashlib
import inspect
import os
import warnings
from typing import Any

GRAPH_CACHE_MAX = 4096  # captured graphs kept per callable: far above what an epoch needs (~150 in all)

_installed_limit: int | None = None
_exit_wait_registered = False
STABLE_IDS_VAR = "BULBJAX_STABLE_WARP_IDS"  # set (1/true/yes/on): `install()` also calls `stable_call_ids()`


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
    if os.environ.get(STABLE_IDS_VAR, "").strip().lower() in ("1", "true", "yes", "on"):
        stable_call_ids()


def wait_at_exit() -> None:
    """Register (once) an exit handler that waits for the device work still running.

    Why: every MJX-Warp call is a `ctypes` callback that XLA calls from one of its own threads and
    that takes the GIL. A script whose last step is still running when it reaches its end (JAX
    dispatches asynchronously: printing `state.obs.shape` does not wait) never exited. Python
    starts finalising; the XLA thread that then asks for the GIL is ended by Python on the spot
    (`PyThread_exit_thread`), so that step never completes; the last reference to JAX's client
    goes in the final garbage collection (`Garbage-collecting` in a stack dump), and the client's
    destructor waits forever for its thread pool, one of whose tasks will never finish. Exit
    handlers run before finalisation, while the callback can still take the GIL, and
    registered after JAX's own (which cannot free the client while arrays hold it) this one runs
    first: it waits for every live array and every ordered effect, so the client has nothing
    running when it is freed."""
    global _exit_wait_registered
    if not _exit_wait_registered:
        atexit.register(_wait_for_device_work)
        _exit_wait_registered = True


def _wait_for_device_work() -> None:
    """Block until every live array of each initialised JAX backend is computed (an array
    already deleted or donated is skipped), then until JAX's effects are done."""
    import sys

    jax = sys.modules.get("jax")
    if jax is None:
        return
    try:
        arrays = jax.live_arrays()
    except Exception:  # no backend initialised (nothing dispatched) or already torn down
        return
    for a in arrays:
        try:
            a.block_until_ready()
        except Exception:  # deleted, donated, or failed: nothing left to wait for
            pass
    try:
        jax.effects_barrier()
    except Exception:
        pass


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


def _signature_id(name: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> int:
    """A 63-bit id of one call's signature: the target, each array argument's shape and dtype, each
    static argument's value, the keyword arguments. Equal in every process for an equal call."""
    parts = [name]
    for a in args:
        shape, dtype = getattr(a, "shape", None), getattr(a, "dtype", None)
        parts.append(f"{tuple(shape)}:{dtype}" if shape is not None and dtype is not None else repr(a))
    parts += [f"{k}={kwargs[k]!r}" for k in sorted(kwargs)]
    digest = hashlib.blake2b("|".join(parts).encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") & (2**63 - 1)


def stable_call_ids() -> bool:
    """Give each Warp JAX callable's call an id taken from its signature, not a per-process counter.

    Warp numbers every trace of a `jax_callable` call (`call_id`) with a counter and writes the
    number into the lowered program, where the handler finds the trace's static arguments by it.
    Two traces of the same program therefore lower to different text, and JAX's persistent
    compilation cache (keyed on that text) never serves a program with MJX-Warp in it to a second
    trace in the same process: each re-trace of an env step, a reset or an epoch compiles again (a
    12-world GeomOnIncline reset: ~10 s on 2 CPU cores, every time). With the id a hash of the
    call's signature (target, argument shapes and dtypes, static values), equal calls share one id
    and one record of their static arguments (which are equal), and equal programs lower to equal
    text. (Warp's `jax_kernel` has a counter too; MJX does not use it, so it is left alone.)
    Returns False, changing nothing, when this Warp's callable has no such counter."""
    try:
        from warp._src.jax import ffi
    except ImportError:
        return False
    cls = getattr(ffi, "FfiCallable", None)
    if cls is None:
        return False
    if getattr(cls.__call__, "_bulbjax_stable_ids", False):
        return True
    try:
        source = inspect.getsource(cls.__call__)
    except (OSError, TypeError):  # no source to check against: leave it alone
        return False
    if "self.call_id += 1" not in source:  # another Warp: leave it alone
        return False
    original = cls.__call__

    @functools.wraps(original)
    def __call__(self: Any, *args: Any, **kwargs: Any) -> Any:
        self.call_id = _signature_id(self.name, args, kwargs)
        return original(self, *args, **kwargs)

    __call__._bulbjax_stable_ids = True  # type: ignore[attr-defined]
    cls.__call__ = __call__
    return True
