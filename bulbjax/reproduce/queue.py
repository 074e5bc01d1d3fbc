"""The queue: one `bulbjax run` (or `recon`) process per free GPU, each taking the next job of the
plan whose inputs are ready, until every job is done, failed twice, or the time is up.

Each slot is one GPU (`CUDA_VISIBLE_DEVICES` names it) or, on a machine without one, one CPU
worker process. A job's console goes to `OUT/logs/<job>.txt`. A job that exits with an error is
reported with the last line it wrote and started once more (continuing from its checkpoint); a
second failure leaves it failed and the queue goes on with the rest. SIGINT or SIGTERM (and
`max_minutes`) stop the running jobs the way `bulbjax run` stops: at the end of their epoch,
with a checkpoint, so the same command later continues them. Progress is printed on every
change and every `progress_every` seconds: jobs done / running / queued / failed, each running
job's epoch, its epoch time and the time left.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

from bulbjax.reproduce import jobs as J
from bulbjax.reproduce.estimate import Timing, hms, queue_order, simulate, timing_key, timing_of
from bulbjax.reproduce.plan import Job

ATTEMPTS = 2  # a failed job is retried once
STOP_GRACE_S = 180.0  # after SIGTERM, time for a job to checkpoint before it is killed
# the GPU memory JAX's processes on one GPU take together when slots share it (JAX's default for
# one process): three jobs of the pendulums at 0.25 each ran on one H200 with room for Warp's own
SHARED_MEMORY = 0.75


@dataclass
class Slot:
    """Where a job runs: its GPUs (`gpu`, a CUDA_VISIBLE_DEVICES value: one GPU, or two, "0,1",
    with the learners apart) or a CPU worker (None) showing `cpu_devices` devices to JAX.
    `mem_fraction`: the share of the GPU's memory JAX may take, for a GPU that several slots
    share (JAX takes 75% by default; the user's XLA_PYTHON_CLIENT_MEM_FRACTION wins)."""

    name: str
    gpu: str | None
    cpu_devices: int = 1
    mem_fraction: float | None = None

    def env(self) -> dict[str, str]:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if self.mem_fraction is not None:
            env.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", f"{self.mem_fraction:.3f}")
        if self.gpu is None:
            env.update(JAX_PLATFORMS="cpu", CUDA_VISIBLE_DEVICES="")
            if self.cpu_devices > 1:
                flag = f"--xla_force_host_platform_device_count={self.cpu_devices}"
                env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {flag}".strip()
        else:
            env["CUDA_VISIBLE_DEVICES"] = self.gpu
        return env


@dataclass
class Track:
    """A job's state in this command: queued, running, done, failed or stopped; its attempts,
    the slot and process of its current attempt, and the times measured."""

    job: Job
    status: str = "queued"
    attempts: int = 0
    slot: Slot | None = None
    proc: subprocess.Popen | None = None
    started: float = 0.0
    first_epoch_at: float | None = None  # when its first new record appeared
    last_epoch_at: float | None = None  # when its latest new record appeared (seen by `_watch`)
    epochs_at_start: int = 0
    epochs_at_first: int = 0
    epochs_at_last: int = 0
    busy_s: float = 0.0  # slot-seconds held, all attempts of this command
    stop_at: float | None = None  # asked to stop: killed if still running then
    epoch_s: float | None = None  # measured seconds per epoch of its last attempt
    startup_s: float | None = None  # measured seconds from its start to its first epoch
    end_s: float | None = None  # measured seconds from its last epoch's record to its exit
    errors: list[str] = field(default_factory=list)
    too_late: bool = False  # not started: the time left (--max-minutes) was below its start-up + 60 s

    def record(self) -> dict:
        out = {k: getattr(self, k) for k in ("status", "attempts", "busy_s", "epoch_s", "startup_s", "end_s", "errors")}
        out["slot"] = self.slot.name if self.slot else None
        return out


class Queue:
    """Runs `jobs` (in `queue_order`) on `slots`. `out`: the plan's folder. `times`: the epoch and
    start-up estimates. `deadline`: a `time.monotonic()` after which no job starts and running
    ones are asked to stop (None: none). `learners_of`: each job's learners (Fig. 4's columns).
    `on_first_epoch`: called with a run job once its first epoch is written (its programs compiled).
    `warm`: the timing keys whose programs the compile cache held at the start (the estimate's)."""

    def __init__(self, out: str, jobs: Sequence[Job], all_jobs: Sequence[Job], slots: Sequence[Slot],
                 times: dict[str, Timing], deadline: float | None = None, progress_every: float = 30.0,
                 learners_of: Callable[[Job], Sequence[str]] = lambda j: (), log: Callable[[str], None] = print,
                 status_file: str = "status.json", poll_s: float = 1.0, run_flags: Sequence[str] = (),
                 on_first_epoch: Callable[[Job], None] = lambda j: None, warm: frozenset[str] = frozenset()):
        self.out, self.slots, self.times, self.deadline = out, list(slots), times, deadline
        self.by_id = {j.id: j for j in all_jobs}
        self.tracks = {j.id: Track(j) for j in queue_order(jobs, times)}
        self.progress_every, self.learners_of, self.log = progress_every, learners_of, log
        self.status_path = os.path.join(out, status_file)
        self.poll_s = poll_s
        self.run_flags = tuple(run_flags)  # `J.command`'s: how a fresh run job runs on its slot
        self.on_first_epoch = on_first_epoch  # a run job's first epoch written (its programs compiled)
        self.warm = set(warm)  # and the keys of the jobs that compiled here since: the time left says so
        self.stopping: str | None = None
        self.t0 = time.monotonic()
        for t in self.tracks.values():
            if J.is_done(out, t.job):
                t.status = "done"

    # ------------------------------------------------------------------ the loop
    def run(self) -> dict:
        """Run until nothing is left to start or run; returns the summary (`summary`)."""
        old = {s: signal.signal(s, self._signal) for s in (signal.SIGINT, signal.SIGTERM)}
        last_progress = -1e9
        said_last = False  # the loop's last pass printed the progress: the end does not print it again
        try:
            while True:
                said_last = False
                changed = self._reap()
                if self.deadline is not None and time.monotonic() > self.deadline and not self.stopping:
                    self._stop("the time given (--max-minutes) is up")
                changed |= self._start_ready()
                running = [t for t in self.tracks.values() if t.status == "running"]
                self._watch(running)
                now = time.monotonic()
                if changed or now - last_progress >= self.progress_every:
                    self.progress()
                    self._write_status()
                    last_progress, said_last = now, True
                if not running and not self._startable():
                    break
                time.sleep(self.poll_s)
        finally:
            for s, h in old.items():
                signal.signal(s, h)
        if not said_last:
            self.progress()
        self._write_status()
        return self.summary()

    def _signal(self, signum: int, _frame: object) -> None:
        if self.stopping and signum == signal.SIGINT:
            for t in self.tracks.values():
                if t.proc is not None and t.proc.poll() is None:
                    t.proc.kill()
            raise KeyboardInterrupt
        self._stop(f"{signal.Signals(signum).name}")

    def _stop(self, why: str) -> None:
        """Start nothing more; ask every running job to checkpoint and stop."""
        self.stopping = why
        self.log(f"{why}: stopping the running jobs at the end of their epoch (they checkpoint; "
                 "the same command continues them)" + (" - SIGINT again to kill them now" if why == "SIGINT" else ""))
        for t in self.tracks.values():
            if t.proc is not None and t.proc.poll() is None:
                t.proc.send_signal(signal.SIGTERM)
                t.stop_at = time.monotonic() + STOP_GRACE_S

    def _ready(self, t: Track) -> bool:
        a = t.job.after
        return a is None or (a in self.tracks and self.tracks[a].status == "done") or \
            (a not in self.tracks and J.is_done(self.out, self.by_id[a]))

    def _startable(self) -> list[Track]:
        if self.stopping:
            return []
        return [t for t in self.tracks.values() if t.status == "queued" and not t.too_late and self._ready(t)]

    def _start_ready(self) -> bool:
        busy = {t.slot.name for t in self.tracks.values() if t.status == "running" and t.slot}
        free = [s for s in self.slots if s.name not in busy]
        started = False
        for slot in free:
            t = self._next_in_time()
            if t is None:
                break
            self._launch(t, slot)
            started = True
        return started

    def _next_in_time(self) -> Track | None:
        """The next job to start, passing over (and saying so, once) those that would stop before
        their first epochs in the time --max-minutes leaves; the time left only shrinks, so they
        stay unstarted and the command ends when nothing else runs."""
        for t in self._startable():
            if self.deadline is not None:
                left = self.deadline - time.monotonic()
                need = timing_of(t.job, self.times).startup_warm_s + 60
                if left < need:
                    t.too_late = True
                    self.log(f"{t.job.id} not started: {left:.0f} s left of --max-minutes, less than its "
                             f"start-up (~{need - 60:.0f} s) and a minute of epochs")
                    continue
            return t
        return None

    def _launch(self, t: Track, slot: Slot) -> None:
        job = t.job
        minutes = 0.0
        if self.deadline is not None:
            minutes = max(0.5, (self.deadline - time.monotonic()) / 60.0)
        source = self.by_id.get(job.after) if job.after else None
        cmd = J.command(self.out, job, timing_of(job, self.times).epoch_s, minutes, source,
                        self.learners_of(source) if source else (), self.run_flags)
        os.makedirs(os.path.join(self.out, "logs"), exist_ok=True)
        logf = open(self._log_path(job), "a")
        logf.write(f"\n=== attempt {t.attempts + 1}, slot {slot.name}: {' '.join(cmd)}\n")
        logf.flush()
        t.proc = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, env=slot.env(),
                                  start_new_session=True)
        logf.close()
        t.status, t.slot, t.started = "running", slot, time.monotonic()
        t.attempts += 1
        t.first_epoch_at = t.last_epoch_at = t.end_s = None
        t.epochs_at_start = J.epochs_done(self.out, job)
        self.log(f"start {job.id} on {slot.name} (attempt {t.attempts}"
                 + (f", from epoch {t.epochs_at_start}" if t.epochs_at_start else "") + ")")

    def _log_path(self, job: Job) -> str:
        return os.path.join(self.out, "logs", job.id.replace("/", "_") + ".txt")

    def _reap(self) -> bool:
        changed = False
        for t in self.tracks.values():
            if t.status != "running" or t.proc is None:
                continue
            rc = t.proc.poll()
            if rc is None:
                if t.stop_at is not None and time.monotonic() > t.stop_at:
                    t.proc.kill()
                continue
            changed = True
            t.epoch_s = self._rate(t, between_records=True) or t.epoch_s
            if t.last_epoch_at is not None and t.epochs_at_last > t.epochs_at_first:
                t.end_s = time.monotonic() - t.last_epoch_at
            t.busy_s += time.monotonic() - t.started
            t.proc, t.stop_at = None, None
            if J.is_done(self.out, t.job):
                t.status = "done"
                self.log(f"done {t.job.id} ({hms(time.monotonic() - t.started)} on {t.slot.name})")
            elif rc == 0 or self.stopping:
                t.status = "stopped"
                self.log(f"stopped {t.job.id} at epoch {J.epochs_done(self.out, t.job)} of {t.job.epochs} "
                         "(continues on the next run of this command)")
            else:
                said = J.last_line(self._log_path(t.job))
                t.errors.append(f"exit {rc}: {said}")
                retry = t.attempts < ATTEMPTS
                t.status = "queued" if retry else "failed"
                self.log(f"FAILED {t.job.id} (exit {rc}; its log {self._log_path(t.job)}): {said}"
                         + ("; trying it once more" if retry else "; giving up on it, the others go on"))
        return changed

    def _watch(self, running: Sequence[Track]) -> None:
        now = time.monotonic()
        for t in running:
            if t.job.kind != "run":
                continue
            n = J.epochs_written(self.out, t.job)
            if t.first_epoch_at is None:
                if n > t.epochs_at_start:
                    t.first_epoch_at, t.epochs_at_first = now, n
                    t.last_epoch_at, t.epochs_at_last = now, n
                    t.startup_s = now - t.started
                    self.warm.add(timing_key(t.job))
                    self.on_first_epoch(t.job)
            elif n > t.epochs_at_last:
                t.last_epoch_at, t.epochs_at_last = now, n

    # ------------------------------------------------------------------ what it says
    def _rate(self, t: Track, between_records: bool = False) -> float | None:
        """Measured seconds per epoch of a job after its first epoch, or None: up to now (a
        running job: its progress), or with `between_records` from its first new record to its
        latest (an ended job: what it ran at, without the last checkpoint and the exit after its
        last record, `end_s`, which a short job would otherwise spread over its few epochs: ~10 s,
        +0.35 s an epoch over 30 epochs of fig3-rearrange-geom on an H200)."""
        if t.first_epoch_at is None:
            return None
        if between_records:
            n = t.epochs_at_last - t.epochs_at_first
            return (t.last_epoch_at - t.first_epoch_at) / n if n > 0 else None
        n = J.epochs_written(self.out, t.job) - t.epochs_at_first
        return (time.monotonic() - t.first_epoch_at) / n if n > 0 else None

    def progress(self) -> None:
        counts = {s: sum(t.status == s for t in self.tracks.values())
                  for s in ("done", "running", "queued", "stopped", "failed")}
        left = [t.job for t in self.tracks.values() if t.status in ("running", "queued")]
        done_ep = {t.job.id: J.epochs_written(self.out, t.job) if t.status == "running" else J.epochs_done(self.out, t.job)
                   for t in self.tracks.values() if t.status in ("running", "queued")}
        eta = simulate(left, self.times, len(self.slots), done_ep, warm=self.warm).wall_s if left else 0.0
        busy = counts["running"]
        head = (f"[{hms(time.monotonic() - self.t0)}] {counts['done']} done, {counts['running']} running, "
                f"{counts['queued']} queued" + (f", {counts['stopped']} stopped" if counts["stopped"] else "")
                + (f", {counts['failed']} failed" if counts["failed"] else "")
                + f"; {busy}/{len(self.slots)} {self._slot_word()} busy"
                + (f"; about {hms(eta)} left" if left and not self.stopping else ""))
        lines = [head]
        for t in self.tracks.values():
            if t.status != "running":
                continue
            if t.job.kind == "recon":
                lines.append(f"  {t.job.id:<28} {t.slot.name:<7} drawing ({hms(time.monotonic() - t.started)})")
                continue
            n = J.epochs_written(self.out, t.job)
            rate = self._rate(t)
            what = (f"epoch {n}/{t.job.epochs}, {rate:.2f} s/epoch, about {hms(rate * (t.job.epochs - n))} left"
                    if rate else f"starting ({hms(time.monotonic() - t.started)})" if n <= t.epochs_at_start
                    else f"epoch {n}/{t.job.epochs}")
            lines.append(f"  {t.job.id:<28} {t.slot.name:<7} {what}")
        self.log("\n".join(lines))

    def _slot_word(self) -> str:
        if not self.slots or self.slots[0].gpu is None:
            return "slots"
        return "GPU slots" if self.slots[0].mem_fraction is not None else "GPUs"

    def _write_status(self) -> None:
        data = {"elapsed_s": time.monotonic() - self.t0, "stopping": self.stopping,
                "jobs": {i: t.record() for i, t in self.tracks.items()}}
        tmp = f"{self.status_path}.tmp{os.getpid()}"
        with open(tmp, "w") as f:
            json.dump(data, f, indent=1)
        os.replace(tmp, self.status_path)

    def summary(self) -> dict:
        """What this command did: slots, wall time, busy slot-seconds and utilisation, each job's
        status, attempts, errors and measured epoch time."""
        wall = time.monotonic() - self.t0
        busy = sum(t.busy_s for t in self.tracks.values())
        jobs = {i: t.record() for i, t in self.tracks.items()}
        return {"slots": [dataclasses.asdict(s) for s in self.slots], "wall_s": wall, "busy_s": busy,
                "utilisation": busy / (len(self.slots) * wall) if wall > 0 else None,
                "failed": [i for i, t in self.tracks.items() if t.status == "failed"],
                "unfinished": [i for i, t in self.tracks.items() if t.status in ("queued", "stopped", "running")],
                "jobs": jobs}
