"""A resume (`bulbjax run --resume RUN_DIR`): the run folder's config.json, read once
(`SavedRun`); the config and options a stretch continues the run with, resolved once on it
(`Resume`, made by `resolve.resolve_resume`); and the checks that refuse a resume that would
change what the run computes (its settings, its process count). What was read is handed down:
`run(cfg, opts, run_dir, resume=Resume)` does not read config.json again."""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any

import jax

from bulbjax.config import IDENTITY, ExperimentConfig, RunOptions, read_run_config, run_options_of


@dataclass(frozen=True)
class SavedRun:
    """A run folder's config.json, read once: the ExperimentConfig the run was made with
    (`config`) and the whole JSON (`raw`: `experiment`, `run` options, `provenance`, `resumes`)."""

    run_dir: str
    config: ExperimentConfig
    raw: dict[str, Any]

    @classmethod
    def read(cls, run_dir: str) -> "SavedRun":
        return cls(run_dir, *read_run_config(run_dir))

    @property
    def identity(self) -> dict[str, Any]:
        """The identity options saved (`IDENTITY`; defaults for runs that predate them)."""
        return run_options_of(self.raw)

    @property
    def processes(self) -> int:
        """The process count the run was made with (its first stretch's provenance; 1 before it
        was recorded)."""
        return int(self.raw.get("provenance", {}).get("processes", 1))

    def json(self) -> dict[str, Any]:
        """A copy of config.json's contents, for a stretch to add its own provenance to."""
        return copy.deepcopy(self.raw)


@dataclass(frozen=True)
class Resume:
    """A resumed stretch, resolved once (`resolve.resolve_resume`): the run as saved and the
    config and options this stretch continues it with."""

    saved: SavedRun
    config: ExperimentConfig
    options: RunOptions

    def check(self, processes: int | None = None) -> None:
        """Refuse (ValueError) settings or a process count (default this run's) that would change
        what the run computes."""
        check_resume(self.saved, self.config, self.options)
        check_processes(self.saved, processes)


def config_differences(saved: ExperimentConfig, saved_run: dict[str, Any], cfg: ExperimentConfig,
                       opts: RunOptions) -> list[str]:
    """What a resume would change: every differing config field (nested ones by dotted path,
    `epochs` excepted: a run may be extended) and identity option, as 'field: saved X, given Y'."""
    out = []

    def walk(prefix: str, a: Any, b: Any) -> None:
        if isinstance(a, dict) and isinstance(b, dict):
            for k in sorted(set(a) | set(b)):
                walk(f"{prefix}{k}" if not prefix else f"{prefix}.{k}", a.get(k), b.get(k))
        elif a != b and prefix != "epochs":
            out.append(f"{prefix}: saved {a!r}, given {b!r}")

    walk("", dataclasses.asdict(saved), dataclasses.asdict(cfg))
    for k in IDENTITY:
        if saved_run[k] != getattr(opts, k):
            out.append(f"{k}: saved {saved_run[k]!r}, given {getattr(opts, k)!r}")
    return out


def check_resume(run: str | SavedRun, cfg: ExperimentConfig, opts: RunOptions) -> None:
    """Raise ValueError when `cfg`/`opts` would change what the run (its folder, or its config
    as read) computes."""
    saved = run if isinstance(run, SavedRun) else SavedRun.read(run)
    diff = config_differences(saved.config, saved.identity, cfg, opts)
    if diff:
        raise ValueError(f"--resume {saved.run_dir}: the given settings differ from the run's config.json: "
                         + "; ".join(diff) + ". Resume without those flags (the run keeps its own "
                         "settings; only --epochs may grow), or start a new run with another --out")


def check_processes(saved: SavedRun, processes: int | None = None) -> None:
    """Raise ValueError when this resume runs with another process count (`processes`, default
    this run's) than the run: each process's checkpoints hold its own seed groups."""
    made, now = saved.processes, jax.process_count() if processes is None else processes
    if made != now:
        raise ValueError(f"--resume {saved.run_dir}: the run was made by {made} process(es) and this resume has "
                         f"{now}; each process checkpoints its own seeds, so resume with {made} process(es) "
                         "(the same --num-processes, or the same SLURM/MPI task count)")
