"""PPO: GAE against hand-computed values, running obs statistics, act/random_act shapes and
dtypes, determinism under a key, vmapping over seeds, and a short training run on the real
MJX CartPole that must clearly improve the mean episode return."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.rl import PPO, PPOConfig, RunningStats, Transition, compute_gae, train

CFG = PPOConfig(num_envs=8, num_steps=4, num_minibatches=2, update_epochs=2)


def _gae(done, truncated, bootstrap=True):
    r = jnp.array([1.0, 1.0, 1.0])
    v = jnp.array([0.5, 0.4, 0.3])
    return compute_gae(r, v, jnp.array(done), jnp.array(truncated), jnp.array(0.2), 0.9, 0.8, bootstrap)


def test_gae_hand_computed_termination():
    # gamma 0.9, lambda 0.8, episode terminates at t=1, bootstrap V=0.2 after t=2:
    # d2 = 1 + .9*.2 - .3 = .88            A2 = .88
    # d1 = 1 + 0 - .4 = .6 (terminal)       A1 = .6
    # d0 = 1 + .9*.4 - .5 = .86             A0 = .86 + .9*.8*.6 = 1.292
    adv, target = _gae([0.0, 1.0, 0.0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(adv, [1.292, 0.6, 0.88], rtol=1e-6)
    np.testing.assert_allclose(target, [1.792, 1.0, 1.18], rtol=1e-6)


def test_gae_hand_computed_truncation():
    # Truncated at t=1: reward gets + gamma * V(s_1) = .36 -> d1 = .96, A0 = .86 + .72*.96 = 1.5512.
    adv, _ = _gae([0.0, 1.0, 0.0], [0.0, 1.0, 0.0])
    np.testing.assert_allclose(adv, [1.5512, 0.96, 0.88], rtol=1e-6)
    # Without bootstrapping, truncation is a termination.
    adv, _ = _gae([0.0, 1.0, 0.0], [0.0, 1.0, 0.0], bootstrap=False)
    np.testing.assert_allclose(adv, [1.292, 0.6, 0.88], rtol=1e-6)


def test_gae_matches_reference_loop_batched():
    rng = np.random.default_rng(0)
    T, N, g, lam = 7, 3, 0.97, 0.9
    r, v = rng.normal(size=(T, N)), rng.normal(size=(T, N))
    d = (rng.random((T, N)) < 0.3).astype(np.float32)
    tr = d * (rng.random((T, N)) < 0.5)
    lv = rng.normal(size=N)
    adv, _ = compute_gae(*map(jnp.asarray, (r, v, d, tr, lv)), g, lam, True)
    ref, gae, nv = np.zeros((T, N)), np.zeros(N), lv
    for t in reversed(range(T)):
        rt = r[t] + g * tr[t] * v[t]
        delta = rt + g * nv * (1 - d[t]) - v[t]
        gae = delta + g * lam * (1 - d[t]) * gae
        ref[t], nv = gae, v[t]
    np.testing.assert_allclose(adv, ref, rtol=1e-5, atol=1e-5)


def test_running_stats_match_numpy():
    rng = np.random.default_rng(1)
    a, b = rng.normal(2.0, 3.0, size=(5, 10, 3)), rng.normal(-1.0, 0.5, size=(7, 3))
    s = RunningStats.create(3).update(jnp.asarray(a)).update(jnp.asarray(b))
    allx = np.concatenate([a.reshape(-1, 3), b])
    np.testing.assert_allclose(s.mean, allx.mean(0), rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(s.var, allx.var(0), rtol=1e-3)


@pytest.mark.parametrize("discrete", [True, False])
def test_act_shapes_dtypes_and_log_prob(discrete):
    ppo = PPO(CFG, obs_size=5, num_actions=3 if discrete else None, action_size=2)
    state = ppo.init(jax.random.PRNGKey(0))
    obs = jax.random.normal(jax.random.PRNGKey(1), (8, 5))
    action, logp, value = jax.jit(ppo.act)(state, obs, jax.random.PRNGKey(2))
    assert logp.shape == value.shape == (8,)
    assert logp.dtype == value.dtype == jnp.float32
    assert bool(jnp.all(logp <= 0.0)) if discrete else bool(jnp.all(jnp.isfinite(logp)))
    if discrete:
        assert action.shape == (8,) and action.dtype == jnp.int32
        assert bool(jnp.all((action >= 0) & (action < 3)))
    else:
        assert action.shape == (8, 2) and action.dtype == jnp.float32
        env_a = ppo.env_action(action * 10.0)
        assert bool(jnp.all(jnp.abs(env_a) <= 1.0))
    # log_prob of the sampled action is what the loss recomputes.
    re_logp, ent, re_v = ppo._evaluate(state.params, ppo.normalize(state, obs), action)
    np.testing.assert_allclose(re_logp, logp, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(re_v, value, rtol=1e-5, atol=1e-5)
    assert bool(jnp.all(ent > 0))
    # deterministic acting gives the mode
    a_det, _, _ = ppo.act(state, obs, jax.random.PRNGKey(3), deterministic=True)
    a_det2, _, _ = ppo.act(state, obs, jax.random.PRNGKey(4), deterministic=True)
    np.testing.assert_array_equal(a_det, a_det2)


@pytest.mark.parametrize("discrete", [True, False])
def test_random_act(discrete):
    ppo = PPO(CFG, obs_size=4, num_actions=2 if discrete else None, action_size=3)
    a = ppo.random_act(jax.random.PRNGKey(0), 1000)
    if discrete:
        assert a.shape == (1000,) and a.dtype == jnp.int32
        assert set(np.unique(a).tolist()) == {0, 1}
    else:
        assert a.shape == (1000, 3) and a.dtype == jnp.float32
        assert float(a.min()) >= -1.0 and float(a.max()) <= 1.0 and float(jnp.abs(a).max()) > 0.9


def _flat(tree) -> np.ndarray:
    return np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])


def _fake_traj(ppo: PPO, state, key, T=4, N=8, obs_size=5):
    """A synthetic (but self-consistent) trajectory: actions and log-probs come from the policy."""
    k_obs, k_act, k_r = jax.random.split(key, 3)
    obs = jax.random.normal(k_obs, (T, N, obs_size)) * 2.0 + 1.0
    action, logp, value = jax.vmap(ppo.act, in_axes=(None, 0, 0))(state, obs, jax.random.split(k_act, T))
    reward = jax.random.uniform(k_r, (T, N))
    done = jnp.zeros((T, N)).at[2, :3].set(1.0)
    truncated = jnp.zeros((T, N)).at[2, 0].set(1.0)
    return Transition(obs, action, reward, done, truncated, logp, value), obs[-1]


@pytest.mark.parametrize("discrete", [True, False])
def test_update_determinism_and_effect(discrete):
    ppo = PPO(CFG, obs_size=5, num_actions=2 if discrete else None, action_size=1)
    s0 = ppo.init(jax.random.PRNGKey(0))
    s0b = ppo.init(jax.random.PRNGKey(0))
    for a, b in zip(jax.tree.leaves(s0), jax.tree.leaves(s0b)):
        np.testing.assert_array_equal(a, b)
    other = ppo.init(jax.random.PRNGKey(1))
    assert not np.allclose(_flat(s0.params), _flat(other.params))

    traj, last_obs = jax.jit(lambda s, k: _fake_traj(ppo, s, k))(s0, jax.random.PRNGKey(2))
    upd = jax.jit(ppo.update)
    s1, m1 = upd(s0, traj, last_obs, jax.random.PRNGKey(3))
    s1b, m1b = upd(s0, traj, last_obs, jax.random.PRNGKey(3))
    for a, b in zip(jax.tree.leaves((s1, m1)), jax.tree.leaves((s1b, m1b))):
        np.testing.assert_array_equal(a, b)
    assert int(s1.step) == 1
    assert all(np.isfinite(float(v)) for v in m1.values())
    assert not np.allclose(_flat(s1.params), _flat(s0.params))
    # obs statistics moved towards the data (mean 1, std 2)
    np.testing.assert_allclose(s1.obs_stats.mean, traj.obs.reshape(-1, 5).mean(0), atol=1e-3)
    # the first minibatch starts on-policy, so the updates stay small
    assert float(m1["approx_kl"]) < 0.05


def test_vmap_over_seeds():
    ppo = PPO(CFG, obs_size=5, num_actions=2)
    seeds = jax.random.split(jax.random.PRNGKey(0), 3)
    states = jax.jit(jax.vmap(ppo.init))(seeds)
    obs = jax.random.normal(jax.random.PRNGKey(1), (3, 8, 5))
    a, lp, v = jax.jit(jax.vmap(ppo.act))(states, obs, seeds)
    assert a.shape == lp.shape == v.shape == (3, 8)
    traj, last_obs = jax.jit(jax.vmap(lambda s, k: _fake_traj(ppo, s, k)))(states, seeds)
    new, metrics = jax.jit(jax.vmap(ppo.update))(states, traj, last_obs, seeds)
    assert new.step.shape == (3,) and metrics["total_loss"].shape == (3,)


def test_training_improves_real_cartpole():
    """Short PPO run on MJX CartPole (16 worlds): the mean finished-episode return must rise."""
    import bulbjax

    env = bulbjax.make("CartPole", num_envs=16, render=False)
    cfg = PPOConfig(num_envs=16, num_steps=64)
    t0 = time.time()
    state, metrics = train(env, cfg, jax.random.PRNGKey(0), num_updates=20)
    ret = np.asarray(metrics["mean_episode_return"])
    elapsed = time.time() - t0
    print(f"CartPole PPO 20 updates x 1024 steps: {elapsed:.1f}s, returns {ret.round(1).tolist()}")
    assert int(state.step) == 20
    assert np.all(np.isfinite(ret))
    early, late = ret[:3].mean(), ret[-5:].mean()
    assert late > 2.0 * early and late > 100.0, (early, late)


def _bandit_frames(key: jax.Array, n: int) -> tuple[jax.Array, jax.Array]:
    """16x16 frames with a white square on the left or right half; the side is the label."""
    side = jax.random.bernoulli(key, 0.5, (n,)).astype(jnp.int32)
    cols = jnp.arange(16)
    lit = jnp.where(side[:, None] == 1, cols[None] >= 10, cols[None] < 6)  # [n, 16]
    rows = (jnp.arange(16) >= 5) & (jnp.arange(16) < 11)
    img = (rows[None, :, None] & lit[:, None, :]).astype(jnp.uint8) * 255
    return jnp.repeat(img[..., None], 3, -1), side


# shift 2 in the slow tier: the shift's effect on an update is test_pixel_shift_moves_the_update_and_only_for_frames
@pytest.mark.parametrize("shift", [0, pytest.param(2, marks=pytest.mark.slow)])
def test_pixel_ppo_learns_a_visual_bandit(shift: int):
    """PPO from pixels (`frame_shape`): the conv torso and the policy learn, from the PPO loss
    alone, which action a frame rewards (the square's side); a state-free task only the pixels
    can solve. Random play is right half the time. With `pixel_shift` 2 the update sees the
    frames shifted by up to 2 px (the sides stay apart) and learns as well."""
    cfg = PPOConfig(num_steps=4, num_minibatches=2, update_epochs=4, lr=1e-3, reward_scale=1.0, pixel_shift=shift)
    ppo = PPO(cfg, 0, num_actions=2, frame_shape=(16, 16, 3))
    assert ppo.pixels and ppo.obs_size == 0
    state = ppo.init(jax.random.PRNGKey(0))

    @jax.jit
    def one_update(state, key):
        k_obs, k_act, k_upd = jax.random.split(key, 3)
        frames, side = _bandit_frames(k_obs, 4 * 32)
        frames = frames.reshape((4, 32) + frames.shape[1:])
        action, logp, value = ppo.act(state, frames.reshape((-1,) + frames.shape[2:]), k_act)
        reward = (action == side).astype(jnp.float32).reshape(4, 32)
        ones = jnp.ones((4, 32))
        traj = Transition(frames, action.reshape(4, 32), reward, ones, 0 * ones, logp.reshape(4, 32),
                          value.reshape(4, 32))
        state, m = ppo.update(state, traj, frames[-1], k_upd)
        return state, reward.mean()

    acc = []
    for i in range(60):
        state, r = one_update(state, jax.random.PRNGKey(i + 1))
        acc.append(float(r))
    assert np.mean(acc[:3]) < 0.75, acc[:3]
    frames, side = _bandit_frames(jax.random.PRNGKey(999), 256)
    greedy, _, _ = ppo.act(state, frames, jax.random.PRNGKey(0), deterministic=True)
    assert float((greedy == side).mean()) > 0.95, float((greedy == side).mean())
    # frames are not normalised with running statistics (the torso scales them)
    assert float(state.obs_stats.count) < 1.0


def test_pixel_shift_moves_the_update_and_only_for_frames():
    """`pixel_shift` changes a pixel policy's update (its minibatches see shifted frames) and
    nothing else: a state policy's update is the same bit for bit; a negative shift is refused."""
    frames, side = _bandit_frames(jax.random.PRNGKey(3), 4 * 8)
    frames = frames.reshape((4, 8) + frames.shape[1:])
    ones = jnp.ones((4, 8))

    def updated(shift: int, pixels: bool):
        cfg = PPOConfig(num_steps=4, num_minibatches=2, update_epochs=1, pixel_shift=shift)
        ppo = PPO(cfg, 0 if pixels else 3, num_actions=2, frame_shape=(16, 16, 3) if pixels else None)
        state = ppo.init(jax.random.PRNGKey(0))
        obs = frames if pixels else jnp.tile(side.reshape(4, 8, 1).astype(jnp.float32), (1, 1, 3))
        action, logp, value = ppo.act(state, obs.reshape((32,) + obs.shape[2:]), jax.random.PRNGKey(1))
        traj = Transition(obs, action.reshape(4, 8), ones, ones, 0 * ones, logp.reshape(4, 8), value.reshape(4, 8))
        return jax.tree.leaves(ppo.update(state, traj, obs[-1], jax.random.PRNGKey(2))[0].params)

    moved = [not np.array_equal(a, b) for a, b in zip(updated(0, True), updated(3, True))]
    assert any(moved)
    assert all(np.array_equal(a, b) for a, b in zip(updated(0, False), updated(3, False)))
    with pytest.raises(ValueError, match="pixel_shift"):
        PPOConfig(pixel_shift=-1)
