"""Would a seed's learners in a process of their own, beside its environment work on the same GPU,
shorten the epoch? (issue 63: the measurement before building it)

Why: on one GPU a seed's epoch runs its two halves one after the other on one stream: the
environment's (PPO's rollouts and updates, the frames rendered: MuJoCo Warp's chains of small
kernels, the GPU half idle) and the learners' updates (big kernels, the GPU full). `--overlap
apart` runs them at once on two devices. This times the two halves of a preset's epoch
(`Experiment.env_data` and `Learning.learn_phase`, each jitted on an initialised run state, the
same inputs every call) in two processes: each alone, then both at once with their timed windows
lined up (a barrier after both have compiled). The epoch apart on one GPU would take about the
longer of the two halves at once (plus the small insert and probe program); the plain epoch about
the sum of the two alone.

Measured (fig2-halfcheetah, one seed, bf16, one H200, 2026-11-29; docs/performance.md): two
processes time-sliced (no MPS) gain nothing (env 0.71 -> 1.30 s, learn 1.06 -> 2.21 s at once);
under MPS (`--mps`) the learners keep their pace and the env side slows 2.2x (1.51 s at once,
against 1.77 s one after the other). `--learn-sm-percent` and `--learn-priority` time the learn
side with a smaller share of the SMs or a lower MPS client priority, so that the env side's small
kernels wait less: below-normal priority gave env 1.26 s / learn 1.18 s at once (~1.26 s an
epoch), 60% of the SMs env 0.97 s / learn 1.59 s (a fresh H200, the same day).

    python benchmarks/bench_split.py --preset fig2-halfcheetah --bf16 --seeds 1 --seconds 30 \
        --compile-cache /tmp/jc --out-dir "$OUT"
    python benchmarks/bench_split.py --preset fig2-halfcheetah --bf16 --seeds 1 --seconds 15 \
        --compile-cache /tmp/jc --mps --learn-sm-percent 100,60 --learn-priority normal,below
    python benchmarks/bench_split.py --preset fig2-halfcheetah --small --seeds 1 --seconds 3  # CPU
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import os
import signal
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
PRIORITIES = {"normal": "0", "below": "1"}  # CUDA_MPS_CLIENT_PRIORITY's values
T0 = time.perf_counter()


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


def _launch(a: argparse.Namespace, sides: tuple[str, ...], learn_env: dict[str, str] | None = None
            ) -> dict[str, Any]:
    """`sides` in processes of their own, at once; their results by side. `learn_env`: variables
    for the learn side's process alone (its MPS share and priority)."""
    with tempfile.TemporaryDirectory() as folder:
        env = dict(os.environ, XLA_PYTHON_CLIENT_MEM_FRACTION=str(round(0.8 / len(sides), 2)),
                   BULBJAX_STABLE_WARP_IDS="1")
        argv = [sys.executable, __file__, *_config_argv(a), "--barrier", folder,
                "--parties", str(len(sides))]
        procs = {s: subprocess.Popen([*argv, "--side", s], stdout=subprocess.PIPE, text=True,
                                     env=dict(env, **(learn_env or {})) if s == "learn" else env)
                 for s in sides}
        _LIVE.extend(procs.values())
        try:
            out = {}
            for s, p in procs.items():
                text = p.communicate()[0]
                if p.returncode:
                    raise RuntimeError(f"the {s} side failed (exit {p.returncode}); its output:\n"
                                       f"{text[-2000:]}")
                out[s] = json.loads(text.strip().splitlines()[-1])
            return out
        finally:  # stopped by an error: no side left running on the GPU
            for p in procs.values():
                if p.poll() is None:
                    p.kill()
                _LIVE.remove(p)


_LIVE: list[subprocess.Popen] = []  # the sides running now
_CLEANUP: list[Any] = []  # the MPS daemon while it runs


def _on_term(*_: Any) -> None:
    """SIGTERM (a timeout): kill the sides, quit the daemon, exit 143, here and now (an exception
    raised from a handler can land in a garbage-collection callback and be dropped)."""
    for p in _LIVE:
        if p.poll() is None:
            p.kill()
    for d in _CLEANUP:
        d.__exit__(None, None, None)
    os._exit(143)


def _settings(a: argparse.Namespace) -> list[tuple[int, str]]:
    """The learn side's MPS settings to time beside the env side: (SM percent, priority)."""
    given = a.learn_sm_percent.split(",")
    sms = [int(x) if x.strip().isdigit() else -1 for x in given]
    prios = a.learn_priority.split(",")
    bad = [x for x, sm in zip(given, sms) if not 1 <= sm <= 100]
    bad += [x for x in prios if x not in PRIORITIES]
    if bad:
        raise SystemExit(f"bad --learn-sm-percent / --learn-priority value(s) {bad}: SM percents "
                         f"1-100, priorities {'/'.join(PRIORITIES)}")
    if not a.mps and (sms != [100] or prios != ["normal"]):
        raise SystemExit("--learn-sm-percent and --learn-priority are MPS settings: add --mps")
    return [(sm, pr) for sm in sms for pr in prios]


def _learn_env(sm: int, priority: str) -> dict[str, str]:
    """The learn side's MPS variables for a setting (none for the defaults)."""
    out = {"CUDA_MPS_ACTIVE_THREAD_PERCENTAGE": str(sm)} if sm != 100 else {}
    if priority != "normal":
        out["CUDA_MPS_CLIENT_PRIORITY"] = PRIORITIES[priority]
    return out


def measure(a: argparse.Namespace, settings: list[tuple[int, str]], res: dict[str, Any],
            save: Any) -> None:
    """Each half alone (the learn side once per SM share), then both at once per setting
    (`_settings`); each result printed and `save`d as it comes."""
    def step(name: str, value: Any) -> None:
        print(f"[{time.perf_counter() - T0:7.1f} s] {name}: {json.dumps(value)}", file=sys.stderr,
              flush=True)
        save()

    res["alone"] = _launch(a, ("env",))
    res["device_kind"] = res["alone"]["env"]["device_kind"]
    step("env alone", res["alone"]["env"])
    learn_alone: dict[int, Any] = {}
    for sm, priority in settings:
        if sm not in learn_alone:
            learn_alone[sm] = _launch(a, ("learn",), _learn_env(sm, "normal"))["learn"]
            step("learn alone" + (f" at {sm}% of the SMs" if a.mps else ""), learn_alone[sm])
        together = _launch(a, SIDES, _learn_env(sm, priority))
        run = {"learn_sm_percent": sm, "learn_priority": priority, "learn_alone": learn_alone[sm],
               "together": together,
               "plain_epoch_estimate_s": (res["alone"]["env"]["median_s"]
                                          + learn_alone[sm]["median_s"]),
               "apart_one_gpu_epoch_estimate_s": max(together[s]["median_s"] for s in SIDES)}
        res["settings"].append(run)
        how = f", learn side at {sm}% of the SMs, {priority} priority" if a.mps else ""
        step("together" + how, {s: round(together[s]["median_s"], 4) for s in SIDES})


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
    p.add_argument("--mps", action="store_true",
                   help="run every process under an MPS control daemon started for the purpose "
                        "(quit at the end): their kernels share the SMs instead of taking turns")
    p.add_argument("--learn-sm-percent", default="100",
                   help="with --mps: the learn side's share of the SMs "
                        "(CUDA_MPS_ACTIVE_THREAD_PERCENTAGE), comma-separated to time several")
    p.add_argument("--learn-priority", default="normal",
                   help="with --mps: the learn side's MPS client priority, normal or below "
                        "(CUDA_MPS_CLIENT_PRIORITY 0 / 1), comma-separated to time both")
    p.add_argument("--side", default="", choices=("",) + SIDES, help=argparse.SUPPRESS)
    p.add_argument("--barrier", default="", help=argparse.SUPPRESS)
    p.add_argument("--parties", type=int, default=1, help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.side:
        print(json.dumps(run_side(a)), flush=True)
        return
    settings = _settings(a)  # a bad setting refused before anything starts
    signal.signal(signal.SIGTERM, _on_term)
    # no JAX in this process: it would hold GPU memory the two sides need
    res: dict[str, Any] = {"argv": sys.argv, "preset": a.preset, "seeds": a.seeds, "bf16": a.bf16,
                           "small": a.small, "mps": a.mps, "settings": []}
    os.makedirs(a.out_dir, exist_ok=True)
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    path = os.path.join(a.out_dir, f"split_{a.preset}{'_mps' if a.mps else ''}_{stamp}.json")

    def save() -> None:  # after every launch: a run stopped early keeps what it measured
        with open(path, "w") as f:
            json.dump(res, f, indent=1)

    daemon: Any = contextlib.nullcontext()
    if a.mps:  # here: bulbjax.reproduce imports JAX (no GPU memory taken: no backend started)
        from bulbjax.reproduce.mps import MpsDaemon

        try:  # no control program, or a daemon that did not start: one line
            daemon = MpsDaemon().__enter__()
        except ValueError as err:
            raise SystemExit(str(err)) from None
        _CLEANUP.append(daemon)
    try:
        measure(a, settings, res, save)
    finally:
        _CLEANUP.clear()
        daemon.__exit__(None, None, None)
    slug = res["device_kind"].lower().replace(" ", "_")
    final = path.replace(f"_{stamp}.json", f"_{slug}_{stamp}.json")
    os.replace(path, final)
    print(json.dumps(res, indent=1))
    print(f"written: {final}")


if __name__ == "__main__":
    main()
