"""Do XLA compiles of independent programs overlap when started in threads side by side?

The split epoch programs (`ExperimentConfig.programs="split"`) compiled in threads on an H100
ended in clusters and started the first epoch no sooner than the fused program (benchmarks/
README.md, "Split programs"). This isolates the question on programs that need only jax and
flax (no MuJoCo, so it runs on the GPU machine before any wheel is staged): K VAE updates that
differ in batch size (so no two share a convolution's autotuning), lowered first, then compiled
one after another (`--mode seq`) or in K threads at once (`--mode threads`). Run each mode in its
own process (XLA keeps autotuning results per process); `--xla-autotune-level 0` in XLA_FLAGS
tells whether the autotuner is what serialises them.

    python benchmarks/diagnostics/diag_parallel_compile.py --mode seq --out "$OUT"
    python benchmarks/diagnostics/diag_parallel_compile.py --mode threads --out "$OUT"
    XLA_FLAGS=--xla_gpu_autotune_level=0 python benchmarks/diagnostics/diag_parallel_compile.py --mode threads --tag at0 --out "$OUT"
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import threading
import time
import types
from typing import Any

import jax
import jax.numpy as jnp

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
if "bulbjax" not in sys.modules:  # the learners without bulbjax/__init__ (which imports MuJoCo)
    _pkg = types.ModuleType("bulbjax")
    _pkg.__path__ = [os.path.join(ROOT, "bulbjax")]
    sys.modules["bulbjax"] = _pkg
from bulbjax.learners import LearnerConfig, make_learner  # noqa: E402


def lowered_updates(k: int, batch: int, dtype: str) -> list[Any]:
    """K lowered VAE updates, batch `batch + 64 i` for the i-th (distinct shapes)."""
    learner = make_learner("vae", 8, LearnerConfig(compute_dtype=dtype))
    state = jax.eval_shape(lambda key: learner.init(key, (64, 64, 3)), jax.random.PRNGKey(0))
    key = jax.ShapeDtypeStruct((2,), jnp.uint32)
    out = []
    for i in range(k):
        frames = jax.ShapeDtypeStruct((batch + 64 * i, 64, 64, 3), jnp.uint8)
        out.append(jax.jit(learner.update).trace(state, frames, key).lower())
    return out


def compile_all(lowered: list[Any], mode: str) -> tuple[float, list[tuple[float, float]]]:
    """Wall time of compiling every program, and each one's (start, end) in seconds."""
    spans: list[tuple[float, float]] = [(0.0, 0.0)] * len(lowered)
    t0 = time.perf_counter()

    def one(i: int) -> None:
        s = time.perf_counter() - t0
        lowered[i].compile()
        spans[i] = (s, time.perf_counter() - t0)

    if mode == "seq":
        for i in range(len(lowered)):
            one(i)
    else:
        threads = [threading.Thread(target=one, args=(i,)) for i in range(len(lowered))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    return time.perf_counter() - t0, spans


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--mode", choices=("seq", "threads"), default="threads")
    p.add_argument("--programs", type=int, default=4)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--dtype", default="bfloat16")
    p.add_argument("--tag", default="")
    p.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results"))
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    lowered = lowered_updates(a.programs, a.batch, a.dtype)
    lower_s = time.perf_counter() - t0
    wall, spans = compile_all(lowered, a.mode)
    res = {"what": "K VAE updates (distinct batch sizes) compiled one after another or in threads",
           "mode": a.mode, "programs": a.programs, "batch": a.batch, "dtype": a.dtype,
           "xla_flags": os.environ.get("XLA_FLAGS", ""), "device_kind": jax.devices()[0].device_kind,
           "jax": jax.__version__, "lower_s": lower_s, "compile_wall_s": wall, "spans_s": spans,
           "sum_of_compiles_s": sum(e - s for s, e in spans)}
    print(f"{a.mode}: {a.programs} programs compiled in {wall:.1f} s (sum of their spans "
          f"{res['sum_of_compiles_s']:.1f} s); spans {[(round(s, 1), round(e, 1)) for s, e in spans]}")
    os.makedirs(a.out, exist_ok=True)
    kind = jax.devices()[0].device_kind.lower().replace(" ", "_")
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    name = f"parallel_compile_{a.mode}{'_' + a.tag if a.tag else ''}_{kind}_{stamp}.json"
    with open(os.path.join(a.out, name), "w") as f:
        json.dump(res, f, indent=1)
    return res


if __name__ == "__main__":
    main()
