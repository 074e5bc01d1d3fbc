"""Would a seed's learners in a process of their own, beside its environment work on the same GPU,
shorten the epoch? (issue 63: the measurement before building it)

Why: on one GPU a seed's epoch runs its two halves one after the other on one stream: the
environment's (PPO's rollouts and updates, the frames rendered: MuJoCo Warp's chains of small
kernels, the GPU half idle) and the learners' updates (big kernels, the GPU full). `--overlap
apart` runs them at once on two devices; on one GPU two processes take turns on it, and a pair of
a latency-bound and a throughput-bound process overlaps well that way (`diagnostics/mps_probe.py`:
106% + 77% of their rates alone). This times the two halves of a preset's epoch
(`Experiment.env_data` and `Learning.learn_phase`, each jitted on an initialised run state, the
same inputs every call) in two processes: each alone, then both at once with their timed windows
lined up (a barrier after both have compiled). The epoch apart on one GPU would take about the
longer of the two halves at once (plus the small insert and probe program); the plain epoch about
the sum of the two alone.

    python benchmarks/bench_split.py --preset fig2-halfcheetah --bf16 --seeds 1 --seconds 30 \
        --compile-cache /tmp/jc --out-dir "$OUT"
    python benchmarks/bench_split.py --preset fig2-halfcheetah --small --seeds 1 --seconds 3  # CPU
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

SIDES = ("env", "learn")


def _config_argv(a: argparse.Namespace) -> list[str]:
    """The preset flags, passed on to each side's process."""
    out = ["--preset", a.preset, "--seconds", str(a.seconds)]
    if a.compile_cache:
        out += ["--compile-cache", a.compile_cache]
    if a.seeds:
        out += ["--seeds", str(a.seeds)]
    return out + (["--bf16"] if a.bf16 else []) + (["--small"] if a.small else [])


def _barrier(folder: str, side: str, parties: int, timeout_s: float = 1200.0) -> None:
    """Say this side is ready, then wait until `parties` sides are."""
    open(os.path.join(folder, f"ready_{side}"), "w").close()
    end = time.monotonic() + timeout_s
    while sum(n.startswith("ready_") for n in os.listdir(folder)) < parties:
        if time.monotonic() > end:
            raise TimeoutError(f"the other side was not ready after {timeout_s:.0f} s")
        time.sleep(0.05)


def run_side(a: argparse.Namespace) -> dict[str, Any]:
    """One half of the epoch in a loop for `a.seconds` after compiling (and the barrier)."""
    import jax

    from bulbjax.epoch.loop import Experiment
    from profile_epoch import build_config

    a.learners, a.seed_loop, a.no_shared_updates, a.deconv_impl, a.rnn_unroll, a.learner_option = (
        "", "", False, "", 0, [])
    if a.compile_cache:  # later runs load their programs (Warp's calls numbered stably)
        from bulbjax.compile_cache import enable

        enable(a.compile_cache)
    exp = Experiment(build_config(a))
    key = jax.random.PRNGKey(0)
    rs = jax.block_until_ready(exp.init(key))
    if a.side == "env":
        fn = jax.jit(exp.env_data)
        args = (rs.ppo, rs.train_env, rs.policy_history.get("train"), None, key)
    else:
        fn = jax.jit(exp.learning.learn_phase)
        args = (rs.learners, rs.buffers, key, rs.windows)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(fn(*args))
    if a.barrier:
        _barrier(a.barrier, a.side, a.parties)
    times: list[float] = []
    start = time.perf_counter()
    while time.perf_counter() - start < a.seconds:
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return {"side": a.side, "device_kind": jax.devices()[0].device_kind, "calls": len(times),
            "median_s": statistics.median(times), "min_s": min(times), "max_s": max(times),
            "first_call_s": compile_s}


def _launch(a: argparse.Namespace, sides: tuple[str, ...]) -> dict[str, Any]:
    """`sides` in processes of their own, at once; their results by side."""
    with tempfile.TemporaryDirectory() as folder:
        env = dict(os.environ, XLA_PYTHON_CLIENT_MEM_FRACTION=str(round(0.8 / len(sides), 2)),
                   BULBJAX_STABLE_WARP_IDS="1")
        argv = [sys.executable, __file__, *_config_argv(a), "--barrier", folder,
                "--parties", str(len(sides))]
        procs = {s: subprocess.Popen([*argv, "--side", s], stdout=subprocess.PIPE, text=True,
                                     env=env) for s in sides}
        out = {}
        for s, p in procs.items():
            text = p.communicate()[0]
            if p.returncode:
                raise RuntimeError(f"the {s} side failed (exit {p.returncode}); its output:\n"
                                   f"{text[-2000:]}")
            out[s] = json.loads(text.strip().splitlines()[-1])
        return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="fig2-halfcheetah")
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--bf16", action="store_true")
    p.add_argument("--small", action="store_true", help="CPU sizes (small_config)")
    p.add_argument("--seconds", type=float, default=30.0,
                   help="timed seconds of each side, each time")
    p.add_argument("--out-dir", default=os.path.join(HERE, "results"))
    p.add_argument("--compile-cache", default="",
                   help="JAX's persistent compilation cache folder for the sides' processes: "
                        "the side-by-side runs load what the runs alone compiled")
    p.add_argument("--side", default="", choices=("",) + SIDES, help=argparse.SUPPRESS)
    p.add_argument("--barrier", default="", help=argparse.SUPPRESS)
    p.add_argument("--parties", type=int, default=1, help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.side:
        print(json.dumps(run_side(a)), flush=True)
        return
    # no JAX in this process: it would hold GPU memory the two sides need
    res: dict[str, Any] = {"argv": sys.argv, "preset": a.preset, "seeds": a.seeds, "bf16": a.bf16,
                           "small": a.small}
    res["alone"] = {**_launch(a, ("env",)), **_launch(a, ("learn",))}
    res["device_kind"] = res["alone"]["env"]["device_kind"]
    res["together"] = _launch(a, SIDES)
    alone, together = res["alone"], res["together"]
    res["plain_epoch_estimate_s"] = alone["env"]["median_s"] + alone["learn"]["median_s"]
    res["apart_one_gpu_epoch_estimate_s"] = max(together[s]["median_s"] for s in SIDES)
    print(json.dumps(res, indent=1))
    slug = res["device_kind"].lower().replace(" ", "_")
    os.makedirs(a.out_dir, exist_ok=True)
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    path = os.path.join(a.out_dir, f"split_{a.preset}_{slug}_{stamp}.json")
    with open(path, "w") as f:
        json.dump(res, f, indent=1)
    print(f"written: {path}")


if __name__ == "__main__":
    main()
