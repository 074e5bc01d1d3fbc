"""Per-phase profile of one experiment epoch (issue 13): where an epoch's time goes.

For a preset (`--preset fig2-invpend`, ...) it builds the experiment, times the build and the
init, then jits every phase of `Experiment._epoch` on its own and times it on the run state of
a warmed-up run (median of `--repeats` calls, each ended by `block_until_ready`):
PPO rollout and update (`Policy.rl_phase`), rendering and writing replay frames
(`Streams.replay_phase`), cutting and rendering windows (`Streams.window_phase`), each learner's
`learner_batches` updates (`Learning.learn_phase` restricted to that learner), the held-out
rollouts (`Streams.eval_phase`), each learner's probe fit and evaluation (`Probing.probe_phase`
for that learner); with the learners apart (`--overlap apart`) the phases are the epoch's
programs, each alone (`apart_programs`). Then the whole jitted epoch with and without probing
(compile time, then the median call), the host transfer of its metrics (`jax.device_get`) and
the host-side record building (`records.epoch_records`).
The phases timed one by one add up to more than the fused epoch (no overlap between them,
one dispatch each): their shares say what to make cheaper, the fused numbers what a run costs.

Optionally (`--trace DIR`) a JAX profiler trace of two fused epochs of each executable (probing,
not probing) under DIR/probe and DIR/no_probe, each with its optimised HLO (`epoch.hlo.txt`), for
`trace_summary.py DIR/probe` (device time by phase scope) or TensorBoard/Perfetto.
Writes `<out-dir>/profile_<preset>_<device>_<timestamp>.json` and prints a table.

GPU:  python benchmarks/profile_epoch.py --preset fig2-invpend --bf16
CPU smoke run:  python benchmarks/profile_epoch.py --preset fig2-invpend --small --seeds 1 --repeats 1
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import functools
import json
import os
import statistics
import sys
import time
from typing import Any, Callable

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
sys.path.insert(0, REPO)

import jax  # noqa: E402

import bulbjax  # noqa: E402

import warp_ffi_stats  # noqa: E402
from timing import time_fn  # noqa: E402

from bulbjax.config import ExperimentConfig  # noqa: E402
from bulbjax.envs.env_config import POSE_BRANCHES  # noqa: E402
from bulbjax.epoch.loop import Experiment  # noqa: E402
from bulbjax.epoch.programs import Programs, without_probes  # noqa: E402
from bulbjax.report.records import epoch_records  # noqa: E402
from bulbjax.run.settings import resolve  # noqa: E402
from bulbjax.xla_options import parse_named_options  # noqa: E402


def add_config_args(p: argparse.ArgumentParser) -> None:
    """The options `build_config` reads (preset and its overrides), for every script that builds
    an experiment from a preset."""
    p.add_argument("--preset", default="fig2-invpend")
    p.add_argument("--small", action="store_true", help="CPU sizes (small_config)")
    p.add_argument("--seeds", type=int, default=0, help="override the preset's seeds")
    p.add_argument("--learners", default="", help="override the preset's learners (comma-separated)")
    p.add_argument("--bf16", action="store_true")
    p.add_argument("--deconv-impl", default="", help="decoder form (transpose, subpixel, dgrad)")
    p.add_argument("--rnn-unroll", type=int, default=0, help="sequential learners' LSTM unroll (default: the preset's)")
    p.add_argument("--learner-option", action="append", default=[], metavar="KEY=VALUE",
                   help="a LearnerConfig field (repeatable), e.g. channel_pad=8 or bias_grad=split")
    p.add_argument("--seed-loop", default="", choices=("", "auto", "vmap", "map", "hybrid"),
                   help="learner work over the seed axis (default: the preset's)")
    p.add_argument("--programs", default="", choices=("", "fused", "split"),
                   help="init and the epoch as one program each or several (ExperimentConfig.programs; "
                        "default: the preset's)")
    p.add_argument("--overlap", default="", choices=("", "none", "pipeline", "apart"),
                   help="the next epoch's PPO work beside this epoch's learner updates (ExperimentConfig.overlap; apart: "
                        "the learners on a second device, two devices visible; "
                        "default: the preset's)")
    p.add_argument("--graph-mode", default="", help="how MJX-Warp's calls use CUDA graphs on a GPU "
                   "(ExperimentConfig.graph_mode: warp, jax, warp_staged, warp_staged_ex, none; "
                   "default: MJX's, warp)")
    p.add_argument("--no-shared-updates", action="store_true",
                   help="one update and probe program per frame VAE, not one for vae/vae_rpl/beta_vae "
                        "(ExperimentConfig.shared_updates)")


def build_config(a: argparse.Namespace) -> ExperimentConfig:
    """The preset resolved as `bulbjax run` resolves it (`bulbjax.run.settings`: the
    domain's PPO settings, --small, then the flags given)."""
    overrides: dict[str, Any] = {}
    if a.seeds:
        overrides["seeds"] = a.seeds
    if a.learners:
        overrides["learners"] = a.learners
    if a.seed_loop:
        overrides["learner_seed_loop"] = a.seed_loop
    if a.no_shared_updates:
        overrides["shared_updates"] = False
    if getattr(a, "programs", ""):
        overrides["programs"] = a.programs
    if getattr(a, "overlap", ""):
        overrides["overlap"] = a.overlap
    if getattr(a, "graph_mode", ""):
        overrides["graph_mode"] = a.graph_mode
    learner: dict[str, Any] = {}
    if a.bf16:
        learner["compute_dtype"] = "bfloat16"
    if a.deconv_impl:
        learner["deconv_impl"] = a.deconv_impl
    if a.rnn_unroll:
        learner["rnn_unroll"] = a.rnn_unroll
    return resolve(a.preset, overrides=overrides, learner=learner, learner_options=a.learner_option,
                   small=a.small)


def only_learner(exp: Experiment, name: str) -> tuple[Any, Any]:
    """The experiment's learning and probing with one learner only (for timing it on its own)."""
    team = dataclasses.replace(exp.team, learners={name: exp.learners[name]})
    return dataclasses.replace(exp.learning, team=team), dataclasses.replace(exp.probing, team=team)


def profile(cfg: ExperimentConfig, repeats: int, warm_epochs: int, trace_dir: str | None,
            log: Callable[[str], None] = print, phases: bool = True,
            save: Callable[[dict[str, Any]], None] = lambda out: None,
            variants: dict[str, dict[str, Any]] | None = None,
            tags: tuple[str, ...] = ("probe", "no_probe"), warp_stats: bool = False,
            program: str = "flag", hlo_dir: str | None = None) -> dict[str, Any]:
    """Every phase's time and the fused epoch's, as a JSON-able dict. `save(out)` is called
    after every stage, so that a run cut short (a GPU call's time limit) keeps what it measured.
    `variants`: named XLA compile options, each compiling and timing the fused epoch (`tags`:
    the probing and/or non-probing executable) in this process on the same run state.
    `warp_stats`: record MuJoCo Warp's FFI handler calls, graph captures and host seconds per
    timed epoch (`warp_ffi_stats.install()` must have run before the build).
    `hlo_dir`: write each timed executable's optimised HLO there (a trace from the start).
    `program`: "flag" (what a run probing every k epochs uses: one program, `Experiment.epoch_flag`,
    whose start-up is timed as `bulbjax run` does it, init and epoch compiled side by side) or
    "static" (one specialised program per tag, compiled one after the other, as before 2026-11-25)."""
    out: dict[str, Any] = {"phases": {}, "fused": {}, "done": False, "program": program,
                           "overlap": cfg.overlap}
    if cfg.overlap == "apart" and program != "flag":
        raise ValueError("--overlap apart runs its three programs as a run does: use --program flag")
    t0 = time.perf_counter()
    exp = Experiment(cfg)
    out["build_s"] = time.perf_counter() - t0
    key = jax.random.PRNGKey(0)
    flag_compiled = None
    if program == "flag":
        # start-up as `bulbjax run` does it (fresh run, probing every k): init and the one epoch
        # program traced in order, lowered, compiled side by side in threads, init run
        t0 = time.perf_counter()
        progs = Programs.of(exp, (True, False))
        out["trace_s"] = time.perf_counter() - t0
        out["split_programs"] = progs.split
        out["programs"] = progs.names
        t0 = time.perf_counter()
        progs.prepare(*progs.startup(resume=False)[:-1])  # init (and a pipelined run's prime)
        t_lower_init = time.perf_counter() - t0
        progs.prepare("epoch")
        out["lower_s"] = time.perf_counter() - t0
        out["lower_init_s"] = t_lower_init
        rs = jax.block_until_ready(progs.init(key))
        if exp.pipelined:  # the first epoch's environment work (ExperimentConfig.overlap)
            rs = jax.block_until_ready(progs.prime(rs, jax.random.fold_in(key, 99)))
        out["init_s"] = time.perf_counter() - t0  # lowering + init's compile (or load) + run
        flag_compiled = progs.compiled("epoch")
        out["epoch_ready_s"] = time.perf_counter() - t0  # lowering + the epoch's compile (or load)
        out["compile_spans_s"] = dict(progs.compile_spans)  # per program: (start, end) of its compile, s after tracing ended
        out["to_first_epoch_s"] = out["build_s"] + out["trace_s"] + out["epoch_ready_s"]
        log(f"build {out['build_s']:.1f} s, trace {out['trace_s']:.1f} s, lower {out['lower_s']:.1f} s, "
            f"init ready+run {out['init_s']:.1f} s, epoch ready {out['epoch_ready_s']:.1f} s: "
            f"first epoch starts {out['to_first_epoch_s']:.1f} s after the build began")
    else:
        t0 = time.perf_counter()
        rs = jax.block_until_ready(exp.init(key))
        if exp.pipelined:
            rs = jax.block_until_ready(exp.prime(rs, jax.random.fold_in(key, 99)))
        out["init_s"] = time.perf_counter() - t0  # compile + run of init
        log(f"build {out['build_s']:.1f} s, init (compile + run) {out['init_s']:.1f} s")
    if warp_stats:
        out["warp_ffi_after_init"] = warp_ffi_stats.snapshot()
    save(out)

    # the fused epoch: compile, first call, then timed calls (probing and not), once per variant
    # of XLA compile options (the first variant's numbers are the profile's `fused`)
    compiled_by_tag = {}
    variants = variants or {"default": {}}
    out["variants"] = {}
    for vi, (vname, vopts) in enumerate(variants.items()):
        res_v = out["variants"][vname] = {"compiler_options": vopts}
        flag_variant = None
        for probe in (True, False):
            tag = "probe" if probe else "no_probe"
            if tag not in tags:
                continue
            k = jax.random.fold_in(key, 100 + probe)
            if program == "flag" and (progs.split or exp.apart is not None):  # as a run calls them
                if vopts:
                    raise ValueError("--variant compiles the fused epoch program: use --programs fused "
                                     "and --overlap none or pipeline")
                compiled = functools.partial(progs.epoch, probe=probe)
                lower_s, compile_s = out["lower_s"], out["epoch_ready_s"]
            elif program == "flag":  # one program for both tags: compiled once per variant
                if vi == 0 and not vopts:
                    flag_variant = (flag_compiled, out["lower_s"], out["epoch_ready_s"])
                elif flag_variant is None:
                    t0 = time.perf_counter()
                    lowered = exp.epoch_flag.lower(rs, k, exp.abstract_flag())
                    lower_s = time.perf_counter() - t0
                    t0 = time.perf_counter()
                    flag_variant = (lowered.compile(compiler_options=vopts or None), lower_s,
                                    time.perf_counter() - t0)
                fc, lower_s, compile_s = flag_variant
                compiled = _with_flag(fc, exp.put_flag(probe), probe)
            else:
                t0 = time.perf_counter()
                lowered = exp.epoch.lower(rs, k, probe=probe)
                lower_s = time.perf_counter() - t0  # tracing + lowering to StableHLO
                t0 = time.perf_counter()
                compiled = lowered.compile(compiler_options=vopts or None)
                compile_s = time.perf_counter() - t0  # XLA compile (or a persistent-cache hit)
            if vi == 0:
                compiled_by_tag[tag] = compiled
                if hlo_dir:  # the executable's optimised HLO, for trace_summary's scopes
                    with open(os.path.join(hlo_dir, f"epoch_{program}_{tag}.hlo.txt"), "w") as f:
                        f.write(_hlo_text(flag_compiled if program == "flag" else compiled))
            what = _what(out)
            log(f"[{vname}] {what} ({tag}): lower {lower_s:.1f} s, compile {compile_s:.1f} s")
            times, get_s, rec_s, ffi = [], [], [], []
            for i in range(warm_epochs + repeats):
                snap = warp_ffi_stats.snapshot() if warp_stats else None
                t0 = time.perf_counter()
                # a host span per timed epoch: `trace_summary.py --window bj_timed_<tag>` keeps
                # the device events inside them (a trace begun at the start, `--trace-from-start`)
                with jax.profiler.TraceAnnotation(f"bj_timed_{tag}" if i >= warm_epochs else f"bj_warm_{tag}"):
                    rs, m = compiled(rs, jax.random.fold_in(k, i))
                    jax.block_until_ready(rs)
                t1 = time.perf_counter()
                m = jax.device_get(m)
                t2 = time.perf_counter()
                epoch_records(i, m, exp.spec)
                t3 = time.perf_counter()
                if warp_stats:
                    ffi.append(warp_ffi_stats.delta(warp_ffi_stats.snapshot(), snap))
                if i >= warm_epochs:
                    times.append(t1 - t0)
                    get_s.append(t2 - t1)
                    rec_s.append(t3 - t2)
            res_v[tag] = {"lower_s": lower_s, "compile_s": compile_s, "median_s": statistics.median(times),
                          "min_s": min(times), "device_get_s": statistics.median(get_s),
                          "records_s": statistics.median(rec_s), "times_s": times}
            if warp_stats:  # per epoch: the first (after compile), then the timed ones
                res_v[tag]["warp_ffi"] = {"first": ffi[0], "last": ffi[-1],
                                          "per_epoch_totals": [f["total"] for f in ffi]}
                log(f"[{vname}] warp ffi per epoch ({tag}): first {ffi[0]['total']}, last {ffi[-1]['total']}")
            log(f"[{vname}] {what} ({tag}): median {res_v[tag]['median_s']:.3f} s")
            del compiled
            save(out)
        flag_variant = None
        if "probe" in res_v and "no_probe" in res_v:
            f_p, f_n = res_v["probe"]["median_s"], res_v["no_probe"]["median_s"]
            res_v["epoch_s_probe_every_10"] = (f_p + 9 * f_n) / 10  # issue 13's target: <= 1.5 s
            res_v["epoch_s_probe_every_1"] = f_p  # target: <= 3 s
    first = next(iter(out["variants"].values()))
    out["fused"] = {t: first[t] for t in ("probe", "no_probe") if t in first}
    for name in ("epoch_s_probe_every_10", "epoch_s_probe_every_1"):
        if name in first:
            out[name] = first[name]
    save(out)

    if trace_dir:  # per executable: <dir>/<tag>/ with two traced epochs and its optimised HLO
        for tag, comp in compiled_by_tag.items():
            d = os.path.join(trace_dir, tag)
            os.makedirs(d, exist_ok=True)
            with open(os.path.join(d, "epoch.hlo.txt"), "w") as f:  # instruction -> phase scope
                f.write(_hlo_text(flag_compiled if program == "flag" else comp))  # (trace_summary.hlo_scopes)
            with jax.profiler.trace(d):
                for i in range(2):
                    rs, m = comp(rs, jax.random.fold_in(key, 200 + i))
                jax.block_until_ready(rs)
        out["trace_dir"] = trace_dir

    if not phases:
        out["done"] = True
        save(out)
        return out
    if exp.apart is not None:  # its phases: the programs, each alone (they take both devices' inputs)
        out["phases"], out["apart_warp_ffi"] = apart_programs(exp, progs, rs, key, repeats, warp_stats)
        out["phases_sum_s"] = _shares(out["phases"])
        out["done"] = True
        save(out)
        return out
    # phases one by one, on the warmed-up state (inputs made once, outside the timings)
    keys = jax.random.split(jax.random.fold_in(key, 300), 6)
    ph = out["phases"]
    rl = jax.jit(exp.policy.rl_phase)
    ph["rl (ppo rollout + update)"] = time_fn(lambda: rl(rs.ppo, rs.train_env, keys[0]), repeats)
    ppo_state, _, _, _, _, steps, _ = rl(rs.ppo, rs.train_env, keys[0])
    rep = jax.jit(exp.streams.replay_phase)
    ph["replay (render + insert)"] = time_fn(lambda: rep(rs.buffers, steps, keys[1]), repeats)
    if rs.windows:
        win = jax.jit(exp.streams.window_phase)
        ph["windows (cut + render + insert)"] = time_fn(lambda: win(rs.windows, steps, keys[2]), repeats)
    ev = jax.jit(exp.streams.eval_phase)
    ph["eval (held-out rollouts + render)"] = time_fn(lambda: ev(ppo_state, rs.curr_env, rs.rand_env, keys[3]),
                                                      repeats)
    _, _, held, _ = ev(ppo_state, rs.curr_env, rs.rand_env, keys[3])
    for name in list(exp.learners):
        learning, probing = only_learner(exp, name)
        learn = jax.jit(learning.learn_phase)
        sub = {name: rs.learners[name]}
        ph[f"learn {name}"] = time_fn(lambda: learn(sub, rs.buffers, keys[4], rs.windows), repeats)
        pr = jax.jit(probing.probe_phase)
        ph[f"probe {name}"] = time_fn(lambda: pr(sub, rs.buffers, held, keys[5], rs.windows), repeats)
        log(f"  learn {name} {ph[f'learn {name}']['median_s']:.3f} s, probe {ph[f'probe {name}']['median_s']:.3f} s")
        save(out)
    out["phases_sum_s"] = _shares(ph)
    out["done"] = True
    save(out)
    return out


def apart_programs(exp: Experiment, progs: Programs, rs: Any, key: jax.Array, repeats: int,
                   warp_stats: bool) -> tuple[dict[str, dict[str, Any]], list[dict[str, Any]]]:
    """The phases of an epoch with the learners apart: its programs ("env", "near", "learn",
    "finish"), each run alone and waited for (`Apart.timings`), over `repeats` epochs that do not
    probe: the epoch itself runs the two devices' programs at once, so their sum exceeds it. With
    `warp_stats` also each epoch's MuJoCo Warp totals: an epoch whose buffer addresses Warp has
    not met captures its CUDA graphs again (a locomotion epoch's ~40 captures cost the environment's
    program ~0.5 s on an H200, over a run's first ~50 epochs: docs/performance.md)."""
    exp.apart.timings, ffi = {}, []
    try:
        for i in range(repeats):
            snap = warp_ffi_stats.snapshot() if warp_stats else None
            rs, _ = progs.epoch(rs, jax.random.fold_in(key, 400 + i), probe=False)
            if warp_stats:
                ffi.append(warp_ffi_stats.delta(warp_ffi_stats.snapshot(), snap)["total"])
        timings = exp.apart.timings
    finally:
        exp.apart.timings = None
    return {name: {"first_s": ts[0], "median_s": statistics.median(ts), "min_s": min(ts), "times_s": ts}
            for name, ts in timings.items()}, ffi


def _shares(phases: dict[str, dict[str, Any]]) -> float:
    """Give each phase its share of the phases' summed medians; returns the sum."""
    total = sum(v["median_s"] for v in phases.values())
    for v in phases.values():
        v["share"] = v["median_s"] / total if total else float("nan")
    return total


def _what(out: dict[str, Any]) -> str:
    """What the timed epoch is: the fused program, the split programs, or the three programs of
    the learners apart (`ExperimentConfig.overlap`)."""
    if out.get("overlap") == "apart":
        return "apart epoch"
    return "split epoch" if out.get("split_programs") else "fused epoch"


def _hlo_text(exe: Any) -> str:
    """An executable's optimised HLO; split programs (a dict of them) one after another."""
    if isinstance(exe, dict):
        return "\n".join(e.as_text() for e in exe.values())
    return exe.as_text()


def _with_flag(compiled: Callable, flag: jax.Array, probe: bool) -> Callable:
    """`Experiment.epoch_flag`'s executable called as a tag's epoch: `(rs, key) -> (rs, metrics)`,
    without `probes` when not probing (as `Programs.epoch` returns them)."""
    def call(rs: Any, key: jax.Array) -> tuple[Any, Any]:
        rs, m = compiled(rs, key, flag)
        return rs, m if probe else without_probes(m)
    return call


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_config_args(p)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--warm-epochs", type=int, default=2, help="untimed epochs after compile")
    p.add_argument("--trace", default="", help="write a JAX profiler trace of two epochs here")
    p.add_argument("--trace-from-start", default="",
                   help="trace everything from before the build into this folder (with the epochs' "
                        "optimised HLO): MuJoCo Warp's CUDA graphs are then all captured while the "
                        "profiler runs; summarise with trace_summary.py DIR --window bj_timed_no_probe")
    p.add_argument("--out-dir", default=os.path.join(HERE, "results"))
    p.add_argument("--tag", default="", help="label for the file name (e.g. before/after)")
    p.add_argument("--no-phases", action="store_true", help="time the fused epoch only (skip the phases one by one)")
    p.add_argument("--variant", action="append", default=[], metavar="NAME[=KEY:VALUE;...]",
                   help="time the fused epoch compiled with these XLA options (repeatable; the first "
                        "is the profile's `fused`), e.g. while=xla_gpu_enable_command_buffer:FUSION,WHILE")
    p.add_argument("--tags", default="probe,no_probe", help="fused executables to time (probe, no_probe)")
    p.add_argument("--program", default="flag", choices=("flag", "static"),
                   help="flag: one epoch program with a probe flag, start-up timed as a run does it "
                        "(default); static: one program per tag, compiled one after the other")
    p.add_argument("--compile-cache", default="",
                   help="JAX persistent compilation cache folder (default: none, so compile times are cold)")
    p.add_argument("--warp-stats", action="store_true",
                   help="count MuJoCo Warp's FFI calls, graph captures and their host time per epoch "
                        "(not with --trace: its traces show copies its untraced epochs do not pay)")
    p.add_argument("--warp-graph-cache", default="",
                   help="captured CUDA graphs kept per Warp callable (an int, or none: unbounded; default: "
                        "bulbjax.envs.warp_graphs.GRAPH_CACHE_MAX; Warp's own default is 32)")
    p.add_argument("--separate-substeps", action="store_true",
                   help="step the physics in MJX's separate calls (EnvConfig.fuse_substeps=False): "
                        "the before of issue 63's one-call-per-env-step measurement")
    p.add_argument("--pose-branch", choices=POSE_BRANCHES, default="auto",
                   help="how step gives reset worlds their poses (EnvConfig.reset_pose_branch): a lax.cond, "
                        "whose predicate a GPU reads on the host each step, a select, or auto (the select "
                        "on a GPU where the pose pass is the kinematics pass)")
    a = p.parse_args(argv)
    if a.separate_substeps or a.pose_branch != "auto":  # the experiment builds its env through bulbjax.make
        bulbjax.make = functools.partial(bulbjax.make, fuse_substeps=not a.separate_substeps,
                                         reset_pose_branch=a.pose_branch)
    if a.warp_stats or a.warp_graph_cache:
        gcm = a.warp_graph_cache
        warp_ffi_stats.install("default" if not gcm else None if gcm == "none" else int(gcm))
    cfg = build_config(a)
    if a.compile_cache:
        from bulbjax.compile_cache import enable as enable_compile_cache
        enable_compile_cache(a.compile_cache)
    t_start = time.perf_counter()
    res: dict[str, Any] = {"preset": a.preset, "argv": sys.argv if argv is None else argv, "tag": a.tag,
                           "config": dataclasses.asdict(cfg), "device_kind": jax.devices()[0].device_kind,
                           "platform": jax.default_backend(), "jax": jax.__version__,
                           "compile_cache": a.compile_cache or None,
                           "warp_graph_cache": a.warp_graph_cache or "default",
                           "fuse_substeps": not a.separate_substeps, "reset_pose_branch": a.pose_branch,
                           # settings given by the environment (XLA_FLAGS, JAX_* such as
                           # JAX_THREEFRY_GPU_KERNEL_LOWERING), so that a result says what it ran
                           "env": {k: v for k, v in os.environ.items()
                                   if k == "XLA_FLAGS" or (k.startswith("JAX_") and "CACHE" not in k)}}
    slug = res["device_kind"].lower().replace(" ", "_")
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    os.makedirs(a.out_dir, exist_ok=True)
    path = os.path.join(a.out_dir, f"profile_{a.preset}{'_' + a.tag if a.tag else ''}_{slug}_{stamp}.json")

    def save(out: dict[str, Any]) -> None:
        res.update(out)
        res["total_s"] = time.perf_counter() - t_start
        with open(path + ".tmp", "w") as f:
            json.dump(res, f, indent=1, default=str)
        os.replace(path + ".tmp", path)

    variants = dict(parse_named_options(v) for v in a.variant) or None
    tags = tuple(t for t in a.tags.split(",") if t)
    if a.trace_from_start:
        os.makedirs(a.trace_from_start, exist_ok=True)
        jax.profiler.start_trace(a.trace_from_start)
    try:
        profile(cfg, a.repeats, a.warm_epochs, a.trace or None, phases=not a.no_phases, save=save,
                variants=variants, tags=tags, warp_stats=a.warp_stats, program=a.program,
                hlo_dir=a.trace_from_start or None)
    finally:
        if a.trace_from_start:
            jax.profiler.stop_trace()
    print(f"\n== epoch profile: {a.preset} on {res['device_kind']} ({cfg.seeds} seeds, "
          f"{len(cfg.learners)} learners, {cfg.learner.compute_dtype}) ==")
    print(f"build {res['build_s']:.1f} s, init {res['init_s']:.1f} s"
          + (f", first epoch starts at {res['to_first_epoch_s']:.1f} s" if "to_first_epoch_s" in res else ""))
    for vname, rv in res["variants"].items():
        for tag in ("probe", "no_probe"):
            if tag in rv:
                v = rv[tag]
                what = _what(res)
                print(f"[{vname}] {what} {tag:8}: lower {v['lower_s']:5.1f} s, compile {v['compile_s']:6.1f} s, "
                      f"median {v['median_s']:.3f} s, device_get {v['device_get_s'] * 1e3:.1f} ms, "
                      f"records {v['records_s'] * 1e3:.1f} ms")
        if "epoch_s_probe_every_10" in rv:
            print(f"[{vname}] epoch with probing every 10: {rv['epoch_s_probe_every_10']:.3f} s; every epoch: "
                  f"{rv['epoch_s_probe_every_1']:.3f} s")
    print(f"{'phase (jitted alone)':40} {'median s':>9} {'share':>6} {'first s':>8}")
    for name, v in res["phases"].items():
        print(f"{name:40} {v['median_s']:9.3f} {100 * v['share']:5.1f}% {v['first_s']:8.1f}")
    print(f"written: {path}")
    return res


if __name__ == "__main__":
    main()
