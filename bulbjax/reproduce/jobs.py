"""A plan's jobs on disk: what each has done (read from its run folder, so a rerun of the same
command knows without a record of its own), and the command line that starts or continues it."""

from __future__ import annotations

import glob
import os
import sys
from typing import Sequence

from bulbjax.reproduce.plan import Job, fig4_learners
from bulbjax.run import checkpoint_steps

# a periodic checkpoint about every this many seconds of epochs, so that a killed job loses
# little; a job stopped by a signal or --max-minutes checkpoints as it stops anyway
CHECKPOINT_SECONDS = 300.0


def job_dir(out: str, job: Job) -> str:
    return os.path.join(out, job.run_dir)


def begun(out: str, job: Job) -> bool:
    """Whether `job`'s folder under `out` holds anything (a run begun, finished or not)."""
    d = job_dir(out, job)
    return os.path.isdir(d) and bool(os.listdir(d))


def epochs_done(out: str, job: Job) -> int:
    """Epochs of `job`'s run kept in its newest complete checkpoint (0: none yet); a recon job
    counts its epochs once its figure is drawn."""
    if job.kind == "recon":
        return job.epochs if recon_done(out, job) else 0
    steps = checkpoint_steps(job_dir(out, job))
    if steps:
        return max(steps)
    # a finished job brought back from another machine without its checkpoints (a shard of a
    # GPU host whose disk went with it: its reduced metrics, `metrics.jsonl.gz`, and reports):
    # done when its metrics hold its last epoch; a part of a job without a checkpoint is nothing
    return job.epochs if metrics_epochs(job_dir(out, job)) >= job.epochs else 0


def metrics_epochs(run_dir: str) -> int:
    """Epochs recorded in a run folder's metrics (`metrics.jsonl`, read from its end, else a
    committed `metrics.jsonl.gz`); 0 without either."""
    if os.path.exists(os.path.join(run_dir, "metrics.jsonl")):
        return _last_epoch(os.path.join(run_dir, "metrics.jsonl"))
    gz = os.path.join(run_dir, "metrics.jsonl.gz")
    if not os.path.exists(gz):
        return 0
    import gzip
    import json

    last = 0
    with gzip.open(gz, "rt") as f:
        for line in f:
            try:
                last = max(last, int(json.loads(line)["epoch"]) + 1)
            except (ValueError, KeyError, TypeError):
                continue
    return last


def recon_done(out: str, job: Job) -> bool:
    return bool(glob.glob(os.path.join(glob.escape(job_dir(out, job)), "recon_*.png")))


def is_done(out: str, job: Job) -> bool:
    """Whether `job` has nothing left to do: its run checkpointed its last epoch, or its figure
    is drawn."""
    return recon_done(out, job) if job.kind == "recon" else epochs_done(out, job) >= job.epochs


def finished_elsewhere(out: str, job: Job) -> bool:
    """Whether run `job` counts as done here without a checkpoint: it finished on a host whose disk
    kept its last checkpoint, so a Fig. 4 job cannot draw from it in `out`."""
    return is_done(out, job) and not checkpoint_steps(job_dir(out, job))


def epochs_written(out: str, job: Job) -> int:
    """Epochs whose records a running job has written (the last whole line of its metrics.jsonl,
    read from the file's end: a long run's file is large); 0 before the first. The window read
    grows until it holds a whole line: a probing epoch's records with the probe variants are
    ~80 KB a line (Fig. 2 CartPole on an H200), longer than a fixed window would hold."""
    return _last_epoch(os.path.join(job_dir(out, job), "metrics.jsonl"))


def _last_epoch(path: str) -> int:
    """The epoch after the last whole record of a JSON-lines metrics file, read from its end; 0
    without one."""
    import json

    window = 65536
    try:
        with open(path, "rb") as f:
            size = f.seek(0, os.SEEK_END)
            while True:
                start = max(0, size - window)
                f.seek(start)
                lines = f.read().splitlines()
                if start > 0:
                    lines = lines[1:]  # the first may begin before the window
                for line in reversed(lines):
                    try:
                        return int(json.loads(line)["epoch"]) + 1
                    except (ValueError, KeyError, TypeError):
                        continue
                if start == 0:
                    return 0
                window *= 4
    except OSError:
        return 0


def command(out: str, job: Job, epoch_s: float, max_minutes: float = 0.0, source: Job | None = None,
            learners: Sequence[str] = (), run_flags: Sequence[str] = ()) -> list[str]:
    """The `bulbjax` command line that starts `job`, or continues it from its newest checkpoint
    (a folder without one, from a job killed while starting, starts afresh over it).
    `max_minutes` > 0: the run stops itself (checkpointing) after that long. A recon job draws
    the Fig. 4 columns among `learners`, the learners of its `source` run. `run_flags`: how a
    fresh run job runs on its slot, not what it computes (e.g. `--overlap apart`)."""
    base = [sys.executable, "-m", "bulbjax"]
    d = job_dir(out, job)
    if job.kind == "recon":
        if source is None:
            raise ValueError(f"job {job.id} redraws a run: give its source job")
        cols = fig4_learners(learners)
        cmd = [*base, "recon", job_dir(out, source), "--out", d]
        return cmd + (["--learners", ",".join(cols)] if cols else [])
    every = job.checkpoint_every or max(10, int(CHECKPOINT_SECONDS / max(epoch_s, 1e-3)))
    stretch = ["--epochs", str(job.epochs), "--checkpoint-every", str(every)]
    if max_minutes > 0:
        stretch += ["--max-minutes", f"{max_minutes:.2f}"]
    if checkpoint_steps(d):
        return [*base, "run", "--resume", d, *stretch]
    fresh = [*base, "run", "--preset", job.preset, "--seeds", str(job.seeds), "--seed", str(job.seed),
             "--probe-every", str(job.probe_every), "--out", d, *job.flags, *run_flags, *stretch]
    if job.recon_every:
        fresh += ["--recon-every", str(job.recon_every)]
    if os.path.exists(os.path.join(d, "config.json")):
        fresh.append("--overwrite")  # a start that never reached a checkpoint: nothing to keep
    return fresh


def last_line(path: str, width: int = 300) -> str:
    """The last non-empty line of a log (what a failed job said last), shortened to `width`."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - 16384))
            lines = [ln.strip() for ln in f.read().decode(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return "(no log)"
    line = lines[-1] if lines else "(empty log)"
    return line if len(line) <= width else line[: width - 3] + "..."
