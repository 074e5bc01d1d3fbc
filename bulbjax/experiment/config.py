"""Experiment configuration: one frozen dataclass for a whole run, plus named presets."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from bulbjax.eval.probe import ProbeConfig
from bulbjax.learners import LEARNER_NAMES, LearnerConfig
from bulbjax.rl.ppo import PPOConfig


@dataclass(frozen=True)
class ExperimentConfig:
    """Everything one run needs; defaults follow the paper (Sec. IV.A-B) where it says.

    An epoch is `ppo_updates_per_epoch` PPO updates (each a rollout of `ppo.num_steps` steps of
    `num_envs` worlds per seed), then `frames_per_epoch` of those steps rendered and written into
    replay, then `learner_batches` updates of every learner, then a probe fit and evaluation on
    held-out frames from the current policy and from a random policy."""

    env: str = "CartPole"
    multicolour: bool = False
    learners: tuple[str, ...] = ("vae", "vae_rpl", "beta_vae")
    seeds: int = 3
    epochs: int = 50
    num_envs: int = 64  # the paper's parallel simulators, per seed
    resolution: int = 64
    ppo: PPOConfig = field(default_factory=PPOConfig)
    ppo_updates_per_epoch: int = 1
    frames_per_epoch: int = 1024  # new frames into replay per epoch, per seed
    replay_capacity: int = 5000
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    learner_batches: int = 10  # 10 per epoch for pendulums, 50 for locomotion (paper)
    latent_factor: int = 2  # latent size = factor * true-state dimension (paper: 2)
    eval_frames: int = 512  # held-out frames per stream (pi_curr, pi_rand), per seed
    probe_train_frames: int = 2048
    probe: ProbeConfig = field(default_factory=ProbeConfig)

    def __post_init__(self) -> None:
        unknown = [n for n in self.learners if n not in LEARNER_NAMES]
        if unknown or not self.learners:
            raise ValueError(f"unknown learners {unknown}; accepted: {', '.join(LEARNER_NAMES)}")
        for name in ("seeds", "epochs", "num_envs", "ppo_updates_per_epoch", "learner_batches"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("frames_per_epoch", "eval_frames"):
            v = getattr(self, name)
            if v < self.num_envs or v % self.num_envs:
                raise ValueError(f"{name}={v} must be a positive multiple of num_envs={self.num_envs} "
                                 "(frames are rendered one step of all worlds at a time)")
        steps = self.ppo_updates_per_epoch * self.ppo.num_steps
        if self.frames_per_epoch // self.num_envs > steps:
            raise ValueError(f"frames_per_epoch={self.frames_per_epoch} needs "
                             f"{self.frames_per_epoch // self.num_envs} rollout steps, the epoch has {steps}")
        if self.frames_per_epoch > self.replay_capacity:
            raise ValueError("frames_per_epoch must not exceed replay_capacity")
        if self.ppo.num_envs != self.num_envs:
            object.__setattr__(self, "ppo", dataclasses.replace(self.ppo, num_envs=self.num_envs))

    def replace(self, **kw) -> "ExperimentConfig":
        return dataclasses.replace(self, **kw)


def small_config(base: ExperimentConfig) -> ExperimentConfig:
    """A CPU-sized version of `base` (the README's main job): fewer worlds, a smaller buffer,
    network and batch, so that an epoch takes seconds on 2 cores. Not the paper's settings."""
    return base.replace(
        num_envs=16,
        ppo=dataclasses.replace(base.ppo, num_envs=16, num_steps=64),
        ppo_updates_per_epoch=4,
        frames_per_epoch=128,
        replay_capacity=1024,
        learner=dataclasses.replace(base.learner, batch_size=32, conv_features=(16, 32, 32, 64),
                                    hidden=128, lr=1e-3),
        learner_batches=4,
        eval_frames=128,
        probe_train_frames=512,
        probe=dataclasses.replace(base.probe, steps=300, hidden=(128, 128)),
    )
