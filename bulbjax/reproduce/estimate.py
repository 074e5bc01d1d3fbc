"""How long a plan should take: per-preset epoch and start-up times (`epoch_times.json`, measured
by `benchmarks/epoch_times.py`), each job's cost, and the plan's wall time on G GPUs from the
same queue the scheduler runs (`queue_order`, list scheduling: each free GPU takes the next
job whose inputs are ready).

A job's cost is its start-up plus its epochs left times the preset's epoch time. The first job of
a preset on a host starts cold (XLA compiles the programs); later ones find them in the
persistent compile cache (`bulbjax.compile_cache`, shared by the host's processes) once the first
has compiled, and start warm.

A run job of the plan's "fp32" entry (no `--bf16`, at full size) is timed by the table's
row `<preset> fp32` where one was measured, else by the preset's bf16 row with its epoch times
times `FP32_EPOCH_FACTOR`, marked derived (`timing_of`; `--dry-run` says so).
"""

from __future__ import annotations

import dataclasses
import heapq
import json
import subprocess
from dataclasses import dataclass
from importlib import resources
from typing import Any, Collection, Sequence

from bulbjax.reproduce.plan import Job

TIMES_FILE = "epoch_times.json"


@dataclass(frozen=True)
class Timing:
    """One preset's times on one device kind: seconds per epoch (one seed per process) and from
    process start to the first epoch, cold and warm (`derived`: how an unmeasured entry was
    worked out)."""

    epoch_s: float
    startup_cold_s: float
    startup_warm_s: float
    extra_seed_s: float = 0.0  # seconds each further seed of the same process adds to an epoch
    derived: str = ""

    def epoch_of(self, seeds: int) -> float:
        """Seconds per epoch of a process running `seeds` seeds."""
        return self.epoch_s + self.extra_seed_s * max(0, seeds - 1)


# fp32 epochs over bf16 ones where no fp32 row was measured: InvertedPendulum's, one seed per
# H200, 0.569 s (fp32/fig2-invpend/seed0) against 0.41 s (bf16): 1.39x. The learners' updates run
# ~2x slower in fp32 (a VAE update, batch 1,024, H100: 150.5 against 309.3 /s) and are under half
# of the epoch; PPO's launch-bound rollouts and the rendering are the same in both.
FP32_EPOCH_FACTOR = 1.4
FP32_ROW = "{preset} fp32"  # the table's key of a preset's measured fp32 times


def is_fp32(job: Job) -> bool:
    """Whether `job` is a run of the plan's fp32 entry at full size (no `--small`), its learners
    in fp32 where the table's rows time bf16 ones; the CPU rows are the tiny scale's `--small`
    runs, fp32 as measured, so a tiny fp32 job is timed as its preset."""
    return job.kind == "run" and job.figure == "fp32" and "--bf16" not in job.flags and "--small" not in job.flags


RECON_ROW = "recon {preset}"


def timing_key(job: Job) -> str:
    """The table row that times `job`, and the programs it compiles (a job starts warm after one
    of the same key): "recon", `<preset> fp32` for an fp32 run (`is_fp32`), else its preset."""
    if job.kind == "recon":
        return "recon"
    return FP32_ROW.format(preset=job.preset) if is_fp32(job) else job.preset


def timing_of(job: Job, times: dict[str, Timing]) -> Timing:
    """`job`'s times: its row (`timing_key`); a recon job its preset's `recon <preset>` row where
    the table has one (a locomotion grid took 59 s where InvertedPendulum's took 45), else the
    "recon" row; for an fp32 run without a row of its own, its preset's bf16 row with the epoch
    times x `FP32_EPOCH_FACTOR` (start-ups as they are), its `derived` saying so."""
    key = timing_key(job)
    if key == "recon":
        return times.get(RECON_ROW.format(preset=job.preset), times[key])
    if key in times or key == job.preset:
        return times[key]
    t = times[job.preset]
    return dataclasses.replace(
        t, epoch_s=t.epoch_s * FP32_EPOCH_FACTOR, extra_seed_s=t.extra_seed_s * FP32_EPOCH_FACTOR,
        derived=f"no {key!r} row: {job.preset}'s bf16 epoch times x FP32_EPOCH_FACTOR {FP32_EPOCH_FACTOR} "
                "(bulbjax/reproduce/estimate.py)")


# Jobs side by side on one GPU (`--jobs-per-gpu N`, N > 1), one H200, each job its own process.
# Time-sliced (no MPS), at N = 3 (2026-11-29, fig2-cartpole seeds 3 and 4 and fig2-invpend seed 0):
# 1.076-1.080 s per epoch each against 0.408-0.414 s alone, so the GPU did 1.14x the seed-epochs of
# one job (it was 99% busy); start-up 283-286 s against 186 s alone on a fresh machine (three
# compiles side by side). Under an MPS daemon (`--mps`), at N = 2 (2026-11-29, fig2-invpend seeds 2
# and 3): 0.542-0.545 s per epoch each against 0.410 s alone, 1.51x; their start-ups 49-51 s warm
# (the compile cache carried), as one job's warm start-up (52-54 s), so under MPS the warm start-up
# is taken as it is and the cold one x SHARED_STARTUP (not measured under MPS). Seeds 4 and 5 the
# same way (the sixth allocation): 0.533 s each, 1.54x, start-ups 38-41 s warm; MPS_GAIN keeps the
# lower of the two. Other N are taken at the same gains (an estimate, said in --dry-run). The fp32
# pendulum gains less under MPS (2026-12-01, fp32 seeds 2 and 3: 0.869-0.871 s each against
# 0.562 s alone, 1.29x, start-ups fully cold 205-206 s against 159 x 1.53 = 243; seeds 4 and 5,
# warm: 0.888 s each, 1.27x, start-ups 36 s): with MPS_GAIN those two pairs' estimates were 8% and
# 14% short, so a measured fp32 row (`<preset> fp32`) takes MPS_GAIN_FP32, the lower of the two;
# an fp32 row derived from a bf16 one (`timing_of`) keeps its bf16 row's gain.
SHARED_GAIN = 1.14
SHARED_STARTUP = 1.53
MPS_GAIN = 1.51
MPS_GAIN_FP32 = 1.27


def shared_times(times: dict[str, Timing], jobs_per_gpu: int, mps: bool = False) -> dict[str, Timing]:
    """The table's times for a job running beside `jobs_per_gpu - 1` others on its GPU: its
    epochs `jobs_per_gpu / gain` times as long (`MPS_GAIN` under an MPS daemon, else
    `SHARED_GAIN`; a measured fp32 row under MPS `MPS_GAIN_FP32`), its cold start-up
    `SHARED_STARTUP` times, its warm one too unless under MPS (measured so); unchanged for 1."""
    if jobs_per_gpu <= 1:
        return times
    warm = 1.0 if mps else SHARED_STARTUP

    def shared(key: str, t: Timing) -> Timing:
        if not mps:
            gain, name = SHARED_GAIN, "SHARED_GAIN"
        elif key.endswith(FP32_ROW.format(preset="")):
            gain, name = MPS_GAIN_FP32, "MPS_GAIN_FP32"
        else:
            gain, name = MPS_GAIN, "MPS_GAIN"
        slow = jobs_per_gpu / gain
        note = (f"{jobs_per_gpu} jobs per GPU{' under MPS' if mps else ''}: epochs x {slow:.2f}, "
                f"start-ups x {SHARED_STARTUP} cold / x {warm} warm (estimate.{name})")
        return dataclasses.replace(t, epoch_s=t.epoch_s * slow, extra_seed_s=t.extra_seed_s * slow,
                                   startup_cold_s=t.startup_cold_s * SHARED_STARTUP,
                                   startup_warm_s=t.startup_warm_s * warm,
                                   derived="; ".join(x for x in (t.derived, note) if x))
    return {k: shared(k, t) for k, t in times.items()}


# A job whose learners run on a second GPU (`--learners-apart`, `bulbjax run --overlap apart`):
# the table's row `<preset> apart` where one was measured (an epoch takes about the longer of its
# two sides: fig2-halfcheetah 1.096 s against 1.747 s on one H200), else the preset's one-GPU row:
# an upper bound (its two sides one after the other), marked derived.
APART_ROW = "{preset} apart"


def without_apart_rows(times: dict[str, Timing]) -> dict[str, Timing]:
    """The table's rows for jobs on one GPU each: every row but the `<preset> apart` ones."""
    return {k: t for k, t in times.items() if not k.endswith(APART_ROW.format(preset=""))}


def apart_times(times: dict[str, Timing]) -> dict[str, Timing]:
    """The table's times for jobs with their learners on a GPU of their own: each row's
    `<row> apart` where the table has one, else the row itself marked derived; the apart rows
    themselves are not rows of the result."""
    out = {}
    for k, t in without_apart_rows(times).items():
        row = times.get(APART_ROW.format(preset=k))
        note = "no apart row: its one-GPU times, an upper bound (estimate.apart_times)"
        out[k] = row if row is not None else dataclasses.replace(
            t, derived="; ".join(x for x in (t.derived, note) if x))
    return out


def derived_fp32(jobs: Sequence[Job], times: dict[str, Timing]) -> list[str]:
    """One line per fp32 row `jobs` are estimated with that the table does not hold (`timing_of`
    derived it), for the plan's printout."""
    keys = dict.fromkeys(timing_key(j) for j in jobs if is_fp32(j) and timing_key(j) not in times)
    return [f"{k}: estimated, {timing_of(next(j for j in jobs if timing_key(j) == k), times).derived}"
            for k in keys]


def device_kind(gpus: Sequence[str] = ()) -> str:
    """The kind of this host's first usable GPU as `nvidia-smi` names it ("NVIDIA H100 80GB
    HBM3"), or "cpu" without one. Asks nvidia-smi, not JAX: the scheduler must not take GPU
    memory its workers need."""
    if not gpus:
        return "cpu"
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader", "-i", str(gpus[0])],
                             capture_output=True, text=True, timeout=30)
        name = out.stdout.strip().splitlines()[0].strip() if out.returncode == 0 and out.stdout.strip() else ""
    except (OSError, subprocess.SubprocessError, IndexError):
        name = ""
    return name or "unknown GPU"


def _table() -> dict[str, Any]:
    return json.loads(resources.files("bulbjax.reproduce").joinpath(TIMES_FILE).read_text())


def table_kinds() -> list[str]:
    """The device kinds the table times (nvidia-smi's names, and cpu)."""
    return list(_table()["kinds"])


def load_times(kind: str) -> tuple[dict[str, Timing], str]:
    """The times of `kind` and the kind they are for: the kind's own where the table has it,
    else the table's fallback (an H100's), said in the second value."""
    table = _table()
    kinds = table["kinds"]
    used = kind if kind in kinds else table["fallback"]
    times = {p: Timing(**{k: v for k, v in t.items() if k in Timing.__dataclass_fields__})
             for p, t in kinds[used].items()}
    return times, used


def job_cost(job: Job, times: dict[str, Timing], warm: bool = False, epochs_done: int = 0) -> float:
    """Seconds `job` should hold a GPU: start-up (warm or cold) plus its epochs left at the
    epoch time of its seeds."""
    t = timing_of(job, times)
    start = t.startup_warm_s if warm else t.startup_cold_s
    left = 0 if job.kind == "recon" else max(0, job.epochs - epochs_done)
    return start + left * t.epoch_of(job.seeds)


def queue_order(jobs: Sequence[Job], times: dict[str, Timing]) -> list[Job]:
    """The order GPUs take jobs in: longest (cold) first, so short jobs fill in beside long
    ones at the end; ties keep the plan's order."""
    return sorted(jobs, key=lambda j: (-job_cost(j, times), jobs.index(j)))


@dataclass(frozen=True)
class Estimate:
    """A plan's estimate on `gpus` GPUs: the busy GPU-seconds, the wall time, each job's
    start and end (seconds from the start)."""

    gpus: int
    gpu_s: float
    wall_s: float
    spans: dict[str, tuple[float, float]]

    @property
    def utilisation(self) -> float:
        return self.gpu_s / (self.gpus * self.wall_s) if self.wall_s > 0 else 1.0


def simulate(jobs: Sequence[Job], times: dict[str, Timing], gpus: int,
             epochs_done: dict[str, int] | None = None, finished: Sequence[str] = (),
             warm: Collection[str] = ()) -> Estimate:
    """The schedule the queue makes of `jobs` on `gpus` GPUs (jobs in `finished` skipped, runs
    continued from `epochs_done`): each free GPU takes the first job of `queue_order` whose
    input job (`after`) has ended; a job starts warm when a job of its preset has started and
    compiled (its cold start-up passed) on this host before, or its `timing_key` is in `warm`
    (the compile cache holds its programs: `compile_cache.warm_keys`)."""
    if gpus < 1:
        raise ValueError(f"a plan needs at least one GPU (or CPU slot), got {gpus}")
    done = dict.fromkeys(finished, 0.0)
    ids = {j.id for j in jobs}
    done.update({j.after: 0.0 for j in jobs if j.after and j.after not in ids})  # inputs made before
    epochs_done = epochs_done or {}
    todo = [j for j in queue_order(jobs, times) if j.id not in done]
    free = [(0.0, g) for g in range(gpus)]
    heapq.heapify(free)
    compiled: dict[str, float] = dict.fromkeys(warm, 0.0)  # key -> when its programs are in the cache
    spans: dict[str, tuple[float, float]] = {}
    end_of: dict[str, float] = dict(done)
    gpu_s = 0.0
    while todo:
        now, g = heapq.heappop(free)
        ready = [j for j in todo if j.after is None or j.after in end_of]
        if not ready:  # every job left waits for one that is still running: wait for the next end
            later = min(t for t in (spans[j.after][1] for j in todo if j.after in spans) if t > now)
            heapq.heappush(free, (later, g))
            continue
        j = min(ready, key=lambda x: (max(now, end_of.get(x.after, 0.0)), todo.index(x)))
        start = max(now, end_of.get(j.after, 0.0) if j.after else now)
        key = timing_key(j)
        warm = key in compiled and compiled[key] <= start
        cost = job_cost(j, times, warm, epochs_done.get(j.id, 0))
        t = timing_of(j, times)
        compiled.setdefault(key, start + (t.startup_warm_s if warm else t.startup_cold_s))
        spans[j.id] = (start, start + cost)
        end_of[j.id] = start + cost
        gpu_s += cost
        todo.remove(j)
        heapq.heappush(free, (start + cost, g))
    wall = max((e for _, e in spans.values()), default=0.0)
    return Estimate(gpus, gpu_s, wall, spans)


def fit_jobs(jobs: Sequence[Job], times: dict[str, Timing], gpus: int, minutes: float,
             epochs_done: dict[str, int] | None = None, warm: Collection[str] = ()) -> list[Job]:
    """The unfinished `jobs` (runs continued from `epochs_done`) that fit `minutes` of wall time
    on `gpus` GPUs by `simulate`'s schedule (`warm`: keys that start warm): longest first, a job
    kept when the schedule with it still ends in time, a Fig. 4 job only with the run it reads
    (both kept, or neither). For a
    host held for a limited time (an allocation, a SLURM task's time limit): what it can finish,
    since a job cut short without its checkpoint (a wiped disk) is lost."""
    if minutes <= 0:
        raise ValueError(f"--fit-minutes must be > 0, got {minutes:g}")
    epochs_done = epochs_done or {}
    ids = {j.id for j in jobs}
    units = [[j] + [r for r in jobs if r.after == j.id] for j in jobs
             if j.after is None or j.after not in ids]  # a run with the Fig. 4 job reading it
    cost = {j.id: job_cost(j, times, epochs_done=epochs_done.get(j.id, 0)) for j in jobs}
    chosen: list[Job] = []
    for unit in sorted(units, key=lambda u: -sum(cost[j.id] for j in u)):
        trial = chosen + unit
        if simulate(trial, times, gpus, epochs_done, warm=warm).wall_s <= 60 * minutes:
            chosen = trial
    return [j for j in jobs if j in chosen]


def hours_unit(kind: str) -> str:
    """What a plan's busy hours are hours of on slots of `kind` (`device_kind`): "CPU-hours" on a
    host without a GPU (its slots are CPU worker processes), else "GPU-hours"."""
    return "CPU-hours" if kind == "cpu" else "GPU-hours"


def hms(seconds: float) -> str:
    """Seconds as h:mm:ss."""
    s = int(round(max(0.0, seconds)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def times_markdown() -> str:
    """The table of `epoch_times.json` as markdown (docs/reproduce.md holds it; a test keeps the
    two equal)."""
    table = _table()
    lines = ["| device | preset | s per epoch, 1 seed | + per further seed | start-up cold / warm (s) | source |",
             "|---|---|---|---|---|---|"]
    for kind, presets in table["kinds"].items():
        for preset, t in presets.items():
            lines.append(f"| {kind} | {preset} | {t['epoch_s']} | {t.get('extra_seed_s', 0)} | "
                         f"{t['startup_cold_s']} / {t['startup_warm_s']} | "
                         f"{'measured: ' + t['measured'] if t.get('measured') else 'derived: ' + t.get('derived', '')} |")
    return "\n".join(lines)
