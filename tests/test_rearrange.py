"""Rearrange domains (ReacherRearrange*, FrankaRearrange*): shapes and bulb's state layout,
objects settled on the table after reset, per-object state against the scene, object and table
pixels where the camera projects them, torques moving the joints the right way (and gravity
compensation holding the Franka), a scripted sweep pushing an object, reward towards targets,
workspace termination, per-world random versions, determinism, and clear errors."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bulbjax
from bulbjax.envs.objects import rearrange as R
from bulbjax.envs.registry import _REGISTRY

YCB_DIR = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "ycb"))
N = 4
VERSIONS = np.array([0, 2, 3, 8])  # birch, orange, blue tables; 8: black background
CORNERS = np.array([[0.31, 0.31, 0.06], [0.31, -0.31, 0.06], [-0.31, 0.31, 0.06], [-0.31, -0.31, 0.06]])
UPRIGHT = np.array([1.0, 0.0, 0.0, 0.0])


class Bundle:
    """An env with its jitted reset, fixed-draw reset and step (compiled once per module)."""

    def __init__(self, env):
        self.env = env
        self.reset = jax.jit(env.reset)
        self.reset_with = jax.jit(lambda key, fixed: env.reset_with(key, **fixed))
        self.step = jax.jit(env.step)

    def fixed(self, robot_qpos, obj_pos, version=None, torques=0.0):
        """Every draw fixed (one compiled reset_with per env): objects upright at `obj_pos`."""
        env = self.env
        out = {"robot_qpos": jnp.broadcast_to(jnp.asarray(robot_qpos, jnp.float32), (N, len(env.joint_names))),
               "obj_pos": jnp.broadcast_to(jnp.asarray(obj_pos, jnp.float32), (N, env.num_objects, 3)),
               "obj_quat": jnp.broadcast_to(jnp.asarray(UPRIGHT, jnp.float32), (N, env.num_objects, 4)),
               "torques": jnp.broadcast_to(jnp.asarray(torques, jnp.float32), (N, R.RANDOM_TORQUE_STEPS, env.controlled))}
        if env.random_version:
            out["version"] = jnp.asarray(VERSIONS if version is None else version, jnp.int32)
        return out


@pytest.fixture(scope="module")
def reacher():
    return Bundle(bulbjax.make("ReacherRearrangeGeom", num_envs=N, resolution=64, version="random"))


@pytest.fixture(scope="module")
def franka():
    pytest.importorskip("pybullet_data")
    return Bundle(bulbjax.make("FrankaRearrangeGeom", num_envs=N, resolution=32, version=1))


def _raw(env, state):
    """Joint angles `[N, J]` and per-object position `[N, M, 3]`, quaternion `[N, M, 4]`, from
    `info["lowdim_raw"]`."""
    raw = np.asarray(state.info["lowdim_raw"])
    nj = len(env.joint_names)
    obj = raw[:, 2 * nj:2 * nj + 13 * env.num_objects].reshape(len(raw), env.num_objects, 13)
    return raw[:, :nj], obj[..., :3], obj[..., 3:7]


def _project(env, state, points):
    """Pixel (column, row) of world points `[N, 3]` in each world's bulb camera."""
    pos = np.asarray(state.data.cam_xpos[:, 0])
    mat = np.asarray(state.data.cam_xmat[:, 0]).reshape(-1, 3, 3)
    local = np.einsum("nji,nj->ni", mat, points - pos)
    half = np.tan(np.deg2rad(env.camera.fovy) / 2)
    res = env.resolution
    col = (local[:, 0] / -local[:, 2] / half + 1) / 2 * res
    row = (1 - local[:, 1] / -local[:, 2] / half) / 2 * res
    return np.stack([col, row], axis=1)


def test_reset_step_shapes_spec_and_random_versions(reacher):
    env = reacher.env
    state = reacher.reset(jax.random.PRNGKey(0))
    for _ in range(2):
        state = reacher.step(state, jnp.zeros((N, 2)))
    d = len(env.state_spec)
    assert d == 2 * 2 + 4 * (12 + 3 + 9) == len(_REGISTRY["ReacherRearrangeGeom"].state_spec)
    assert state.lowdim.shape == (N, d) and state.lowdim.dtype == jnp.float32
    assert state.pixels.shape == (N, 64, 64, 3) and state.pixels.dtype == jnp.uint8
    assert state.info["lowdim_raw"].shape == (N, len(env.raw_state_spec))
    low = np.asarray(state.lowdim)
    assert np.isfinite(low).all() and (np.abs(low) <= 1 + 1e-6).all()
    groups = [e.group for e in env.state_spec]
    assert groups == ["robot"] * 4 + ["object_static"] * 48 + ["object_position"] * 12 + ["object_orientation"] * 36
    names = [e.name for e in env.state_spec]
    assert names[:4] == ["j0_sin", "j0_cos", "j1_sin", "j1_cos"] and names[4] == "obj0_rgb_r"
    assert names[52:55] == ["obj0_x", "obj0_y", "obj0_z"] and names[64] == "obj0_rot0"
    # FrankaRearrange reports the 7 arm joints and the 2 (fixed) fingers, as bulb does
    assert len(_REGISTRY["FrankaRearrangeOneYcb"].state_spec) == 9 * 2 + 12 + 3 + 9
    # per-world versions: one batch holds several, and the static properties follow them
    versions = np.asarray(reacher.reset(jax.random.PRNGKey(1)).params["version"])
    state = reacher.reset_with(jax.random.PRNGKey(1), reacher.fixed((0.0, 0.0), CORNERS))
    np.testing.assert_array_equal(np.asarray(state.params["version"]), VERSIONS)
    props = np.asarray(state.lowdim[:, 4:52]).reshape(N, 4, 12)
    # object 0 is bulb's cylinder in versions 0-4: blue in v0, green in v2, red in v3, magenta in v8 (= v2's
    # list with GEOM_COLORS[8] = v2's colours)
    np.testing.assert_allclose(props[:, 0, :3], [[-1, -1, 1], [-1, 1, -1], [1, -1, -1], [-1, 1, -1]])
    assert props[0, 0, 6] == pytest.approx(2 * 1 / 3 - 1)  # shape id 1 (cylinder) of [0, 3]
    assert versions.min() >= 0 and versions.max() < R.NUM_VERSIONS


def test_objects_settle_on_the_table_and_state_matches_the_scene(reacher):
    env = reacher.env
    state = reacher.reset(jax.random.PRNGKey(2))
    _, pos, quat = _raw(env, state)
    assert np.isfinite(pos).all()
    assert (np.abs(pos[..., :2]) < 0.4).all(), "objects inside the tray's borders"
    # bulb's reset drops four objects into a 0.3 m square and lets the arm hit them: most rest on
    # the floor at one of their half-extents, some lean on or lie on another; none sinks or flies
    resting = []
    for i, v in enumerate(np.asarray(state.params["version"])):
        for k, name in enumerate(R.OBJECT_LISTS["Geom"][v % 6]):
            dims = R.GEOM_INFO[name].dims
            assert min(dims) - 0.01 < pos[i, k, 2] < 0.2, (name, pos[i, k])
            resting.append(pos[i, k, 2] < max(dims) + 0.01)
    assert np.mean(resting) >= 0.6, resting
    # the state's positions and rotation matrices are the objects' (bodies of the version's slots)
    low = np.asarray(state.lowdim)
    lo, hi = R.OBJ_XYZ_MIN, R.OBJ_XYZ_MAX
    np.testing.assert_allclose(low[:, 52:64].reshape(N, 4, 3), (pos - lo) / (hi - lo) * 2 - 1, atol=1e-5)
    slots = np.asarray(env._version_slots)[np.asarray(state.params["version"])]
    xmat = np.asarray(state.data.xmat)[np.arange(N)[:, None], env._slot_bodies[slots]]
    np.testing.assert_allclose(low[:, 64:].reshape(N, 4, 9), xmat.reshape(N, 4, 9), atol=1e-4)
    xpos = np.asarray(state.data.xpos)[np.arange(N)[:, None], env._slot_bodies[slots]]
    np.testing.assert_allclose(xpos, pos, atol=1e-5)
    # unused objects of the union are parked far above
    parked = np.setdiff1d(np.arange(len(env.slot_names)), slots[0])
    assert (np.asarray(state.data.xpos)[0, env._slot_bodies[parked], 2] > 40).all()


def test_table_object_and_background_pixels(reacher):
    env = reacher.env
    state = reacher.reset_with(jax.random.PRNGKey(3), reacher.fixed((0.0, 0.0), CORNERS))
    frames = np.asarray(state.pixels).astype(int)
    # a spot of the tray's bottom no object or arm reaches (between two corner objects)
    spot = _project(env, state, np.tile([[0.36, 0.0, 0.0]], (N, 1)))
    for i, v in enumerate(VERSIONS):
        c, r = np.floor(spot[i]).astype(int)
        rgb = frames[i, r, c]
        if v >= 6:
            assert rgb.max() < 40, f"version {v}: black background, got {rgb}"
        else:
            table = R.TABLE_RGB[v] * 255
            # shaded, but in the texture's hue: the channels ordered as the table colour's
            assert np.argmax(rgb) == np.argmax(table) and np.argmin(rgb) == np.argmin(table), (v, rgb, table)
    # each corner object is drawn where its centre projects (mask: pixels that change when the
    # objects are parked out of view)
    ri = state.render_input
    parked = ri.replace(qpos=jnp.broadcast_to(env._qpos_park.at[env._robot_qadr].set(ri.qpos[0, env._robot_qadr]),
                                              ri.qpos.shape))
    empty = np.asarray(jax.jit(env.render_frames)(parked)).astype(int)
    mask = np.abs(frames - empty).sum(-1) > 30
    _, pos, _ = _raw(env, state)
    for k in range(4):
        px = _project(env, state, pos[:, k])
        for i in range(N):
            c, r = np.floor(px[i]).astype(int)
            assert mask[i, max(r - 1, 0):r + 2, max(c - 1, 0):c + 2].any(), f"world {i} object {k} not at {px[i]}"


def test_torques_move_the_reacher_and_its_sweep_pushes_an_object(reacher):
    env = reacher.env
    s = reacher.reset_with(jax.random.PRNGKey(4), reacher.fixed((0.0, 0.5), CORNERS))
    q0, p0, _ = _raw(env, s)
    np.testing.assert_allclose(q0, [[0.0, 0.5]] * N, atol=1e-4)  # no torques at reset, nothing touched
    # objects dropped upright in the corners come to rest standing on the floor at their half-heights
    vel = np.asarray(s.info["lowdim_raw"])[:, 4:56].reshape(N, 4, 13)[..., 7:13]
    for i, v in enumerate(VERSIONS):
        half = [R.GEOM_INFO[n].dims[2] for n in R.OBJECT_LISTS["Geom"][v % 6]]
        np.testing.assert_allclose(p0[i, :, 2], half, atol=3e-3)
    np.testing.assert_allclose(p0[..., :2], np.broadcast_to(CORNERS[:, :2], (N, 4, 2)), atol=0.01)
    assert np.abs(vel).max() < 0.05, "at rest"
    actions = jnp.asarray([[1.0, -1.0], [-1.0, 1.0], [0.0, 0.0], [0.0, 0.0]])
    for _ in range(8):
        s = reacher.step(s, actions)
    q, _, _ = _raw(env, s)
    dq = q - q0
    # the arm is slow (armature 1 per joint): ~0.01 rad after 8 steps at full torque
    assert dq[0, 0] > 0.005 and dq[0, 1] < -0.005 and dq[1, 0] < -0.005 and dq[1, 1] > 0.005, dq
    np.testing.assert_allclose(dq[2:], 0.0, atol=1e-4)  # no torque, no motion
    # a counter-clockwise sweep of joint 0 from (0, 0) runs into an object beside the arm
    pos = CORNERS.copy()
    pos[0] = [0.2, 0.095, 0.06]  # object 0, the r 0.06 cylinder, 0.01 m from the shoulder capsule
    s = reacher.reset_with(jax.random.PRNGKey(4), reacher.fixed((0.0, 0.0), pos, version=[0, 1, 2, 3]))
    _, p0, _ = _raw(env, s)
    for _ in range(40):
        s = reacher.step(s, jnp.asarray([[1.0, 0.0]] * N))
    q1, p1, _ = _raw(env, s)
    moved = np.linalg.norm(p1[:, 0, :2] - p0[:, 0, :2], axis=1)
    assert (q1[:, 0] > 0.1).all(), q1
    assert (moved > 0.015).all(), f"the swept object should move: {moved}"
    assert (np.linalg.norm(p1[:, 1:, :2] - p0[:, 1:, :2], axis=2) < 0.01).all(), "corner objects stay"


def test_reward_rises_near_targets_and_leaving_the_workspace_ends_the_episode(reacher):
    env = reacher.env
    near = np.array([[0.12, 0.12, 0.06], [0.28, 0.12, 0.08], [0.12, 0.28, 0.04], [0.28, 0.28, 0.06]])
    far = np.array([[-0.3, 0.3, 0.06], [-0.3, -0.3, 0.08], [-0.12, -0.3, 0.04], [-0.3, 0.0, 0.06]])
    out = far.copy()
    out[0] = [0.6, 0.0, 0.06]  # beyond the box [-0.45, 0.45]: outside the tray, on the floor
    pos = np.stack([near, far, out, near])
    s = reacher.reset_with(jax.random.PRNGKey(5), reacher.fixed((np.pi / 2, 0.0), pos, version=[0, 0, 0, 0]))
    s1 = reacher.step(s, jnp.zeros((N, 2)))
    r = np.asarray(s1.reward)
    _, p, _ = _raw(env, s)
    dist = np.minimum(np.linalg.norm(p[..., :2] - R.TARGETS[1], axis=2), 1.0)  # geoms: the (0.2, 0.2) target
    np.testing.assert_allclose(r[[0, 1, 3]], ((1 - dist.mean(1)) / R.EPISODE_STEPS)[[0, 1, 3]], atol=2e-5)
    assert r[0] > r[1] + 1e-3
    done = np.asarray(s1.done)
    assert done[2] == 1 and done[[0, 1, 3]].sum() == 0 and np.asarray(s1.truncated)[2] == 0
    assert int(s1.step_count[2]) == 0 and int(s1.step_count[0]) == 1  # world 2 was reset
    assert float(s1.info["episode_length"][2]) == 1


def test_determinism_under_a_key(reacher):
    s1, s2 = reacher.reset(jax.random.PRNGKey(7)), reacher.reset(jax.random.PRNGKey(7))
    a = jnp.full((N, 2), 0.3)
    for _ in range(2):
        s1, s2 = reacher.step(s1, a), reacher.step(s2, a)
    np.testing.assert_array_equal(np.asarray(s1.lowdim), np.asarray(s2.lowdim))
    np.testing.assert_array_equal(np.asarray(s1.pixels), np.asarray(s2.pixels))
    s3 = reacher.reset(jax.random.PRNGKey(8))
    assert not np.array_equal(np.asarray(s3.lowdim), np.asarray(s1.lowdim))


def test_franka_gravity_compensation_torques_and_random_pose(franka):
    env = franka.env
    # a pose with the hand above the table (at bulb's rest pose this Panda's longer fingers touch the floor)
    pose = np.array([0.0, 0.3, 0.0, -2.2, 0.0, 2.6, 0.8])
    s = franka.reset_with(jax.random.PRNGKey(0), franka.fixed(pose, CORNERS))
    q0, _, _ = _raw(env, s)
    np.testing.assert_allclose(q0, np.tile(pose, (N, 1)), atol=2e-3)  # held by gravity compensation
    actions = np.zeros((N, 7), np.float32)
    actions[0, 0], actions[1, 0], actions[2, 3] = 0.5, -0.5, -0.5
    for _ in range(6):
        s = franka.step(s, jnp.asarray(actions))
    q, _, _ = _raw(env, s)
    dq = q - q0
    assert dq[0, 0] > 0.01 and dq[1, 0] < -0.01 and dq[2, 3] < -0.01, dq
    np.testing.assert_allclose(dq[3], 0.0, atol=2e-3)
    low = np.asarray(s.lowdim)
    assert low.shape == (N, 18 + 4 * 24) and np.isfinite(low).all()
    np.testing.assert_allclose(low[:, 14:18], [[0, 1, 0, 1]] * N, atol=1e-6)  # fingers fixed at 0
    assert s.pixels.shape == (N, 32, 32, 3)
    # random reset pose: bulb's end-effector targets solved by IK within the joint ranges; the
    # reachable ones (within 0.75 m of the shoulder) are met, the hand pointing as asked
    keys = jax.random.split(jax.random.PRNGKey(1), 16)
    targets = jax.vmap(env._ee_target)(keys)
    q = jax.jit(jax.vmap(env.solve_ik))(*targets)
    hand, rot, zs = jax.vmap(env.hand_pose)(q)
    q = np.asarray(q)
    assert (q >= np.asarray(env._jnt_lo) - 1e-5).all() and (q <= np.asarray(env._jnt_hi) + 1e-5).all()
    reach = np.linalg.norm(np.asarray(targets[0]) - (np.asarray(R.FRANKA_BASE) + [0, 0, 0.333]), axis=1) < 0.75
    assert reach.sum() >= 4
    err = np.linalg.norm(np.asarray(hand) - np.asarray(targets[0]), axis=1)
    assert np.median(err[reach]) < 0.01, err[reach]
    assert np.median(np.abs(np.asarray(rot) - np.asarray(targets[1])).max(axis=(1, 2))[reach]) < 0.05
    assert (np.asarray(rot)[:, 2, 2] < 0.1).mean() > 0.5, "the gripper mostly points down"


def test_ycb_variant_settles_and_missing_ycb_dir_is_a_clear_error(tmp_path, monkeypatch):
    if os.path.isdir(YCB_DIR):
        env = bulbjax.make("ReacherRearrangeOneYcb", num_envs=2, resolution=32, version=3, ycb_dir=YCB_DIR)
        s = jax.jit(env.reset)(jax.random.PRNGKey(0))
        _, pos, _ = _raw(env, s)
        assert np.isfinite(pos).all() and (np.abs(pos[..., :2]) < 0.4).all()
        # pudding box (version 3): its COM rests between its smallest and largest half-extent
        assert (pos[..., 2] > 0.01).all() and (pos[..., 2] < 0.1).all(), pos
        assert len(env.state_spec) == 4 + 24 and env.slot_names == ["008_pudding_box"]
    monkeypatch.delenv("BULBJAX_YCB_DIR", raising=False)
    with pytest.raises(FileNotFoundError, match="BULBJAX_YCB_DIR"):
        bulbjax.make("ReacherRearrangeYcb", num_envs=1, ycb_dir=str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match="BULBJAX_YCB_DIR"):
        bulbjax.make("FrankaRearrangeOneYcb", num_envs=1)


def test_bad_version_and_fields_are_errors(reacher):
    with pytest.raises(ValueError, match="version"):
        bulbjax.make("ReacherRearrangeGeom", num_envs=1, version=12)
    with pytest.raises(ValueError, match="unknown environment"):
        bulbjax.make("ReacherRearrangeGeomMulticolour", num_envs=1)
    with pytest.raises(ValueError, match="unknown reset fields"):
        reacher.env.reset_with(jax.random.PRNGKey(0), mass=1.0)
