"""Timing of jitted calls for the benchmark scripts. Needs only jax, so a script that must run
without MuJoCo can share it with those that import bulbjax."""

from __future__ import annotations

import statistics
import time
from typing import Any, Callable

import jax


def time_fn(fn: Callable[[], Any], repeats: int) -> dict[str, float]:
    """First call (compile + run) and the median/min of `repeats` further calls, in seconds."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return {"first_s": first, "median_s": statistics.median(times), "min_s": min(times)}
