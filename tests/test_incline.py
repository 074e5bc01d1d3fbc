"""Incline domains (GeomOnIncline, YcbOnIncline): reset/step of every version, object pixels
where the object is, slide physics (pitch, friction, push), per-world parameters, depth and
point clouds against the object's pose, determinism, and the YCB path error."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bulbjax
from bulbjax.envs.objects.incline import NUM_VERSIONS, START_POS

YCB_DIR = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "ycb"))
N = 12
ALL_VERSIONS_KEY = jax.random.PRNGKey(3)


@pytest.fixture(scope="module")
def geom_env():
    return bulbjax.make("GeomOnIncline", num_envs=N, version="random", render="depth")


@pytest.fixture(scope="module")
def ycb_env():
    if not os.path.isdir(YCB_DIR):
        pytest.skip(f"YCB models not found at {YCB_DIR}")
    return bulbjax.make("YcbOnIncline", num_envs=N, version="random", ycb_dir=YCB_DIR)


def _versions(env) -> jax.Array:
    """Per-world versions that cover all six (two worlds each)."""
    return jnp.arange(env.num_envs) % NUM_VERSIONS


def _rollout(env, state, actions):
    step = jax.jit(env.step)
    out = [state]
    for a in actions:
        out.append(step(out[-1], a))
    return out


def _project(env, state, points: np.ndarray) -> np.ndarray:
    """Pixel (column, row) of world points `[N, 3]` in each world's bulb camera."""
    cam = 0  # the bulb camera is the model's first
    pos = np.asarray(state.data.cam_xpos[:, cam])
    mat = np.asarray(state.data.cam_xmat[:, cam]).reshape(-1, 3, 3)
    local = np.einsum("nji,nj->ni", mat, points - pos)  # camera frame: x right, y up, -z forward
    half = np.tan(np.deg2rad(env.camera.fovy) / 2)
    res = env.resolution
    col = (local[:, 0] / -local[:, 2] / half + 1) / 2 * res
    row = (1 - local[:, 1] / -local[:, 2] / half) / 2 * res
    return np.stack([col, row], axis=1), -local[:, 2]


def _in_frame(px: np.ndarray, margin: float = 6.0, res: int = 64) -> np.ndarray:
    return ((px > margin) & (px < res - margin)).all(axis=1)


def _object_mask(env, state) -> np.ndarray:
    """`[N, H, W]` pixels that change when the world's object is moved out of view."""
    ri = state.render_input
    parked = ri.replace(qpos=jnp.asarray(np.asarray(env._qpos_park)[None].repeat(env.num_envs, 0)))
    frames = np.asarray(jax.jit(env.render_frames)(ri)).astype(int)
    empty = np.asarray(jax.jit(env.render_frames)(parked)).astype(int)
    return np.abs(frames - empty).sum(-1) > 30


@pytest.mark.parametrize("family", ["geom", "ycb"])
def test_every_version_resets_steps_and_shows_its_object(family, request):
    env = request.getfixturevalue(f"{family}_env")
    state = jax.jit(lambda k: env.reset_with(k, version=_versions(env)))(ALL_VERSIONS_KEY)
    states = _rollout(env, state, [jnp.zeros((N, 1))] * 6)
    last = states[-1]
    assert last.pixels.shape == (N, 64, 64, 3) and last.pixels.dtype == jnp.uint8
    assert last.lowdim.shape == (N, len(env.state_spec)) and last.lowdim.dtype == jnp.float32
    for s in states:
        low, raw = np.asarray(s.lowdim), np.asarray(s.info["lowdim_raw"])
        assert np.isfinite(low).all() and np.isfinite(raw).all()
        assert (low >= 0).all() and (low <= 1).all()
    np.testing.assert_array_equal(np.asarray(state.params["version"]), np.asarray(_versions(env)))
    np.testing.assert_allclose(np.asarray(state.lowdim[:, 1]), np.asarray(_versions(env)) / 6, atol=1e-6)
    # after the initial fall the object is on the incline, past its start
    raw = np.asarray(state.info["lowdim_raw"])
    assert (raw[:, 0] > 0.0).all() and (raw[:, 0] < 0.5).all() and (np.abs(raw[:, 1]) < 0.1).all()
    # it is drawn where its centre projects (bulb's camera crops the incline's top: checked on
    # the worlds whose centre lies inside the frame, after a few steps of sliding)
    last = states[-1]
    mask = _object_mask(env, last)
    px, _ = _project(env, last, np.asarray(last.info["lowdim_raw"])[:, :3])
    seen = _in_frame(px) & (np.asarray(last.step_count) > 0)
    assert seen.sum() >= N // 2, f"too few objects in view: {px}"
    for i in np.nonzero(seen)[0]:
        rows, cols = np.nonzero(mask[i])
        assert len(rows) > 20, f"world {i}: object hardly visible"
        c, r = px[i]
        assert cols.min() - 2 <= c <= cols.max() + 2 and rows.min() - 2 <= r <= rows.max() + 2, (
            f"world {i} (version {i % 6}): projected centre {px[i]} outside the object's pixels")
        assert np.hypot(cols.mean() - c, rows.mean() - r) < 8


def _distance_after(env, steps: int, push: np.ndarray, **fixed) -> np.ndarray:
    state = jax.jit(lambda k: env.reset_with(k, **fixed))(jax.random.PRNGKey(0))
    start = np.asarray(state.info["lowdim_raw"][:, 0])
    states = _rollout(env, state, [jnp.asarray(push, jnp.float32)[:, None]] * steps)
    x = np.array([np.asarray(s.info["lowdim_raw"][:, 0]) for s in states[1:]])
    done = np.array([np.asarray(s.done) for s in states[1:]])
    # x before any reset: stop following a world at its first done
    first = np.where(done.any(0), done.argmax(0), steps - 1)
    last = np.where(done.any(0), x[np.maximum(first - 1, 0), np.arange(env.num_envs)], x[-1])
    return last - start


def test_slide_speeds_up_with_pitch_and_down_with_friction_and_push(geom_env):
    env = geom_env
    # worlds in pairs: (steep, shallow) at friction 0.2; (low, high) friction at pitch 0.45;
    # pushes -1, 0, +1 (bulb's force along the object's own z axis, which its reset pose points
    # down the slope); all with the same block (version 0), mass, texture and start pose
    theta = np.array([0.5, 0.3, 0.45, 0.45, 0.45, 0.45, 0.45] + [0.45] * (N - 7))
    fric = np.array([0.2, 0.2, 0.1, 0.45, 0.25, 0.25, 0.25] + [0.25] * (N - 7))
    push = np.array([0, 0, 0, 0, -1.0, 0.0, 1.0] + [0.0] * (N - 7))
    d = _distance_after(env, 6, push, theta=theta, friction=fric, version=0, mass=0.2, eps=0.0,
                        start_x=0.05, texture=0)
    assert d[0] > d[1] + 0.02, f"steeper incline should slide further: {d[:2]}"
    assert d[2] > d[3] + 0.02, f"lower friction should slide further: {d[2:4]}"
    assert d[4] < d[5] - 0.02 < d[6] - 0.04, f"a push against the slide slows it, along it speeds it: {d[4:7]}"


def test_per_world_parameters_differ_and_reach_the_model(geom_env):
    env = geom_env
    state = jax.jit(env.reset)(jax.random.PRNGKey(1))
    for k in ("mass", "friction", "theta"):
        v = np.asarray(state.params[k])
        assert v.shape == (N,) and len(np.unique(v)) == N, k
    mx = env._world_model(state.params)
    bodies = env._obj_bodies[np.asarray(state.params["version"])]
    np.testing.assert_allclose(np.asarray(mx.body_mass)[np.arange(N), bodies], np.asarray(state.params["mass"]),
                               rtol=1e-6)
    np.testing.assert_allclose(np.asarray(mx.geom_friction)[:, env._incline_geom, 0],
                               np.asarray(state.params["friction"]) ** 2, rtol=1e-6)
    raw = np.asarray(state.info["lowdim_raw"])
    np.testing.assert_allclose(raw[:, 17], np.asarray(state.params["theta"]), rtol=1e-6)
    # the incline's pose follows each world's pitch
    q = np.asarray(state.data.mocap_quat[:, 0])
    np.testing.assert_allclose(2 * np.arctan2(q[:, 2], q[:, 0]), np.asarray(state.params["theta"]), atol=1e-5)


def test_depth_agrees_with_the_object_pose(geom_env):
    env = geom_env
    state = jax.jit(lambda k: env.reset_with(k, version=_versions(env)))(ALL_VERSIONS_KEY)
    state = _rollout(env, state, [jnp.zeros((N, 1))] * 6)[-1]
    depth = np.asarray(state.depth)
    assert depth.shape == (N, 64, 64) and depth.dtype == np.float32
    raw = np.asarray(state.info["lowdim_raw"])
    px, z = _project(env, state, raw[:, :3])
    seen = _in_frame(px)
    assert seen.sum() >= N // 2
    for i in np.nonzero(seen)[0]:
        c, r = np.floor(px[i]).astype(int)
        d = depth[i, r, c]
        # the surface seen at the centre's pixel lies in front of the centre, within the object
        assert z[i] - 0.2 < d < z[i] + 1e-3, f"world {i}: depth {d} vs centre depth {z[i]}"


def test_point_cloud_holds_the_object_only():
    env = bulbjax.make("GeomOnIncline", num_envs=4, version=0, render="pointcloud", num_points=256)
    state = jax.jit(env.reset)(jax.random.PRNGKey(2))
    pts = np.asarray(state.points)
    assert pts.shape == (4, 256, 3) and pts.dtype == np.float32
    assert state.pixels.shape == (4, 0, 0, 3)
    centre = np.asarray(state.info["lowdim_raw"][:, :3])
    radius = np.linalg.norm([0.0625, 0.125, 0.1875])  # the scaled block's half-diagonal
    for i in range(4):
        real = pts[i][np.abs(pts[i]).sum(-1) > 0]
        assert len(real) == 256, "the block is seen by enough pixels to fill the cloud"
        dist = np.linalg.norm(real - centre[i], axis=1)
        assert dist.max() < radius + 0.01, "only the object's points (plane and incline left out)"
        assert dist.max() > 0.8 * radius, "points cover the object, not one spot"


def test_determinism_under_a_key(geom_env):
    env = geom_env
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    a = jnp.full((N, 1), 0.3, jnp.float32)  # not weakly typed: the step program the other tests compiled
    s1, s2 = reset(jax.random.PRNGKey(5)), reset(jax.random.PRNGKey(5))
    for _ in range(2):
        s1, s2 = step(s1, a), step(s2, a)
    np.testing.assert_array_equal(np.asarray(s1.lowdim), np.asarray(s2.lowdim))
    np.testing.assert_array_equal(np.asarray(s1.pixels), np.asarray(s2.pixels))
    s3 = reset(jax.random.PRNGKey(6))
    assert not np.array_equal(np.asarray(s3.lowdim), np.asarray(reset(jax.random.PRNGKey(5)).lowdim))


def test_missing_ycb_dir_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.delenv("BULBJAX_YCB_DIR", raising=False)
    with pytest.raises(FileNotFoundError, match="BULBJAX_YCB_DIR"):
        bulbjax.make("YcbOnIncline", num_envs=1, ycb_dir=str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match="BULBJAX_YCB_DIR"):
        bulbjax.make("YcbOnIncline", num_envs=1)


def test_bad_version_and_multicolour_are_errors():
    with pytest.raises(ValueError, match="version"):
        bulbjax.make("GeomOnIncline", num_envs=1, version=6)
    with pytest.raises(ValueError, match="unknown environment"):
        bulbjax.make("GeomOnInclineMulticolour", num_envs=1)
    assert "YcbOnInclineSm" in bulbjax.envs.env_names() and "YcbOnInclineMulticolour" not in bulbjax.envs.env_names()
    assert START_POS == (-0.05, 0.0, 0.7)
