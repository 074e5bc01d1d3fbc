"""Chunked resets in `step` (`MjxPixelEnv._reset_done`, `resets.reset_in_chunks`): the worlds
that ended are reset K at a time, in as many chunks as it takes, from their own keys and fixed
draws; the other worlds are untouched; nothing changes when no world is done.

What is compared with the full-batch reset (reset_chunk=0) from the same per-world keys: the
draws (parameters, colour scheme, incline pitch) bit for bit. The simulated part (Incline's fall,
Rearrange's settle) is compared bit for bit with the full-batch code run on each chunk's worlds
as a batch: MJX-Warp on CPU gives a world's contacts last-bit differences that depend on the
world's index in the batch (measured: the same world at index 0 and at index 1 of a batch, or
5 of 8, gets contact distances that differ in the last bits; the contact-rich fall turns them
into up to 4e-4 m of position after the fall), so a world's fall is reproducible only at a fixed
position in a batch, for the old full-batch path as for the chunks."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bulbjax

N, K = 8, 2
DONE = jnp.array([1, 0, 1, 1, 0, 1, 0, 1], bool)  # 5 done with K = 2: three chunks, the last padded


def _pair(name: str) -> tuple:
    """The domain with chunks of K worlds and with the full-batch reset."""
    make = lambda chunk: bulbjax.make(name, num_envs=N, version="random", render=False, reset_chunk=chunk)
    return make(K), make(0)


@pytest.fixture(scope="module", params=["GeomOnIncline", pytest.param("ReacherRearrangeGeom", marks=pytest.mark.slow)])
def envs(request):
    chunked, full = _pair(request.param)
    assert (chunked.reset_chunk, full.reset_chunk) == (K, 0)
    state = jax.jit(chunked.reset)(jax.random.PRNGKey(0))
    keys = jax.random.split(jax.random.PRNGKey(1), N)
    return chunked, full, state, keys


def _with_fixed(env, fixed, fn):
    """`fn()` with `reset_with`-style fixed draws in place (as `reset_with` sets them)."""
    saved, env._fixed = env._fixed, fixed or {}
    try:
        return fn()
    finally:
        env._fixed = saved


def _reset_done(env, fixed=None):
    """`env._reset_done` jitted, with fixed draws `[N]` in place while tracing."""
    return jax.jit(lambda *args: _with_fixed(env, fixed, lambda: env._reset_done(*args)))


def _leaves(tree) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def _assert_same(a, b) -> None:
    la, lb = _leaves(a), _leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(x, y)


def _per_world(data) -> dict[str, np.ndarray]:
    return {f: np.asarray(getattr(data, f)) for f in ("qpos", "qvel", "mocap_pos", "mocap_quat")}


def test_chunked_reset_resets_the_done_worlds_as_the_full_batch_code_does(envs):
    chunked, full, state, keys = envs
    args = (keys, DONE, state.data, state.scheme, state.params)
    fixed = None
    if "theta" in chunked.RESET_FIELDS:  # Incline: a fixed draw per world must follow its world
        fixed = {"theta": jnp.linspace(0.26, 0.49, N)}
    data, scheme, params = _reset_done(chunked, fixed)(*args)
    done = np.asarray(DONE)
    # the draws: bit for bit the full-batch reset's
    _, want_scheme, want_params = _reset_done(full, fixed)(*args)
    np.testing.assert_array_equal(np.asarray(scheme), np.asarray(want_scheme))
    _assert_same(params, want_params)
    if fixed is not None:
        np.testing.assert_array_equal(np.asarray(params["theta"])[done], np.asarray(fixed["theta"])[done])
    # the simulated reset: each chunk (done worlds in order, K at a time, the last padded) is
    # the full-batch code's reset of those worlds as a batch
    order = np.concatenate([np.flatnonzero(done), [N]])
    assert len(order) == 3 * K, "the case runs three chunks"
    batch = jax.jit(lambda k, d, fx: _with_fixed(full, fx, lambda: full._reset_batch(k, d, forward=False)))
    after = _per_world(data)
    for c in range(3):
        idx = order[c * K:(c + 1) * K]
        rows, valid = np.minimum(idx, N - 1), idx < N
        fx = {k: v[rows] for k, v in (fixed or {}).items()}
        want = _per_world(batch(keys[rows], jnp.asarray(valid), fx)[0])
        for f in after:
            np.testing.assert_array_equal(after[f][idx[valid]], want[f][valid], err_msg=f"chunk {c} {f}")
    # the worlds not done keep everything
    before = _per_world(state.data)
    for f in before:
        np.testing.assert_array_equal(after[f][~done], before[f][~done])
    _assert_same({k: v[~done] for k, v in params.items()}, {k: v[~done] for k, v in state.params.items()})
    assert all(not np.array_equal(after["qpos"][i], before["qpos"][i]) for i in np.flatnonzero(done))


def test_no_world_done_resets_nothing(envs):
    chunked, _, state, keys = envs
    got = _reset_done(chunked)(keys, jnp.zeros(N, bool), state.data, state.scheme, state.params)
    _assert_same(got, (state.data, state.scheme, state.params))


def test_reset_chunk_is_checked_and_defaults_to_a_fraction_of_the_batch():
    env = bulbjax.make("CartPole", num_envs=4, render=False)
    assert env.reset_chunk == 0, "cheap resets keep the full-batch path"
    assert bulbjax.make("GeomOnIncline", num_envs=20, render=False).reset_chunk == 3  # ceil(20 / 8)
    assert bulbjax.make("GeomOnIncline", num_envs=20, render=False, reset_chunk=50).reset_chunk == 20
    with pytest.raises(ValueError, match="reset_chunk"):
        bulbjax.make("CartPole", num_envs=4, render=False, reset_chunk=-1)
