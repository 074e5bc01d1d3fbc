"""Do two processes' kernels share one GPU at once under CUDA MPS? (issue 63's open question)

Why: one locomotion seed leaves the H200 under-used in PPO's phase (MuJoCo Warp's chains of tiny
kernels for 64 worlds: ~0.6 s of the 1.75 s epoch) while its learners' big kernels wait their
turn on the same stream. Without MPS two processes on one GPU take turns (time-slicing: three
reproduce jobs on one H200 gave 1.14x the seed-epochs of one). Under MPS their kernels can run
side by side; if they do, a seed's learners in a process of their own could run beside its
rollouts, and jobs sharing a GPU would gain more.

Two workloads, each a jitted loop timed in its own process: `tiny` (a chain of dependent
elementwise kernels on a [64, 32] array: launch- and latency-bound, as the rollouts) and `big`
(bf16 matmuls of side `--big`, 8,192: the GPU full, as the learners). Timed alone, both at
once without MPS, then both at once with an MPS control daemon started for the purpose (and quit
after). Writes JSON to --out.

    python benchmarks/diagnostics/mps_probe.py --out mps_probe.json
    CPU smoke run (no MPS there):  python benchmarks/diagnostics/mps_probe.py --seconds 1 --big 256
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time


def worker(kind: str, seconds: float, big: int) -> None:
    import jax
    import jax.numpy as jnp

    if kind == "tiny":
        x = jnp.ones((64, 32), jnp.float32)

        @jax.jit
        def run(x):
            return jax.lax.fori_loop(0, 2000, lambda i, v: jnp.sin(v) * 1.0001 + 0.5, x)
    else:
        x = jnp.ones((big, big), jnp.bfloat16) * 0.01

        @jax.jit
        def run(x):
            return jax.lax.fori_loop(0, 20, lambda i, v: (v @ v) * 0.01, x)
    jax.block_until_ready(run(x))  # compile
    calls, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        jax.block_until_ready(run(x))
        calls += 1
    print(json.dumps({"kind": kind, "calls_per_s": calls / (time.perf_counter() - t0)}), flush=True)


def launch(kinds: list[str], seconds: float, big: int) -> dict[str, float]:
    argv = [sys.executable, __file__, "--seconds", str(seconds), "--big", str(big)]
    procs = [subprocess.Popen([*argv, "--worker", k], stdout=subprocess.PIPE, text=True)
             for k in kinds]
    out = {}
    for k, p in zip(kinds, procs):
        line = p.communicate()[0].strip().splitlines()[-1]
        out[k] = json.loads(line)["calls_per_s"]
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--worker", default="")
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--out", default="mps_probe.json")
    p.add_argument("--big", type=int, default=8192,
                   help="the big workload's matrix side (CPU smoke run: 256)")
    a = p.parse_args()
    if a.worker:
        return worker(a.worker, a.seconds, a.big)
    res: dict = {"seconds": a.seconds}
    res["alone"] = {**launch(["tiny"], a.seconds, a.big), **launch(["big"], a.seconds, a.big)}
    res["together_no_mps"] = launch(["tiny", "big"], a.seconds, a.big)
    ctl = shutil.which("nvidia-cuda-mps-control")
    res["mps_control"] = ctl
    if ctl:
        dirs = {"CUDA_MPS_PIPE_DIRECTORY": "/tmp/mps_pipe",
                "CUDA_MPS_LOG_DIRECTORY": "/tmp/mps_log"}
        env = dict(os.environ, **dirs)
        os.makedirs("/tmp/mps_pipe", exist_ok=True)
        os.makedirs("/tmp/mps_log", exist_ok=True)
        started = subprocess.run([ctl, "-d"], env=env, capture_output=True, text=True)
        res["mps_start"] = {"rc": started.returncode, "err": started.stderr[-300:]}
        os.environ.update(dirs)
        try:
            if started.returncode == 0:
                res["together_mps"] = launch(["tiny", "big"], a.seconds, a.big)
                res["alone_mps"] = {**launch(["tiny"], a.seconds, a.big),
                                    **launch(["big"], a.seconds, a.big)}
        except Exception as err:  # noqa: BLE001 - a probe: say what failed
            res["mps_error"] = repr(err)
        finally:
            subprocess.run([ctl], input="quit\n", env=env, capture_output=True, text=True)
            res["mps_log"] = open("/tmp/mps_log/control.log").read()[-600:] if os.path.exists(
                "/tmp/mps_log/control.log") else None
    with open(a.out, "w") as f:
        json.dump(res, f, indent=1)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
