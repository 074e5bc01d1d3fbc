"""Non-finite physics and bad actions never reach a returned state: a world whose physics goes
NaN is reset (an ended episode, reward 0) and counted in `EnvState.counts`; NaN actions act as
0 and out-of-range ones as the nearest bound, counted; an epoch reports the resets of PPO's
worlds as `nonfinite_resets`, and its replay holds only finite states. CPU, a few worlds."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bulbjax
from bulbjax.envs.base import COUNTS

N = 3


@pytest.fixture(scope="module")
def pend():
    env = bulbjax.make("InvertedPendulum", num_envs=N, render=False)
    return env, jax.jit(env.step), env.reset(jax.random.PRNGKey(0))


def _poison(s, world: int, value: float = np.nan):
    return s.replace(data=s.data.replace(qvel=s.data.qvel.at[world].set(value)))


def test_reset_starts_every_count_at_zero(pend):
    _, _, s = pend
    assert set(s.counts) == set(COUNTS)
    assert all(np.array_equal(np.asarray(v), np.zeros(N, np.int32)) for v in s.counts.values())


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_nonfinite_world_is_reset_and_counted(pend, value):
    env, step, s = pend
    a = jnp.zeros((N, 1))
    clean = jax.device_get(step(s, a))
    out = jax.device_get(step(_poison(s, 1, value), a))
    # world 1: its episode ended (terminated, not truncated), reward 0, a fresh episode started
    assert out.done[1] == 1.0 and out.truncated[1] == 0.0 and out.reward[1] == 0.0
    assert out.step_count[1] == 0 and out.episode_return[1] == 0.0
    assert out.info["episode_length"][1] == 1
    assert out.counts["nonfinite_resets"].tolist() == [0, 1, 0]
    assert out.counts["nonfinite_entries"][1] > 0 and out.counts["nonfinite_entries"][[0, 2]].tolist() == [0, 0]
    # nothing non-finite anywhere in what the step returns (state, obs, raw state, Data)
    for leaf in jax.tree.leaves(out):
        if np.issubdtype(np.asarray(leaf).dtype, np.inexact):
            assert np.all(np.isfinite(leaf))
    # the new episode's state is a reset state: upright, within the reset distribution
    assert np.all(np.abs(out.data.qpos[1]) < 0.1) and np.all(np.abs(out.data.qvel[1]) < 0.1)
    # the other worlds are untouched, bit for bit
    for w in (0, 2):
        np.testing.assert_array_equal(out.obs[w], clean.obs[w])
        np.testing.assert_array_equal(out.data.qpos[w], clean.data.qpos[w])
    assert clean.counts["nonfinite_resets"].tolist() == [0, 0, 0] and not clean.done.any()


def test_counts_accumulate_and_survive_resets(pend):
    env, step, s = pend
    a = jnp.zeros((N, 1))
    s = step(_poison(s, 0), a)
    s = step(_poison(s, 0), a)
    s = step(_poison(s, 2), jnp.array([[np.nan], [0.5], [3.0]]))
    assert np.asarray(s.counts["nonfinite_resets"]).tolist() == [2, 0, 1]
    assert np.asarray(s.counts["actions_fixed"]).tolist() == [1, 0, 1]


def test_nan_and_out_of_range_actions_are_repaired_and_counted(pend):
    env, step, s = pend
    bad = step(s, jnp.array([[np.nan], [5.0], [-np.inf]]))
    good = step(s, jnp.array([[0.0], [1.0], [-1.0]]))
    np.testing.assert_array_equal(np.asarray(bad.obs), np.asarray(good.obs))  # NaN -> 0, clipped to [-1, 1]
    assert np.asarray(bad.counts["actions_fixed"]).tolist() == [1, 1, 1]
    assert np.asarray(good.counts["actions_fixed"]).tolist() == [0, 0, 0]
    assert np.all(np.isfinite(np.asarray(bad.obs)))


def test_discrete_actions_are_clipped_and_counted():
    env = bulbjax.make("CartPole", num_envs=2, render=False)
    s = env.reset(jax.random.PRNGKey(1))
    step = jax.jit(env.step)
    bad, good = step(s, jnp.array([7, -3], jnp.int32)), step(s, jnp.array([1, 0], jnp.int32))
    np.testing.assert_array_equal(np.asarray(bad.obs), np.asarray(good.obs))
    assert np.asarray(bad.counts["actions_fixed"]).tolist() == [1, 1]


def test_epoch_reports_nonfinite_resets_and_keeps_replay_finite():
    """An epoch whose PPO worlds start from a NaN world: that seed's record counts the reset,
    and no replay state (what the probes train on) is NaN."""
    from bulbjax.epoch import Experiment, ExperimentConfig
    from bulbjax.eval.probe import ProbeConfig
    from bulbjax.learners import LearnerConfig
    from bulbjax.report import records
    from bulbjax.rl.ppo import PPOConfig

    cfg = ExperimentConfig(
        env="CartPole", learners=("vae",), seeds=2, epochs=1, num_envs=4, resolution=16,
        ppo=PPOConfig(num_envs=4, num_steps=4, num_minibatches=1, update_epochs=1),
        ppo_updates_per_epoch=1, frames_per_epoch=8, replay_capacity=16,
        learner=LearnerConfig(batch_size=4, conv_features=(4, 4, 4, 4), hidden=8),
        learner_batches=1, eval_frames=4, probe_train_frames=8,
        probe=ProbeConfig(hidden=(8,), steps=2, batch_size=4), reference_steps=4)
    exp = Experiment(cfg)
    rs = exp.init(jax.random.PRNGKey(0))
    # world 1 of seed 0 (worlds are laid out [seed 0's N, seed 1's N])
    rs = rs.replace(train_env=_poison(rs.train_env, 1))
    rs, m = exp.epoch(rs, jax.random.PRNGKey(1), probe=False)
    m, rs = jax.device_get(m), jax.device_get(rs)
    assert m["nonfinite_resets"].tolist() == [1, 0]
    recs = records.epoch_records(0, m, exp.spec)
    assert [r["nonfinite_resets"] for r in recs] == [1, 0]
    for buf in rs.buffers.values():
        assert np.all(np.isfinite(buf.states))
    assert np.all(np.isfinite(rs.train_env.data.qpos)) and np.all(np.isfinite(rs.train_env.obs))


def test_gym_adapter_never_shows_a_nan_last_observation():
    """gymnasium's NEXT_STEP autoreset shows an ended episode's last observation: for a world whose
    physics went non-finite that is its last finite one (before the step), then the new episode."""
    from bulbjax.interop.gym import make_vec

    venv = make_vec("InvertedPendulum", N, obs="state", render=False)
    venv.reset(seed=0)
    before = np.asarray(venv.state.lowdim)
    venv._state = _poison(venv.state, 1)  # as if the physics had gone NaN in world 1
    a = np.zeros((N, 1), np.float32)
    obs, rew, term, trunc, info = venv.step(a)
    assert term.tolist() == [False, True, False] and not trunc.any() and rew[1] == 0.0
    assert np.all(np.isfinite(obs))
    np.testing.assert_array_equal(obs[1], before[1])
    obs, rew, term, trunc, info = venv.step(a)  # the new episode's first observation, reward 0
    assert np.all(np.isfinite(obs)) and rew[1] == 0.0 and not term[1]
    np.testing.assert_array_equal(obs[1], np.asarray(venv.state.lowdim)[1])
    assert np.asarray(venv.state.counts["nonfinite_resets"]).tolist() == [0, 1, 0]
