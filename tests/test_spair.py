"""Tests of the SPAIR learner (bulbjax/learners/spair/) and the object probe (eval/objects.py).

Geometry, compositing and the count prior are checked exactly; one small SPAIR (32x32 frames,
4x4 grid, 12 px glimpses) is trained for a few hundred updates on one fixed batch of synthetic
scenes (three coloured squares on a two-colour backdrop) and must put present boxes on the
squares of new scenes, and few elsewhere. The paper-sized model is checked with eval_shape.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.eval.objects import object_scores, summarise
from bulbjax.learners import SPAIR, FrameLearner, LearnerConfig, check_finite, make_learner
from bulbjax.learners.spair import synthetic_scene
from bulbjax.learners.spair.parts import (
    composite,
    count_prior_kl,
    count_prior_log_odds,
    extract_glimpses,
    render_glimpses,
)

RES = 32
STEPS = 200
SMALL = {"spair_grid": 4, "spair_glimpse": 12, "spair_what_dim": 16, "lr": 1e-3, "batch_size": 32,
         "spair_count_decay_steps": 30, "spair_training_wheels": 0}


# ---------------------------------------------------------------------------- geometry
def test_glimpse_round_trip() -> None:
    """A box of exactly g pixels at integer pixels cuts the patch out unchanged, and rendering
    it back puts it in place with zeros elsewhere; at other scales the round trip is close."""
    g, top, left = 8, 5, 17
    rng = np.random.default_rng(0)
    frame = np.zeros((1, RES, RES, 3), np.float32)
    patch = rng.uniform(size=(g, g, 3)).astype(np.float32)
    frame[0, top : top + g, left : left + g] = patch
    centre = jnp.array([[[(top + g / 2) / RES, (left + g / 2) / RES]]])
    size = jnp.full((1, 1, 2), g / RES)
    glimpse = extract_glimpses(jnp.asarray(frame), centre, size, g)
    np.testing.assert_allclose(glimpse[0, 0], patch, atol=1e-6)
    back = render_glimpses(glimpse, centre, size, (RES, RES))
    np.testing.assert_allclose(back[0, 0], frame[0], atol=1e-6)

    # A smooth 16 px patch through a 32 px glimpse (2x upsampling) and back.
    yy, xx = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    smooth = np.stack([yy / 15, xx / 15, (yy + xx) / 30], -1).astype(np.float32)
    frame2 = np.zeros((1, RES, RES, 3), np.float32)
    frame2[0, 8:24, 8:24] = smooth
    c2, s2 = jnp.full((1, 1, 2), 0.5), jnp.full((1, 1, 2), 0.5)
    up = extract_glimpses(jnp.asarray(frame2), c2, s2, 32)
    back2 = render_glimpses(up, c2, s2, (RES, RES))
    np.testing.assert_allclose(back2[0, 0, 9:23, 9:23], smooth[1:-1, 1:-1], atol=0.02)


def test_composite_respects_depth() -> None:
    """Two opaque boxes overlap: the nearer (larger depth) one shows in the overlap whichever
    cell it is; each shows alone in its own part; the background shows outside both."""
    h = w = 8
    red, blue = jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 0.0, 1.0])
    a = jnp.zeros((h, w)).at[1:5, 1:5].set(1.0)
    b = jnp.zeros((h, w)).at[3:7, 3:7].set(1.0)
    alpha = jnp.stack([a, b])[None]  # [1, 2, H, W]
    colour = alpha[..., None] * jnp.stack([red, blue])[None, :, None, None, :]
    bg = jnp.full((1, h, w, 3), 0.5)
    for depth, front in (([3.0, 1.0], red), ([1.0, 3.0], blue)):
        out = composite(colour, alpha, jnp.array([depth]), bg)[0]
        np.testing.assert_allclose(out[4, 4], front, atol=0.01)
        np.testing.assert_allclose(out[1, 1], red, atol=1e-6)
        np.testing.assert_allclose(out[6, 6], blue, atol=1e-6)
        np.testing.assert_allclose(out[0, 7], [0.5, 0.5, 0.5], atol=1e-6)
    # Half-transparent alone: an even blend with the background.
    out = composite(0.5 * colour[:, :1], 0.5 * alpha[:, :1], jnp.zeros((1, 1)), bg)[0]
    np.testing.assert_allclose(out[2, 2], [0.75, 0.25, 0.25], atol=1e-6)


def _count_kl_reference(log_odds, present, prior_log_odds):
    """The original's obj KL, written as its loop over cells (numpy, float64)."""
    b, k = log_odds.shape
    support = np.arange(k + 1)
    q = 1.0 / (1.0 + np.exp(-prior_log_odds))
    dist = np.tile((1 - q) * q**support, (b, 1))
    dist /= dist.sum(1, keepdims=True)
    so_far = np.zeros((b, 1))
    prob = 1.0 / (1.0 + np.exp(-log_odds))
    kl = np.zeros((b, k))
    for i in range(k):
        p_given = np.maximum(support[None] - so_far, 0) / (k - i)
        p_z = np.clip((dist * p_given).sum(1), 1e-6, 1 - 1e-6)
        kl[:, i] = prob[:, i] * (np.log(prob[:, i]) - np.log(p_z)) + (1 - prob[:, i]) * (
            np.log(1 - prob[:, i]) - np.log(1 - p_z))
        s = present[:, i : i + 1].astype(float)
        dist = dist * (s * p_given + (1 - s) * (1 - p_given))
        dist /= np.maximum(dist.sum(1, keepdims=True), 1e-6)
        so_far += s
    return kl


def test_count_prior_kl_matches_the_original() -> None:
    rng = np.random.default_rng(1)
    log_odds = rng.normal(0, 2, (3, 9))
    present = rng.uniform(size=(3, 9)) < 0.4
    for prior in (13.8, 0.0, -4.38):
        ours = count_prior_kl(jnp.asarray(log_odds, jnp.float32), jnp.asarray(present), jnp.float32(prior))
        np.testing.assert_allclose(ours, _count_kl_reference(log_odds, present, prior), rtol=2e-4, atol=2e-5)


def test_annealing_schedule() -> None:
    cfg = LearnerConfig()
    assert float(count_prior_log_odds(cfg, 0)) == pytest.approx(np.log(1e6), rel=1e-5)
    assert float(count_prior_log_odds(cfg, 3000)) == pytest.approx(np.log(1e3 + 0.0125), rel=1e-4)
    assert float(count_prior_log_odds(cfg, 100000)) == pytest.approx(np.log(0.0125), rel=1e-4)


# ---------------------------------------------------------------------------- object probe
def test_object_scores() -> None:
    centres = jnp.array([[[10.0, 10.0], [20.0, 20.0], [5.0, 28.0]], [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]])
    pres = jnp.array([[0.9, 0.8, 0.7], [0.1, 0.2, 0.3]])
    objects = jnp.array([[[11.0, 10.0], [20.0, 24.0]], [[1.0, 1.0], [9.0, 9.0]]])
    sc = jax.jit(functools.partial(object_scores, radius=3.0))(centres, pres, objects)
    np.testing.assert_allclose(sc["distance"][0], [1.0, 4.0])
    assert np.isinf(np.asarray(sc["distance"][1])).all()  # no present box in frame 1
    np.testing.assert_array_equal(sc["found"], [[True, False], [False, False]])
    np.testing.assert_array_equal(sc["nearest"], [[0, 1], [-1, -1]])
    np.testing.assert_array_equal(sc["spurious"], [2, 0])  # boxes 1 and 2 are near no object
    s = summarise(sc, names=("a", "b"))
    assert s["per_object"]["a"] == {"error": 1.0, "found": 0.5}
    assert s["error_mean"] == 2.5 and s["found_share"] == 0.25 and s["missing"] == 0.5
    assert s["spurious_per_frame"] == 1.0 and s["present_per_frame"] == 1.5


# ---------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def trained():
    """SMALL SPAIR after STEPS updates of 32 scenes drawn from 256; evaluated on 64 new ones.
    Also the loss of one fixed batch (same key and step) before and after training."""
    learner = make_learner("spair", 8, SMALL)
    frames, _ = synthetic_scene(jax.random.key(1), 256, RES)
    test_frames, test_pos = synthetic_scene(jax.random.key(2), 64, RES)
    state = jax.jit(functools.partial(learner.init, frame_shape=(RES, RES, 3)))(jax.random.key(0))
    fixed_loss = jax.jit(lambda p: learner.loss(p, frames[:32], jax.random.key(7), jnp.int32(STEPS))[0])
    before = float(fixed_loss(state.params))
    update = jax.jit(learner.update)
    rng = np.random.default_rng(0)
    metrics = []
    for i in range(STEPS):
        state, m = update(state, frames[rng.integers(0, 256, 32)], jax.random.key(100 + i))
        metrics.append(m)
    metrics = jax.device_get(jax.tree.map(lambda *v: jnp.stack(v), *metrics))
    losses = (before, float(fixed_loss(state.params)))
    return learner, state, metrics, test_frames, test_pos, update, losses


def test_loss_falls(trained) -> None:
    learner, state, metrics, *_, losses = trained
    check_finite(metrics, "test_spair")
    assert int(state.step) == STEPS
    before, after = losses
    assert after < before - 0.5 * abs(before), losses  # Gaussian NLL: it goes below 0
    loss = np.asarray(metrics["loss"])
    assert loss[-20:].mean() < loss[0] - 0.5 * abs(loss[0]), loss[::20]
    np.testing.assert_allclose(metrics["loss"], metrics["recon"] + metrics["kl"], rtol=1e-4, atol=1e-2)


def test_boxes_on_the_squares(trained) -> None:
    learner, state, _, frames, pos, *_ = trained
    centres, sizes, pres = jax.jit(learner.boxes)(state.params, frames)
    assert centres.shape == sizes.shape == (64, 16, 2) and pres.shape == (64, 16)
    s = summarise(object_scores(centres, pres, pos, radius=3.0))
    print("SPAIR object probe:", s)
    assert s["found_share"] >= 0.9, s
    assert s["error_mean"] < 2.0, s
    assert s["spurious_per_frame"] < 0.3, s
    # Present boxes are about the squares' size (6 px), not the frame's.
    on = np.asarray(pres) > 0.5
    assert 3.0 < float(np.median(np.asarray(sizes)[on])) < 12.0


def test_encode_reconstruct_shapes(trained) -> None:
    learner, state, _, frames, *_ = trained
    z = jax.jit(learner.encode)(state.params, frames[:8])
    assert learner.latent_dim == 16 * (6 + 16) and z.shape == (8, learner.latent_dim) and z.dtype == jnp.float32
    cells = np.asarray(z).reshape(8, 16, 22)
    assert np.all((cells[..., 4] >= 0) & (cells[..., 4] <= 1))  # presence probabilities
    rec = jax.jit(learner.reconstruct)(state.params, frames[:8])
    assert rec.shape == (8, RES, RES, 3) and rec.dtype == jnp.float32
    assert float(rec.min()) >= 0.0 and float(rec.max()) <= 1.0
    err = float(jnp.abs(rec - frames[:8] / 255.0).mean())
    assert err < 0.12, err  # held-out scenes; a mean-colour frame is ~0.2 off


def test_nan_guard(trained) -> None:
    learner, state, _, frames, _, update, _ = trained
    bad = state.replace(params=jax.tree.map(lambda p: p * jnp.nan, state.params))
    _, metrics = update(bad, frames[:32], jax.random.key(0))
    with pytest.raises(FloatingPointError, match="spair update"):
        check_finite(metrics, "spair update, step 0")
    with pytest.raises(TypeError, match="uint8"):
        learner.encode(state.params, frames.astype(jnp.float32))


# ---------------------------------------------------------------------------- registry
def test_registry_and_paper_shapes() -> None:
    learner = make_learner("spair", 8)
    assert isinstance(learner, SPAIR) and isinstance(learner, FrameLearner) and not learner.sequential
    assert learner.batch_size == 64 and learner.retain_fraction == 0.5 and learner.config.lr == 1e-4
    assert learner.config.spair_grid == 4 and learner.config.spair_glimpse == 28
    six = make_learner("spair", 8, {"spair_grid": 6})
    state = jax.eval_shape(functools.partial(six.init, frame_shape=(64, 64, 3)), jax.random.key(0))
    frames = jax.ShapeDtypeStruct((64, 64, 64, 3), jnp.uint8)
    assert jax.eval_shape(six.encode, state.params, frames).shape == (64, 36 * (6 + 50))
    _, metrics = jax.eval_shape(six.update, state, frames, jax.random.key(0))
    assert metrics["loss"].shape == ()
    with pytest.raises(ValueError, match="spair_grid"):
        LearnerConfig(spair_grid=0)
