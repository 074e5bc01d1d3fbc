"""Rearrange's `show_targets` option: bulb's two target areas drawn as discs on the tray floor
(visual only). With it, the pixels where the targets project have the targets' colours; without
it (the default, bulb's frames), the tray's; the physics is bit-identical either way. About 40 s
on 2 CPU cores (two env builds and compiles)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bulbjax
from bulbjax.envs.objects import rearrange as R
from bulbjax.eval.objects import project_points, world_camera

N = 2
VERSIONS = (0, 3)  # birch table, blue-purple table (the closest to the violet target)
CORNERS = np.array([[0.31, 0.31, 0.06], [0.31, -0.31, 0.06], [-0.31, 0.31, 0.06], [-0.31, -0.31, 0.06]])


@pytest.fixture(scope="module")
def envs():
    """(without targets, with targets), each with its jitted `reset_with` (every draw fixed, so
    one compile serves both tests) and `physics`."""
    out = []
    for show in (False, True):
        env = bulbjax.make("ReacherRearrangeGeom", num_envs=N, resolution=64, version="random", show_targets=show)
        out.append((env, jax.jit(lambda k, f, e=env: e.reset_with(k, **f)),
                    jax.jit(lambda d, a, p, e=env: e.physics(d, a, p))))
    return out


def _fixed(robot_qpos, obj_pos, obj_quat, torques) -> dict[str, jax.Array]:
    return {"version": jnp.asarray(VERSIONS, jnp.int32),
            "robot_qpos": jnp.broadcast_to(jnp.asarray(robot_qpos, jnp.float32), (N, 2)),
            "obj_pos": jnp.broadcast_to(jnp.asarray(obj_pos, jnp.float32), (N, 4, 3)),
            "obj_quat": jnp.broadcast_to(jnp.asarray(obj_quat, jnp.float32), (N, 4, 4)),
            "torques": jnp.broadcast_to(jnp.asarray(torques, jnp.float32), (N, R.RANDOM_TORQUE_STEPS, 2))}


def _chroma(rgb: np.ndarray) -> np.ndarray:
    """Colour without brightness (the renderer's shading and saturation change brightness)."""
    rgb = np.asarray(rgb, float)
    return rgb / max(rgb.sum(), 1e-9)


def test_targets_are_drawn_only_when_asked(envs):
    (plain, reset_plain, _), (shown, reset_shown, _) = envs
    assert plain.mj_model.ngeom + 2 == shown.mj_model.ngeom
    for i in range(2):
        g = shown.mj_model.geom(f"target{i}")
        assert g.contype == 0 and g.conaffinity == 0
    # the arm pointing away from the targets (-x), the objects parked upright in the corners
    fixed = _fixed((np.pi, 0.0), CORNERS, (1.0, 0, 0, 0), 0.0)
    frames = [np.asarray(r(jax.random.PRNGKey(0), fixed).pixels) for r in (reset_plain, reset_shown)]
    pos, mat, fovy = world_camera(shown.mj_model)
    top = 0.0005 + 2 * R.TARGET_HALF_HEIGHT
    px = np.asarray(project_points(jnp.asarray(np.c_[R.TARGETS, [top, top]]), pos, mat, fovy, 64)).astype(int)
    targets = [_chroma(rgba[:3]) for rgba in R.TARGET_RGBA]
    for w, v in enumerate(VERSIONS):
        tray = _chroma(R.TABLE_RGB[v])
        for i, (col, row) in enumerate(px):
            without, with_ = frames[0][w, row, col], frames[1][w, row, col]
            # nearest in colour (tray vs the two targets): without -> the tray, with -> target i
            near = lambda p: int(np.argmin([np.abs(_chroma(p) - c).sum() for c in (tray, *targets)]))
            assert near(without) == 0, (v, i, without)
            assert near(with_) == 1 + i, (v, i, with_)
            assert np.abs(with_.astype(int) - without.astype(int)).max() > 80, (v, i, with_, without)


def test_physics_is_identical_with_and_without_targets(envs):
    """Same draws (the arm swinging into four objects dropped in a heap) and actions: bit-equal
    states through bulb's reset (20 settle and 10 random-torque steps) and 3 more steps."""
    rng = np.random.default_rng(0)
    quat = rng.uniform(size=(N, 4, 4))
    fixed = _fixed(rng.uniform(-2.0, 2.0, (N, 2)), rng.uniform([-0.15, -0.15, 0.04], [0.15, 0.15, 0.075], (N, 4, 3)),
                   quat / np.linalg.norm(quat, axis=-1, keepdims=True), rng.uniform(-0.5, 0.5, (N, 10, 2)))
    actions = jnp.asarray(rng.uniform(-1, 1, (3, N, 2)), jnp.float32)
    out = []
    for env, reset_with, physics in envs:
        state = reset_with(jax.random.PRNGKey(1), fixed)
        data = state.data
        for a in actions:
            data = physics(data, a, state.params)
        out.append((state, data))
    (s0, d0), (s1, d1) = out
    np.testing.assert_array_equal(np.asarray(s0.lowdim), np.asarray(s1.lowdim))
    for field in ("qpos", "qvel", "qacc", "qfrc_constraint"):
        np.testing.assert_array_equal(np.asarray(getattr(d0, field)), np.asarray(getattr(d1, field)), err_msg=field)
    assert np.abs(np.asarray(d0.qvel)).max() > 0.1  # things moved (contacts happened)


def test_show_targets_is_refused_where_there_are_none():
    with pytest.raises(ValueError, match="no targets"):
        bulbjax.make("CartPole", num_envs=1, render=False, show_targets=True)
    with pytest.raises(ValueError, match="show_targets must be True or False"):
        bulbjax.make("ReacherRearrangeGeom", num_envs=1, render=False, show_targets="yes")


def test_target_colours_stand_apart_from_the_scene():
    """The stated margin: each target colour at least 0.5 (largest channel difference) from every
    tray colour (black included), geom-object colour, the reacher's white and orange, the Franka
    floor and the other target."""
    scene = [*R.TABLE_RGB, (0, 0, 0), *[c for v in R.GEOM_COLOURS for c in v], (1, 1, 1), (1, 0.6, 0.15),
             R.FrankaRearrange.floor_rgba[:3]]
    for i, rgba in enumerate(R.TARGET_RGBA):
        others = [*scene, R.TARGET_RGBA[1 - i][:3]]
        assert np.abs(np.asarray(others, float) - rgba[:3]).max(1).min() >= 0.5 - 1e-9, i
