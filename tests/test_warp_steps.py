"""An env step's substeps as one MJX-Warp call (`envs.warp_steps.multi_step`,
`EnvConfig.fuse_substeps`): the locomotion domains step in one call per env step, and their
episodes are those of MJX's separate calls bit for bit (every leaf of the state: Data,
observations, rewards, ends); the domains whose action is more than the controls, or that step
once without a kinematics pass, keep the separate calls; bad values are one line. And every
MuJoCo Warp callable keeps enough captured CUDA graphs for an epoch (`envs.warp_graphs`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import warp  # annotations of the Warp callables in test_warp_graph_cache_holds_an_epoch

import bulbjax
from bulbjax.envs import warp_steps

N, STEPS = 4, 3


def _episode(env):
    @jax.jit
    def run(key):
        def body(st, k):
            a = jax.random.uniform(k, (N, env.action_size), minval=-1.0, maxval=1.0)
            return env.step(st, a), None
        return jax.lax.scan(body, env.reset(key), jax.random.split(jax.random.PRNGKey(5), STEPS))[0]
    return run(jax.random.PRNGKey(2))


@pytest.mark.parametrize("name", ["HalfCheetah", "Ant"])
def test_fused_substeps_are_the_separate_calls_bit_for_bit(name):
    fused = bulbjax.make(name, num_envs=N, render=False)
    separate = bulbjax.make(name, num_envs=N, render=False, fuse_substeps=False)
    assert fused._fused_substeps and not separate._fused_substeps
    end_a, end_b = _episode(fused), _episode(separate)
    a, b = jax.tree.leaves(end_a), jax.tree.leaves(end_b)
    assert len(a) == len(b)
    differ = [i for i, (x, y) in enumerate(zip(a, b)) if not np.array_equal(x, y, equal_nan=True)]
    assert not differ, f"{len(differ)} of {len(a)} state leaves differ"
    start = fused.reset(jax.random.PRNGKey(2))  # the steps moved the bodies (the kinematics too)
    assert not np.allclose(start.data.qpos, end_a.data.qpos)
    assert not np.allclose(start.data.xpos, end_a.data.xpos)


def test_only_domains_with_several_calls_and_plain_controls_fuse():
    assert warp_steps.available()
    cartpole = bulbjax.make("CartPole", num_envs=2, render=False)
    assert not cartpole._fused_substeps  # one step, no kinematics


def test_bad_values_are_one_line():
    with pytest.raises(ValueError, match="at least one substep"):
        warp_steps.multi_step(0, True)
    with pytest.raises(ValueError, match="fuse_substeps must be True or False"):
        bulbjax.make("HalfCheetah", num_envs=2, render=False, fuse_substeps="yes")


def test_warp_graph_cache_holds_an_epoch() -> None:
    """Every MuJoCo Warp callable that stepping and rendering made keeps `GRAPH_CACHE_MAX`
    captured CUDA graphs (Warp's own default, 32, made GPU epochs re-capture graphs every
    epoch); a limit passed to `warp.jax_callable` explicitly is kept."""
    from bulbjax.envs import warp_graphs

    env = bulbjax.make("InvertedPendulum", num_envs=N, resolution=64)
    s = jax.eval_shape(env.reset, jax.random.PRNGKey(0))  # traces: makes the callables
    jax.eval_shape(env.step, s, jnp.zeros((N, env.action_size)))
    limits = warp_graphs.limits()
    assert len(limits) >= 2 and set(limits.values()) == {warp_graphs.GRAPH_CACHE_MAX}, limits

    def double(x: warp.array(dtype=float), y: warp.array(dtype=float)) -> None:
        pass

    def triple(x: warp.array(dtype=float), y: warp.array(dtype=float)) -> None:
        pass

    assert warp.jax_callable(double, num_outputs=1, graph_cache_max=7).graph_cache_max == 7
    assert warp.jax_callable(triple, num_outputs=1).graph_cache_max == warp_graphs.GRAPH_CACHE_MAX
    with pytest.raises(ValueError, match="at least 1"):
        warp_graphs.install(0)
