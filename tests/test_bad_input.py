"""Bad input through every door, one test per door: the Python API (`env.step` refuses a wrong
shape or dtype when traced, naming the shape it takes), the gymnasium adapters (single and
vector: an action outside the space is gymnasium's `InvalidAction`, also a ValueError), the Brax
wrapper (a wrong shape names the shape) and the command line (a bad flag value is one line,
`bulbjax: error: ...`, exit status 2, naming the flag or value). NaN and out-of-range actions
given to `env.step` itself are repaired and counted (tests/test_nonfinite.py). Nothing here
steps physics: the refusals come before it."""

from __future__ import annotations

import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bulbjax
from bulbjax.cli import main

ENV = "InvertedPendulum"  # the cheapest continuous domain; CartPole for the discrete one


def _abstract_state(env):
    return jax.eval_shape(env.reset, jax.random.PRNGKey(0))


@pytest.mark.parametrize("name, action, expected", [
    ("InvertedPendulum", jnp.zeros((3,)), r"float actions of shape \(3, 1\)"),
    ("InvertedPendulum", jnp.zeros((3, 2)), r"float actions of shape \(3, 1\)"),
    ("InvertedPendulum", jnp.zeros((3, 1), jnp.int32), r"float actions of shape \(3, 1\).*got int32"),
    ("CartPole", jnp.zeros((3,), jnp.float32), r"integer actions of shape \(3,\).*got float32"),
    ("CartPole", jnp.zeros((3, 1), jnp.int32), r"integer actions of shape \(3,\)"),
])
def test_python_api_refuses_wrong_shape_or_dtype_when_traced(name, action, expected):
    env = bulbjax.make(name, num_envs=3, render=False)
    with pytest.raises(ValueError, match=expected):
        jax.eval_shape(env.step, _abstract_state(env), action)  # tracing alone: no physics runs


def test_gymnasium_single_env_refuses_actions_outside_its_space():
    import gymnasium

    import bulbjax.gym  # noqa: F401  registers bulbjax/<Name>-v0
    from bulbjax.gym import InvalidAction

    env = gymnasium.make(f"bulbjax/{ENV}-v0", obs="state", render=False)
    env.reset(seed=0)
    state = env.unwrapped._state
    for bad in (np.array([1.5], np.float32), np.array([np.nan], np.float32), np.array([-np.inf])):
        assert not env.action_space.contains(bad)
        with pytest.raises(gymnasium.error.InvalidAction, match=r"invalid action.*action_space is `Box\(-1.0, 1.0"):
            env.step(bad)
        with pytest.raises(ValueError):  # InvalidAction is a ValueError too
            env.step(bad)
    assert issubclass(InvalidAction, ValueError)
    with pytest.raises(ValueError, match=r"action of shape \(1,\)"):
        env.step(np.zeros(3, np.float32))
    assert env.unwrapped._state is state  # nothing was stepped


def test_gymnasium_vector_env_refuses_actions_outside_its_space():
    import gymnasium

    from bulbjax.interop.gym import make_vec

    venv = make_vec(ENV, 2, obs="state", render=False)
    venv.reset(seed=0)
    state = venv.state
    for bad in (np.array([[0.5], [1.01]], np.float32), np.array([[np.nan], [0.0]])):
        assert not venv.action_space.contains(bad.astype(np.float32))
        with pytest.raises(gymnasium.error.InvalidAction, match=r"world [01];"):
            venv.step(bad)
    with pytest.raises(ValueError, match=r"float actions of shape \(2, 1\)"):
        venv.step(np.zeros((3, 1), np.float32))
    assert venv.state is state  # nothing was stepped
    discrete = make_vec("CartPole", 3, obs="state", render=False)
    discrete.reset(seed=0)
    state = discrete.state
    # the first bad value, its world, how many worlds, the space and the fix (issue 58: the
    # batch's min..max was named)
    with pytest.raises(gymnasium.error.InvalidAction,
                       match=r"invalid action `5` \(world 2; 1 world\(s\) not an integer in \[0, 2\)\)"
                             r"\. The supported action_space is `Discrete\(2\)`: CartPole's actions "
                             r"are integers"):
        discrete.step(np.array([0, 1, 5]))
    with pytest.raises(gymnasium.error.InvalidAction,
                       match=r"invalid action `-1` \(world 0; 2 world\(s\)"):
        discrete.step(np.array([-1, 1, 2]))
    with pytest.raises(gymnasium.error.InvalidAction, match=r"invalid action `0.5` \(world 1;"):
        discrete.step(np.array([0.0, 0.5, 1.0]))
    with pytest.raises(ValueError, match=r"integer actions of shape \(3,\)"):
        discrete.step(np.zeros((3, 2), np.int64))
    assert discrete.state is state
    discrete.step(np.array([0.0, 1.0, 1.0]))  # integral floats are actions


def test_gymnasium_single_discrete_env_names_the_bad_action():
    """`step(2)` and `step(0.7)` of a `Discrete(2)` env name the value and the space (issue 58:
    `2..2`, and "integer actions of shape (1,)" for 0.7)."""
    import gymnasium

    import bulbjax.gym  # noqa: F401

    env = gymnasium.make("bulbjax/CartPole-v0", obs="state", render=False)
    env.reset(seed=0)
    state = env.unwrapped._state
    for bad in (2, 0.7, -1, np.nan):
        with pytest.raises(gymnasium.error.InvalidAction,
                           match=rf"invalid action `{bad}`\. The supported action_space is "
                                 r"`Discrete\(2\)`: CartPole's actions are integers in \[0, 2\)$"):
            env.step(bad)
    with pytest.raises(ValueError, match="takes one integer action"):
        env.step(np.array([0, 1]))
    assert env.unwrapped._state is state


def test_reset_and_make_name_what_they_take():
    """`env.reset(0)` and `make(..., render="rgbd")` say what they take (issue 58: JAX's raw
    PRNG-key TypeError; an answer about `observation`)."""
    env = bulbjax.make("CartPole", num_envs=2, render=False)
    for bad, given in ((0, "int 0"), (np.zeros(3, np.uint32), r"uint32 \(3,\)"),
                       (jax.random.split(jax.random.PRNGKey(0)), r"uint32 \(2, 2\)")):
        with pytest.raises(ValueError,
                           match=rf"reset takes one PRNG key, e\.g\. jax\.random\.PRNGKey\(0\).*{given}"):
            env.reset(bad)
    with pytest.raises(ValueError, match=r"reset takes one PRNG key.*int32 \(\)"):
        jax.eval_shape(env.reset, 0)  # an int traced under jit
    typed = jax.eval_shape(env.reset, jax.random.key(0))  # a typed key is taken as its data
    raw = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    def shapes(tree):
        return jax.tree.map(lambda x: (x.shape, x.dtype), tree)

    assert shapes(typed) == shapes(raw)
    with pytest.raises(ValueError, match=r"render must be True, False or an observation "
                                         r"\(rgb, depth, pointcloud\), got 'rgbd'"):
        bulbjax.make("CartPole", num_envs=2, render="rgbd")


def test_brax_wrapper_refuses_wrong_shape():
    from bulbjax.interop.brax import BraxEnv

    benv = BraxEnv(bulbjax.make(ENV, num_envs=3, render=False))
    state = jax.eval_shape(benv.reset, jax.random.PRNGKey(0))
    for bad in (jnp.zeros((3,)), jnp.zeros((2, 1)), jnp.zeros((3, 1, 1))):
        with pytest.raises(ValueError, match=r"takes actions of shape \(3, 1\)"):
            jax.eval_shape(benv.step, state, bad)
    # the right shape traces (NaN and out-of-range values are then repaired and counted by env.step)
    out = jax.eval_shape(benv.step, state, jnp.zeros((3, 1)))
    assert out.pipeline_state.counts["actions_fixed"].shape == (3,)


@pytest.mark.parametrize("args, message", [
    (["run", "--seed", "-1"], "--seed must be a non-negative integer"),
    (["run", "--epochs", "0"], "epochs must be >= 1, got 0"),
    (["run", "--seeds", "-2"], "seeds must be >= 1, got -2"),
    (["run", "--ppo-updates", "-1"], "ppo_updates_per_epoch must be >= 1"),
    (["run", "--probe-every", "0"], "--probe-every must be >= 1, got 0"),
    (["run", "--keep", "0"], "--keep must be >= 1"),
    (["run", "--max-minutes", "-5"], "--max-minutes must be >= 0"),
    (["run", "--env", "Pendulum"], "unknown environment 'Pendulum'; available: CartPole"),
    (["run", "--learners", "vae,vea"], r"unknown learners \['vea'\]"),
    (["run", "--preset", "fig9"], "unknown preset 'fig9'; available: fig2-cartpole"),
    (["run", "--version", "-1"], "--version must be a non-negative int or 'random'"),
    (["run", "--devices", "0"], "--devices 0: this machine has"),
    (["fit", "--env", "SyntheticMovers", "--seed", "-3"], "--seed must be a non-negative integer"),
    (["fit", "--env", "SyntheticMovers", "--data-worlds", "0"], "--data-worlds must be >= 1, got 0"),
    (["fit", "--env", "SyntheticMovers", "--probe-every", "0"], "--probe-every must be >= 1, got 0"),
    (["fit", "--env", "SyntheticMovers", "--updates", "0"], "--updates must be >= 1, got 0"),
    (["fit", "--env", "SyntheticMovers", "--data-seed", "-1"], "--data-seed must be a non-negative integer"),
    (["fit", "--env", "Nope"], "unknown environment 'Nope'; available: CartPole.*, SyntheticMovers"),
    (["render", "--frames", "0"], "--frames must be >= 1, got 0"),
    (["render", "--steps", "-1"], "--steps must be >= 0"),
])
def test_cli_bad_values_are_one_line_errors(args, message, tmp_path, capsys):
    out = str(tmp_path / "out")
    assert main([*args, "--out", out]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("bulbjax: error: ")
    assert re.search(message, err), err
    assert not os.path.exists(out)  # refused before anything was written


@pytest.mark.parametrize("args, message", [
    (["render", "--env", "FrankaRearrangeGeom"],
     r"need pybullet .*: pip install 'bulbjax\[pybullet\]' \(in a checkout: pip install -e '\.\[pybullet\]'\)$"),
    (["run", "--env", "FrankaRearrangeGeom", "--small", "--epochs", "1", "--seeds", "1"],
     r"need pybullet .*pip install 'bulbjax\[pybullet\]'"),
    (["run", "--env", "ReacherRearrangeYcb", "--small", "--epochs", "1", "--seeds", "1"],
     r"YCB models not found: .*BULBJAX_YCB_DIR is not set"),
    (["run", "--env", "YcbOnIncline", "--small", "--epochs", "1", "--seeds", "1"],
     r"YCB models not found: .*BULBJAX_YCB_DIR is not set"),
])
def test_cli_missing_downloads_are_one_line_errors(args, message, tmp_path, capsys, monkeypatch):
    """A domain whose files come from outside bulbjax (pybullet's Panda, the YCB meshes) without
    them: one line saying what to install or set, for a wheel's user too (issue 65: a 39-line
    traceback ending in a checkout-only `pip install -e`), and no run folder (it held log.txt)."""
    import sys

    monkeypatch.setitem(sys.modules, "pybullet_data", None)  # as without pybullet: importing it fails
    monkeypatch.delenv("BULBJAX_YCB_DIR", raising=False)
    out = str(tmp_path / "out")
    assert main([*args, "--out", out]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("bulbjax: error: "), err
    assert re.search(message, err), err
    assert not os.path.exists(out)  # refused before anything was written
