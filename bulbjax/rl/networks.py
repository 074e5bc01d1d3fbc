"""Actor-critic networks for PPO (Flax linen), PureJaxRL style.

Separate actor and critic MLP towers (tanh, orthogonal init) so that the value
loss, whose scale grows with the return, does not distort the policy features.
"""

from __future__ import annotations

from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax.linen.initializers import constant, orthogonal


def _mlp(x: jax.Array, hidden: Sequence[int]) -> jax.Array:
    for width in hidden:
        x = nn.Dense(width, kernel_init=orthogonal(np.sqrt(2)), bias_init=constant(0.0))(x)
        x = nn.tanh(x)
    return x


class Critic(nn.Module):
    """State-value head V(s)."""

    hidden: Sequence[int] = (64, 64)

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        h = _mlp(obs, self.hidden)
        return nn.Dense(1, kernel_init=orthogonal(1.0), bias_init=constant(0.0))(h)[..., 0]


class DiscreteActorCritic(nn.Module):
    """Categorical policy logits and value for discrete action spaces."""

    num_actions: int
    hidden: Sequence[int] = (64, 64)

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        h = _mlp(obs, self.hidden)
        logits = nn.Dense(self.num_actions, kernel_init=orthogonal(0.01), bias_init=constant(0.0))(h)
        return logits, Critic(self.hidden)(obs)


class GaussianActorCritic(nn.Module):
    """Diagonal Gaussian policy (no tanh squashing, state-independent log-std) and value.

    Returns (mean, log_std, value); log_std is broadcast to the mean's shape.
    """

    action_size: int
    hidden: Sequence[int] = (64, 64)
    init_log_std: float = 0.0

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        h = _mlp(obs, self.hidden)
        mean = nn.Dense(self.action_size, kernel_init=orthogonal(0.01), bias_init=constant(0.0))(h)
        log_std = self.param("log_std", constant(self.init_log_std), (self.action_size,))
        return mean, jnp.broadcast_to(log_std, mean.shape), Critic(self.hidden)(obs)


class PixelTorso(nn.Module):
    """Small conv encoder of uint8 frames `[..., H, W, 3]` for PPO from pixels (issue 15's
    baseline): three stride-2 ReLU convolutions (32, 64, 64 channels) and a 256-unit dense layer,
    trained end to end by the PPO loss. Input is scaled to [-0.5, 0.5] here, so PPO's running
    observation statistics are not used for frames."""

    features: int = 256

    @nn.compact
    def __call__(self, frames: jax.Array) -> jax.Array:
        lead = frames.shape[:-3]
        x = frames.reshape((-1,) + frames.shape[-3:]).astype(jnp.float32) / 255.0 - 0.5
        for ch in (32, 64, 64):
            x = nn.Conv(ch, (4, 4), strides=(2, 2), kernel_init=orthogonal(np.sqrt(2)))(x)
            x = nn.relu(x)
        x = x.reshape((x.shape[0], -1))
        x = nn.relu(nn.Dense(self.features, kernel_init=orthogonal(np.sqrt(2)))(x))
        return x.reshape(lead + (self.features,))


class PixelActorCritic(nn.Module):
    """An actor-critic (discrete or Gaussian, as `head`) over the features of a shared
    `PixelTorso`; the torso is shared because separate conv towers double the cost of the
    policy's forward pass for little gain (the usual Atari/DMC choice)."""

    head: nn.Module

    @nn.compact
    def __call__(self, frames: jax.Array):
        return self.head(PixelTorso()(frames))
