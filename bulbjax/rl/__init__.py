"""Reinforcement learning: PPO (PureJaxRL style) that drives the data-collecting policy."""

from bulbjax.rl.networks import DiscreteActorCritic, GaussianActorCritic
from bulbjax.rl.ppo import (
    PPO,
    PPOConfig,
    PPOState,
    RunningStats,
    Transition,
    compute_gae,
    rollout,
    train,
)

__all__ = [
    "PPO",
    "PPOConfig",
    "PPOState",
    "RunningStats",
    "Transition",
    "compute_gae",
    "rollout",
    "train",
    "DiscreteActorCritic",
    "GaussianActorCritic",
]
