"""`bulbjax reproduce`: the paper's figures by one command, over every GPU of a host (or a share of
the plan on each of several hosts), continued by running the same command again.

The steps: the plan (`plan.plan_jobs`: figures -> jobs of one seed each), this host's share of it
(`--shard K/N`), the estimate on this host's GPUs (`estimate.simulate`, printed before anything
starts, and alone with `--dry-run`), the queue (`queue.Queue`: one process per GPU), then the
results page (`results.write`) and `summary.json` (GPUs, utilisation, estimated and measured wall
time, each job's measured epoch time).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import shutil
import time
from dataclasses import dataclass, replace
from typing import Any, Callable, Sequence

from bulbjax import compile_cache
from bulbjax.config import PRESETS
from bulbjax.reproduce import jobs as J
from bulbjax.reproduce import results
from bulbjax.reproduce.estimate import (MPS_GAIN, SHARED_GAIN, Estimate, Timing, apart_times, derived_fp32,
                                       fit_jobs, hms, hours_unit, job_cost, load_times, shared_times, simulate,
                                       table_kinds, timing_key, without_apart_rows)
from bulbjax.reproduce.estimate import device_kind as host_kind
from bulbjax.reproduce.mps import MpsDaemon
from bulbjax.reproduce.plan import (PLAN_FILE, Job, grown_from, parse_figures, parse_jobs, parse_shard,
                                    plan_differences, plan_jobs, plan_record, read_plan, shard_of)
from bulbjax.reproduce.queue import SHARED_MEMORY, Queue, Slot


def learner_names(specs: Sequence[str]) -> list[str]:
    """The registered names of `--add-learner` specs (a registered name, `pkg.module:Name` or
    `path/file.py:Name`, imported and registered by `bulbjax.learners.plugins.load_learner_spec`);
    a clear one-line error for one that does not load or is one of the paper's learners."""
    from bulbjax.learners import learner_names as known
    from bulbjax.learners.plugins import parse_learner_list

    paper = {n for p in PRESETS.values() for n in p.learners}
    out = []
    for spec in specs:
        (name,) = parse_learner_list([spec])  # a name, a spec loaded, or an installed package's learner
        if name not in known():
            raise ValueError(f"--add-learner {spec!r}: not a registered learner; give pkg.module:Name of your "
                             f"learner (docs/extending.md) or one of: {', '.join(known())}")
        if name in paper:
            raise ValueError(f"--add-learner {spec}: {name!r} is already in the paper's runs; add a learner of "
                             "your own")
        out.append(name)
    return out


def slots_of(gpus: int | None, per_slot: int = 1, jobs_per_gpu: int = 1,
             as_kind: str | None = None) -> tuple[list[Slot], str]:
    """This host's slots: one per visible GPU (the first `gpus` of them), or per `per_slot` GPUs
    (the learners apart: 2), or `gpus` CPU workers (default 1) on a host without one, each
    showing `per_slot` CPU devices; and the device kind. `jobs_per_gpu` > 1: that many slots per
    GPU, each with its share of the GPU's memory (`Slot.mem_fraction`), so the jobs' processes
    run side by side on it (one's launch-bound rollouts beside another's learners). `as_kind`:
    the slots of a host of `gpus` (default 1) GPUs of that kind instead of this one's (a dry run's
    estimate for other hosts, from a login node without GPUs)."""
    from bulbjax import local_processes

    if as_kind is not None:
        kinds = [k for k in table_kinds() if k != "cpu"]
        if as_kind not in kinds:
            raise ValueError(f"--device-kind {as_kind!r}: the table times {', '.join(repr(k) for k in kinds)} "
                             "(nvidia-smi's names; bulbjax/reproduce/epoch_times.json)")
    visible = local_processes.visible_gpus() if as_kind is None else [str(i) for i in range(gpus or 1)]
    kind_of = host_kind if as_kind is None else (lambda _: as_kind)
    if gpus is not None and gpus < 1:
        raise ValueError(f"--gpus {gpus}: give 1 or more (the GPUs of this host to use)")
    if jobs_per_gpu < 1:
        raise ValueError(f"--jobs-per-gpu {jobs_per_gpu}: give 1 or more (jobs side by side on each GPU)")
    if jobs_per_gpu > 1 and per_slot > 1:
        raise ValueError("--jobs-per-gpu shares a GPU between jobs and --learners-apart gives each job two: "
                         "use one of them")
    if visible:
        if gpus is not None and gpus > len(visible):
            raise ValueError(f"--gpus {gpus}: this host has {len(visible)} GPU(s) "
                             f"({', '.join(visible)}; CUDA_VISIBLE_DEVICES / nvidia-smi)")
        use = visible[: gpus or None]
        if per_slot > 1:
            groups = [",".join(use[i:i + per_slot]) for i in range(0, len(use) - per_slot + 1, per_slot)]
            if not groups:
                raise ValueError(f"--learners-apart runs each job on {per_slot} GPUs and this host has "
                                 f"{len(use)} to use ({', '.join(use)}): leave it out, or give more GPUs")
            return [Slot(f"GPUs {g}", g) for g in groups], kind_of(use)
        if jobs_per_gpu > 1:
            share = SHARED_MEMORY / jobs_per_gpu
            return [Slot(f"GPU {g}.{k}", g, mem_fraction=share) for g in use for k in range(jobs_per_gpu)], \
                kind_of(use)
        return [Slot(f"GPU {g}", g) for g in use], kind_of(use)
    if jobs_per_gpu > 1:
        raise ValueError(f"--jobs-per-gpu {jobs_per_gpu} shares a GPU between jobs and this host has none: "
                         "leave it out (CPU workers: --gpus N)")
    return [Slot(f"cpu{i}", None, per_slot) for i in range(gpus or 1)], "cpu"


def _check_ycb(jobs: Sequence[Job]) -> None:
    """Fig. 5's models where its runs will read them (`$BULBJAX_YCB_DIR/<name>/google_16k/
    textured.obj` for every YCB object), or the one-line error those runs would end with."""
    if any("ycb" in j.preset for j in jobs):
        from bulbjax.assets.ycb import OBJ_FILE, YCB_DIR_ENV, YCB_INFO, ycb_object_files

        def lacks(name: str) -> bool:
            try:
                ycb_object_files(name, d)  # where the runs look, as they look
                return False
            except FileNotFoundError:
                return True

        d = os.environ.get(YCB_DIR_ENV)
        missing = [n for n in YCB_INFO if lacks(n)] if d and os.path.isdir(d) else []
        if not d or not os.path.isdir(d) or missing:
            why = ("is not set" if not d else f"names no folder ({d})" if not os.path.isdir(d) else
                   f"({d}) lacks {len(missing)} of its {len(YCB_INFO)} models (first: {missing[0]}/{OBJ_FILE})")
            raise ValueError(f"Fig. 5 (fig5-rearrange-ycb) reads the YCB models from ${YCB_DIR_ENV}, which "
                             f"{why}: set it to the YCB google_16k folder, or leave Fig. 5 out "
                             "(--figures fig2,fig3,fig4,fp32 for a new plan; --jobs or --fit-minutes "
                             "picks a share of one that holds Fig. 5)")


def _open_out(out: str, record: dict, overwrite: bool, dry_run: bool) -> list[str]:
    """Check `out` can hold this plan: missing, empty, or holding the same plan (continued), or
    the plan of a former "all" that this one grows (`plan.grown_from`: its jobs kept, the ids of
    the jobs added returned). Another plan there is refused unless `overwrite`, which clears a
    plan's folder (and only a plan's: a folder holding anything else is never deleted)."""
    path = os.path.join(out, PLAN_FILE)
    if os.path.exists(path):
        saved = read_plan(path)
        diff = plan_differences(saved, record)
        if overwrite:
            if not dry_run:
                shutil.rmtree(out)
        elif diff:
            raise ValueError(f"{out} holds a plan made with other settings ({'; '.join(diff)}): run the same "
                             "command to continue it, or add --overwrite to start afresh (deletes its runs)")
        else:
            return grown_from(saved, record)
    elif os.path.isdir(out) and os.listdir(out):
        raise ValueError(f"{out} is not empty and holds no reproduce plan: give --out a new or empty folder")
    return []


def plan_table(out: str, jobs: Sequence[Job], times: dict, est_gpus: int,
               warm: frozenset[str] = frozenset()) -> tuple[list[str], Any]:
    done = {j.id for j in jobs if J.is_done(out, j)}
    ep = {j.id: J.epochs_done(out, j) for j in jobs if j.id not in done}
    est = simulate(jobs, times, est_gpus, ep, finished=sorted(done), warm=warm)
    lines = [f"{'job':<28} {'epochs':>11} {'estimate':>9}  state"]
    for j in jobs:
        state = "done" if j.id in done else f"continue from epoch {ep[j.id]}" if ep.get(j.id) else "new"
        span = est.spans.get(j.id)  # the schedule's: cold for a preset's first job, warm after it
        cost = span[1] - span[0] if span else 0.0
        epochs = "recon" if j.kind == "recon" else f"{ep.get(j.id, j.epochs if j.id in done else 0)}/{j.epochs}"
        lines.append(f"{j.id:<28} {epochs:>11} {hms(cost):>9}  {state}")
    return lines, est


def reproduce(figures: str | Sequence[str] = "all", scale: str = "paper", out: str = "runs/reproduce",
              gpus: int | None = None, shard: str | None = None, add_learners: Sequence[str] = (),
              dry_run: bool = False, overwrite: bool = False, max_minutes: float = 0.0,
              progress_every: float = 30.0, log: Callable[[str], None] = print,
              jobs: str | Sequence[str] | None = None, fit_minutes: float = 0.0,
              learners_apart: bool = False, jobs_per_gpu: int = 1, device_kind: str | None = None,
              mps: bool = False, apart_env_learners: str | None = None) -> dict[str, Any]:
    """Run (or with `dry_run`, only plan) the paper's `figures` at `scale` into `out`; returns the
    summary (also `out/summary.json`). Rerunning with the same arguments continues unfinished
    jobs and skips finished ones. `shard` "K/N": this host's share of a plan split over N hosts.
    `add_learners`: learner specs run beside the paper's learners in every figure. `jobs`: only
    these jobs of the plan (ids, with their Fig. 4 partners); `fit_minutes`: of the unfinished
    jobs left, those that fit this many minutes on this host (`estimate.fit_jobs`), for a host
    held for a limited time. A stretch that selects jobs writes `summary_<UTC time>.json`, so the
    stretches of one plan folder (several hosts, several allocations) each keep theirs.
    `learners_apart`: every job on two GPUs, its learners on the second (`bulbjax run --overlap
    apart`: the same numbers; its epochs beside its PPO work). `jobs_per_gpu`: that many jobs side by
    side on each GPU, each its own process (`slots_of`); the summary's GPU-hours count each GPU
    once (its slots' busy time / `jobs_per_gpu`). `device_kind` (with `dry_run` only): estimate the
    plan on `gpus` (default 1) GPUs of that kind, not this host's. `mps`: the jobs' processes under
    an MPS control daemon started for the stretch (`mps.MpsDaemon`), so that jobs side by side on
    a GPU run their kernels at once instead of taking turns. `apart_env_learners` (with
    `learners_apart`): the learners updated on each job's first GPU (`bulbjax run
    --apart-env-learners`; default "auto" with `learners_apart`: pred there, 0.997 s a fig2-ant
    epoch over 1,000 against 1.132 s with every learner on the second GPU)."""
    figs, share = parse_figures(figures), parse_shard(shard)
    _check_options(share, overwrite, max_minutes, device_kind, dry_run, fit_minutes)
    names = learner_names(add_learners)
    run_flags = apart_flags(learners_apart, apart_env_learners)
    env_side = dict(zip(run_flags[::2], run_flags[1::2])).get("--apart-env-learners")  # as the jobs run
    all_jobs = plan_jobs(figs, scale, list(add_learners))
    host = host_of(gpus, learners_apart, jobs_per_gpu, mps, device_kind)
    daemon = MpsDaemon() if mps and not dry_run else None  # no control program: said before planning
    named = parse_jobs(jobs, all_jobs)
    mine = _select(out, all_jobs, host, share, named, fit_minutes, overwrite, log)
    _check_ycb(mine)  # --dry-run too: no plan of Fig. 5 without its models; before --overwrite clears anything
    record = plan_record(figs, scale, list(add_learners), all_jobs)
    grown = _open_out(out, record, overwrite, dry_run)
    if grown:
        joined = ", ".join(sorted({_job(all_jobs, i).figure for i in grown}))
        log(f"{out} holds this plan as it was before {joined} joined --figures all: its "
            f"{len(all_jobs) - len(grown)} jobs continue, {len(grown)} added")
    picked = (f", {len(mine)} picked" + (f" to fit {fit_minutes:g} min" if fit_minutes else " by --jobs")
              if fit_minutes or named is not None else "")
    est = _announce(out, mine, host, f"plan: {len(mine)} job(s)" + (f", shard {share[0]}/{share[1]}" if share else "")
                    + (f" of {len(all_jobs)}" if share or picked else "") + picked + f", scale {scale}", log)
    summary: dict[str, Any] = {"gpus": len(host.slots) * host.per_job // jobs_per_gpu, "device_kind": host.kind,
                               "times_of": host.times_kind, "estimated_wall_s": est.wall_s,
                               "estimated_gpu_s": est.gpu_s * host.gpu_share, "shard": list(share) if share else None,
                               "jobs_planned": len(mine), "learners_apart": learners_apart,
                               "apart_env_learners": env_side,
                               "jobs_per_gpu": jobs_per_gpu, "mps": mps}
    if dry_run:
        return summary
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, PLAN_FILE), "w") as f:
        json.dump(record, f, indent=1)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    selected = bool(fit_minutes) or named is not None
    status, summary_name = (_stretch_file(k, share, selected, stamp) for k in ("status", "summary"))
    q = Queue(out, mine, all_jobs, host.slots, host.times,
              time.monotonic() + 60 * max_minutes if max_minutes else None, progress_every, _learners_of(names),
              log, status, run_flags=run_flags,
              on_first_epoch=lambda j: compile_cache.mark_warm(host.cache_kind, timing_key(j)), warm=host.warm)
    with daemon or contextlib.nullcontext():
        ran = q.run()
    return _finish(out, ran, est, host, summary, summary_name, log)


@dataclass(frozen=True)
class Host:
    """Where a stretch runs: its slots and their device kind, the times its estimate reads (the
    table's rows for that kind, or the fallback kind's, `times_kind`, as jobs hold GPUs here), and
    how its jobs hold GPUs: two each with the learners apart, N jobs a GPU, under MPS or not."""

    slots: list[Slot]
    kind: str
    times: dict[str, Timing]
    times_kind: str
    jobs_per_gpu: int = 1
    learners_apart: bool = False
    mps: bool = False
    warm: frozenset[str] = frozenset()  # timing keys whose programs the compile cache holds here

    @property
    def cache_kind(self) -> str:
        """What `compile_cache.mark_warm` files this host's programs under: the device kind, and
        whether the learners run apart (other programs)."""
        return self.kind + (" learners apart" if self.learners_apart else "")

    @property
    def per_job(self) -> int:
        """GPUs one job holds (`results.gpus_held`: a CPU worker with the learners apart, one)."""
        return int(results.gpus_held(self.learners_apart, self.kind))

    @property
    def gpu_share(self) -> float:
        """The GPUs one job's busy time counts for (`results.gpu_share` reads a summary so)."""
        return results.gpus_held(self.learners_apart, self.kind, self.jobs_per_gpu)


def host_of(gpus: int | None, learners_apart: bool = False, jobs_per_gpu: int = 1, mps: bool = False,
            device_kind: str | None = None) -> Host:
    """This host's (or, with `device_kind`, a host of that kind's) slots and the times its
    estimate reads: the apart rows with `learners_apart`, slowed by the measured gain of
    `jobs_per_gpu` jobs a GPU (under MPS or time-sliced; `estimate.shared_times`)."""
    slots, kind = slots_of(gpus, 2 if learners_apart else 1, jobs_per_gpu, as_kind=device_kind)
    if mps and any(s.gpu is None for s in slots):
        raise ValueError("--mps shares GPUs between processes and this host runs CPU workers: run without it")
    times, times_kind = load_times(kind)
    times = shared_times(apart_times(times) if learners_apart else without_apart_rows(times), jobs_per_gpu, mps)
    host = Host(slots, kind, times, times_kind, jobs_per_gpu, learners_apart, mps)
    return replace(host, warm=compile_cache.warm_keys(host.cache_kind))


def _stretch_file(what: str, share: tuple[int, int] | None, selected: bool, stamp: str) -> str:
    """The name of a stretch's `what` file ("status", "summary"): one per shard of a sharded plan,
    one per stretch that selected its jobs (by its UTC start), else the plan's one."""
    if share and not selected:
        return f"{what}_shard{share[0]}of{share[1]}.json"
    return f"{what}_{stamp}.json" if selected else f"{what}.json"


def apart_flags(learners_apart: bool, env_learners: str | None) -> tuple[str, ...]:
    """The flags every job's `bulbjax run` gets for how its learners lie: `--overlap apart` with
    `learners_apart`, and `--apart-env-learners` (given: refused without it; else "auto")."""
    if env_learners is not None and not learners_apart:
        raise ValueError("--apart-env-learners names learners for the first GPU of a job's two: give "
                         "--learners-apart too")
    if not learners_apart:
        return ()
    from bulbjax.learners import learner_names as known

    unknown = [n for n in (env_learners or "none").split(",") if n not in ("auto", "none", *known())]
    if unknown:
        raise ValueError(f"--apart-env-learners {env_learners}: no learner {', '.join(unknown)}; give auto, none "
                         "or learners' names joined by commas (e.g. pred)")
    return ("--overlap", "apart", "--apart-env-learners", env_learners or "auto")


def _check_options(share: tuple[int, int] | None, overwrite: bool, max_minutes: float,
                   device_kind: str | None, dry_run: bool, fit_minutes: float) -> None:
    """Refuse option pairs that cannot go together, each in one line that says what to do."""
    if share is not None and overwrite:
        raise ValueError("--overwrite deletes the plan's folder, which every shard shares: start afresh by "
                         "deleting it once (or with --overwrite on one host, without --shard)")
    if max_minutes < 0:
        raise ValueError(f"--max-minutes must be >= 0 (0: no limit), got {max_minutes}")
    if device_kind is not None and not dry_run:
        raise ValueError(f"--device-kind {device_kind!r} estimates a plan for other hosts: add --dry-run (a run "
                         "uses this host's devices)")
    if fit_minutes and overwrite:
        raise ValueError("--fit-minutes picks among the plan's unfinished jobs: drop --overwrite")


def _select(out: str, all_jobs: list[Job], host: Host, share: tuple[int, int] | None,
            named: Sequence[Job] | None, fit_minutes: float, overwrite: bool,
            log: Callable[[str], None]) -> list[Job]:
    """This stretch's jobs: the shard's (`--shard K/N`, by estimated cost), those `--jobs` named
    (those done here said: they do not run again), less a Fig. 4 job whose run finished on another
    host (said), and of the unfinished rest those that fit `fit_minutes` here
    (`estimate.fit_jobs`)."""
    mine = all_jobs
    if share is not None:
        k, n = share
        where = shard_of(all_jobs, {j.id: job_cost(j, host.times) for j in all_jobs}, n)
        mine = [j for j in all_jobs if where[j.id] == k - 1]
        if not mine:
            log(f"shard {k}/{n} has no jobs: the plan's {len(all_jobs)} job(s) make fewer than {n} shares "
                "(an array of fewer tasks covers it)")
    if named is not None:
        mine = [j for j in mine if j in named]
        done = [] if overwrite else [j for j in mine if J.is_done(out, j)]  # --overwrite runs them again
        for j in done:
            log(f"{j.id} is done here already and does not run again: delete "
                f"{J.job_dir(out, j)} to run it again")
    lost = [] if overwrite else [j for j in mine if not J.is_done(out, j) and j.after
                                 and J.finished_elsewhere(out, _job(all_jobs, j.after))]
    for j in lost:  # its run finished on a host whose disk (and the checkpoint) went with it
        log(f"{j.id} left out: its run {j.after} finished on another host and left no checkpoint here to "
            f"draw from; delete {J.job_dir(out, _job(all_jobs, j.after))} to run both again")
    mine = [j for j in mine if j not in lost]
    if not fit_minutes:
        return mine
    left = [j for j in mine if not J.is_done(out, j)]  # before the YCB check: Fig. 5 may not be among what fits
    from bulbjax.assets.ycb import YCB_DIR_ENV  # here: it imports trimesh

    if any("ycb" in j.preset for j in left) and not os.environ.get(YCB_DIR_ENV):
        log("--fit-minutes: Fig. 5's jobs left out ($BULBJAX_YCB_DIR is not set)")
        left = [j for j in left if "ycb" not in j.preset]
    mine = fit_jobs(left, host.times, len(host.slots), fit_minutes, {j.id: J.epochs_done(out, j) for j in left},
                    warm=host.warm)
    if not mine and left:
        shortest = min(job_cost(j, host.times) for j in left if j.kind == "run")
        raise ValueError(f"--fit-minutes {fit_minutes:g}: no unfinished job fits (the shortest needs "
                         f"{hms(shortest)} here); give more minutes")
    return mine


def _announce(out: str, mine: list[Job], host: Host, what: str, log: Callable[[str], None]) -> Estimate:
    """Say the plan before anything starts: `what` (its jobs, shard, scale), the slots, each job's
    epochs, estimate and state, how derived times were worked out, the GPU-hours and wall time."""
    lines, est = plan_table(out, mine, host.times, len(host.slots), host.warm)
    lines += derived_fp32(mine, host.times)
    warm = sorted({timing_key(j) for j in mine} & host.warm)
    if warm:
        lines.append(f"warm start-ups for {', '.join(warm)}: the compile cache ({compile_cache.cache_dir()}) holds "
                     "their programs (a job of each reached its first epoch with it)")
    if host.jobs_per_gpu > 1:
        lines.append(f"{host.jobs_per_gpu} jobs per GPU: estimated from one measurement (the GPU's seed-epochs "
                     + (f"x {MPS_GAIN} at 2 jobs per H200 under MPS" if host.mps else
                        f"x {SHARED_GAIN} at 3 jobs per H200") + "; bulbjax/reproduce/estimate.py)")
    if host.learners_apart:
        lines += [f"{p}: estimated, {t.derived}" for p, t in host.times.items()
                  if "no apart row" in t.derived and any(j.preset == p and j.kind == "run" for j in mine)]
    if host.times_kind == "cpu" and any(j.kind == "run" and "--small" not in j.flags for j in mine):
        lines.append("cpu rows: measured on the tiny scale's --small runs, and this plan's jobs run at full "
                     "size, far slower on a CPU: the estimate is a lower bound (a GPU's: --device-kind "
                     "'NVIDIA H200')")
    note = "" if host.times_kind == host.kind else f" (estimates of an {host.times_kind}: none measured on this kind yet)"
    n = len(host.slots)
    log(f"{what}, on {n} {host.kind} slot(s)" + (" of two GPUs each (the learners apart)" if host.per_job == 2 else "")
        + f"{note}\n" + "\n".join(lines)
        + f"\nestimated: {est.gpu_s * host.gpu_share / 3600:.2f} {hours_unit(host.kind)}, {hms(est.wall_s)} wall "
        f"on {n} slot(s) (utilisation {est.utilisation:.0%})")
    return est


def _finish(out: str, ran: dict[str, Any], est: Estimate, host: Host, summary: dict[str, Any],
            summary_name: str, log: Callable[[str], None]) -> dict[str, Any]:
    """After the queue: each job's estimate beside what it took, the stretch's summary (written
    where a job ran) and the results page, said in one line."""
    for jid, r in ran["jobs"].items():  # what the plan estimated for each job it ran, beside what it took
        span = est.spans.get(jid)
        r["estimated_s"] = span[1] - span[0] if span and r.get("attempts") else None
    summary.update(measured_wall_s=ran["wall_s"], utilisation=ran["utilisation"], busy_s=ran["busy_s"],
                   gpu_hours=ran["busy_s"] / 3600 * host.gpu_share, failed=ran["failed"],
                   unfinished=ran["unfinished"], jobs=ran["jobs"],
                   finished_utc=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))
    ran_any = any(r["attempts"] for r in ran["jobs"].values())
    if ran_any:  # a rerun that found everything done keeps the summary of the stretch that ran
        with open(os.path.join(out, summary_name), "w") as f:
            json.dump(summary, f, indent=1)
    page = results.write(out, summary if ran_any else results.read_summary(out), out_name=out)
    log(f"results: {page}" + (f"; failed: {', '.join(ran['failed'])}" if ran["failed"] else "")
        + (f"; unfinished: {len(ran['unfinished'])} job(s): run the same command to continue"
           if ran["unfinished"] else ""))
    return summary


def _job(jobs: Sequence[Job], job_id: str) -> Job:
    return next(j for j in jobs if j.id == job_id)


def _learners_of(added: Sequence[str]) -> Callable[[Job], list[str]]:
    """A run job's learners (its `--learners` flag, else its preset's, with `added`)."""
    def of(job: Job) -> list[str]:
        flags = list(job.flags)
        if "--learners" in flags:
            specs = flags[flags.index("--learners") + 1].split(",")
            own = [s for s in specs if ":" not in s]
            return own + [n for n in added if n not in own]
        return [*PRESETS[job.preset].learners, *added]
    return of
