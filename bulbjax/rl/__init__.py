"""Reinforcement learning: PPO (PureJaxRL style) that drives the data-collecting policy."""

from bulbjax.rl.networks import DiscreteActorCritic, GaussianActorCritic
from bulbjax.rl.ppo import (
    PPO,
    PPOState,
    RunningStats,
    Transition,
    compute_gae,
    floor_log_std,
    mean_log_std,
    rollout,
    train,
)
from bulbjax.rl.ppo_config import LR_SCHEDULES, PPOConfig, lr_factor

__all__ = [
    "PPO",
    "PPOConfig",
    "PPOState",
    "RunningStats",
    "Transition",
    "compute_gae",
    "floor_log_std",
    "lr_factor",
    "mean_log_std",
    "LR_SCHEDULES",
    "rollout",
    "train",
    "DiscreteActorCritic",
    "GaussianActorCritic",
]
