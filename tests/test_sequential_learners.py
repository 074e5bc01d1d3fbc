"""Sequential learners (svae, pred, dsa): loss falls on a fixed batch of moving-square windows,
per-step latent shapes, padding ignored, equalised batch sizes, input errors, DSA variants.

Training uses a reduced network at 32x32; the paper-sized network is checked with
jax.eval_shape (shapes only, no compile)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.data.sequence import Windows
from bulbjax.learners import (
    DSA_ENCODERS,
    LEARNER_NAMES,
    SEQUENCE_LEARNER_NAMES,
    SequenceLearner,
    check_finite,
    make_learner,
)

RES, B, L, K, LATENT, ACT = 32, 4, 6, 2, 4, 2
STEPS = 50
SMALL = {"conv_features": (8, 8, 16, 16), "hidden": 32, "lr": 2e-3, "sequence_length": L,
         "pred_horizon": K}


def moving_squares(b: int, t: int, seed: int = 0) -> Windows:
    """Windows of a square moving at a constant random velocity; one-hot actions; the last
    window ends early (valid False from step L-2 on, its frames there noise)."""
    rng = np.random.default_rng(seed)
    frames = np.zeros((b, t, RES, RES, 3), np.uint8)
    states = np.zeros((b, t, 2), np.float32)
    for i in range(b):
        x, v = rng.integers(0, RES - 8), rng.integers(-2, 3)
        for s in range(t):
            xx = int(np.clip(x + v * s, 0, RES - 8))
            frames[i, s, 12:20, xx:xx + 8] = (200, 120, 60)
            states[i, s] = (xx, v)
    valid = np.ones((b, t), bool)
    valid[-1, L - 2:] = False
    frames[-1, L - 2:] = rng.integers(0, 256, size=frames[-1, L - 2:].shape)
    actions = np.eye(ACT, dtype=np.float32)[rng.integers(0, ACT, size=(b, t))] * valid[..., None]
    return Windows(jnp.asarray(frames), jnp.asarray(actions), jnp.asarray(states), jnp.asarray(valid))


WINDOWS = moving_squares(B, L + K)


@pytest.fixture(scope="module", params=SEQUENCE_LEARNER_NAMES)
def trained(request):
    learner = make_learner(request.param, LATENT, SMALL, action_dim=ACT)

    @jax.jit
    def run(key):
        k_init, k_steps = jax.random.split(key)
        state = learner.init(k_init, (RES, RES, 3))
        state, metrics = jax.lax.scan(lambda s, k: learner.update(s, WINDOWS, k), state,
                                      jax.random.split(k_steps, STEPS))
        return state, metrics, learner.encode(state.params, WINDOWS), learner.reconstruct(state.params, WINDOWS)

    return (learner, *run(jax.random.key(0)))


def test_loss_falls(trained) -> None:
    learner, state, metrics, _, _ = trained
    check_finite(metrics, f"{learner} test")
    loss = np.asarray(metrics["loss"])
    assert loss.shape == (STEPS,) and int(state.step) == STEPS
    assert loss[-5:].mean() < 0.6 * loss[0], loss
    np.testing.assert_allclose(metrics["loss"], metrics["recon"] + learner.config.beta * metrics["kl"], rtol=1e-5)
    # the last window's padded steps (from L-2 on) are left out of the loss
    expected = 1 - (learner.window_length - (L - 2)) / (B * learner.window_length)
    np.testing.assert_allclose(metrics["valid_frac"], expected, rtol=1e-6)


def test_per_step_latents(trained) -> None:
    learner, _, _, z, rec = trained
    assert isinstance(learner, SequenceLearner) and learner.sequential
    assert z.shape == (B, L, LATENT) and z.dtype == jnp.float32 and np.all(np.isfinite(z))
    assert not np.allclose(z[:, 0], z[:, -1])  # latents differ over time
    assert rec.shape == (B, learner.window_length, RES, RES, 3)
    assert float(rec.min()) >= 0 and float(rec.max()) <= 1


def test_encode_from_per_frame_features(trained) -> None:
    """`encode_features` on `frame_features` computed one frame at a time (as PPO's rolling
    window keeps them) gives `encode`'s latents; bad shapes are clear errors."""
    learner, state, _, z, _ = trained
    w = WINDOWS.head(L)
    one_by_one = jnp.concatenate([learner.frame_features(state.params, w.frames[:, t:t + 1])
                                  for t in range(L)], axis=1)
    z2 = learner.encode_features(state.params, one_by_one, w.actions)
    np.testing.assert_allclose(np.asarray(z2), np.asarray(z), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="features"):
        learner.encode_features(state.params, one_by_one[:, :-1], w.actions[:, :-1])
    with pytest.raises(TypeError, match="uint8"):
        learner.frame_features(state.params, w.frames.astype(jnp.float32))


def test_padding_does_not_change_the_loss(trained) -> None:
    """Padded steps' reconstruction terms are masked out: their target frames never matter, and
    for the causal svae their input frames do not either."""
    learner, state, _, _, _ = trained
    key = jax.random.key(5)
    base = learner.loss(state.params, WINDOWS, key)[1]["loss"]
    first = L if type(learner).__name__ == "PRED" else L - 2  # PRED's steps >= L are targets only
    if type(learner).__name__ == "DSA":
        first = L + K  # DSA's encoders see the whole window: nothing to change
    other = WINDOWS.replace(frames=WINDOWS.frames.at[-1, first:].set(0))
    np.testing.assert_allclose(learner.loss(state.params, other, key)[1]["loss"], base, rtol=1e-6)
    # a valid frame does change it
    changed = WINDOWS.replace(frames=WINDOWS.frames.at[0, 0].set(255))
    assert learner.loss(state.params, changed, key)[1]["loss"] != base


def test_registry_and_equalised_batches() -> None:
    assert LEARNER_NAMES == ("vae", "vae_rpl", "beta_vae", "svae", "pred", "dsa", "spair", "spair6")
    for name in SEQUENCE_LEARNER_NAMES:
        learner = make_learner(name, 8, {"sequence_length": 24}, action_dim=2)
        assert learner.retain_fraction == 0.5 and learner.config.lr == 1e-4
        assert learner.batch_size == 1024 // 24 == 42
    assert make_learner("pred", 8, {"sequence_length": 16, "pred_horizon": 4}).window_length == 20
    assert make_learner("svae", 8, {"sequence_length": 16}).batch_size == 64
    assert make_learner("vae", 8).batch_size == 1024 and not make_learner("vae", 8).sequential
    with pytest.raises(ValueError, match="svae, pred, dsa"):
        make_learner("lstm_vae", 8)
    with pytest.raises(ValueError, match="dsa_encoder"):
        make_learner("dsa", 8, {"dsa_encoder": "transformer"})
    with pytest.raises(ValueError, match="sequence_length"):
        make_learner("svae", 8, {"sequence_length": 1})


def test_input_errors(trained) -> None:
    learner, state, _, _, _ = trained
    short = WINDOWS.head(L - 1)
    with pytest.raises(ValueError, match="wrong sequence length"):
        learner.encode(state.params, short)
    with pytest.raises(ValueError, match="action_dim"):
        learner.encode(state.params, WINDOWS.replace(actions=WINDOWS.actions[..., :1]))
    with pytest.raises(TypeError, match="uint8"):
        learner.encode(state.params, WINDOWS.replace(frames=WINDOWS.frames.astype(jnp.float32)))
    with pytest.raises(TypeError, match="Windows"):
        learner.encode(state.params, WINDOWS.frames)


@pytest.mark.parametrize("encoder", DSA_ENCODERS)
def test_dsa_variants_build(encoder: str) -> None:
    """Every DSA variant initialises and encodes to per-step latents (shapes only)."""
    learner = make_learner("dsa", LATENT, {**SMALL, "dsa_encoder": encoder}, action_dim=ACT)
    state = jax.eval_shape(functools.partial(learner.init, frame_shape=(RES, RES, 3)), jax.random.key(0))
    assert jax.eval_shape(learner.encode, state.params, WINDOWS).shape == (B, L, LATENT)
    new, m = jax.eval_shape(learner.update, state, WINDOWS, jax.random.key(1))
    assert m["loss"].shape == () and jax.tree.structure(new.params) == jax.tree.structure(state.params)
    assert learner.static_dim + learner.dynamic_dim == LATENT


def test_paper_sized_shapes() -> None:
    """64x64 frames, convs 64-64-128-256, FC/LSTM 512, L=24 (PRED k=4), shapes only."""
    windows = jax.ShapeDtypeStruct((2, 28, 64, 64, 3), jnp.uint8)
    w = Windows(windows, jax.ShapeDtypeStruct((2, 28, 2), jnp.float32),
                jax.ShapeDtypeStruct((2, 28, 5), jnp.float32), jax.ShapeDtypeStruct((2, 28), bool))
    for name in SEQUENCE_LEARNER_NAMES:
        learner = make_learner(name, 10, {"sequence_length": 24}, action_dim=2)
        state = jax.eval_shape(functools.partial(learner.init, frame_shape=(64, 64, 3)), jax.random.key(0))
        assert jax.eval_shape(learner.encode, state.params, w).shape == (2, 24, 10)
        assert state.params["conv"]["conv3"]["kernel"].shape == (4, 4, 128, 256)
    svae = make_learner("svae", 10, {"sequence_length": 24}, action_dim=2)
    state = jax.eval_shape(functools.partial(svae.init, frame_shape=(64, 64, 3)), jax.random.key(0))
    lstm = jax.tree.leaves(state.params["rnn"])
    assert any(x.shape == (4 * 4 * 256 + 2, 512) for x in lstm)  # conv output + action -> LSTM(512)


def test_nan_loss_is_reported() -> None:
    with pytest.raises(FloatingPointError, match="lower the learning rate"):
        check_finite({"loss": jnp.array([1.0, jnp.nan])}, "svae update, epoch 3")


def assert_same_loss_and_grads(ref, other, params, loss_rtol: float) -> None:
    """Two learners that differ only in how they compute give, from the same params, window batch
    and key, the same loss (to `loss_rtol`) and gradients (to float reassociation)."""
    k = jax.random.key(2)
    (l0, _), g0 = jax.jit(jax.value_and_grad(ref.loss, has_aux=True))(params, WINDOWS, k)
    (l1, _), g1 = jax.jit(jax.value_and_grad(other.loss, has_aux=True))(params, WINDOWS, k)
    np.testing.assert_allclose(float(l1), float(l0), rtol=loss_rtol)
    for a, b in zip(jax.tree.leaves(g0), jax.tree.leaves(g1)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("name", ["svae", pytest.param("dsa", marks=pytest.mark.slow)])
def test_rnn_unroll_gives_the_same_function(name: str) -> None:
    """`rnn_unroll` only changes how the LSTM scans are laid out: the same loss, gradients and
    latents from the same parameters (up to float reassociation)."""
    plain = make_learner(name, LATENT, SMALL, action_dim=ACT)
    unrolled = make_learner(name, LATENT, {**SMALL, "rnn_unroll": L}, action_dim=ACT)
    params = plain.init(jax.random.key(1), (RES, RES, 3)).params
    assert_same_loss_and_grads(plain, unrolled, params, loss_rtol=1e-5)
    np.testing.assert_allclose(np.asarray(unrolled.encode(params, WINDOWS)),
                               np.asarray(plain.encode(params, WINDOWS)), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="rnn_unroll"):
        make_learner(name, LATENT, {**SMALL, "rnn_unroll": 0}, action_dim=ACT)


@pytest.mark.parametrize("kind", ["lstm", "bilstm"])
def test_sequence_model_lstm_is_flax_lstm(kind: str) -> None:
    """SequenceModel's LSTMs (input projection hoisted out of the loop, both directions in one
    loop) compute flax's `nn.RNN(nn.OptimizedLSTMCell)` / `nn.Bidirectional` from the same
    parameters, and create those parameters as flax does (same tree, same values): the outputs
    and the input-kernel gradients match flax's own modules."""
    import flax.linen as nn

    from bulbjax.learners.networks import lecun_normal_flat
    from bulbjax.learners.temporal import SequenceModel

    class FlaxReference(nn.Module):
        @nn.compact
        def __call__(self, x):
            cells = [nn.OptimizedLSTMCell(8, kernel_init=lecun_normal_flat,
                                          recurrent_kernel_init=lecun_normal_flat)
                     for _ in range(1 if kind == "lstm" else 2)]
            if kind == "lstm":
                return nn.RNN(cells[0])(x)
            return nn.Bidirectional(nn.RNN(cells[0]), nn.RNN(cells[1]))(x)

    x = jax.random.normal(jax.random.key(1), (3, 7, 5))
    ours, ref = SequenceModel(kind, 8), FlaxReference()
    p = ours.init(jax.random.key(0), x)["params"]
    p_ref = ref.init(jax.random.key(0), x)["params"]
    assert jax.tree.structure(p) == jax.tree.structure(p_ref)
    for a, b in zip(jax.tree.leaves(p), jax.tree.leaves(p_ref)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    p = jax.tree.map(lambda a: a + 0.1 * jax.random.normal(jax.random.key(3), a.shape), p)  # nonzero biases
    out, out_ref = ours.apply({"params": p}, x), ref.apply({"params": p}, x)
    assert out.shape == (3, 7, 8 if kind == "lstm" else 16)
    np.testing.assert_allclose(np.asarray(out), np.asarray(out_ref), rtol=1e-5, atol=1e-6)
    g = jax.grad(lambda q: (ours.apply({"params": q}, x) ** 2).sum())(p)
    g_ref = jax.grad(lambda q: (ref.apply({"params": q}, x) ** 2).sum())(p)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("directions", [1, 2])
def test_written_lstm_gradient_is_autodiffs(directions: int) -> None:
    """`lstm_scan`'s written-out backward pass (W_h's gradient as one matmul after the loop)
    gives autodiff's gradients for the projected inputs and the recurrent kernel, under vmap over
    seeds and with the scan unrolled, for a cotangent on every step's output."""
    from bulbjax.learners.temporal import lstm_scan, lstm_scan_autodiff

    seeds, b, t, h = 2, 3, 7, 5
    k = jax.random.split(jax.random.key(4), 3)
    xi = jax.random.normal(k[0], (seeds, directions, b, t, 4 * h))
    wh = jax.random.normal(k[1], (seeds, directions, h, 4 * h)) / np.sqrt(h)
    r = jax.random.normal(k[2], (seeds, directions, b, t, h))
    for unroll in (1, 3):
        def grads(scan):
            f = lambda x, w, rr: (scan(x, w, unroll) * rr).sum()  # noqa: E731
            return jax.jit(jax.vmap(jax.value_and_grad(f, argnums=(0, 1))))(xi, wh, r)
        (v, (gx, gw)), (v_ref, (gx_ref, gw_ref)) = grads(lstm_scan), grads(lstm_scan_autodiff)
        np.testing.assert_allclose(np.asarray(v), np.asarray(v_ref), rtol=1e-6)
        np.testing.assert_allclose(np.asarray(gx), np.asarray(gx_ref), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(gw), np.asarray(gw_ref), rtol=1e-5, atol=1e-6)
        assert float(jnp.abs(gw).max()) > 1e-3  # a gradient that reaches W_h


def test_lstm_grad_option() -> None:
    """DSA's loss and gradients are the same whichever LSTM backward pass it runs; an unknown
    `lstm_grad` is refused, naming the accepted ones."""
    written = make_learner("dsa", LATENT, SMALL, action_dim=ACT)
    auto = make_learner("dsa", LATENT, {**SMALL, "lstm_grad": "autodiff"}, action_dim=ACT)
    params = written.init(jax.random.key(1), (RES, RES, 3)).params
    assert_same_loss_and_grads(auto, written, params, loss_rtol=1e-6)
    with pytest.raises(ValueError, match="lstm_grad"):
        make_learner("dsa", LATENT, {**SMALL, "lstm_grad": "cudnn"}, action_dim=ACT)
