"""Where and how a stretch of a run was made (its `config.json` provenance): command line,
package versions, the bulbjax source (git commit, dirty flag, a hash of the sources), devices and
layout, host, time. The run loop (`loop.py`) records it for every stretch."""

from __future__ import annotations

import datetime
import hashlib
import importlib.metadata
import os
import platform
import shlex
import subprocess
import sys
from typing import Any, Sequence

import jax

from bulbjax.epoch import Experiment, SeedGroups

VERSIONED = ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "mujoco", "mujoco-mjx",
             "mujoco-warp", "warp-lang", "numpy", "bulbjax")


def provenance(argv: Sequence[str] | None = None, experiment: Experiment | SeedGroups | None = None
               ) -> dict[str, Any]:
    """Where and how a stretch of the run was made: command line, package versions, git commit
    of the bulbjax checkout (and whether it had uncommitted changes), devices, host, time."""
    versions = {}
    for pkg in VERSIONED:
        try:
            versions[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            versions[pkg] = None
    devs = jax.devices()
    out = {
        "command": shlex.join(sys.argv if argv is None else argv),
        "cwd": os.getcwd(),
        "time_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "versions": versions,
        "python": platform.python_version(),
        "host": platform.node(),
        "backend": jax.default_backend(),
        "device_kind": devs[0].device_kind,
        "device_count": len(devs),
        **git_state(),
        "source_sha256": source_hash(),
    }
    if isinstance(experiment, SeedGroups):
        out.update(experiment.provenance())
        out["compiler_options"] = dict(experiment.exp.compiler_options)
    elif experiment is not None:
        out["mesh"] = dict(experiment.mesh.shape)
        out["compiler_options"] = dict(experiment.compiler_options)
    return out


def source_hash(package_dir: str | None = None) -> str:
    """SHA-256 of the bulbjax package's Python sources (relative paths and contents, in sorted
    order). Names the code a run used where git cannot: a copy of the tree on another machine
    whose `.git` is stale or missing reports a wrong or no commit, but the same hash as the
    commit's own checkout."""
    root = package_dir or os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    h = hashlib.sha256()
    files = sorted(os.path.relpath(os.path.join(d, f), root)
                   for d, _, fs in os.walk(root) for f in fs if f.endswith(".py"))
    for rel in files:
        h.update(rel.replace(os.sep, "/").encode() + b"\0")
        with open(os.path.join(root, rel), "rb") as f:
            h.update(f.read() + b"\0")
    return h.hexdigest()


def git_state() -> dict[str, Any]:
    """Commit and dirty flag of the git checkout bulbjax is imported from (None outside git)."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

    def git(*args: str) -> str | None:
        try:
            r = subprocess.run(["git", "-C", root, *args], capture_output=True, text=True, timeout=20)
        except (OSError, subprocess.SubprocessError):
            return None
        return r.stdout.strip() if r.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"git_commit": commit, "git_dirty": None if status is None else bool(status)}
