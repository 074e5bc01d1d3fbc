"""Run folders: what an earlier run left in one, refusing to start over it by accident, and
checking that it can be written before anything runs.

`bulbjax run --out DIR` (and `bulbjax fit --out DIR`) on a folder that holds a run stops with one
line naming the run and the two ways on (`--resume`, or `--overwrite` to start afresh): one
repeated command must not delete a long run's checkpoints. A folder that cannot be written
(read-only, full) is an error before the environment is built, not after minutes of compiling.
The metrics in it are appended whole (`bulbjax.report.records.append_whole`).
"""

from __future__ import annotations

import errno
import glob
import json
import os
from typing import Any, Sequence

CHECKPOINT_DIR = "checkpoints"  # as `bulbjax.run.checkpoint.CHECKPOINT_DIR` (no orbax import here)
RUN_FILES = ("config.json", "metrics.jsonl", "metrics.jsonl.gz")  # a `bulbjax run`'s own files
FIT_FILES = ("config.json", "curves.jsonl")  # a `bulbjax fit`'s own files
LOG_FILE = "log.txt"
DELETING = ".deleting-"  # `checkpoints.deleting-<pid>`: an earlier run's checkpoints on their way out


def log_name(process: int = 0) -> str:
    """The log file of a run's process: `log.txt` (process 0), `log_process<i>.txt` (others)."""
    return LOG_FILE if process == 0 else f"log_process{process}.txt"


class RunFolderExists(ValueError):
    """A fresh run was asked to start in a folder that holds a run (neither resume nor overwrite)."""


def _steps_in(d: str) -> set[int]:
    try:
        names = os.listdir(d)
    except OSError:
        return set()
    return {int(n) for n in names if n.isdigit() and os.path.isdir(os.path.join(d, n))}


def checkpoint_steps(run_dir: str) -> list[int]:
    """Epochs (or updates) of the complete checkpoints in `run_dir/checkpoints`, oldest first.
    Orbax writes a checkpoint into `<step>.orbax-checkpoint-tmp-<n>` and renames it to `<step>`
    once complete, so a folder named by digits alone is a complete checkpoint. A multi-process
    run keeps one folder per process (`process_<i>/<step>`): the steps every process has."""
    d = os.path.join(run_dir, CHECKPOINT_DIR)
    procs = sorted(glob.glob(os.path.join(glob.escape(d), "process_*")))
    if procs:
        return sorted(set.intersection(*(_steps_in(p) for p in procs)))
    return sorted(_steps_in(d))


def partial_checkpoints(run_dir: str) -> list[str]:
    """Unfinished checkpoint folders (a process killed while writing one); orbax removes them when
    the run's next stretch opens its checkpoints."""
    d = glob.escape(os.path.join(run_dir, CHECKPOINT_DIR))
    return sorted(glob.glob(os.path.join(d, "*.orbax-checkpoint-tmp*"))
                  + glob.glob(os.path.join(d, "process_*", "*.orbax-checkpoint-tmp*")))


def holds(run_dir: str, files: Sequence[str] = RUN_FILES) -> list[str]:
    """What in `run_dir` belongs to a run: those of `files` that exist, and `checkpoints` when it
    holds a checkpoint (complete or not). An empty `checkpoints` folder (a run stopped while
    compiling) or other files (a dataset cache, log.txt) do not make a run."""
    out = [f for f in files if os.path.exists(os.path.join(run_dir, f))]
    if checkpoint_steps(run_dir) or partial_checkpoints(run_dir):
        out.append(CHECKPOINT_DIR)
    return out


def _read_records(path: str) -> list[dict[str, Any]]:
    """The whole JSON records of a metrics file (a half-written or unreadable line skipped): what
    a run folder holds, read here rather than through `records` (which writes through this module)."""
    try:
        with open(path) as f:
            lines = f.read().split("\n")
    except OSError:
        return []
    out = []
    for line in lines:
        if line.strip():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return out


def describe(run_dir: str, fit: bool = False) -> str:
    """One phrase naming what `run_dir` holds: env, learners and progress, e.g. "CartPole
    (vae, vae_rpl), 3 of 6 epochs in metrics.jsonl, newest checkpoint at epoch 3"."""
    parts, raw = [], None
    try:
        with open(os.path.join(run_dir, "config.json")) as f:
            raw = json.load(f)
    except FileNotFoundError:
        parts.append("no config.json")
    except (OSError, ValueError):
        parts.append("config.json unreadable")
    exp = (raw or {}).get("base" if fit else "experiment", raw if raw and "env" in raw else None)
    total = None
    if isinstance(exp, dict) and "env" in exp:
        learners = ", ".join(exp.get("learners") or ())
        parts.append(f"{exp['env']}" + (f" ({learners})" if learners else ""))
        total = (raw.get("offline", {}).get("updates") if fit else exp.get("epochs"))
    elif raw is not None:
        other = "experiment" in raw if fit else "offline" in raw
        parts.append(f"the config.json of a `bulbjax {'run' if fit else 'fit'}`" if other
                     else "a config.json of another kind")
    unit = "updates" if fit else "epochs"
    name = "curves.jsonl" if fit else "metrics.jsonl"
    path = os.path.join(run_dir, name)
    if not os.path.exists(path) and not fit and os.path.exists(path + ".gz"):
        path, name = path + ".gz", name + ".gz"
    if os.path.exists(path):
        recs = _read_records(path)
        if fit:
            done = max((r.get("update", 0) for r in recs), default=0)
        else:
            done = len({r.get("epoch") for r in recs})
        parts.append(f"{done}{f' of {total}' if total else ''} {unit} in {name}")
    steps = checkpoint_steps(run_dir)
    parts.append(f"newest checkpoint at {unit[:-1]} {steps[-1]}" if steps else "no complete checkpoint")
    return ", ".join(parts)


def check_out_dir(run_dir: str, *, resume: bool, overwrite: bool, fit: bool = False) -> None:
    """Before a run starts in `run_dir`: refuse to start afresh over a run unless `overwrite`,
    refuse `resume` with `overwrite`, create the folder and check that it can be written. Raises
    ValueError (`RunFolderExists` for a run in the way) with one line that says what to do.
    Idempotent: the CLI calls it before opening the run's log file, `run` again."""
    cmd = "bulbjax fit" if fit else "bulbjax run"
    if resume and overwrite:
        raise ValueError("--resume continues the run in its folder and --overwrite deletes it: give one of them")
    if os.path.exists(run_dir) and not os.path.isdir(run_dir):
        raise ValueError(f"--out {run_dir} is a file, not a folder: give a folder for the run")
    if not resume and not overwrite:
        found = holds(run_dir, FIT_FILES if fit else RUN_FILES)
        if found:
            how = (f"`{cmd} ... --out {run_dir} --resume` (its own flags)" if fit
                   else f"`{cmd} --resume {run_dir}` (--epochs N to extend it)")
            raise RunFolderExists(f"{run_dir} holds a run ({describe(run_dir, fit)}): continue it with {how}, "
                                  f"or start afresh with --overwrite (deletes its {'curves' if fit else 'metrics'}, "
                                  "checkpoints and plots), or give another --out")
    try:
        os.makedirs(run_dir, exist_ok=True)
    except OSError as err:
        raise ValueError(f"cannot create the run folder {run_dir}: {_oserror(err)}; give another --out") from err
    probe_writable(run_dir)


def _oserror(err: OSError) -> str:
    code = errno.errorcode.get(err.errno or 0, "")
    return f"{err.strerror or err}" + (f" ({code})" if code else "")


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def probe_writable(run_dir: str, size: int = 65536) -> None:
    """Create, write `size` bytes to, sync and remove a file in `run_dir`: a read-only or full
    folder is a clear error now rather than a lost epoch later."""
    import socket

    path = os.path.join(run_dir, f".bulbjax-write-probe-{socket.gethostname()}-{os.getpid()}")
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(fd, b"\0" * size)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.remove(path)
    except OSError as err:
        try:
            os.remove(path)
        except OSError:
            pass
        raise ValueError(f"cannot write to the run folder {run_dir}: {_oserror(err)}; "
                         "give a writable --out (or free space there)") from err


def remove_tree(path: str) -> None:
    """Delete the folder `path`, renaming it first (atomic): a process killed meanwhile leaves no
    half-deleted checkpoint that a resume would take for a complete one."""
    import shutil

    if os.path.isdir(path):
        gone = f"{path}{DELETING}{os.getpid()}"
        os.rename(path, gone)
        shutil.rmtree(gone)


def remove_stale_temporaries(run_dir: str) -> None:
    """Temporary files of an atomic rewrite (`<name>.tmp<pid>`) and checkpoint folders being
    deleted (`checkpoints.deleting-<pid>`) that a killed process left."""
    import shutil

    for p in glob.glob(os.path.join(glob.escape(run_dir), "*" + DELETING + "*")):
        shutil.rmtree(p, ignore_errors=True)
    for name in ("config.json", "metrics.jsonl", "curves.jsonl"):
        for p in glob.glob(os.path.join(glob.escape(run_dir), glob.escape(name) + ".tmp*")):
            if p[len(os.path.join(run_dir, name)) + 4:].isdigit():
                try:
                    os.remove(p)
                except OSError:
                    pass
