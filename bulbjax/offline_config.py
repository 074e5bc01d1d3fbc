"""Configuration of an offline fit (`bulbjax fit`): `OfflineConfig`, an `ExperimentConfig` for the
env, learners and probes plus the fixed dataset's size and the update schedule. Apart from
`bulbjax.config` because a fit computes something else than a run: learners trained on a fixed
dataset of random-policy (or synthetic) worlds, no PPO, no replay."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from bulbjax.config import ExperimentConfig
from bulbjax.data import synthetic


@dataclass(frozen=True)
class OfflineConfig:
    """An offline fit. `base` gives the env, learners, seeds, resolution, learner and probe
    settings (as for `bulbjax run`); the rest sizes the dataset and the schedule.

    The dataset is `data_steps` steps of `data_worlds` random-policy worlds; the held-out set
    `heldout_steps` steps of another `data_worlds` worlds (a different reset key), cut into
    consecutive windows of L steps. `updates_per_call` updates run in one jitted `lax.scan`
    (0: the whole chunk between two probes on an accelerator, 1 on the CPU, where XLA runs the
    conv nets ~10x slower inside a rolled loop)."""

    base: ExperimentConfig = field(default_factory=ExperimentConfig)
    updates: int = 5000
    probe_every: int = 250
    data_worlds: int = 256
    data_steps: int = 200
    heldout_steps: int = 48
    data_seed: int = 0
    updates_per_call: int = 0
    movers: synthetic.MoversConfig | None = None  # SyntheticMovers settings (resolution from base)

    def __post_init__(self) -> None:
        for name in ("updates", "probe_every", "data_worlds", "data_steps", "heldout_steps"):
            if getattr(self, name) < 1:  # named as `bulbjax fit`'s flag, as RunOptions names run's
                raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        lw = max(self.base.window_length, 1)
        if self.data_steps < lw:
            raise ValueError(f"data_steps={self.data_steps} is shorter than a training window ({lw} steps)")
        if self.heldout_steps < self.eval_length:
            raise ValueError(f"heldout_steps={self.heldout_steps} is shorter than a held-out window "
                             f"({self.eval_length} steps)")
        if self.updates_per_call < 0:
            raise ValueError(f"updates_per_call must be >= 0, got {self.updates_per_call}")
        if self.data_seed < 0:
            raise ValueError(f"--data-seed must be a non-negative integer, got {self.data_seed}")

    @property
    def synthetic(self) -> bool:
        return self.base.env == synthetic.NAME

    @property
    def eval_length(self) -> int:
        """Held-out window length: L with sequential learners, else 1."""
        return self.base.seq_len if self.base.window_length else 1

    def replace(self, **kw) -> "OfflineConfig":
        return dataclasses.replace(self, **kw)

    def movers_config(self) -> synthetic.MoversConfig:
        m = self.movers or synthetic.MoversConfig(resolution=self.base.resolution)
        return m if m.resolution == self.base.resolution else m.replace(resolution=self.base.resolution)
