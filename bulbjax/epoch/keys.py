"""The layout of a run's random keys, stated once.

A run draws every random number from two kinds of key: the init key (`Experiment.init_env`,
`Experiment.reference_states` and `Learning.init_learner` each take their part of it) and an
epoch's key (`Experiment.env_data` splits it into its phases' keys). Each split is one function
here returning named keys, so a part that reads one key of a layout names it instead of
repeating the split and indexing by position. The order of the fields is the order of
`jax.random.split`'s output, so the keys, and the numbers of every run, are the ones the
positional splits gave (tested against them).
"""

from __future__ import annotations

from typing import NamedTuple

import jax


class InitKeys(NamedTuple):
    """The init key's five parts."""

    ppo: jax.Array  # PPO's parameters, one key per seed (`Team.seed_keys`)
    learners: jax.Array  # every learner's init, folded in with its position (`Learning.init_learner`)
    worlds: jax.Array  # the worlds' resets and the reference rollout (`WorldKeys`)
    fill: jax.Array  # the random policy's frames that first fill replay
    keep: jax.Array  # which of them the retaining learners keep


class WorldKeys(NamedTuple):
    """`InitKeys.worlds`' four parts: the three sets of worlds' resets and the random policy's
    reference rollout (the reference spread of every state entry)."""

    train: jax.Array
    curr: jax.Array
    rand: jax.Array
    reference: jax.Array


class EpochKeys(NamedTuple):
    """An epoch's key's five parts, one per phase."""

    rl: jax.Array  # PPO's rollouts and updates
    replay: jax.Array  # which of the rollouts' steps enter replay and the window buffers
    learn: jax.Array  # the learners' updates
    eval: jax.Array  # the held-out rollouts of an epoch that probes
    probe: jax.Array  # the probes' fits


def init_keys(key: jax.Array) -> InitKeys:
    """The run's init key as its named parts."""
    return InitKeys(*jax.random.split(key, 5))


def world_keys(key: jax.Array) -> WorldKeys:
    """The run's init key's world part (`InitKeys.worlds`) as its named parts."""
    return WorldKeys(*jax.random.split(init_keys(key).worlds, 4))


def epoch_keys(key: jax.Array) -> EpochKeys:
    """An epoch's key as its phases' keys."""
    return EpochKeys(*jax.random.split(key, 5))
