"""`per_seed`: a function vmapped over seeds that loops over them (forward and backward) instead
of batching its operations; and the sequential learners with their frame networks run that way
(`per_seed_frames`, the "hybrid" seed loop): same loss and gradients as batched, no grouped
convolution left in the program."""

from __future__ import annotations

import dataclasses

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.learners import make_learner
from bulbjax.learners.per_seed import per_seed, per_seed_loss
from test_sequential_learners import ACT, LATENT, RES, SMALL, WINDOWS

SEEDS = 3


def conv(w: dict, frames: jax.Array) -> jax.Array:
    """A small conv layer on uint8 frames [B, H, W, C] -> [B, H', W', F]."""
    x = frames.astype(jnp.float32) / 255.0
    y = jax.lax.conv_general_dilated(x, w["k"], (2, 2), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return jnp.tanh(y + w["b"])


def convs(jaxpr) -> tuple[int, int]:
    """(plain, grouped) convolutions in a (closed) jaxpr, nested ones included; grouped: more
    than one feature or batch group."""
    n = np.zeros(2, int)
    for eqn in getattr(jaxpr, "jaxpr", jaxpr).eqns:
        if eqn.primitive.name == "conv_general_dilated":
            n[int(eqn.params["feature_group_count"] > 1 or eqn.params["batch_group_count"] > 1)] += 1
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            n += convs(sub)
    return n


def grouped_convs(jaxpr) -> int:
    """Grouped convolutions in a jaxpr; asserts that it has convolutions at all (forward and
    backward), so that none grouped means all plain, not none found."""
    plain, grouped = convs(jaxpr)
    assert plain + grouped >= 2
    return int(grouped)


def loss(fn, w: dict, frames: jax.Array, r: jax.Array) -> jax.Array:
    return (fn(w, frames) * r).sum()


@pytest.fixture(scope="module")
def inputs():
    k = jax.random.split(jax.random.key(0), 4)
    w = {"k": jax.random.normal(k[0], (SEEDS, 3, 3, 3, 4)), "b": jax.random.normal(k[1], (SEEDS, 4))}
    frames = jax.random.randint(k[2], (SEEDS, 5, 8, 8, 3), 0, 256).astype(jnp.uint8)
    r = jax.random.normal(k[3], (SEEDS, 5, 4, 4, 4))
    return w, frames, r


def seed_loss(w: dict, frames: jax.Array, r: jax.Array) -> jax.Array:
    """`loss` of `conv` through `per_seed_loss` (per-item terms weighted by r's means)."""
    terms = lambda w, f: (conv(w, f) ** 2).mean(axis=(1, 2, 3))  # noqa: E731
    return per_seed_loss(terms)(w, frames, r.mean(axis=(1, 2, 3)))


def seed_loss_ref(w: dict, frames: jax.Array, r: jax.Array) -> jax.Array:
    return ((conv(w, frames) ** 2).mean(axis=(1, 2, 3)) * r.mean(axis=(1, 2, 3))).sum()


FORMS = {  # wrapped loss, the plain loss it must equal
    "remat": (lambda w, x, r: loss(per_seed(conv, remat=True), w, x, r), lambda w, x, r: loss(conv, w, x, r)),
    "saved": (lambda w, x, r: loss(per_seed(conv, remat=False), w, x, r), lambda w, x, r: loss(conv, w, x, r)),
    "loss": (seed_loss, seed_loss_ref),
}


@pytest.mark.parametrize("form", FORMS)
def test_per_seed_is_the_function_and_its_gradient(inputs, form: str) -> None:
    """Vmapped over seeds or called on one seed: the value and gradient of the plain function
    (`per_seed` saving or recomputing activations; `per_seed_loss`, scaled by the cotangent)."""
    w, frames, r = inputs
    wrapped, plain = FORMS[form]
    for f in (jax.vmap, lambda g: (lambda *a: g(*jax.tree.map(lambda x: x[0], a)))):
        got = jax.jit(f(jax.value_and_grad(lambda *a: 3.0 * wrapped(*a))))(w, frames, r)
        ref = jax.jit(f(jax.value_and_grad(lambda *a: 3.0 * plain(*a))))(w, frames, r)
        jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5), got, ref)
        assert float(jnp.abs(got[1]["k"]).max()) > 1e-3


@pytest.mark.parametrize("form", FORMS)
def test_per_seed_leaves_no_grouped_convolution(inputs, form: str) -> None:
    """vmap turns a convolution over per-seed weights into a grouped one (forward and backward);
    under `per_seed` every convolution stays a plain one, inside a loop over seeds."""
    w, frames, r = inputs
    wrapped, plain = FORMS[form]
    grad = lambda fn: jax.make_jaxpr(jax.vmap(jax.grad(fn)))(w, frames, r)  # noqa: E731
    assert grouped_convs(grad(plain)) >= 2
    looped = grad(wrapped)
    assert grouped_convs(looped) == 0
    assert str(looped).count("custom_vmap") >= 1


@pytest.mark.parametrize("name,how", [pytest.param("svae", "remat", marks=pytest.mark.slow), ("dsa", "remat"),
                                      ("svae", "saved")])
def test_per_seed_frames_gives_the_same_updates(name: str, how: str) -> None:
    """A sequential learner with its frame networks one seed at a time (`per_seed_frames`):
    vmapped over seeds, the same loss and gradients as batched, and no grouped convolution."""
    plain = make_learner(name, LATENT, SMALL, action_dim=ACT)
    looped = dataclasses.replace(plain, per_seed_frames=how)
    params = jax.vmap(lambda k: plain.init(k, (RES, RES, 3)).params)(jax.random.split(jax.random.key(1), 2))
    windows = jax.tree.map(lambda x: jnp.stack([x, x[::-1]]), WINDOWS)
    keys = jax.random.split(jax.random.key(2), 2)

    def grads(learner):
        return jax.vmap(jax.value_and_grad(learner.loss, has_aux=True))

    (l0, _), g0 = jax.jit(grads(plain))(params, windows, keys)
    (l1, _), g1 = jax.jit(grads(looped))(params, windows, keys)
    np.testing.assert_allclose(np.asarray(l1), np.asarray(l0), rtol=1e-5)
    assert not np.allclose(l0[0], l0[1])
    for a, b in zip(jax.tree.leaves(g0), jax.tree.leaves(g1)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-3, atol=1e-6)
    assert grouped_convs(jax.make_jaxpr(grads(plain))(params, windows, keys)) > 0
    assert grouped_convs(jax.make_jaxpr(grads(looped))(params, windows, keys)) == 0
    enc = lambda l: jax.jit(jax.vmap(l.encode))(params, windows)  # noqa: E731
    np.testing.assert_allclose(np.asarray(enc(looped)), np.asarray(enc(plain)), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="per_seed_frames"):
        dataclasses.replace(plain, per_seed_frames="yes")
