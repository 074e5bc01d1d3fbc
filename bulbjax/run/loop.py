"""The run loop of `bulbjax run`: epochs, checkpoints, logs, reports, resume.

A run folder holds `config.json` (the ExperimentConfig, the options that change results, the
provenance of every stretch), `metrics.jsonl` (one record per epoch and seed), `checkpoints/`
(orbax, the last K), `fig2.png`, `table.md`, `log.txt` (the CLI's console and C++ log lines,
`console.py`) and, with `--tensorboard`, `tb/` event files. A fresh run never starts over a
folder that holds a run unless told to (`overwrite`; `rundir.py`, docs/runs.md).

Resuming is exact: a checkpoint holds the whole `RunState` and the host-side key chain, the
epoch after it draws the same key as in an uninterrupted run, and `metrics.jsonl` is cut back
to the checkpoint's epoch, so 2 epochs + resume + 2 epochs write the records of 4 epochs straight.
Checkpoints are taken only between jitted calls (today one epoch per call; a chunked multi-epoch
call would checkpoint at chunk ends) and when the run stops: at its last epoch, at
`--max-minutes`, after `stop_after` epochs, or at the end of the epoch in which SIGINT/SIGTERM
arrived (a second SIGINT interrupts at once).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import sys
import time
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import jax

from bulbjax import distributed
from bulbjax.config import IDENTITY, ExperimentConfig, RunOptions
from bulbjax.epoch import Experiment, SeedGroups
from bulbjax.report import (ends_mid_line, epoch_records, files_written, last_returns, nanmean, read_jsonl, scalars,
                            write_jsonl, write_jsonl_atomic, write_reports)
from bulbjax.run import rundir
from bulbjax.run.checkpoint import CHECKPOINT_DIR, Checkpointer, CheckpointWriteError
from bulbjax.run.console import StageLog, bar_options
from bulbjax.run.provenance import provenance
from bulbjax.run.resume import Resume, SavedRun, check_processes, check_resume

TB_DIR = "tb"


@dataclass
class RunResult:
    epochs_done: int
    stopped: str  # "done", "max-minutes", "stop-after", "signal SIGTERM", ...
    records: list[dict[str, Any]]
    checkpoint: int | None  # epoch of the newest checkpoint


# ---------------------------------------------------------------------------- config.json
def _write_json_atomic(path: str, obj: Any) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
    os.replace(tmp, path)


# ---------------------------------------------------------------------------- signals
class StopSignal:
    """SIGINT/SIGTERM handler: the first signal asks the loop to stop at the end of the current
    epoch (and checkpoint); a second SIGINT interrupts at once."""

    def __init__(self, log: Callable[[str], None] = print):
        self.signum: int | None = None
        self.log = log
        self._old: dict[int, Any] = {}

    def __call__(self, signum: int, frame: Any = None) -> None:
        if self.signum is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signum = signum
        self.log(f"{signal.Signals(signum).name}: stopping at the end of this epoch and checkpointing "
                 "(SIGINT again to interrupt now)")

    def __enter__(self) -> "StopSignal":
        for s in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old[s] = signal.signal(s, self)
            except ValueError:  # not the main thread: no handlers, the loop runs to its end
                pass
        return self

    def __exit__(self, *exc: Any) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)


# ---------------------------------------------------------------------------- the loop
def _probe_now(epoch: int, cfg: ExperimentConfig, opts: RunOptions) -> bool:
    return epoch % opts.probe_every == 0 or epoch == cfg.epochs - 1


def _start_fresh(run_dir: str, log: Callable[[str], None]) -> None:
    """Remove what an earlier run left in `run_dir` (metrics, checkpoints, TensorBoard events)."""
    for name in ("metrics.jsonl", "fig2.png", "table.md"):
        p = os.path.join(run_dir, name)
        if os.path.exists(p):
            os.remove(p)
    for name in (CHECKPOINT_DIR, TB_DIR):
        p = os.path.join(run_dir, name)
        if os.path.isdir(p):
            log(f"starting afresh: removing {p} of an earlier run in {run_dir} (--overwrite)")
            rundir.remove_tree(p)
    from bulbjax.run.recon import figure_files

    for p in figure_files(run_dir):
        os.remove(p)


def _metrics_up_to(path: str, epoch: int, seeds: int) -> list[dict[str, Any]]:
    """The records of epochs < `epoch` (later ones, written after the checkpoint, and a
    half-written last line are cut off and the file rewritten); an error if any is missing."""
    records = read_jsonl(path, tolerate_partial=True) if os.path.exists(path) else []
    keep = [r for r in records if r["epoch"] < epoch]
    have = {(r["epoch"], r["seed"]) for r in keep}
    missing = sorted({e for e in range(epoch) for s in range(seeds) if (e, s) not in have})
    if missing:
        raise ValueError(f"{path} lacks the records of epochs {missing[:5]}{'...' if len(missing) > 5 else ''} "
                         f"that the checkpoint of epoch {epoch} has passed; the metrics cannot be continued "
                         "without a gap. Start a new run")
    if len(keep) != len(records) or ends_mid_line(path):  # later epochs, or half a record
        write_jsonl_atomic(path, keep)
    return keep


class _TensorBoard:
    """The scalars of metrics.jsonl as TensorBoard events (tensorboardX, optional extra)."""

    def __init__(self, run_dir: str, purge_step: int | None):
        try:
            from tensorboardX import SummaryWriter
        except ImportError as err:
            raise ValueError("--tensorboard needs tensorboardX: pip install 'bulbjax[tensorboard]'") from err
        self.writer = SummaryWriter(os.path.join(run_dir, TB_DIR), purge_step=purge_step)

    def write(self, records: Sequence[dict[str, Any]]) -> None:
        for r in records:
            for tag, v in scalars(r).items():
                self.writer.add_scalar(tag, v, global_step=r["epoch"])
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def run(cfg: ExperimentConfig, opts: RunOptions, run_dir: str, *, resume: bool | Resume = False,
        overwrite: bool = False, devices: Sequence[jax.Device] | None = None,
        experiment: Experiment | None = None, argv: Sequence[str] | None = None,
        log: Callable[[str], None] = print, progress: bool = True,
        on_epoch: Callable[[int], None] | None = None,
        compiler_options: dict[str, Any] | None = None, layout: str = "auto", t0: float | None = None,
        compile_only: bool = False) -> RunResult:
    """Run (or, with `resume`, continue) the experiment `cfg` in `run_dir`; see the module doc.
    `resume`: True (the run's config.json is read here) or the `Resume` that `resolve_resume`
    made of it (read there, not again).
    A fresh run refuses a folder that holds a run (ValueError naming it) unless `overwrite`,
    which deletes that run's metrics, checkpoints and plots first (`rundir.check_out_dir`).
    `devices` (default: every device of every process) carry the seeds as `SeedGroups` lays them
    out (`layout`: "auto", "groups", "sharded", "single"); `experiment` reuses a built
    `Experiment(cfg)` (tests: one compile for several runs). With several processes
    (`bulbjax.distributed`) every process calls this with the same arguments: each runs its
    devices' seed groups and writes its own checkpoints (`checkpoints/process_<i>`), process 0
    alone writes config.json, metrics.jsonl and the reports;
    `on_epoch(epochs_done)` is called after each epoch's metrics are written (tests);
    `compiler_options`: XLA options for the jitted init and epoch (recorded in the provenance);
    `t0`: when the stretch started (default now; the CLI's: its process start), from which the
    stage lines and --max-minutes count; `compile_only`: build, trace and compile init and the
    epoch (filling the compile cache), then stop, writing no config, metrics or checkpoint."""
    from tqdm import tqdm

    from bulbjax.learners import check_finite

    t0 = time.time() if t0 is None else t0
    writer = distributed.is_writer()
    if not writer:
        progress = False
    rundir.check_out_dir(run_dir, resume=bool(resume), overwrite=overwrite)  # nothing lost by accident
    if writer:
        rundir.remove_stale_temporaries(run_dir)
    stages = StageLog(log, t0)
    metrics_path = os.path.join(run_dir, "metrics.jsonl")
    config_path = os.path.join(run_dir, "config.json")
    if resume:  # the run's config.json as resolved (`resolve_resume`), or read here
        saved_run = resume.saved if isinstance(resume, Resume) else SavedRun.read(run_dir)
        check_resume(saved_run, cfg, opts)
        check_processes(saved_run)
        raw = saved_run.json()
    else:
        if writer:
            _start_fresh(run_dir, log)
        raw = {"experiment": dataclasses.asdict(cfg),
               "run": {k: getattr(opts, k) for k in IDENTITY}}
    distributed.barrier("bulbjax-run-folder")  # process 0 cleared the folder before anyone writes
    if experiment is not None and experiment.config != cfg:
        raise ValueError("run(experiment=...) was built for another config")
    if experiment is not None:
        groups = SeedGroups.of(experiment)
    else:
        with stages("building the environment and learners"):
            groups = SeedGroups(cfg, devices=devices, compiler_options=compiler_options, form=layout, log=log)
    exp = groups.exp
    log(f"devices: {groups.describe()}")
    stretch = provenance(argv, groups)
    if resume:
        raw.setdefault("resumes", []).append(stretch)
        raw["experiment"]["epochs"] = cfg.epochs
    else:
        raw["provenance"] = stretch
    # cleanup_tmp: a checkpoint a killed stretch left half-written goes (each process writes its own)
    # background: each process's checkpoint files are written while the next epochs run
    ckpt = Checkpointer(run_dir, keep=opts.keep, process=jax.process_index() if groups.processes > 1 else None,
                        cleanup_tmp=True, background=True)
    # init and the epochs this run uses, traced before anything else in this process so that a
    # resumed stretch compiles the same programs as the fresh one (and hits the compile cache);
    # probe_every is part of a run's identity, so fresh and resumed stretches trace the same ones
    with stages("tracing and lowering " + ("the epoch" if resume else "init and the epoch")):
        programs = groups.programs((True,) if opts.probe_every == 1 else (True, False))
        # compiles (or compile-cache loads) in background threads: init's and the epoch's overlap,
        # and a resume's restore overlaps the epoch's
        programs.prepare(*programs.startup(resume))
    # MuJoCo Warp's kernels built (or loaded) beside the compiles, so init finds them ready. Not
    # on a resume: the one resume that ran it beside the checkpoint's restore and a compile
    # ended in a SIGSEGV of process 1 (two H200s; the same resume without it ran), and a resume
    # finds the kernels in Warp's cache of the machine that ran the stretch before
    warming = None if resume else groups.warm_physics(jax.random.PRNGKey(opts.seed))
    stages.line("compiling " + ("the epoch" if resume else "init and the epoch")
                + " in the background (or loading them from the compile cache)")
    if compile_only:
        with stages("compiling init and the epoch"):
            for name in programs.startup(False):
                programs.compiled(name)
        warming = _physics_ready(warming, stages)
        log("compiled init and the epoch into the compile cache (--compile-only: no epoch ran)")
        distributed.barrier("bulbjax-run-end")
        return RunResult(epochs_done=0, stopped="compile-only", records=[], checkpoint=None)
    if resume:
        like = {"run": groups.abstract_state(), "key": groups.abstract_key()}
        with stages(f"restoring the checkpoint of epoch {ckpt.latest()}"):
            state, host, start = ckpt.restore(like)
        rs, key = state["run"], state["key"]
        if int(groups.group_state(rs).epoch) != start or host.get("epoch") != start:
            raise ValueError(f"checkpoint {start} holds epoch {int(rs.epoch)}: the checkpoint folder is inconsistent")
        records = _metrics_up_to(metrics_path, start, cfg.seeds)
        raw["resumes"][-1]["from_epoch"] = start
        log(f"resuming {run_dir} at epoch {start} (checkpoints: {ckpt.steps()})")
    else:
        with stages("compiling init"):
            programs.compiled("init")
        warming = _physics_ready(warming, stages)
        # several processes: init gathers the reference states of all, so it waits for the slowest
        with stages("running init" + (" (with the other processes)" if groups.processes > 1 else "")):
            rs = programs.init(jax.random.PRNGKey(opts.seed))
            jax.block_until_ready(rs)
        key, start, records = groups.put_key(jax.random.PRNGKey(opts.seed + 1)), 0, []
        if exp.pipelined:  # the first epoch's environment work, with the first epoch's key
            with stages("running the first epoch's rollouts (--overlap)"):
                key, k = jax.random.split(key)
                rs = groups.prime(rs, k)
                jax.block_until_ready(rs)
    if writer:
        _write_json_atomic(config_path, raw)
    jax.block_until_ready(rs)
    if start < cfg.epochs:
        with stages("compiling the epoch"):
            programs.compiled("epoch")
    warming = _physics_ready(warming, stages)
    t_init = time.time() - t0
    tb = _TensorBoard(run_dir, purge_step=start if resume else None) if opts.tensorboard and writer else None
    figs, drawn = None, None
    if opts.recon_every and writer:
        from bulbjax.run.recon import RunFigures

        figs = RunFigures(exp, run_seed=opts.seed)

    epoch, stopped, t_first, saved = start, "done", None, ckpt.latest() if resume else None
    bar = tqdm(total=cfg.epochs, initial=start, desc=f"{cfg.env} x{cfg.seeds} seeds", unit="epoch",
               disable=not progress, **bar_options(sys.stderr))
    if progress:
        stages.log = bar.write  # the first epoch's lines above the bar

    def late() -> bool:
        return bool(opts.max_minutes) and time.time() - t0 > 60 * opts.max_minutes

    try:
        with StopSignal(bar.write) as stop:
            # every process takes process 0's decisions (their clocks and signals differ): one
            # collective before the first epoch, then one after each
            if epoch < cfg.epochs:
                with (stages("waiting for the other processes") if groups.processes > 1
                      else contextlib.nullcontext()):
                    if distributed.broadcast_flag(late()):
                        stopped = "max-minutes"
            while epoch < cfg.epochs and stopped == "done":
                if opts.stop_after and epoch - start >= opts.stop_after:
                    stopped = "stop-after"
                    break
                key, k = jax.random.split(key)
                with stages(f"first epoch ({epoch})") if t_first is None else contextlib.nullcontext():
                    rs, m = programs.epoch(rs, k, probe=_probe_now(epoch, cfg, opts))
                if t_first is None:
                    t_first = time.time() - t0 - t_init
                for name, lm in m["learners"].items():
                    check_finite(lm, where=f"learner {name} at epoch {epoch}")
                recs = epoch_records(epoch, m, exp.spec, cfg.probe_variants)
                if writer:
                    try:  # metrics first: a checkpoint never runs ahead; whole records or none
                        write_jsonl(metrics_path, recs)
                    except OSError as err:
                        with contextlib.suppress(Exception):  # a checkpoint written in the background
                            ckpt.wait()  # counts once complete: the message names the newest one
                        raise _write_failed(run_dir, f"metrics.jsonl (epoch {epoch})", err) from err
                if tb:
                    tb.write(recs)
                records += recs
                epoch += 1
                bar.update(1)
                if recs[0]["probes"]:
                    bar.set_postfix(_postfix(recs, records), refresh=False)  # drawn at the next redraw
                if opts.checkpoint_every and epoch % opts.checkpoint_every == 0:
                    _save(ckpt, run_dir, epoch, rs, key)
                    saved = epoch
                if figs is not None and epoch % opts.recon_every == 0:
                    figs.draw(groups.group_state(rs), run_dir, epoch)
                    drawn = epoch
                if on_epoch is not None:
                    on_epoch(epoch)
                signalled, over = distributed.broadcast_flags(stop.signum is not None, late())
                if signalled:
                    stopped = f"signal {signal.Signals(stop.signum).name}" if stop.signum else "signal (process 0)"
                elif over and epoch < cfg.epochs:
                    stopped = "max-minutes"
            if saved != epoch:
                _save(ckpt, run_dir, epoch, rs, key)
                saved = epoch
            _save(ckpt, run_dir, epoch, None, None)  # the last write finished (or its error raised)
    finally:
        bar.close()
        ckpt.close()
        if tb:
            tb.close()
    if figs is not None and epoch > start and drawn != epoch:  # and at the end
        figs.draw(groups.group_state(rs), run_dir, epoch)
    if stopped == "max-minutes" and epoch == start:  # the budget went on start-up
        log(f"start-up took {t_init:.0f} s of the {60 * opts.max_minutes:.0f} s allowed (--max-minutes "
            f"{opts.max_minutes:g}); no epoch ran. Continue with: bulbjax run --resume {run_dir} (and a "
            "larger --max-minutes, or none)")
    elif stopped != "done":
        log(f"stopped after epoch {epoch} ({stopped}); continue with: bulbjax run --resume {run_dir}")
    wall = time.time() - t0
    first = f", first epoch {t_first:.1f} s" if t_first is not None else ""
    timing = (f"wall time of the last stretch {wall:.1f} s (start-up: build, compile, init/restore "
              f"{t_init:.1f} s{first}) on {groups.describe()}")
    if records and writer:
        began = time.time()
        tab = write_reports(run_dir, records, cfg, exp.spec, exp.env.solved_return, footer=timing)
        log(f"\n{tab}\n\n{timing}\n{files_written(run_dir, since=began)}\nmetrics: {metrics_path}")
    groups.settle()  # no compile may still run in a daemon thread when the process exits
    # the other processes wait while process 0 writes the reports (else they would reach JAX's
    # shutdown barrier first and time out there on a slow report)
    distributed.barrier("bulbjax-run-end")
    return RunResult(epochs_done=epoch, stopped=stopped, records=records, checkpoint=saved)


def _physics_ready(warming: Future | None, stages: StageLog) -> None:
    """Wait for `SeedGroups.warm_physics` (a stage line when it is still running). Its failure is
    no run's failure: one line says so, and init builds the kernels at their first launch.
    Returns None, for the caller's `warming` (so that it is waited for, and said, once)."""
    if warming is None:
        return None
    try:
        if warming.done():
            warming.result()
        else:
            with stages("building MuJoCo Warp's kernels (beside the compiles)"):
                warming.result()
    except Exception as err:  # noqa: BLE001
        stages.line(f"warming MuJoCo Warp's kernels failed ({type(err).__name__}: {err}); "
                    "init builds them at their first launch")


def _save(ckpt: Checkpointer, run_dir: str, epoch: int, rs: Any, key: Any) -> None:
    """The checkpoint of `epoch` epochs done (`rs` None: only wait for the one being written); a
    failed write, this one's or an earlier background one's, stops the run with a clear error (the
    checkpoints before it stay: a checkpoint's folder is renamed only once complete)."""
    try:
        if rs is None:
            ckpt.wait()
        else:
            ckpt.save(epoch, {"run": rs, "key": key}, {"epoch": epoch})
    except CheckpointWriteError as err:
        raise _write_failed(run_dir, f"the checkpoint of epoch {err.epoch}", err.__cause__ or err) from err
    except Exception as err:  # OSError, or tensorstore's errors for a full or read-only disk
        raise _write_failed(run_dir, f"the checkpoint of epoch {epoch}", err) from err


def _write_failed(run_dir: str, what: str, err: BaseException) -> ValueError:
    """The error of a write that failed mid-run: what was kept and how to go on."""
    steps = rundir.checkpoint_steps(run_dir)
    on = (f"the newest complete checkpoint is epoch {steps[-1]}; free space (or fix the folder) and "
          f"continue with: bulbjax run --resume {run_dir}" if steps else
          "there is no complete checkpoint yet; fix the folder and start again with --overwrite")
    return ValueError(f"writing {what} in {run_dir} failed ({type(err).__name__}: {err}); the run "
                      f"stopped, metrics.jsonl holds whole records only and {on}")


def _postfix(recs: list[dict], records: list[dict]) -> dict[str, str]:
    """The progress bar's figures at a probed epoch (`recs`, one per seed): the PPO return of the
    latest finished episodes (`records`: the run's so far) and each learner's overall errors."""
    ret, _ = last_returns(records, [recs[0]["epoch"]])
    out = {"return": f"{nanmean(ret):.1f}"}
    for name in recs[0]["probes"]:
        for stream in ("curr", "rand"):
            v = nanmean([r["probes"][name][stream]["overall"]["mae_norm"] for r in recs])
            out[f"{name}/{stream}"] = f"{v:.2f}" if v == v else "excluded"  # NaN: every group excluded
    return out
