"""Sequence windows: cut at episode boundaries, aligned frames/actions/states, and the window
replay buffer (fill, random replacement, retention, sampling) under jit and vmap."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.data import sequence
from bulbjax.data.sequence import Windows

T, N, HW, D, A = 20, 5, 2, 3, 2


def tagged(dones: np.ndarray) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Frames, states and actions of a [T, N] trajectory, all tagged with the step id t*N + n
    (frames mod 256), so any misalignment between them shows."""
    t, n = dones.shape
    ids = np.arange(t * n).reshape(t, n)
    frames = np.broadcast_to((ids % 256).astype(np.uint8)[..., None, None, None], (t, n, HW, HW, 3))
    states = np.broadcast_to(ids.astype(np.float32)[..., None], (t, n, D))
    actions = np.broadcast_to(ids.astype(np.float32)[..., None] + 0.5, (t, n, A))
    return jnp.asarray(frames), jnp.asarray(states), jnp.asarray(actions)


def episode_ids(dones: np.ndarray) -> np.ndarray:
    """Episode index of every stored step: done[t] = 1 means frame t starts the next episode."""
    return np.cumsum(dones, axis=0)


def test_known_boundaries() -> None:
    dones = np.zeros((T, N), np.float32)
    dones[5, 0] = 1  # world 0: episode ends at step 5 -> a window from 2 keeps steps 2, 3, 4
    dones[2, 1] = 1  # world 1: done at the start step itself -> whole window valid
    dones[[3, 4], 2] = 1  # world 2: two dones, cut at the first
    starts = jnp.array([2, 2, 1, 0, 15])  # world 4: start clamped to T - L = 14
    length = 6
    frames, states, actions = tagged(dones)
    w = jax.jit(sequence.cut_windows, static_argnums=5)(frames, states, actions, jnp.asarray(dones),
                                                        starts, length)
    assert w.frames.shape == (N, length, HW, HW, 3) and w.valid.shape == (N, length)
    valid = np.asarray(w.valid)
    np.testing.assert_array_equal(valid[0], [1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(valid[1], [1] * 6)
    np.testing.assert_array_equal(valid[2], [1, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(valid[3], [1] * 6)
    ids = np.asarray(w.states[..., 0]).astype(int)
    np.testing.assert_array_equal(ids[0], np.array([2, 3, 4, 4, 4, 4]) * N + 0)  # padding repeats
    np.testing.assert_array_equal(ids[4], np.arange(14, 20) * N + 4)
    # frames, states and actions come from the same step; padded actions are zero
    np.testing.assert_array_equal(np.asarray(w.frames[:, :, 0, 0, 0]), ids % 256)
    act = np.asarray(w.actions[..., 0])
    np.testing.assert_array_equal(act[valid], ids[valid] + 0.5)
    assert np.all(act[~valid] == 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_windows_never_cross_episodes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    t, n, length = 60, 16, 8
    dones = (rng.random((t, n)) < 0.15).astype(np.float32)
    starts = rng.integers(0, t - length + 1, size=n)
    frames, states, actions = tagged(dones)
    w = sequence.cut_windows(frames, states, actions, jnp.asarray(dones), jnp.asarray(starts), length)
    ep = episode_ids(dones)
    ids = np.asarray(w.states[..., 0]).astype(int)
    valid = np.asarray(w.valid)
    for k in range(n):
        steps = ids[k] // n
        assert np.all(ids[k] % n == k)  # one world per window
        # valid steps: a prefix, consecutive in time, all in the start step's episode
        nv = valid[k].sum()
        assert nv >= 1 and np.all(valid[k][:nv]) and not np.any(valid[k][nv:])
        np.testing.assert_array_equal(steps[:nv], np.arange(starts[k], starts[k] + nv))
        assert np.all(ep[steps[:nv], k] == ep[starts[k], k])
        # the window is cut exactly where the episode ends (or runs its full length)
        if nv < length:
            assert ep[starts[k] + nv, k] != ep[starts[k], k]
    np.testing.assert_array_equal(np.asarray(w.frames[:, :, 0, 0, 0]), ids % 256)


def _windows(first_id: int, b: int, length: int = 4) -> Windows:
    ids = jnp.arange(first_id, first_id + b, dtype=jnp.float32)
    return Windows(
        frames=jnp.broadcast_to((ids % 256).astype(jnp.uint8)[:, None, None, None, None], (b, length, HW, HW, 3)),
        actions=jnp.broadcast_to(ids[:, None, None], (b, length, A)),
        states=jnp.broadcast_to(ids[:, None, None], (b, length, D)),
        valid=jnp.ones((b, length), bool))


def test_buffer_fill_replace_retain_sample() -> None:
    cap = sequence.capacity_in_windows(40, 4)
    assert cap == 10 and sequence.capacity_in_windows(5000, 24) == 208
    buf = sequence.init(cap, 4, (HW, HW, 3), D, A)
    insert = jax.jit(sequence.insert)
    buf = insert(buf, jax.random.PRNGKey(0), _windows(0, cap))
    assert int(buf.size) == cap
    np.testing.assert_array_equal(np.asarray(buf.windows.states[:, 0, 0]), np.arange(cap))
    buf = sequence.retain_initial(buf, jax.random.PRNGKey(1), 0.5)
    kept = np.asarray(buf.retained)
    assert kept.sum() == cap // 2
    for i in range(10):
        buf = insert(buf, jax.random.PRNGKey(10 + i), _windows(100 + 10 * i, 3))
    ids = np.asarray(buf.windows.states[:, 0, 0])
    np.testing.assert_array_equal(ids[kept], np.arange(cap)[kept])  # retained never overwritten
    assert np.all(ids[~kept] >= 100) and int(buf.num_dropped) == 0
    w = jax.jit(sequence.sample, static_argnums=2)(buf, jax.random.PRNGKey(2), 500)
    assert w.frames.shape == (500, 4, HW, HW, 3) and w.frames.dtype == jnp.uint8
    assert set(np.asarray(w.states[:, 0, 0]).tolist()) <= set(ids.tolist())
    np.testing.assert_array_equal(np.asarray(w.frames[:, :, 0, 0, 0]), np.asarray(w.states[..., 0]) % 256)
    assert w.head(2).frames.shape == (500, 2, HW, HW, 3) and w.head(2).valid.shape == (500, 2)
    with pytest.raises(ValueError, match="exceeds capacity"):
        sequence.insert(buf, jax.random.PRNGKey(3), _windows(0, cap + 1))
    with pytest.raises(ValueError, match="shapes"):
        sequence.insert(buf, jax.random.PRNGKey(3), _windows(0, 2, length=5))


def test_buffer_vmapped_over_seeds() -> None:
    def run(key: jax.Array) -> sequence.WindowBuffer:
        buf = sequence.init(8, 4, (HW, HW, 3), D, A)
        buf = sequence.insert(buf, key, _windows(0, 8))
        buf = sequence.retain_initial(buf, key, 0.5)
        return sequence.insert(buf, jax.random.fold_in(key, 1), _windows(50, 4))

    bufs = jax.jit(jax.vmap(run))(jax.random.split(jax.random.PRNGKey(0), 2))
    assert bufs.windows.frames.shape == (2, 8, 4, HW, HW, 3)
    assert np.asarray(bufs.retained).sum(1).tolist() == [4, 4]
    assert not np.array_equal(np.asarray(bufs.retained[0]), np.asarray(bufs.retained[1]))
