"""What MuJoCo Warp's FFI calls cost on the host: callbacks, CUDA-graph captures, host time.

Every MJX-Warp operation (step, kinematics, render, ...) is a `warp.jax_callable`: an XLA FFI
custom call whose handler is a Python function. In the GPU's `GraphMode.WARP` the handler
replays a CUDA graph it captured earlier for the same call site and buffer addresses, or
captures a new one (hundreds of kernel launches recorded, then instantiated) when none matches;
each callable keeps at most `graph_cache_max` (32) captures. This module counts, per callable,
the handler calls, the captures and the host seconds spent in handlers, and reports each
callable's trace counter (`call_id`, which numbers the call sites in the order they were traced
in this process and is written into the program, so into its compile-cache key).

`install()` must run before the first callable is made (before an env is built): the handler
is bound when a callable is constructed. Diagnostics for `profile_epoch.py --warp-stats` and
for a run (`python benchmarks/warp_ffi_stats.py -- bulbjax run ...`); not used by the library.
"""

from __future__ import annotations

import atexit
import json
import sys
import time
from collections import defaultdict
from typing import Any

_COUNTERS = ("calls", "captures", "host_s")
_STATS: dict[str, dict[str, float]] = defaultdict(lambda: dict.fromkeys(_COUNTERS, 0))
_INSTALLED = False
_graph_cache_max: int | None | str = "default"


def install(graph_cache_max: int | None | str = "default") -> None:
    """Wrap Warp's FFI handler and graph capture with counters. `graph_cache_max`: if not
    "default", every callable's capture cache is set to it (None: unbounded) when it is made
    and whenever Warp would reset it."""
    global _INSTALLED, _graph_cache_max
    _graph_cache_max = graph_cache_max
    if _INSTALLED:
        return
    import warp as wp
    from warp._src.jax import ffi as wffi

    orig_cb = wffi.FfiCallable.ffi_callback
    current: list[str] = []

    def ffi_callback(self, call_frame, platform):
        t0 = time.perf_counter()
        current.append(self.name)
        try:
            return orig_cb(self, call_frame, platform)
        finally:
            current.pop()
            s = _STATS[self.name]
            s["calls"] += 1
            s["host_s"] += time.perf_counter() - t0

    wffi.FfiCallable.ffi_callback = ffi_callback

    orig_capture = wp.ScopedCapture

    class CountingCapture(orig_capture):  # type: ignore[misc, valid-type]
        def __enter__(self):
            if current:
                _STATS[current[-1]]["captures"] += 1
            return super().__enter__()

    wp.ScopedCapture = CountingCapture

    if graph_cache_max != "default":
        orig_setter = wffi.FfiCallable.graph_cache_max.fset
        orig_init = wffi.FfiCallable.__init__

        def init(self, *args, **kwargs):
            orig_init(self, *args, **kwargs)
            orig_setter(self, _graph_cache_max)

        wffi.FfiCallable.__init__ = init
        wffi.FfiCallable.graph_cache_max = property(
            wffi.FfiCallable.graph_cache_max.fget, lambda self, v: orig_setter(self, _graph_cache_max))
    _INSTALLED = True


def snapshot() -> dict[str, Any]:
    """Per callable: calls, captures, host seconds so far, its trace counter and capture cache."""
    from warp._src.jax import ffi as wffi

    out: dict[str, Any] = {}
    for c in wffi._FFI_CALLABLE_REGISTRY.values():
        out[c.name] = {**_STATS[c.name], "call_id": c.call_id, "graph_mode": int(c.graph_mode),
                       "graph_cache_size": len(c.captures), "graph_cache_max": c.graph_cache_max}
    return out


def delta(after: dict[str, Any], before: dict[str, Any]) -> dict[str, Any]:
    """Calls, captures and host seconds between two snapshots, with their totals."""
    out: dict[str, Any] = {}
    for name, a in after.items():
        b = before.get(name, dict.fromkeys(_COUNTERS, 0))
        d = {k: a[k] - b[k] for k in _COUNTERS}
        if d["calls"]:
            out[name] = d
    out["total"] = {k: sum(v[k] for v in out.values()) for k in _COUNTERS}
    return out


if __name__ == "__main__":
    # python benchmarks/warp_ffi_stats.py [--graph-cache N|none] -- bulbjax run ...: run the CLI
    # with the counters on, print the snapshot as JSON at exit (to stderr, tagged WARP_FFI_STATS)
    args = sys.argv[1:]
    gcm: int | None | str = "default"
    if args[:1] == ["--graph-cache"]:
        gcm = None if args[1] == "none" else int(args[1])
        args = args[2:]
    if args[:1] == ["--"]:
        args = args[1:]
    install(gcm)
    atexit.register(lambda: print("WARP_FFI_STATS " + json.dumps(snapshot()), file=sys.stderr))
    if args[:1] != ["bulbjax"]:
        raise SystemExit("usage: warp_ffi_stats.py [--graph-cache N|none] -- bulbjax ARGS...")
    from bulbjax.cli import main as cli_main

    raise SystemExit(cli_main(args[1:]))
