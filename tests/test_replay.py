"""Replay buffer: fill-then-replace, retention, sampling, jit/vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.data import replay

C, HW, D = 50, 4, 3


def _batch(start: int, n: int) -> tuple[jax.Array, jax.Array]:
    """Frames/states tagged with a unique id (start..start+n-1) so slots can be traced."""
    ids = jnp.arange(start, start + n)
    frames = jnp.broadcast_to((ids % 256).astype(jnp.uint8)[:, None, None, None], (n, HW, HW, 3))
    states = jnp.broadcast_to(ids.astype(jnp.float32)[:, None], (n, D))
    return frames, states


def _empty() -> replay.ReplayBuffer:
    return replay.init(replay.ReplayConfig(capacity=C), (HW, HW, 3), D)


insert = jax.jit(replay.insert)


def test_fills_then_replaces_exact_count() -> None:
    buf = _empty()
    key = jax.random.PRNGKey(0)
    for start in (0, 20):
        buf = insert(buf, jax.random.fold_in(key, start), *_batch(start, 20))
    ids = np.asarray(buf.states[:, 0])
    assert int(buf.size) == 40
    np.testing.assert_array_equal(ids[:40], np.arange(40))  # empties filled in order
    # 20 more: 10 fill the empties, 10 overwrite distinct old slots.
    buf = insert(buf, jax.random.fold_in(key, 2), *_batch(100, 20))
    ids = np.asarray(buf.states[:, 0])
    assert int(buf.size) == C
    np.testing.assert_array_equal(ids[40:], np.arange(100, 110))  # empties first, in order
    assert np.sum(ids >= 100) == 20 and len(set(ids[ids >= 100])) == 20
    # Full buffer: exactly k slots change, and they hold the new frames.
    for k in (1, 7, C):
        before = np.asarray(buf.states[:, 0])
        buf = insert(buf, jax.random.fold_in(key, 10 + k), *_batch(1000 + 100 * k, k))
        after = np.asarray(buf.states[:, 0])
        changed = before != after
        assert changed.sum() == k
        assert sorted(after[changed]) == list(range(1000 + 100 * k, 1000 + 100 * k + k))
        np.testing.assert_array_equal(np.asarray(buf.frames[:, 0, 0, 0]), after % 256)
    assert int(buf.num_dropped) == 0


def test_retained_never_overwritten_and_fraction() -> None:
    buf = _empty()
    key = jax.random.PRNGKey(1)
    buf = insert(buf, key, *_batch(0, C))
    buf = jax.jit(replay.retain_initial)(buf, jax.random.PRNGKey(2), 0.5)
    retained = np.asarray(buf.retained)
    assert retained.sum() == C // 2
    assert not np.all(retained[: C // 2])  # random subset, not a prefix
    kept = np.asarray(buf.states[:, 0])[retained]
    for i in range(40):
        buf = insert(buf, jax.random.fold_in(key, i), *_batch(1000 + 10 * i, 10))
    np.testing.assert_array_equal(np.asarray(buf.states[:, 0])[retained], kept)
    np.testing.assert_array_equal(np.asarray(buf.retained), retained)
    # The non-retained half has been churned.
    assert np.all(np.asarray(buf.states[:, 0])[~retained] >= 1000)
    # Repeating retention tops up to the fraction, it does not compound.
    again = replay.retain_initial(buf, jax.random.PRNGKey(3), 0.5)
    np.testing.assert_array_equal(np.asarray(again.retained), retained)


def test_overflow_drops_surplus_and_counts() -> None:
    buf = insert(_empty(), jax.random.PRNGKey(0), *_batch(0, C))
    buf = replay.retain_initial(buf, jax.random.PRNGKey(1), 0.8)
    before = np.asarray(buf.states[:, 0])
    buf = insert(buf, jax.random.PRNGKey(2), *_batch(500, 15))  # only 10 replaceable
    after = np.asarray(buf.states[:, 0])
    assert int(buf.num_dropped) == 5
    np.testing.assert_array_equal(after[np.asarray(buf.retained)], before[np.asarray(buf.retained)])
    assert sorted(after[before != after]) == list(range(500, 510))
    with pytest.raises(ValueError):
        replay.insert(buf, jax.random.PRNGKey(3), *_batch(0, C + 1))


def test_sample_only_filled() -> None:
    buf = insert(_empty(), jax.random.PRNGKey(0), *_batch(0, 7))
    frames, states = jax.jit(replay.sample, static_argnums=2)(buf, jax.random.PRNGKey(1), 2000)
    ids = np.asarray(states[:, 0])
    assert frames.shape == (2000, HW, HW, 3) and frames.dtype == jnp.uint8
    assert set(ids) == set(range(7))  # all filled slots hit, never an empty one
    np.testing.assert_array_equal(np.asarray(frames[:, 0, 0, 0]), ids)


def test_jit_vmap_over_seeds() -> None:
    def run(key: jax.Array) -> replay.ReplayBuffer:
        buf = _empty()
        k0, k1, k2 = jax.random.split(key, 3)
        buf = replay.insert(buf, k0, *_batch(0, C))
        buf = replay.retain_initial(buf, k1, 0.5)

        def body(b: replay.ReplayBuffer, k: jax.Array) -> tuple[replay.ReplayBuffer, None]:
            return replay.insert(b, k, *_batch(1000, 10)), None

        buf, _ = jax.lax.scan(body, buf, jax.random.split(k2, 20))
        return buf

    bufs = jax.jit(jax.vmap(run))(jax.random.split(jax.random.PRNGKey(0), 2))
    assert bufs.frames.shape == (2, C, HW, HW, 3)
    retained = np.asarray(bufs.retained)
    assert retained.sum(axis=1).tolist() == [C // 2, C // 2]
    assert not np.array_equal(retained[0], retained[1])  # seeds differ
    ids = np.asarray(bufs.states[..., 0])
    assert np.all(ids[retained] < C) and np.all(ids[~retained] >= 1000)
    frames, states = jax.vmap(lambda b, k: replay.sample(b, k, 5))(bufs, jax.random.split(jax.random.PRNGKey(1), 2))
    assert frames.shape == (2, 5, HW, HW, 3) and states.shape == (2, 5, D)


def test_default_config_and_extras() -> None:
    cfg = replay.ReplayConfig()
    assert cfg.capacity == 5000 and cfg.retain_fraction == 0.0
    buf = replay.init(
        replay.ReplayConfig(capacity=8), (HW, HW, 3), D, extras={"action": jax.ShapeDtypeStruct((2,), jnp.float32)}
    )
    frames, states = _batch(0, 3)
    buf = replay.insert(buf, jax.random.PRNGKey(0), frames, states, extras={"action": states[:, :2]})
    np.testing.assert_array_equal(np.asarray(buf.extras["action"][:3]), np.asarray(states[:, :2]))


@pytest.mark.parametrize("fraction", [0.0, 0.3, 0.5, 1.0])
def test_retain_fraction_at_paper_capacity(fraction: float) -> None:
    cfg = replay.ReplayConfig(capacity=5000, retain_fraction=fraction)
    buf = replay.init(cfg, (1, 1, 3), 1)
    ids = jnp.arange(5000)
    buf = insert(buf, jax.random.PRNGKey(0), jnp.zeros((5000, 1, 1, 3), jnp.uint8), ids[:, None].astype(jnp.float32))
    buf = replay.retain_initial(buf, jax.random.PRNGKey(1), cfg.retain_fraction)
    assert int(buf.retained.sum()) == round(fraction * 5000)
    if 0 < fraction < 1:  # roughly uniform over slots: both halves of the buffer get their share
        first_half = int(buf.retained[:2500].sum())
        assert abs(first_half - fraction * 2500) < 150


def test_sample_with_extras_keeps_each_frames_extras() -> None:
    """The world id written beside each frame comes back with that frame after random
    replacement (frames encode their id in pixel 0)."""
    cfg = replay.ReplayConfig(capacity=32)
    buf = replay.init(cfg, (2, 2, 3), 1, extras={"world": jax.ShapeDtypeStruct((), jnp.int32)})
    for i in range(4):
        ids = jnp.arange(16, dtype=jnp.int32) + 16 * i
        frames = jnp.broadcast_to((ids % 256).astype(jnp.uint8)[:, None, None, None], (16, 2, 2, 3))
        buf = replay.insert(buf, jax.random.PRNGKey(i), frames, ids[:, None].astype(jnp.float32),
                            {"world": ids})
    f, s, ex = replay.sample_with_extras(buf, jax.random.PRNGKey(9), 64)
    assert ex["world"].shape == (64,) and ex["world"].dtype == jnp.int32
    np.testing.assert_array_equal(np.asarray(f[:, 0, 0, 0]), np.asarray(ex["world"]) % 256)
    np.testing.assert_array_equal(np.asarray(s[:, 0]), np.asarray(ex["world"]))
    f2, s2 = replay.sample(buf, jax.random.PRNGKey(9), 64)  # same draw as `sample`
    np.testing.assert_array_equal(np.asarray(f2), np.asarray(f))
