"""Run folders as `bulbjax run` leaves them (config.json, metrics.jsonl), with synthetic records:
for the tests of commands that only read a run (`report`), without running one."""

from __future__ import annotations

import dataclasses
import json
import os

from bulbjax.config import ExperimentConfig
from bulbjax.report import records

# one probe stream's scores: the overall and per-group normalised errors and their baselines
STREAM = {"overall": {"mae_norm": 0.5, "baseline_norm": 1.4},
          "groups": {"position": {"mae_norm": 0.4, "baseline_norm": 1.5},
                     "velocity": {"mae_norm": 0.6, "baseline_norm": 1.2}}}


def write_synthetic_run(path: str, cfg: ExperimentConfig) -> str:
    """`path` made a run folder of `cfg` with the same scores at every epoch and seed, and PPO's
    return 10 x (epoch + 1); returns `path`."""
    os.makedirs(path)
    with open(os.path.join(path, "config.json"), "w") as f:
        json.dump({"experiment": dataclasses.asdict(cfg), "run": {"seed": 0, "probe_every": 1}}, f)
    probes = {n: {"curr": STREAM, "rand": STREAM} for n in cfg.learners}
    records.write_jsonl(os.path.join(path, "metrics.jsonl"),
                        [{"epoch": e, "seed": s, "rl_return": 10.0 * (e + 1), "probes": probes}
                         for e in range(cfg.epochs) for s in range(cfg.seeds)])
    return path
