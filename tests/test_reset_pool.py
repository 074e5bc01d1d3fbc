"""The pool of pre-settled initial states that `step` gives ended worlds (`resets.reset_from_pool`,
EnvConfig.reset_pool): bulb's initial-state distribution (two-sample KS per state entry against
freshly settled states, and the same share of objects resting on each face of theirs), the
pool's bookkeeping (distinct entries, none used twice between refills, a refill that brings new
states, every world ending at once, determinism under the key), and the pool off giving the
chunked resets from each world's own key chain.

One GeomOnIncline env of N worlds (version "random": all six objects) serves every test, so
MJX-Warp on CPU compiles few programs; the bookkeeping drives `reset_from_pool` directly with
chosen `done` masks."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import bulbjax
from bulbjax.envs import resets

N = 32
TAKES = 8  # all-done takes for the distribution tests: 256 states, 3 refills of the 64-entry pool


@pytest.fixture(scope="module")
def env():
    env = bulbjax.make("GeomOnIncline", num_envs=N, version="random", render=False)
    assert (env.reset_pool, env.pool_size) == (2, 2 * N), "the Incline default: a pool of 2 x num_envs"
    return env


@pytest.fixture(scope="module")
def fns(env):
    take = jax.jit(lambda keys, done, state, pool: resets.reset_from_pool(
        env, keys, done, state.data, state.scheme, state.params, pool))
    fresh = jax.jit(lambda keys: env._reset_batch(keys, jnp.ones(N, bool), forward=False)[:3])
    raw = jax.jit(env.raw_state)  # the Incline state reads qpos, qvel and the params only
    return {"reset": jax.jit(env.reset), "take": take, "fresh": fresh, "raw": raw}


@pytest.fixture(scope="module")
def state(fns):
    return fns["reset"](jax.random.PRNGKey(0))


def _entries(pool) -> np.ndarray:
    """`[P, nq]` qpos of a pool's entries in the order they are taken."""
    q = np.asarray(pool["data"]["qpos"])
    return q.reshape(-1, q.shape[-1])


def _keys(i: int) -> jax.Array:
    return jax.random.split(jax.random.PRNGKey(100 + i), N)


def test_ended_worlds_take_distinct_unused_entries_and_a_refill_brings_new_states(fns, state):
    pool0 = _entries(state.pool)
    assert len(np.unique(pool0, axis=0)) == 2 * N, "the pool's entries are distinct states"
    rng = np.random.default_rng(0)
    pool, used, cursor, seen = state.pool, set(), 0, [pool0]
    # 11 + 13 + 20 = 44 entries; then all N = 32 end with 20 left: refill first, then take 32;
    # then 7 (39 of 64)
    for i, n_done in enumerate((11, 13, 20, N, 7)):
        done = np.zeros(N, bool)
        done[rng.choice(N, n_done, replace=False)] = True
        data, scheme, params, pool = fns["take"](_keys(i), jnp.asarray(done), state, pool)
        refilled = cursor + n_done > 2 * N
        entries = _entries(pool)
        if refilled:
            assert not any((entries[:, None] == old[None]).all(-1).any() for old in seen), \
                "a refill brings states never in the pool before"
            seen.append(entries)
            used, cursor = set(), 0
        qpos = np.asarray(data.qpos)
        # each ended world holds one entry, the i-th ended world the cursor's + i, with that
        # entry's parameters and colour scheme; the others keep their state
        taken = [int(np.flatnonzero((entries == qpos[w]).all(1))[0]) for w in np.flatnonzero(done)]
        assert taken == list(range(cursor, cursor + n_done))
        assert not used & set(taken), "no entry used twice between refills"
        used |= set(taken)
        flat = lambda x: np.asarray(x).reshape((2 * N,) + np.asarray(x).shape[2:])  # noqa: E731
        for k in params:
            np.testing.assert_array_equal(np.asarray(params[k])[done], flat(pool["params"][k])[taken])
        np.testing.assert_array_equal(np.asarray(scheme)[done], flat(pool["scheme"])[taken])
        np.testing.assert_array_equal(qpos[~done], np.asarray(state.data.qpos)[~done])
        cursor += n_done
        assert (np.asarray(pool["cursor"]) == cursor).all()
    assert len(seen) == 2, "the sequence ran exactly one refill"


def test_the_pool_is_deterministic_under_the_key(fns, state):
    again = fns["reset"](jax.random.PRNGKey(0))
    for a, b in zip(jax.tree.leaves(state.pool), jax.tree.leaves(again.pool)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    other = fns["reset"](jax.random.PRNGKey(1))
    assert not (_entries(other.pool)[:, None] == _entries(state.pool)[None]).all(-1).any()
    done = jnp.ones(N, bool)  # a refill (cursor 0 + 2 x 32 = 64, then 32 more) from the step's keys
    pool = state.pool
    for i in range(3):
        a = fns["take"](_keys(i), done, state, pool)
        b = fns["take"](_keys(i), done, state, pool)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        pool = a[3]
    c = fns["take"](_keys(7), done, state, state.pool.copy() | {"cursor": jnp.full(N, 2 * N, jnp.int32)})
    assert not np.array_equal(np.asarray(c[0].qpos), _entries(pool)[:N]), \
        "the refill's states follow the step's keys"


def test_blocks_of_worlds_keep_pools_of_their_own(env, fns, state):
    """With `pool_segments=2` (the experiment's seeds: a pool per seed) the first block's resets
    are the same whatever the second block's worlds do; with one pool shared by the batch they
    are not. Block 0 ends 8 of its 16 worlds every step (a refill on the 5th); block 1 ends all
    of its worlds (refills every other step) or none."""
    blocks = jax.jit(lambda keys, done, state, pool: resets.reset_from_pool(
        env, keys, done, state.data, state.scheme, state.params, pool))
    half = N // 2
    first = np.zeros(half, bool)
    first[::2] = True

    def run(take, second_done: bool):
        pool, out = state.pool, []
        for i in range(6):
            done = np.concatenate([first, np.full(half, second_done)])
            data, _, _, pool = take(_keys(i), jnp.asarray(done), state, pool)
            out.append((np.asarray(data.qpos)[:half], np.asarray(pool["cursor"])[:half]))
        return out

    env.pool_segments = 2  # read when `blocks` is traced (its first call)
    try:
        busy, idle = run(blocks, True), run(blocks, False)
    finally:
        env.pool_segments = 1
    for (qa, ca), (qb, cb) in zip(busy, idle):
        np.testing.assert_array_equal(qa, qb)
        np.testing.assert_array_equal(ca, cb)
    assert [int(c[0]) for _, c in busy] == [8, 16, 24, 32, 8, 16], "block 0 counts its own entries, refills on the 5th"
    shared_busy, shared_idle = run(fns["take"], True), run(fns["take"], False)
    assert not all(np.array_equal(a[0], b[0]) for a, b in zip(shared_busy, shared_idle)), \
        "one shared pool: block 0's resets depend on block 1's"


def _resting_face(qpos: np.ndarray, params: dict, theta: np.ndarray) -> np.ndarray:
    """Per world the object's body axis (0..5: +x, -x, +y, -y, +z, -z) that points into the
    incline: the one most anti-aligned with the incline's normal."""
    from scipy.spatial.transform import Rotation

    slot = np.asarray(params["version"])
    quat = np.stack([qpos[i, 7 * s + 3:7 * s + 7] for i, s in enumerate(slot)])
    rot = Rotation.from_quat(quat[:, [1, 2, 3, 0]]).as_matrix()  # columns: body axes in the world
    normal = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], 1)  # Ry(theta) z
    dots = np.einsum("nij,ni->nj", rot, normal)  # [n, 3] body axes . normal
    signed = np.concatenate([dots, -dots], 1)[:, [0, 3, 1, 4, 2, 5]]
    return np.argmin(signed, 1)


def test_pool_states_have_bulbs_initial_distribution(fns, state, env):
    pooled, fresh = [], []
    pool, done = state.pool, jnp.ones(N, bool)
    for i in range(TAKES):
        data, _, params, pool = fns["take"](_keys(i), done, state, pool)
        pooled.append((fns["raw"](data, params), data.qpos, params))
        d, _, p = fns["fresh"](jax.random.split(jax.random.PRNGKey(1000 + i), N))
        fresh.append((fns["raw"](d, p), d.qpos, p))

    def cat(rows):
        raw = np.concatenate([np.asarray(r[0]) for r in rows])
        qpos = np.concatenate([np.asarray(r[1]) for r in rows])
        params = {k: np.concatenate([np.asarray(r[2][k]) for r in rows]) for k in rows[0][2]}
        return raw, qpos, params

    (raw_a, q_a, p_a), (raw_b, q_b, p_b) = cat(pooled), cat(fresh)
    assert raw_a.shape == (TAKES * N, len(env.raw_state_spec)) and np.isfinite(raw_a).all()
    for j, entry in enumerate(env.raw_state_spec):
        p = stats.ks_2samp(raw_a[:, j], raw_b[:, j]).pvalue
        assert p > 1e-3, f"{entry.name}: KS p = {p:.2g} (pool vs freshly settled)"
    faces_a = _resting_face(q_a, p_a, p_a["theta"])
    faces_b = _resting_face(q_b, p_b, p_b["theta"])
    counts = np.stack([np.bincount(faces_a, minlength=6), np.bincount(faces_b, minlength=6)])
    counts = counts[:, counts.sum(0) > 0]
    if counts.shape[1] > 1:
        p = stats.chi2_contingency(counts).pvalue
        assert p > 1e-3, f"resting faces {counts.tolist()}: chi2 p = {p:.2g}"
    else:
        assert counts[0, 0] == counts[1, 0] == TAKES * N


def test_reset_pool_is_checked():
    with pytest.raises(ValueError, match="reset_pool"):
        bulbjax.make("CartPole", num_envs=4, render=False, reset_pool=-1)
    with pytest.raises(ValueError, match="reset_pool"):
        bulbjax.make("CartPole", num_envs=4, render=False, reset_pool=1.5)
    assert bulbjax.make("CartPole", num_envs=4, render=False).reset_pool == 0, "cheap resets keep no pool"
    for bad in (3, 0, True):
        with pytest.raises(ValueError, match="pool_segments must be a positive divisor of num_envs \\(4\\)"):
            bulbjax.make("CartPole", num_envs=4, render=False, pool_segments=bad)


def test_step_takes_from_the_pool_and_the_pool_off_resets_from_each_worlds_keys(env, fns, state):
    off = bulbjax.make("GeomOnIncline", num_envs=N, version="random", render=False, reset_pool=0)
    s_off = jax.jit(off.reset)(jax.random.PRNGKey(0))
    assert off.reset_pool == 0 and s_off.pool == {}
    for a, b in zip(jax.tree.leaves(s_off.replace(pool={})), jax.tree.leaves(state.replace(pool={}))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # the same reset, pool aside
    step_on, step_off = jax.jit(env.step), jax.jit(off.step)
    s_on, ended = state, 0
    for t in range(25):
        act = jnp.full((N, 1), np.sin(t))
        key_before = np.asarray(s_off.key)
        s_on, s_off = step_on(s_on, act), step_off(s_off, act)
        done = np.asarray(s_on.done) > 0
        np.testing.assert_array_equal(done, np.asarray(s_off.done) > 0)  # the same episodes so far
        if not done.any():
            continue
        # pool off: an ended world's new episode is drawn from its own key chain, as before
        reset_keys = jax.vmap(jax.random.split)(jnp.asarray(key_before))[:, 1]
        draws = jax.vmap(off._draws)(reset_keys)
        for k in ("mass", "friction", "theta", "texture", "version"):
            np.testing.assert_array_equal(np.asarray(s_off.params[k])[done], np.asarray(draws[k])[done])
        # pool on: the next entries (the cursor counts them); the first episodes' ends agree
        # with the pool off (same draws up to here), so the worlds are compared once, then stop
        ended += int(done.sum())
        assert (np.asarray(s_on.pool["cursor"]) == ended).all()
        np.testing.assert_array_equal(np.asarray(s_on.params["mass"])[done],
                                      np.asarray(state.pool["params"]["mass"]).reshape(-1)[:ended])
        break
    else:
        pytest.fail("no episode ended in 25 steps")


def test_rearrange_worlds_take_settled_pool_states():
    """ReacherRearrangeGeom (its settle: 30 steps of the arm and four objects): the pool is made
    at `reset` from draws of its own keys, ended worlds take its entries in order, and a refill
    (every world ending with fewer entries left) settles new states, finite and on the table."""
    n = 4
    env = bulbjax.make("ReacherRearrangeGeom", num_envs=n, version="random", render=False)
    assert (env.reset_pool, env.pool_size) == (2, 2 * n)
    state = jax.jit(env.reset)(jax.random.PRNGKey(3))
    keys = resets.pool_keys_at_reset(jax.random.split(jax.random.PRNGKey(3), n), 2)
    np.testing.assert_array_equal(np.asarray(state.pool["params"]["version"]).reshape(-1),
                                  np.asarray(jax.vmap(env._draws)(keys)["version"]))
    take = jax.jit(lambda k, done, pool: resets.reset_from_pool(
        env, k, done, state.data, state.scheme, state.params, pool))
    pool, seen = state.pool, [_entries(state.pool)]
    done = np.array([True, False, True, True])
    for i in range(3):  # 3 + 3 of 8 entries, then 3 more: a refill first
        data, _, params, pool = take(jax.random.split(jax.random.PRNGKey(10 + i), n), jnp.asarray(done), pool)
        entries = _entries(pool)
        if i == 2:
            assert not (entries[:, None] == seen[0][None]).all(-1).any(), "the refill's states are new"
            start = 0
        else:
            start = 3 * i
        np.testing.assert_array_equal(np.asarray(data.qpos)[done], entries[start:start + 3])
        np.testing.assert_array_equal(np.asarray(params["version"])[done],
                                      np.asarray(pool["params"]["version"]).reshape(-1)[start:start + 3])
        assert int(pool["cursor"][0]) == start + 3
    assert np.isfinite(entries).all()
    for v, q in zip(np.asarray(pool["params"]["version"]).reshape(-1), entries):
        slots = np.asarray(env._version_slots[v])
        z = q[np.asarray(env._slot_qadr)[slots] + 2]
        assert (z > 0.0).all() and (z < 0.3).all(), f"settled objects rest on the table: z {z}"
