"""Kill a CPU run with SIGKILL at the worst moments and resume it, K times (issue 40).

A small run (`bulbjax run --env CartPole --learners vae --seeds 1 --epochs E --small
--checkpoint-every 1 --keep 2`) is started in a child process and killed at a moment drawn from a
seeded RNG, then continued (`--resume`, or `--overwrite` when no checkpoint was complete yet), and
so on; a run that reaches its last epoch is compared with an uninterrupted reference run and the
next kills go to a new run. The moments (`--kinds`):

  epoch   during the k-th epoch of the stretch (a random time into it)
  append  during the k-th metrics.jsonl append, with half of the epoch's records on disk (the
          child writes each append in two halves with a pause between, as a buffered writer
          does; bulbjax itself appends with one write)
  commit  during the k-th checkpoint, written but not yet committed (orbax renames the finished
          temporary folder; the child pauses just before that rename)
  delete  just before the oldest checkpoint beyond --keep is deleted
  any     a uniform time after the start: start-up, compile, restore, an epoch or a write

The child is this script (`--child`): it marks each moment in a phase file (time, event), adds
the pauses that make the moments long enough to hit, and runs `bulbjax.cli.main`. After each
kill the parent checks the run folder: metrics.jsonl is whole records in order, with no gap or
duplicate (a half line only after an `append` kill), never behind the newest complete
checkpoint; the next stretch must resume from the newest complete checkpoint; a finished run's
metrics.jsonl must equal the reference's byte for byte (on the CPU) and no unfinished checkpoint
folder may be left. JSON (every kill: when, what was happening, the folder after it, where the
resume started, the outcome) goes to benchmarks/results/, a summary to the console.

    python benchmarks/kill_resume.py                       # 30 kills, --small, 6 epochs per run
    python benchmarks/kill_resume.py --size tiny --kills 3 # CI-sized (tests/test_kill_resume.py)
    python benchmarks/kill_resume.py --plan commit:2,append:1 --epochs 3 --size tiny
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import datetime as dt
import json
import os
import platform
import re
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
KINDS = ("epoch", "append", "commit", "delete", "any")
# what the child was doing after its last phase event
DOING = {"start": "start-up (imports, building, tracing, compiling)",
         "restore-begin": "restoring a checkpoint", "restore-end": "after the restore (compiling, first epoch)",
         "epoch": "in an epoch (jitted program running)",
         "append": "starting a metrics.jsonl append", "append-half": "mid metrics.jsonl append (half the records written)",
         "append-done": "after a metrics append (checkpoint next)",
         "ckpt-begin": "writing a checkpoint (orbax, temporary folder)",
         "ckpt-commit": "checkpoint written, its rename to the final name pending",
         "ckpt-delete": "deleting the oldest checkpoint (beyond --keep)",
         "ckpt-end": "after a checkpoint (next epoch or the reports)"}


# ---------------------------------------------------------------------------- the child
def _tiny_config(small):
    """A CI-sized `small_config`: 4 worlds, 32 px, an 8-frame batch, a 20-step probe."""

    def tiny(base):
        c = small(base)
        return c.replace(num_envs=4, resolution=32,
                         ppo=dataclasses.replace(c.ppo, num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1),
                         ppo_updates_per_epoch=1, frames_per_epoch=8, replay_capacity=32,
                         learner=dataclasses.replace(c.learner, batch_size=8, conv_features=(8, 8, 8, 8), hidden=16),
                         learner_batches=1, eval_frames=8, probe_train_frames=16,
                         probe=dataclasses.replace(c.probe, hidden=(16,), steps=20, batch_size=16), reference_steps=16)
    return tiny


def child(a: argparse.Namespace, cli_args: list[str]) -> int:
    """Mark the run's moments in `a.child` (one `time event` line each, flushed), pause where
    asked, then run `bulbjax <cli_args>` in this process."""
    sys.path.insert(0, ROOT)
    phase = open(a.child, "a", buffering=1)

    def mark(event: str) -> None:
        phase.write(f"{time.time():.6f} {event}\n")
        phase.flush()

    mark("start")
    from bulbjax import config
    from bulbjax.epoch import programs
    from bulbjax.report import records
    from bulbjax.run import checkpoint, settings

    if a.tiny:  # where `--small` is resolved (`bulbjax.run.settings` took the name on import)
        settings.small_config = config.small_config = _tiny_config(config.small_config)

    real_epoch = programs.Programs.epoch

    def epoch(self, rs, key, probe=True):
        mark("epoch")
        return real_epoch(self, rs, key, probe)

    programs.Programs.epoch = epoch
    real_append = records.append_whole

    def append(path: str, data: bytes) -> None:
        if os.path.basename(path) != "metrics.jsonl":
            return real_append(path, data)
        mark("append")
        if a.pause_append > 0:  # two writes with a pause between: a kill there leaves half the records
            half = len(data) // 2
            real_append(path, data[:half])
            mark("append-half")
            time.sleep(a.pause_append)
            real_append(path, data[half:])
        else:
            real_append(path, data)
        mark("append-done")

    records.append_whole = append
    real_save, real_restore = checkpoint.Checkpointer.save, checkpoint.Checkpointer.restore

    def save(self, epoch, state, host=None):
        mark(f"ckpt-begin {epoch}")
        real_save(self, epoch, state, host)
        mark(f"ckpt-end {epoch}")

    def restore(self, like, epoch=None):
        mark("restore-begin")
        out = real_restore(self, like, epoch)
        mark(f"restore-end {out[2]}")
        return out

    checkpoint.Checkpointer.save, checkpoint.Checkpointer.restore = save, restore
    from orbax.checkpoint._src.path import async_path, deleter

    real_rename = async_path.rename

    async def rename(src, dst):
        name = os.path.basename(str(dst))
        if ".orbax-checkpoint-tmp" in str(src) and name.isdigit():
            mark(f"ckpt-commit {name}")
            await asyncio.sleep(a.pause_commit)
        return await real_rename(src, dst)

    async_path.rename = rename
    real_delete = deleter.StandardCheckpointDeleter.delete

    def delete(self, step):
        mark(f"ckpt-delete {step}")
        time.sleep(a.pause_delete)
        return real_delete(self, step)

    deleter.StandardCheckpointDeleter.delete = delete
    from bulbjax.cli import main

    rc = main(cli_args)
    mark(f"exit {rc}")
    return rc


# ---------------------------------------------------------------------------- the folder
def read_phases(path: str) -> list[tuple[float, str]]:
    try:
        with open(path) as f:
            lines = f.read().split("\n")[:-1]  # the last piece may be half written
    except FileNotFoundError:
        return []
    out = []
    for line in lines:
        t, _, ev = line.partition(" ")
        out.append((float(t), ev))
    return out


def inspect(run_dir: str, seeds: int) -> dict[str, Any]:
    """The run folder's state: complete and unfinished checkpoints, and metrics.jsonl checked
    for order, gaps, duplicates and a half-written last line."""
    from bulbjax.run import rundir

    path = os.path.join(run_dir, "metrics.jsonl")
    raw = open(path, "rb").read() if os.path.exists(path) else b""
    lines = raw.split(b"\n")
    half = lines[-1] != b""
    whole, bad = [], []
    for i, line in enumerate(lines[:-1]):
        try:
            r = json.loads(line)
            whole.append((r["epoch"], r["seed"]))
        except (ValueError, KeyError):
            bad.append(i)
    expected = [(e, s) for e in range(len(whole) // seeds + 1) for s in range(seeds)][:len(whole)]
    epochs_whole = len(whole) // seeds
    return {"complete_checkpoints": rundir.checkpoint_steps(run_dir),
            "partial_checkpoints": len(rundir.partial_checkpoints(run_dir)),
            "metrics_records": len(whole), "metrics_epochs": epochs_whole,
            "half_line": half, "corrupt_lines": bad, "in_order": whole == expected and len(whole) % seeds == 0}


def metrics_problems(state: dict[str, Any], half_allowed: bool) -> list[str]:
    out = []
    if state["corrupt_lines"]:
        out.append(f"corrupt lines {state['corrupt_lines']} in metrics.jsonl")
    if not state["in_order"]:
        out.append("metrics.jsonl records out of order, missing, doubled or an epoch cut between seeds")
    if state["half_line"] and not half_allowed:
        out.append("half-written last line without an append kill")
    ck = state["complete_checkpoints"]
    if ck and ck[-1] > state["metrics_epochs"]:
        out.append(f"checkpoint {ck[-1]} ahead of the metrics ({state['metrics_epochs']} epochs)")
    return out


# ---------------------------------------------------------------------------- the parent
@dataclasses.dataclass
class Stretch:
    proc: subprocess.Popen
    phase: str
    console: str
    started: float
    how: str = "fresh"  # fresh, overwrite (no complete checkpoint to resume from) or resume
    expect: int | None = None  # resume: the newest complete checkpoint when it started


STRETCH_FLAGS = ["--checkpoint-every", "1", "--keep", "2"]  # per stretch: a resume must repeat them


def run_flags(a: argparse.Namespace) -> list[str]:
    return ["--env", "CartPole", "--learners", "vae", "--seeds", str(a.seeds), "--epochs", str(a.epochs),
            "--small", *STRETCH_FLAGS]


def start(a: argparse.Namespace, run_dir: str, cli_args: list[str], tag: str, pauses: bool = True) -> Stretch:
    phase = os.path.join(a.work, f"{tag}.phases")
    console = os.path.join(a.work, f"{tag}.console")
    cmd = [sys.executable, os.path.abspath(__file__), "--child", phase,
           "--pause-append", str(a.pause_append if pauses else 0), "--pause-commit", str(a.pause_commit if pauses else 0),
           "--pause-delete", str(a.pause_delete if pauses else 0), *(["--tiny"] if a.size == "tiny" else []),
           "--", *cli_args]
    env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "PYTHONUNBUFFERED": "1"}
    out = open(console, "w")
    return Stretch(subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=ROOT), phase, console,
                   time.time())


def stretch_args(a: argparse.Namespace, run_dir: str) -> tuple[list[str], str, int | None]:
    """How the next stretch starts: resume from the newest complete checkpoint, or start afresh
    (over what a run killed before its first checkpoint left: --overwrite)."""
    from bulbjax.run import rundir

    steps = rundir.checkpoint_steps(run_dir)
    if steps:
        return ["run", "--resume", run_dir, *STRETCH_FLAGS], "resume", steps[-1]
    if rundir.holds(run_dir):
        return ["run", *run_flags(a), "--out", run_dir, "--overwrite"], "overwrite", None
    return ["run", *run_flags(a), "--out", run_dir], "fresh", None


def wait_for(s: Stretch, event: str, n: int, timeout: float) -> float | None:
    """Time of the `n`-th `event` (prefix match) of the stretch, or None if it ended first."""
    end = time.time() + timeout
    while time.time() < end:
        hits = [t for t, ev in read_phases(s.phase) if ev.split(" ")[0] == event]
        if len(hits) >= n:
            return hits[n - 1]
        if s.proc.poll() is not None:
            return None
        time.sleep(0.01)
    raise TimeoutError(f"no {event} #{n} within {timeout:.0f} s ({s.console})")


def resumed_from(s: Stretch) -> tuple[int | None, int | None]:
    """The epoch the stretch restored (phase `restore-end N`) and the one its console names
    ("resuming DIR at epoch N"); None where it did not get so far."""
    ends = [ev for _, ev in read_phases(s.phase) if ev.startswith("restore-end")]
    m = re.search(r"resuming .* at epoch (\d+)", open(s.console, errors="replace").read())
    return (int(ends[0].split()[1]) if ends else None), (int(m.group(1)) if m else None)


def choose(a: argparse.Namespace, rng: np.random.Generator, i: int, remaining: int, first: int | None,
           est: dict[str, float]) -> tuple[str, int, float]:
    """(kind, occurrence in this stretch, delay after it) of kill `i`."""
    if a.plan:
        item = a.plan[i % len(a.plan)]
        kind, _, n = item.partition(":")
        n_occ = int(n) if n else 1
    else:
        kinds = list(a.kinds)
        # deletes come only from the third checkpoint of a run on (--keep 2)
        if "delete" in kinds and (first or 0) + remaining < 3:
            kinds.remove("delete")
        kind = str(rng.choice(kinds))
        n_occ = int(rng.integers(1, min(remaining, 3) + 1))
    if kind == "delete":  # occurrence counts deletes: the first comes at checkpoint 3
        n_occ = min(n_occ, max(1, (first or 0) + remaining - 2))
    delay = {"epoch": rng.uniform(0, est["epoch"]), "append": rng.uniform(0.05, 0.9) * a.pause_append,
             "commit": rng.uniform(0.05, 0.9) * a.pause_commit, "delete": rng.uniform(0.05, 0.9) * a.pause_delete,
             "any": rng.uniform(0, est["startup"] + est["epoch"] * remaining)}[kind]
    return kind, n_occ, float(delay)


EVENT = {"epoch": "epoch", "append": "append-half", "commit": "ckpt-commit", "delete": "ckpt-delete", "any": "start"}


def doing_at(phases: list[tuple[float, str]], t: float) -> tuple[str, list[str]]:
    before = [(pt, ev) for pt, ev in phases if pt <= t]
    last = before[-1][1] if before else "start"
    return DOING.get(last.split(" ")[0], last), [ev for _, ev in before[-4:]]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kills", type=int, default=30, help="SIGKILLs in all (default 30)")
    p.add_argument("--epochs", type=int, default=6, help="epochs per run (default 6)")
    p.add_argument("--seeds", type=int, default=1, help="seeds of the run (default 1)")
    p.add_argument("--seed", type=int, default=0, help="seed of the kill schedule")
    p.add_argument("--size", choices=("small", "tiny"), default="small",
                   help="small: the CLI's --small; tiny: smaller still, for CI (the child shrinks --small)")
    p.add_argument("--kinds", default=",".join(KINDS), help=f"kill moments drawn from (default {','.join(KINDS)})")
    p.add_argument("--plan", default="", help="fixed moments instead of random ones, KIND[:N],... (N: the N-th "
                                              "such moment of the stretch)")
    p.add_argument("--pause-append", type=float, default=0.5, help="seconds between an append's halves")
    p.add_argument("--pause-commit", type=float, default=1.0, help="seconds before a checkpoint's commit")
    p.add_argument("--pause-delete", type=float, default=0.5, help="seconds before an old checkpoint's deletion")
    p.add_argument("--timeout", type=float, default=900, help="seconds a stretch may take to reach its moment")
    p.add_argument("--work", default=None, help="folder of the runs (default: a new temporary folder)")
    p.add_argument("--json", default=None, help="result file (default benchmarks/results/kill_resume_<size>_<time>.json)")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    p.add_argument("--tiny", action="store_true", help=argparse.SUPPRESS)
    argv = list(sys.argv[1:] if argv is None else argv)
    cli_args: list[str] = []
    if "--" in argv:
        cli_args = argv[argv.index("--") + 1:]
        argv = argv[:argv.index("--")]
    a = p.parse_args(argv)
    if a.child:
        sys.exit(child(a, cli_args))
    sys.path.insert(0, ROOT)
    a.kinds = tuple(k for k in a.kinds.split(",") if k)
    a.plan = [x for x in a.plan.split(",") if x]
    for k in (*a.kinds, *(x.partition(":")[0] for x in a.plan)):
        if k not in KINDS:
            p.error(f"unknown kill moment {k!r} (one of {', '.join(KINDS)})")
    a.work = a.work or tempfile.mkdtemp(prefix="kill_resume_")
    os.makedirs(a.work, exist_ok=True)
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    a.json = a.json or os.path.join(HERE, "results", f"kill_resume_{a.size}_{stamp}.json")
    rng = np.random.default_rng(a.seed)
    t_all = time.time()

    # the uninterrupted reference, beside the first stretches (no pauses: they change no number)
    ref_dir = os.path.join(a.work, "reference")
    ref = start(a, ref_dir, ["run", *run_flags(a), "--out", ref_dir], "reference", pauses=False)
    est = {"epoch": 3.0 if a.size == "tiny" else 15.0, "startup": 60.0 if a.size == "tiny" else 90.0}
    kills: list[dict[str, Any]] = []
    runs: list[dict[str, Any]] = []
    run_i, stretch_i, pending = 0, 0, None  # pending: the last kill, waiting for its resume
    run_dir = os.path.join(a.work, f"run{run_i}")

    def finish_run(s: Stretch) -> None:
        nonlocal run_i, run_dir
        rc = s.proc.wait()
        runs.append({"dir": run_dir, "exit": rc, "stretches": stretch_i, "kills": [k["i"] for k in kills
                                                                                  if k["run"] == run_i]})
        run_i += 1
        run_dir = os.path.join(a.work, f"run{run_i}")

    while True:
        args, how, expect = stretch_args(a, run_dir)
        if len(kills) >= a.kills and not any(k["run"] == run_i for k in kills):
            break  # every kill made; no run left unfinished
        tag = f"run{run_i}_s{stretch_i}"
        s = start(a, run_dir, args, tag)
        s.how, s.expect = how, expect
        stretch_i += 1
        if len(kills) >= a.kills:  # the last stretch of the last run: to its end
            if s.proc.wait() != 0:
                raise RuntimeError(f"the final stretch failed: {s.console}")
            _resolve(pending, s)
            finish_run(s)
            break
        first = expect or 0
        kind, n_occ, delay = choose(a, rng, len(kills), max(1, a.epochs - first), first, est)
        t_event = wait_for(s, EVENT[kind], 1 if kind == "any" else n_occ, a.timeout)
        if t_event is not None:
            time.sleep(max(0.0, t_event + delay - time.time()))
        if s.proc.poll() is not None or t_event is None:  # the stretch ended before the moment
            rc = s.proc.wait()
            if rc != 0:
                raise RuntimeError(f"stretch {tag} failed (exit {rc}): {s.console}")
            _resolve(pending, s)
            pending = None
            finish_run(s)
            stretch_i = 0
            continue
        t_kill = time.time()
        os.kill(s.proc.pid, signal.SIGKILL)
        s.proc.wait()
        _resolve(pending, s)
        phases_now = read_phases(s.phase)
        doing, tail = doing_at(phases_now, t_kill)
        state = inspect(run_dir, a.seeds)
        eps = [t for t, ev in phases_now if ev == "epoch"]
        if len(eps) >= 2:
            est["epoch"] = float(np.median(np.diff(eps)))
        if eps:
            est["startup"] = eps[0] - s.started
        rec = {"i": len(kills), "run": run_i, "stretch": tag, "started_as": how, "from_epoch": expect,
               "kind": kind, "occurrence": n_occ, "delay_s": round(delay, 3),
               "t_since_start_s": round(t_kill - s.started, 2), "doing": doing, "last_events": tail,
               "state_after_kill": state,
               # a half line is the child's own two-part append (the pause that makes appends
               # hittable), whichever kind of kill landed in it
               "problems": metrics_problems(state, half_allowed=(kind in ("append", "any")
                                                                 or doing.startswith("mid metrics.jsonl append")))}
        kills.append(rec)
        pending = rec
        print(f"kill {rec['i']:>2} {kind:<6} #{n_occ} +{delay:5.2f} s, {rec['t_since_start_s']:6.1f} s into "
              f"{tag}: {doing}; checkpoints {state['complete_checkpoints']} (+{state['partial_checkpoints']} "
              f"unfinished), {state['metrics_epochs']} epochs in metrics{' + half a line' if state['half_line'] else ''}"
              f"{'; PROBLEMS: ' + '; '.join(rec['problems']) if rec['problems'] else ''}", flush=True)

    # the reference, and every finished run against it
    if ref.proc.wait() != 0:
        raise RuntimeError(f"the reference run failed: {ref.console}")
    with open(os.path.join(ref_dir, "metrics.jsonl"), "rb") as f:
        ref_bytes = f.read()
    for r in runs:
        with open(os.path.join(r["dir"], "metrics.jsonl"), "rb") as f:
            got = f.read()
        r["final_equal"] = got == ref_bytes
        r["final_state"] = inspect(r["dir"], a.seeds)
        r["unfinished_checkpoints_left"] = r["final_state"]["partial_checkpoints"]
    failures = [f"kill {k['i']}: {p}" for k in kills for p in k["problems"]]
    failures += [f"kill {k['i']}: the next stretch started {k.get('next_start')} from {k.get('resumed_from')} "
                 f"(console: {k.get('resumed_from_console')}), newest complete checkpoint {k.get('expected_resume_from')}"
                 for k in kills if k.get("resume_ok") is False]
    cfg = json.load(open(os.path.join(ref_dir, "config.json")))["experiment"]
    if a.size == "tiny" and cfg["num_envs"] != 4:
        failures.append(f"--size tiny did not apply (num_envs {cfg['num_envs']}): the child's patch of small_config")
    failures += [f"{r['dir']}: final metrics differ from the reference" for r in runs if not r["final_equal"]]
    failures += [f"{r['dir']}: {r['unfinished_checkpoints_left']} unfinished checkpoint folders left"
                 for r in runs if r["unfinished_checkpoints_left"]]
    by_kind = {k: sum(x["kind"] == k for x in kills) for k in KINDS}
    by_doing: dict[str, int] = {}
    for k in kills:
        by_doing[k["doing"]] = by_doing.get(k["doing"], 0) + 1
    summary = {"kills": len(kills), "by_kind": by_kind, "by_moment": by_doing,
               "resumes_from_newest_complete_checkpoint": sum(k.get("resume_ok") is True for k in kills),
               "resumes_killed_before_restoring": sum(k.get("resume_ok") is None for k in kills),
               "half_lines_cut": sum(k["state_after_kill"]["half_line"] for k in kills),
               "unfinished_checkpoints_at_kill": sum(k["state_after_kill"]["partial_checkpoints"] > 0 for k in kills),
               "runs_finished": len(runs), "runs_equal_to_reference": sum(r["final_equal"] for r in runs),
               "failures": failures, "wall_s": round(time.time() - t_all, 1)}
    out = {"what": "SIGKILL at random moments and resume (benchmarks/kill_resume.py)",
           "command": " ".join(["python", "benchmarks/kill_resume.py", *argv]),
           "time": stamp, "host": platform.node(), "python": platform.python_version(),
           "settings": {k: v for k, v in vars(a).items() if k not in ("child", "tiny", "json")},
           "run_flags": run_flags(a), "reference": {"dir": ref_dir, "console": ref.console,
                                                    "wall_s": round(time.time() - ref.started, 1)},
           "summary": summary, "runs": runs, "kills": kills}
    os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
    with open(a.json, "w") as f:
        json.dump(out, f, indent=1)
    print(f"\n{len(kills)} kills ({', '.join(f'{k} {n}' for k, n in by_kind.items() if n)}), "
          f"{summary['resumes_from_newest_complete_checkpoint']} resumed from the newest complete checkpoint, "
          f"{summary['half_lines_cut']} half-written lines and {summary['unfinished_checkpoints_at_kill']} "
          f"unfinished checkpoints met; {summary['runs_equal_to_reference']} of {len(runs)} finished runs equal "
          f"the uninterrupted run byte for byte; {len(failures)} failures{': ' if failures else ''}"
          + "; ".join(failures) + f"\nwall {summary['wall_s']:.0f} s; results: {a.json}")
    return out


def _resolve(pending: dict[str, Any] | None, s: Stretch) -> None:
    """Fill in where the stretch `s` after kill `pending` started, against the newest complete
    checkpoint the kill left: a resume must restore exactly that one (and say so on the
    console); with none, the stretch starts afresh. `resume_ok` None: `s` was itself killed
    before its restore ended (nothing to check)."""
    if pending is None or "resume_ok" in pending:
        return
    got, said = resumed_from(s)
    pending.update(next_start=s.how, expected_resume_from=s.expect, resumed_from=got, resumed_from_console=said)
    if s.how != "resume":
        pending["resume_ok"] = not pending["state_after_kill"]["complete_checkpoints"]
    elif got is None:
        pending["resume_ok"] = None if s.proc.returncode == -signal.SIGKILL else False
    else:
        newest = pending["state_after_kill"]["complete_checkpoints"][-1]
        pending["resume_ok"] = got == newest == s.expect and (said is None or said == got)


if __name__ == "__main__":
    res = main()
    sys.exit(1 if res["summary"]["failures"] else 0)
