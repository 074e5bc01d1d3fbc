"""The layout of the run's random keys (`bulbjax.epoch.keys`) is the positional splits the epoch
made before it had names: the same keys, so every run's numbers stay as they were."""

from __future__ import annotations

import jax
import numpy as np

from bulbjax.epoch.keys import epoch_keys, init_keys, world_keys


def test_named_keys_are_the_positional_splits() -> None:
    key = jax.random.PRNGKey(7)
    five = jax.random.split(key, 5)
    init, worlds, epoch = init_keys(key), world_keys(key), epoch_keys(key)
    for named, want in ((init.ppo, five[0]), (init.learners, five[1]), (init.worlds, five[2]),
                        (init.fill, five[3]), (init.keep, five[4]), (epoch.rl, five[0]),
                        (epoch.replay, five[1]), (epoch.learn, five[2]), (epoch.eval, five[3]),
                        (epoch.probe, five[4])):
        np.testing.assert_array_equal(named, want)
    four = jax.random.split(five[2], 4)
    for named, want in zip((worlds.train, worlds.curr, worlds.rand, worlds.reference), four):
        np.testing.assert_array_equal(named, want)
    # the parts differ from each other (a layout that handed one key to two phases would not)
    assert len({tuple(np.asarray(k)) for k in (*init, *worlds)}) == 9
