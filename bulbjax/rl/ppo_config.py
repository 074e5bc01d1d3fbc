"""`PPOConfig`, PPO's hyperparameters (checked when made), and the learning-rate schedule they
define (`lr_factor`, which `PPO.update` applies to each minibatch step).

Kept apart from the learner (`ppo.PPO`) so that the settings and their meaning read in one place;
`bulbjax.rl.ppo` imports both, so `from bulbjax.rl.ppo import PPOConfig` works as before.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Optional, Sequence

import jax
import jax.numpy as jnp

LR_SCHEDULES = ("linear", "cosine")


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO hyperparameters (defaults tuned for CartPole and InvertedPendulum with 64 envs)."""

    num_envs: int = 64  # the paper's number of parallel simulators (used by `make_env`-style callers)
    num_steps: int = 64  # rollout length per update
    lr: float = 1e-3  # 3e-4 learns too, ~2x slower on InvertedPendulum
    # Learning-rate anneal (`lr_factor`): over `anneal_updates` PPO updates (0: constant lr) from
    # lr to lr * lr_floor, "linear" or "cosine", then constant at the floor. Counted in PPO
    # updates (`PPOState.step`), so a resumed run continues the schedule where it stopped.
    anneal_updates: int = 0
    lr_schedule: str = "linear"
    lr_floor: float = 0.0
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    update_epochs: int = 4
    num_minibatches: int = 8
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    hidden: tuple[int, ...] = (64, 64)
    normalize_obs: bool = True  # running mean/var of observations, kept in PPOState
    obs_clip: float = 10.0  # clip normalised observations to [-obs_clip, obs_clip]
    normalize_advantages: bool = True  # per minibatch
    value_clip_eps: Optional[float] = None  # PPO2-style value clipping; None disables it
    # Rewards are multiplied by this inside the update only. Keeps values O(10) for 1-per-step
    # rewards: unscaled returns (~100) make the value gradient dominate the global-norm clip and
    # starve the policy (CartPole then stalls / drifts).
    reward_scale: float = 0.1
    bootstrap_truncated: bool = True  # see `bulbjax.rl.ppo`'s module docstring
    init_log_std: float = 0.0  # Gaussian policies only
    # Gaussian policies: the log-std parameter is projected onto [min_log_std, inf) after every
    # optimiser step (None: no floor). Without it the solved pendulum's log-std falls without
    # bound (-3 at epoch 100, -4.5 at 1,000) and each update's ratio grows with 1/std (docs/ppo.md).
    min_log_std: Optional[float] = None
    # KL early stop (SB3's rule): a minibatch whose approx KL to the rollout policy, measured
    # before its step, exceeds 1.5 * target_kl is not applied, nor any later one of the update.
    target_kl: Optional[float] = None
    # >0: the observation statistics stop updating after this many PPO updates (frozen, so a
    # solved task's narrowing state distribution no longer moves the inputs); 0: never frozen.
    obs_norm_updates: int = 0
    # PPO from pixels only: > 0, every minibatch step of the update sees its frames shifted by up
    # to this many pixels each way (`data.augment.random_shift`, all stacked frames of a sample
    # together; RAD/DrQ's augmentation), the rollout's log-probabilities and values unshifted;
    # 0: the frames as rendered. In 2 of 3 InvertedPendulum seeds PPO's torso never came to
    # encode the pole without it (docs/results/rl_inputs_frames_h200); with it: not measured yet.
    pixel_shift: int = 0

    def __post_init__(self) -> None:
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {self.lr_schedule!r}")
        if not 0.0 <= self.lr_floor <= 1.0:
            raise ValueError(f"lr_floor is a fraction of lr in [0, 1], got {self.lr_floor}")
        if self.anneal_updates < 0 or self.obs_norm_updates < 0:
            raise ValueError("anneal_updates and obs_norm_updates must be >= 0")
        if self.pixel_shift < 0:
            raise ValueError(f"pixel_shift must be >= 0 (pixels of shift; 0: none), got {self.pixel_shift}")
        if self.target_kl is not None and self.target_kl <= 0:
            raise ValueError(f"target_kl must be > 0 (or None), got {self.target_kl}")


def parse_ppo_options(items: Sequence[str]) -> dict[str, Any]:
    """`KEY=VALUE` strings (a command line's `--ppo-option`s) -> `PPOConfig` field values, each
    converted to the field's type (`none` for the optional fields, e.g. `min_log_std=none`;
    `hidden=128,128`). An unknown key or a value of the wrong type is a ValueError naming them."""
    defaults = PPOConfig()
    fields = {f.name: f for f in dataclasses.fields(PPOConfig)}
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or key not in fields:
            raise ValueError(f"PPO option {item!r} must be KEY=VALUE with KEY one of: {', '.join(sorted(fields))}")
        default = getattr(defaults, key)
        optional = "Optional" in str(fields[key].type)
        try:
            if value.lower() == "none":
                if not optional:
                    raise ValueError("only the optional fields take none")
                out[key] = None
            elif isinstance(default, bool):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError("not a boolean")
                out[key] = value.lower() in ("true", "1")
            elif isinstance(default, tuple):
                out[key] = tuple(int(v) for v in value.split(",") if v.strip())
            elif isinstance(default, int):
                out[key] = int(value)
            elif isinstance(default, str):
                out[key] = value
            else:  # float, or an optional float that defaults to None
                out[key] = float(value)
        except ValueError as err:
            raise ValueError(f"PPO option {item!r}: {value!r} does not fit {key} ({err})") from None
    return out


def lr_factor(config: PPOConfig, updates: jax.Array) -> jax.Array:
    """The learning-rate multiplier after `updates` PPO updates (fractional within an update):
    1 without an anneal; else from 1 to `lr_floor` over `anneal_updates`, linear or cosine, then
    `lr_floor`. With `lr_floor=0` and "linear" it is optax's `linear_schedule` to 0."""
    if config.anneal_updates <= 0:
        return jnp.ones((), jnp.float32)
    p = jnp.clip(jnp.asarray(updates, jnp.float32) / config.anneal_updates, 0.0, 1.0)
    shape = 1.0 - p if config.lr_schedule == "linear" else 0.5 * (1.0 + jnp.cos(jnp.pi * p))
    return config.lr_floor + (1.0 - config.lr_floor) * shape
