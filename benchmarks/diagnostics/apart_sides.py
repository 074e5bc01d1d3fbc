"""Where an epoch with the learners apart (`--overlap apart`) spends its time, per setting of
`--apart-env-learners`: the epoch as a run calls it (the environment's and the learners' programs
at once), then each of its programs alone, one after another (`Apart.timings`, every epoch's
seconds kept, beside the train worlds' constraint rows and solver iterations (mean, and the
largest), and MuJoCo Warp's handler calls, CUDA-graph captures and host seconds per epoch). The
open question: the environment's program of a locomotion epoch costs more over the first ~50 epochs
than later (`reproduce` jobs with pred on its GPU: fig2-ant 1.43-1.58 s an epoch to epoch ~55,
0.91-0.97 s after; fig2-halfcheetah alike). Alone, on Ant at one seed, it took 1.17-1.59 s at
epochs 43-50 and 0.66-0.82 s at 51-82 while the worlds' mean constraint rows and solver iterations
did not change (`results/apart_sides_fig2-ant_nvidia_h200_20261130_132154.json`), and the solver is
capped at 4 iterations; Warp's captures per epoch (new buffer addresses) are what this script now
records. Writes `results/apart_sides_<preset>_<device>_<stamp>.json`.

    python benchmarks/diagnostics/apart_sides.py --preset fig2-ant --settings pred --bf16 --warm 0 --epochs 40
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import json
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/: warp_ffi_stats

import jax  # noqa: E402
import numpy as np  # noqa: E402

from bulbjax.epoch.loop import Experiment  # noqa: E402
from bulbjax.epoch.programs import Programs  # noqa: E402
from bulbjax.run.settings import resolve  # noqa: E402
import warp_ffi_stats  # noqa: E402


def physics(data: object) -> dict:
    """Over the train worlds, at the epoch's last substep: the mean of MuJoCo's active constraint
    rows (`nefc`) and of the solver's iterations (`solver_niter`), and the largest iteration count
    (`solver_niter_max`: with `opt.graph_conditional` the captured solver loops until the slowest
    world of the batch converges, so it, not the mean, sets the cost). Is the environment's program
    dearer while some world is hard to solve?"""
    impl = getattr(data, "_impl", None)  # MJX-Warp's own fields (MJX warns on `data.solver_niter`)
    found = {f: getattr(impl, f, None) for f in ("nefc", "solver_niter")}
    out = {f: round(float(np.mean(jax.device_get(v))), 3) for f, v in found.items() if v is not None}
    if found["solver_niter"] is not None:
        out["solver_niter_max"] = int(np.max(jax.device_get(found["solver_niter"])))
    return out


def _warp_totals(before: dict) -> dict:
    """MuJoCo Warp's FFI handler calls, CUDA-graph captures and host seconds since `before`: does
    the environment's program cost more early because Warp captures graphs for buffer addresses it
    has not seen (each capture records and instantiates hundreds of kernels on the host)?"""
    total = warp_ffi_stats.delta(warp_ffi_stats.snapshot(), before)["total"]
    return {"calls": int(total["calls"]), "captures": int(total["captures"]), "host_s": round(total["host_s"], 4)}


def measure(preset: str, setting: str, seeds: int, bf16: bool, small: bool, warm: int, epochs: int) -> dict:
    """One setting: start-up, `epochs` epochs at once (not probing) after `warm`, then `epochs`
    with each program alone; medians in seconds."""
    t0 = time.perf_counter()
    cfg = resolve(preset, overrides={"seeds": seeds, "overlap": "apart", "apart_env_learners": setting},
                  learner={"compute_dtype": "bfloat16"} if bf16 else {}, small=small)
    exp = Experiment(cfg)
    progs = Programs.of(exp, (True, False))
    key = jax.random.PRNGKey(0)
    rs = progs.prime(progs.init(key), jax.random.fold_in(key, 1))
    out: dict = {"setting": setting, "near": [list(u) for u in exp.apart.near]}
    times = []
    out["warp"] = []  # per epoch at once, then per alone epoch: Warp's captures and handler seconds
    for i in range(warm + epochs):
        t, snap = time.perf_counter(), warp_ffi_stats.snapshot()
        rs, _ = progs.epoch(rs, jax.random.fold_in(key, 10 + i), probe=False)
        jax.block_until_ready(rs)
        out["warp"].append(_warp_totals(snap))
        if i == 0:
            out["startup_s"] = time.perf_counter() - t0
        if i >= warm:
            times.append(time.perf_counter() - t)
    out["epoch_s"] = statistics.median(times)
    out["epoch_times_s"] = times
    print(f"{setting}: start-up {out['startup_s']:.1f} s, epoch {out['epoch_s']:.3f} s", flush=True)
    exp.apart.timings = {}
    out["physics"] = []  # per alone epoch: the train worlds' constraint rows and solver iterations
    for i in range(epochs):
        snap = warp_ffi_stats.snapshot()
        rs, _ = progs.epoch(rs, jax.random.fold_in(key, 100 + i), probe=False)
        out["physics"].append(physics(rs.train_env.data))
        out["warp"].append(_warp_totals(snap))
    out["alone_s"] = {k: statistics.median(v) for k, v in exp.apart.timings.items()}
    out["alone_times_s"] = {k: [round(t, 4) for t in v] for k, v in exp.apart.timings.items()}
    print(f"{setting}: epoch {out['epoch_s']:.3f} s; alone " +
          ", ".join(f"{k} {v:.3f} s" for k, v in out["alone_s"].items()), flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="fig2-ant")
    p.add_argument("--settings", default="none;pred", help="--apart-env-learners values, ';' between")
    p.add_argument("--seeds", type=int, default=1, help="seeds in the process (a reproduce job's: 1)")
    p.add_argument("--bf16", action="store_true")
    p.add_argument("--small", action="store_true", help="CPU sizes")
    p.add_argument("--warm", type=int, default=3)
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--out-dir", default=os.path.join(os.path.dirname(HERE), "results"))
    a = p.parse_args()
    warp_ffi_stats.install()  # before any env is built: Warp binds the handler when it makes a callable
    res = {"seeds": a.seeds, "preset": a.preset, "bf16": a.bf16, "device": jax.devices()[0].device_kind, "runs": []}
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%d_%H%M%S")
    kind = res["device"].lower().replace(" ", "_")
    path = os.path.join(a.out_dir, f"apart_sides_{a.preset}_{kind}_{stamp}.json")
    os.makedirs(a.out_dir, exist_ok=True)
    for setting in a.settings.split(";"):
        res["runs"].append(measure(a.preset, setting, a.seeds, a.bf16, a.small, a.warm, a.epochs))
        with open(path, "w") as f:
            json.dump(res, f, indent=1)
        gc.collect()
        jax.clear_caches()
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
