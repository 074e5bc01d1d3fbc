"""Tests of the frame learners (vae, vae_rpl, beta_vae) on small synthetic frames.

Training tests use a reduced network (narrow convs, small FC) and 32x32 frames so the
file runs in well under a minute and a half on a 2-core CPU; the paper-sized network is
checked with jax.eval_shape (shapes only, no compile).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.data.sequence import Windows
from bulbjax.learners import (
    FRAME_LEARNER_NAMES,
    FrameLearner,
    LearnerConfig,
    check_finite,
    make_learner,
)

RES = 32
LATENT = 4
STEPS = 40
SMALL = {"conv_features": (8, 8, 16, 16), "hidden": 32, "lr": 2e-3}


def squares(n: int, res: int, seed: int = 0) -> jnp.ndarray:
    """uint8 frames [n, res, res, 3]: one coloured square per frame on black, random place."""
    rng = np.random.default_rng(seed)
    frames = np.zeros((n, res, res, 3), np.uint8)
    side = res // 4
    for i in range(n):
        x, y = rng.integers(0, res - side, size=2)
        frames[i, y : y + side, x : x + side] = rng.integers(60, 256, size=3)
    return jnp.asarray(frames)


FRAMES = squares(16, RES)


def train(learner, steps: int = STEPS):
    """Jitted key -> (state, per-step metrics, latents, reconstructions) of FRAMES.

    Init, `steps` updates inside lax.scan, then encode/reconstruct, all in one compile.
    """

    def run(key):
        k_init, k_steps = jax.random.split(key)
        state = learner.init(k_init, (RES, RES, 3))
        state, metrics = jax.lax.scan(
            lambda s, k: learner.update(s, FRAMES, k), state, jax.random.split(k_steps, steps)
        )
        z = learner.encode(state.params, FRAMES)
        return state, metrics, z, learner.reconstruct(state.params, FRAMES)

    return jax.jit(run)


# Every VAE learner in float32, plus the VAE with bf16 compute (SPAIR: tests/test_spair.py).
CASES = [(name, "float32") for name in FRAME_LEARNER_NAMES if not name.startswith("spair")] + [("vae", "bfloat16")]


@pytest.fixture(scope="module", params=CASES, ids=[f"{n}-{d}" for n, d in CASES])
def trained(request):
    name, dtype = request.param
    learner = make_learner(name, LATENT, {**SMALL, "compute_dtype": dtype})
    run = train(learner)
    return (learner, run, *run(jax.random.key(0)))


def test_loss_falls(trained) -> None:
    learner, _, state, metrics, _, _ = trained
    check_finite(metrics, "test_loss_falls")
    loss = np.asarray(metrics["loss"])
    assert loss.shape == (STEPS,) and metrics["loss"].dtype == jnp.float32
    assert int(state.step) == STEPS
    # metrics[0] is the loss of the untrained net; the end must be far below it.
    assert loss[-5:].mean() < 0.6 * loss[0], loss
    np.testing.assert_allclose(
        metrics["loss"], metrics["recon"] + learner.config.beta * metrics["kl"], rtol=1e-5
    )


def test_latents_and_reconstructions(trained) -> None:
    _, _, _, _, z, rec = trained
    assert z.shape == (16, LATENT) and z.dtype == jnp.float32
    assert np.all(np.isfinite(z))
    assert rec.shape == (16, RES, RES, 3) and rec.dtype == jnp.float32
    assert float(rec.min()) >= 0.0 and float(rec.max()) <= 1.0


def test_params_stay_float32(trained) -> None:
    """Also under bf16 compute: params and Adam moments are float32."""
    _, _, state, _, _, _ = trained
    for leaf in jax.tree.leaves((state.params, state.opt_state)):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            assert leaf.dtype == jnp.float32, leaf.dtype


def test_deterministic_under_fixed_key(trained) -> None:
    _, run, state, metrics, z, _ = trained
    state2, metrics2, z2, _ = run(jax.random.key(0))
    jax.tree.map(np.testing.assert_array_equal, state.params, state2.params)
    np.testing.assert_array_equal(metrics["loss"], metrics2["loss"])
    np.testing.assert_array_equal(z, z2)
    _, metrics3, _, _ = run(jax.random.key(1))
    assert not np.array_equal(metrics["loss"], metrics3["loss"])


def test_registry_presets() -> None:
    vae, rpl, beta = (make_learner(n, LATENT) for n in ("vae", "vae_rpl", "beta_vae"))
    assert (vae.retain_fraction, vae.config.beta) == (0.0, 1.0)
    assert (rpl.retain_fraction, rpl.config.beta) == (0.5, 1.0)
    assert (beta.retain_fraction, beta.config.beta) == (0.5, 5.0)
    assert vae.config.lr == 1e-4 and vae.config.batch_size == 1024
    for learner in (vae, rpl, beta):
        assert isinstance(learner, FrameLearner)
    # A LearnerConfig's non-default fields override; the name's presets stay otherwise.
    custom = make_learner("vae_rpl", LATENT, LearnerConfig(lr=1e-3))
    assert custom.config.lr == 1e-3 and custom.retain_fraction == 0.5
    assert make_learner("beta_vae", LATENT, LearnerConfig(beta=20.0)).config.beta == 20.0
    assert make_learner("beta_vae", LATENT, {"beta": 1.0}).config.beta == 1.0


def test_unknown_name_raises() -> None:
    with pytest.raises(ValueError, match="vae, vae_rpl, beta_vae"):
        make_learner("svae_typo", LATENT)
    with pytest.raises(ValueError, match="unknown config fields"):
        make_learner("vae", LATENT, {"learning_rate": 1e-3})
    with pytest.raises(ValueError, match="compute_dtype"):
        LearnerConfig(compute_dtype="float16")


def test_vmap_over_seeds() -> None:
    """init/update/encode vmapped over 2 seeds (params with a leading seed axis) in one jit."""
    learner = make_learner("vae", LATENT, SMALL)
    init = functools.partial(learner.init, frame_shape=(RES, RES, 3))

    @jax.jit
    def run(keys):
        states = jax.vmap(init)(keys)
        new, metrics = jax.vmap(learner.update, in_axes=(0, None, 0))(states, FRAMES, keys)
        z = jax.vmap(learner.encode, in_axes=(0, None))(new.params, FRAMES)
        return states, new, metrics, z

    states, new, metrics, z = run(jax.random.split(jax.random.key(3), 2))
    kernel = states.params["encoder"]["conv0"]["kernel"]
    assert kernel.shape == (2, 4, 4, 3, 8) and not np.allclose(kernel[0], kernel[1])
    assert metrics["loss"].shape == (2,) and metrics["loss"][0] != metrics["loss"][1]
    np.testing.assert_array_equal(new.step, [1, 1])
    check_finite(metrics, "test_vmap_over_seeds")
    assert z.shape == (2, 16, LATENT) and not np.allclose(z[0], z[1])


def test_paper_sized_network_shapes() -> None:
    """Default config (64,64,128,256 convs, FC 512) at 64x64 and 128x128, shapes only."""
    learner = make_learner("vae", 8)
    for res in (64, 128):
        init = functools.partial(learner.init, frame_shape=(res, res, 3))
        state = jax.eval_shape(init, jax.random.key(0))
        enc = state.params["encoder"]
        assert [enc[f"conv{i}"]["kernel"].shape[-1] for i in range(4)] == [64, 64, 128, 256]
        assert enc["fc"]["kernel"].shape == ((res // 16) ** 2 * 256, 512)
        frames = jax.ShapeDtypeStruct((2, res, res, 3), jnp.uint8)
        assert jax.eval_shape(learner.encode, state.params, frames).shape == (2, 8)
        assert jax.eval_shape(learner.reconstruct, state.params, frames).shape == (2, res, res, 3)


def test_bad_frame_shape_raises() -> None:
    learner = make_learner("vae", LATENT, SMALL)
    key = jax.random.key(0)
    for shape in [(30, 30, 3), (32, 48, 3), (32, 32, 1), (32, 32), (0, 0, 3)]:
        with pytest.raises(ValueError, match="multiple of 16"):
            learner.init(key, shape)
    with pytest.raises(TypeError, match="static"):
        jax.eval_shape(learner.init, key, (RES, RES, 3))  # frame_shape traced
    state = jax.eval_shape(functools.partial(learner.init, frame_shape=(RES, RES, 3)), key)
    with pytest.raises(ValueError, match="initialised for 32x32x3"):
        learner.encode(state.params, jnp.zeros((2, 64, 64, 3), jnp.uint8))
    with pytest.raises(ValueError, match="multiple of 16"):
        learner.encode(state.params, jnp.zeros((2, 40, 40, 3), jnp.uint8))
    with pytest.raises(TypeError, match="uint8"):
        learner.encode(state.params, jnp.zeros((2, RES, RES, 3), jnp.float32))


def test_check_finite() -> None:
    check_finite({"loss": jnp.ones((2, 3))}, "ok")
    with pytest.raises(FloatingPointError, match="lower the learning rate"):
        check_finite({"loss": jnp.array([1.0, jnp.nan]), "kl": jnp.array(0.0)}, "epoch 3")


def test_config_is_hashable_and_frozen() -> None:
    config = LearnerConfig(conv_features=[8, 8, 16, 16])  # type: ignore[arg-type]
    assert config.conv_features == (8, 8, 16, 16)
    hash(make_learner("vae", LATENT, config))
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.lr = 1.0  # type: ignore[misc]


@pytest.mark.parametrize("impl,pad,bias_grad,edge", [
    ("subpixel", 1, "reduce", "strided"), ("dgrad", 1, "reduce", "strided"),
    ("dgrad", 8, "split", "strided"), ("subpixel", 1, "split", "strided"),
    ("dgrad", 8, "split", "blocked"), ("dgrad", 1, "reduce", "blocked"),
    ("dgrad", 8, "split_apart", "blocked"), ("dgrad", 8, "pallas", "blocked"),
    ("subpixel", 1, "pallas", "strided"), ("dgrad", 8, "pallas_relu", "blocked"),
    ("subpixel", 1, "pallas_relu", "strided")])
def test_decoder_forms_equal_transpose(impl: str, pad: int, bias_grad: str, edge: str) -> None:
    """The decoder forms share parameters and compute the same function (and gradients), so
    switching `deconv_impl` (or padding the 3 output channels, summing the bias gradients
    in two passes, computing the last layer over pixel blocks) for speed cannot change what a
    learner learns."""
    from bulbjax.learners.networks import DeconvDecoder

    z = jax.random.normal(jax.random.PRNGKey(3), (3, 6))
    a = DeconvDecoder(32, (8, 8, 16, 16), 32, impl="transpose")
    b = DeconvDecoder(32, (8, 8, 16, 16), 32, impl=impl, channel_pad=pad, bias_grad=bias_grad,
                      edge_layers=edge)
    params = a.init(jax.random.PRNGKey(4), z)
    assert jax.tree.map(jnp.shape, params) == jax.tree.map(jnp.shape, b.init(jax.random.PRNGKey(4), z))
    # non-zero biases, so a misplaced bias shows
    params = jax.tree.map(lambda p: p + 0.05, params)
    ya, yb = a.apply(params, z), b.apply(params, z)
    assert ya.shape == (3, 32, 32, 3)
    np.testing.assert_allclose(np.asarray(yb), np.asarray(ya), rtol=1e-5, atol=1e-5)
    ga = jax.grad(lambda p: jnp.sum(jnp.sin(a.apply(p, z))))(params)
    gb = jax.grad(lambda p: jnp.sum(jnp.sin(b.apply(p, z))))(params)
    for x, y in zip(jax.tree.leaves(ga), jax.tree.leaves(gb)):
        scale = float(np.abs(np.asarray(x)).max())  # float32 sums in another order: relative to the leaf
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-4, atol=1e-5 * max(scale, 1.0))
    # and under vmap over seeds (params and inputs batched, as in the experiment's seed axis)
    ps = jax.tree.map(lambda p: jnp.stack([p, 1.1 * p]), params)
    zs = jnp.stack([z, 2 * z])
    vg = lambda m: jax.vmap(jax.grad(lambda p, zz: jnp.sum(jnp.sin(m.apply(p, zz)))))(ps, zs)  # noqa: E731
    for x, y in zip(jax.tree.leaves(vg(a)), jax.tree.leaves(vg(b))):
        scale = float(np.abs(np.asarray(x)).max())  # summed in other orders: up to ~1.5e-5 of the leaf
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-4, atol=3e-5 * max(scale, 1.0))


@pytest.mark.parametrize("pad,bias_grad,blocked", [(1, "reduce", False), (8, "reduce", False),
                                                   (8, "split", False), (4, "split", False),
                                                   (1, "reduce", True), (8, "split", True),
                                                   (1, "split_apart", False), (8, "pallas", False),
                                                   (8, "pallas", True)])
def test_conv4x4_equals_flax_conv(pad: int, bias_grad: str, blocked: bool) -> None:
    """The encoder's layer has flax `nn.Conv`'s parameters (names, shapes, init values) and
    function and gradients, whatever its channel padding, bias-gradient form, or computed
    over 2x2 pixel blocks."""
    import flax.linen as nn

    from bulbjax.learners.networks import Conv4x4, lecun_normal_flat

    x = jax.random.uniform(jax.random.PRNGKey(5), (2, 16, 16, 3))
    ref = nn.Conv(6, (4, 4), strides=(2, 2), padding="SAME", kernel_init=lecun_normal_flat)
    ours = Conv4x4(6, channel_pad=pad, bias_grad=bias_grad, blocked=blocked)
    params = ref.init(jax.random.PRNGKey(6), x)
    mine = ours.init(jax.random.PRNGKey(6), x)
    assert jax.tree.map(jnp.shape, mine) == jax.tree.map(jnp.shape, params)
    for p, q in zip(jax.tree.leaves(params), jax.tree.leaves(mine)):
        np.testing.assert_array_equal(np.asarray(q), np.asarray(p))
    params = jax.tree.map(lambda p: p + 0.05, params)  # a non-zero bias
    np.testing.assert_allclose(np.asarray(ours.apply(params, x)), np.asarray(ref.apply(params, x)),
                               rtol=1e-5, atol=1e-5)
    loss = lambda m, p: jnp.sum(jnp.sin(m.apply(p, x)) * jnp.arange(6.0))  # noqa: E731
    for g, h in zip(jax.tree.leaves(jax.grad(lambda p: loss(ref, p))(params)),
                    jax.tree.leaves(jax.grad(lambda p: loss(ours, p))(params))):
        np.testing.assert_allclose(np.asarray(h), np.asarray(g), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("grad", ["split", "split_apart", "pallas", "pallas_relu"])
def test_encoder_bias_gradient_forms_give_autodiffs_gradients(grad: str) -> None:
    """The encoder's conv layers with their ReLUs (Conv4x4 with `relu`), the bias gradients in
    each form, give autodiff's gradients (`reduce`): a scale error in a bias gradient shows here,
    where a learner's first Adam step would hide it."""
    from bulbjax.learners.networks import ConvEncoder

    x = jax.random.uniform(jax.random.PRNGKey(7), (4, 32, 32, 3))
    a = ConvEncoder(6, (8, 8, 16, 16), 32, channel_pad=8, bias_grad="reduce")
    b = ConvEncoder(6, (8, 8, 16, 16), 32, channel_pad=8, bias_grad=grad)
    params = jax.tree.map(lambda p: p + 0.05, a.init(jax.random.PRNGKey(8), x))
    loss = lambda m, p: sum(jnp.sum(jnp.sin(o)) for o in m.apply(p, x))  # noqa: E731
    ga, gb = jax.grad(lambda p: loss(a, p))(params), jax.grad(lambda p: loss(b, p))(params)
    for u, v in zip(jax.tree.leaves(ga), jax.tree.leaves(gb)):
        scale = float(np.abs(np.asarray(u)).max())
        np.testing.assert_allclose(np.asarray(v), np.asarray(u), rtol=1e-4, atol=1e-5 * max(scale, 1.0))


@pytest.mark.parametrize("name,grad", [("vae", "split"), ("vae", "pallas_relu"),
                                       pytest.param("pred", "split", marks=pytest.mark.slow)])
def test_conv_forms_do_not_change_the_learner(name: str, grad: str) -> None:
    """A learner with padded frame channels, two-pass bias gradients (or the ReLU masks and bias
    gradients in one Pallas kernel) and the edge layers over pixel blocks starts from the same
    parameters and takes the same update as with the plain forms."""
    cfg = LearnerConfig(conv_features=(8, 8, 16, 16), hidden=32, batch_size=4, sequence_length=3,
                        pred_horizon=1)
    plain = make_learner(name, LATENT, dataclasses.replace(cfg, channel_pad=1, bias_grad="reduce"), action_dim=1)
    padded = make_learner(name, LATENT, dataclasses.replace(cfg, channel_pad=8, bias_grad=grad,
                                                            edge_layers="blocked"), action_dim=1)
    s0, s1 = plain.init(jax.random.PRNGKey(0), (32, 32, 3)), padded.init(jax.random.PRNGKey(0), (32, 32, 3))
    for p, q in zip(jax.tree.leaves(s0.params), jax.tree.leaves(s1.params)):
        np.testing.assert_array_equal(np.asarray(q), np.asarray(p))
    rng = np.random.default_rng(0)
    if name == "vae":
        batch = jnp.asarray(rng.integers(0, 256, (4, 32, 32, 3), dtype=np.uint8))
    else:
        lw = plain.window_length
        batch = Windows(frames=jnp.asarray(rng.integers(0, 256, (2, lw, 32, 32, 3), dtype=np.uint8)),
                        actions=jnp.asarray(rng.uniform(-1, 1, (2, lw, 1)), jnp.float32),
                        states=jnp.zeros((2, lw, 4), jnp.float32), valid=jnp.ones((2, lw), bool))
    a, ma = plain.update(s0, batch, jax.random.PRNGKey(1))
    b, mb = padded.update(s1, batch, jax.random.PRNGKey(1))
    np.testing.assert_allclose(float(mb["loss"]), float(ma["loss"]), rtol=1e-5)
    for p, q in zip(jax.tree.leaves(a.params), jax.tree.leaves(b.params)):
        np.testing.assert_allclose(np.asarray(q), np.asarray(p), rtol=1e-4, atol=1e-6)


def test_conv_forms_are_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    # 0 picks the padding by compute dtype: 8 channels for bf16's tensor-core kernels, none in float32;
    # bias_grad "auto" the Pallas kernel in bf16 on a GPU only (interpreted on a CPU)
    assert jax.default_backend() == "cpu"
    assert LearnerConfig().conv_forms == {"channel_pad": 1, "bias_grad": "split", "edge_layers": "strided"}
    assert LearnerConfig(compute_dtype="bfloat16").conv_forms == {"channel_pad": 8, "bias_grad": "split",
                                                                  "edge_layers": "blocked"}
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert LearnerConfig(compute_dtype="bfloat16").conv_forms["bias_grad"] == "pallas_relu"
    assert LearnerConfig().conv_forms["bias_grad"] == "split"
    assert LearnerConfig(compute_dtype="bfloat16", bias_grad="split").conv_forms["bias_grad"] == "split"
    monkeypatch.undo()
    assert LearnerConfig(compute_dtype="bfloat16", edge_layers="strided").conv_forms["edge_layers"] == "strided"
    assert LearnerConfig(compute_dtype="bfloat16", channel_pad=1).conv_forms["channel_pad"] == 1
    with pytest.raises(ValueError, match="channel_pad"):
        LearnerConfig(channel_pad=-1)
    with pytest.raises(ValueError, match="bias_grad"):
        LearnerConfig(bias_grad="dot")
    with pytest.raises(ValueError, match="edge_layers"):
        LearnerConfig(edge_layers="tiled")


def test_unknown_decoder_form_is_refused() -> None:
    with pytest.raises(ValueError, match="deconv_impl"):
        LearnerConfig(deconv_impl="nearest")
