"""The contrastive learners (`bulbjax.learners.contrastive`: ST-DIM, CURL) on synthetic movers,
where positives are identifiable (consecutive frames of one square, two shifts of one frame):
the InfoNCE loss falls and a probe reads the square's position from the latent far better than
the constant predictor and than the untrained encoder; plus InfoNCE itself and the equal-compute
batches."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.data import sequence, synthetic
from bulbjax.data.sequence import Windows
from bulbjax.epoch.probing import probe_latents
from bulbjax.eval import linear, probe
from bulbjax.learners import learner_names, make_learner
from bulbjax.data.augment import random_shift
from bulbjax.learners.contrastive import info_nce

MOVERS = synthetic.MoversConfig(resolution=16, num_objects=1, size=5.0, max_speed=1.0, episode_length=16)
SMALL = dict(conv_features=(16, 32, 32), hidden=32, lr=2e-3, batch_size=64, sequence_length=8)


def test_info_nce_known_values() -> None:
    n = 8
    # uniform scores: log N; positives far above the rest: ~0 and every anchor right
    loss, acc = info_nce(jnp.zeros((n, n)))
    np.testing.assert_allclose(loss, np.log(n), rtol=1e-6)
    loss, acc = info_nce(jnp.eye(n) * 50.0)
    assert float(loss) < 1e-6 and float(acc) == 1.0
    # invalid pairs are neither anchors nor negatives: as if the matrix were the valid block
    logits = jax.random.normal(jax.random.PRNGKey(0), (n, n))
    valid = jnp.arange(n) < 5
    np.testing.assert_allclose(info_nce(logits, valid)[0], info_nce(logits[:5, :5])[0], rtol=1e-6)


def test_random_shift_moves_content_within_the_pad() -> None:
    x = jnp.zeros((64, 16, 16, 1)).at[:, 8, 8, 0].set(1.0)
    y = random_shift(jax.random.PRNGKey(1), x, 2)
    assert y.shape == x.shape
    where = np.argwhere(np.asarray(y[..., 0]) == 1.0)  # (frame, row, col) of the dot
    assert len(where) == 64 and np.all(np.abs(where[:, 1:] - 8) <= 2)
    assert len({tuple(w) for w in where[:, 1:]}) > 5  # shifted differently per frame


def test_registered_with_equal_compute_batches() -> None:
    assert {"stdim", "curl"} <= set(learner_names())
    stdim = make_learner("stdim", 8, {"sequence_length": 24})
    curl = make_learner("curl", 8)
    assert stdim.sequential and not curl.sequential
    from bulbjax.learners import has_frame_latent_name
    # ST-DIM's latent is one frame's (PPO reads it from frames, `--rl-frames` stacks it); DSA's is not
    assert has_frame_latent_name("stdim") and has_frame_latent_name("curl") and not has_frame_latent_name("dsa")
    assert stdim.batch_size == 1024 // 24 == 42  # windows: 1,008 frames, each encoded once
    assert curl.batch_size == 512  # frames, each encoded twice (query, key)
    assert stdim.retain_fraction == curl.retain_fraction == 0.5
    assert stdim.config.conv_features == curl.config.conv_features == (64, 64, 128, 256)


@pytest.fixture(scope="module")
def data():
    return (synthetic.generate(jax.random.PRNGKey(0), MOVERS, 64, 32),
            synthetic.generate(jax.random.PRNGKey(1), MOVERS, 32, 16))


@pytest.mark.parametrize("name, options", [("stdim", {}), ("stdim", {"stdim_temperature": 0.1}), ("curl", {})])
def test_loss_falls_and_the_probe_reads_position(name: str, options: dict, data) -> None:
    traj, test = data
    learner = make_learner(name, 4, {**SMALL, **options}, action_dim=1)
    state0 = learner.init(jax.random.PRNGKey(2), MOVERS.frame_shape)

    def sample(k):
        if learner.sequential:
            return sequence.sample_windows(traj, k, learner.batch_size, learner.sequence_length)
        return sequence.sample_steps(traj, k, learner.batch_size)[0]

    @jax.jit
    def train(state, key):
        def one(st, k):
            k1, k2 = jax.random.split(k)
            return learner.update(st, sample(k1), k2)
        return jax.lax.scan(one, state, jax.random.split(key, 150))

    state, m = train(state0, jax.random.PRNGKey(3))
    loss = np.asarray(m["loss"])
    assert np.all(np.isfinite(loss)) and loss[-15:].mean() < 0.85 * loss[:15].mean(), loss
    assert float(m["accuracy"][-15:].mean()) > float(m["accuracy"][:15].mean())

    enc = jax.jit(lambda p, f: learner.frame_features(p, f) if learner.sequential else learner.encode(p, f))
    frames, states = sequence.sample_steps(traj, jax.random.PRNGKey(4), 600)
    test_frames = test.frames.reshape((-1,) + test.frames.shape[2:])
    test_states = test.states.reshape((-1, test.states.shape[-1]))
    val = probe.validation_rows(jax.random.PRNGKey(5), 600)

    def ratio(params):  # linear probe's test MAE / the constant's, per entry
        p = linear.fit(enc(params, frames), states, val)
        pred = linear.predict(p, enc(params, test_frames))
        return np.asarray(probe.mae(pred, test_states) / probe.constant_baseline(states, test_states))

    pos = [i for i, e in enumerate(MOVERS.state_spec) if e.group == "position"]
    trained, untrained = ratio(state.params)[pos], ratio(state0.params)[pos]
    assert np.all(trained < 0.6) and np.all(trained < 0.8 * untrained), (trained, untrained)

    if learner.sequential:  # the probe reads one frame's latent (probe_context 1), width Z
        w = sequence.sample_windows(traj, jax.random.PRNGKey(6), 4, learner.sequence_length)
        lat = probe_latents(learner, state.params, w, {"rand": w}, jax.random.PRNGKey(7),
                            probe.ProbeConfig(), 16)
        assert lat["tz"].shape == (16, 4) and lat["held"]["rand"].shape == (4, learner.sequence_length, 4)
        assert isinstance(w, Windows)


def test_one_epoch_of_the_experiment_with_ppo_on_stdim() -> None:
    """Both learners in one epoch of the experiment (stdim from the window buffer, curl from
    replay), PPO observing stdim's latent: losses, MLP and linear probes of both."""
    from bulbjax.epoch import Experiment, ExperimentConfig
    from bulbjax.eval.probe import ProbeConfig
    from bulbjax.learners import LearnerConfig
    from bulbjax.rl.ppo import PPOConfig

    cfg = ExperimentConfig(
        env="CartPole", learners=("stdim", "curl"), seeds=2, epochs=1, num_envs=4, resolution=32,
        sequence_length=4, rl_input="latent:stdim",
        ppo=PPOConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1),
        ppo_updates_per_epoch=1, frames_per_epoch=8, replay_capacity=32,
        learner=LearnerConfig(batch_size=16, conv_features=(8, 8, 8, 8), hidden=16, lr=1e-3),
        learner_batches=2, eval_frames=8, probe_train_frames=16,
        probe=ProbeConfig(hidden=(8,), steps=10, batch_size=16), reference_steps=16)
    exp = Experiment(cfg)
    rs, m = exp.epoch(exp.init(jax.random.PRNGKey(0)), jax.random.PRNGKey(1))
    m = jax.device_get(m)
    d = exp.env.state_dim
    assert exp.learners["stdim"].batch_size == 4 and exp.learners["curl"].batch_size == 8
    for name in ("stdim", "curl"):
        lm = m["learners"][name]
        assert lm["loss"].shape == (2,) and np.all(np.isfinite(lm["loss"])) and np.all(lm["loss"] > 0)
        for stream in ("curr", "rand"):
            p = m["probes"][name][stream]
            assert p["mae"].shape == p["linear_mae"].shape == (2, d)
            assert np.all(np.isfinite(p["mae"])) and np.all(np.isfinite(p["linear_mae"]))
    assert np.all(np.asarray(m["learners"]["stdim"]["pairs"]) > 0)
    # PPO observes stdim's one-frame latent: 2 x the state's dimension, not two steps of it
    assert exp.ppo.obs_size == exp.learners["stdim"].latent_dim == 2 * d
    assert all(np.all(np.isfinite(v)) for v in m["ppo"].values())


def test_stdim_cosine_scores_are_bounded_and_scale_free(data) -> None:
    """With `stdim_temperature` the scores are cosines over T: the loss does not move when the
    score matrices grow (what made the raw bilinear scores diverge in long runs) and stays below
    ln(N) + 2/T; the raw scores' loss moves with their scale."""
    traj, _ = data
    w = sequence.sample_windows(traj, jax.random.PRNGKey(8), 8, SMALL["sequence_length"])
    n = 8 * (SMALL["sequence_length"] - 1)
    for t in (0.0, 0.1):
        learner = make_learner("stdim", 4, {**SMALL, "stdim_temperature": t}, action_dim=1)
        params = learner.init(jax.random.PRNGKey(9), MOVERS.frame_shape).params
        grown = {**params, "w_gl": params["w_gl"] * 50.0, "w_ll": params["w_ll"] * 50.0}
        base, big = (float(learner.loss(p, w, jax.random.PRNGKey(0))[0]) for p in (params, grown))
        if t:
            assert abs(big - base) < 1e-4 and base < 2 * (np.log(n) + 2 / t), (base, big)
        else:
            assert abs(big - base) > 1.0, (base, big)
    with pytest.raises(ValueError, match="stdim_temperature"):
        make_learner("stdim", 4, {**SMALL, "stdim_temperature": -1.0})
