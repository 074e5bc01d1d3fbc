"""Where an epoch with the learners apart (`--overlap apart`) spends its time, per setting of
`--apart-env-learners`: the epoch as a run calls it (the environment's and the learners' programs
at once), then each of its programs alone, one after another (`Apart.timings`, every epoch's
seconds kept, beside the train worlds' constraint rows and solver iterations). The open question: the environment's program of a fig2-ant epoch costs more over
the first epochs than later (a `reproduce` job with pred on its GPU: 1.43-1.58 s an epoch to
epoch ~55, 0.91-0.97 s after), and alone it measured 1.462 s at one seed (epochs 13-23,
`results/apart_sides_fig2-ant_nvidia_h200_20261130_103743.json`) against 0.717 s at six
(`..._075238.json`). Writes `results/apart_sides_<preset>_<device>_<stamp>.json`.

    python benchmarks/diagnostics/apart_sides.py --preset fig2-ant --settings pred --bf16 --epochs 150
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

import jax  # noqa: E402
import numpy as np  # noqa: E402

from bulbjax.epoch.loop import Experiment  # noqa: E402
from bulbjax.epoch.programs import Programs  # noqa: E402
from bulbjax.run.settings import resolve  # noqa: E402


def physics(data: object) -> dict:
    """The means over the train worlds of MuJoCo's active constraint rows (`nefc`) and the
    solver's iterations of the last substep (`solver_niter`), where the data holds them: is the
    environment's program dearer while its worlds hold more contacts?"""
    impl = getattr(data, "_impl", None)  # MJX-Warp's own fields (MJX warns on `data.solver_niter`)
    found = {f: getattr(impl, f, None) for f in ("nefc", "solver_niter")}
    return {f: round(float(np.mean(jax.device_get(v))), 3) for f, v in found.items() if v is not None}


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
    for i in range(warm + epochs):
        t = time.perf_counter()
        rs, _ = progs.epoch(rs, jax.random.fold_in(key, 10 + i), probe=False)
        jax.block_until_ready(rs)
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
        rs, _ = progs.epoch(rs, jax.random.fold_in(key, 100 + i), probe=False)
        out["physics"].append(physics(rs.train_env.data))
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
