"""Incline parity (CPU, about a minute): the PyBullet original (`pybullet_compat.incline`) against
bulbjax's MJX mirror of GeomOnIncline version 0 from the same draws and states, both against the
analytic slide, the push's sign, and the PyBullet env's own contract (draws, state, errors, same
facts and meshes as the mirror)."""

from __future__ import annotations

import os
from dataclasses import asdict

import numpy as np
import pytest

pytest.importorskip("pybullet")

from pybullet_compat import incline as pbi  # noqa: E402
from pybullet_compat import parity_incline as par  # noqa: E402

YCB_DIR = os.path.normpath(os.path.join(os.path.dirname(__file__), "..", "..", "shared", "ycb"))
CFG = par.InclineParityConfig(name="GeomOnIncline", version=0, worlds=8, steps=10)
DT = pbi.BULLET_DT * pbi.STEPS_PER_ACTION


@pytest.fixture(scope="module")
def mirror():
    return par.InclineMirror(CFG)


@pytest.fixture(scope="module")
def draws():
    rng = np.random.default_rng(0)
    return [pbi.draw_params(rng) for _ in range(CFG.worlds)]


def _live_errors(pb: np.ndarray, mj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    live = ~(par.ended(pb) | par.ended(mj))
    assert live[-1].sum() >= CFG.worlds // 2, "most starts must still be sliding at the horizon"
    dist = np.where(live, np.abs(pb[..., par.DIST] - mj[..., par.DIST]), 0.0)
    speed = np.where(live, np.abs(pb[..., par.SPEED] - mj[..., par.SPEED]), 0.0)
    return dist, speed


@pytest.mark.parametrize("kind", ["zero", "random"])
def test_same_state_trajectories_agree_over_0_4_s(mirror, draws, kind):
    """From the MJX post-reset state, 10 steps (0.4 s): PyBullet as bulb runs it within 2 cm and
    0.1 m/s (the gap is Bullet's base damping, growing with speed), and without that damping
    within 2 mm and 0.03 m/s at every step of every start."""
    acts = par.action_sequences(CFG.steps, CFG.worlds, CFG.seed)[kind]
    state = mirror.reset(draws)
    mj = mirror.play(state, acts)
    starts = mirror.raw(state)[:, :13]
    assert (mj[0, :, 0] > 0.05).all() and (mj[0, :, par.SPEED] > 0.3).all(), "the reset ends mid-slide"
    for damping, dist_tol, speed_tol in ((True, 0.02, 0.1), (False, 0.002, 0.03)):
        side = par.BulletSide(CFG, bullet_damping=damping)
        pb = side.play(draws, acts, starts)
        side.close()
        np.testing.assert_allclose(pb[0, :, :13], starts, atol=1e-6)  # really the same start
        dist, speed = _live_errors(pb, mj)
        assert dist.max() < dist_tol, f"damping={damping}: distance error {dist.max():.4f} m"
        assert speed.max() < speed_tol, f"damping={damping}: speed error {speed.max():.4f} m/s"
        if damping:  # Bullet's damping only takes speed away: PyBullet is never the faster one
            late = np.where(~(par.ended(pb) | par.ended(mj))[-1])[0]
            assert (pb[-1, late, par.SPEED] <= mj[-1, late, par.SPEED] + 0.01).all()


def test_own_resets_agree(mirror, draws):
    """Each simulator runs bulb's whole reset (fall from the same pose to the same start_x) and
    the same zero push: starts within 1.5 cm and 0.06 m/s, trajectories within 3 cm, 0.12 m/s."""
    acts = np.zeros((CFG.steps, CFG.worlds))
    mj = mirror.play(mirror.reset(draws), acts)
    side = par.BulletSide(CFG)
    pb = side.play(draws, acts)
    side.close()
    assert np.abs(pb[0, :, 0] - mj[0, :, 0]).max() < 0.015
    assert np.abs(pb[0, :, par.SPEED] - mj[0, :, par.SPEED]).max() < 0.06
    dist, speed = _live_errors(pb, mj)
    assert dist.max() < 0.03 and speed.max() < 0.12, (dist.max(), speed.max())


def test_both_simulators_follow_the_analytic_slide(mirror):
    """a = g (sin theta - friction^2 cos theta) + F / m on a block put flat on the incline at
    0.5 m/s (8 cases of pitch, friction, mass and push, one decelerating): PyBullet without
    damping within 0.01 m/s^2, PyBullet with its damping within 0.02 of the analytic value
    less 0.04 v (1 + v), MJX within 0.08 m/s^2 (its soft contacts jitter by a few 0.01)."""
    a = par.analytic_check(mirror, CFG)
    assert a["pybullet_no_damping_max_abs_err"] < 0.01
    assert a["pybullet_max_abs_err"] < 0.02
    assert a["mjx_max_abs_err"] < 0.08
    for c in a["cases"]:  # the check can fail: the cases span decelerating to 13 m/s^2
        assert np.sign(c["mjx"]) == np.sign(c["analytic"]) == np.sign(c["pybullet"])
        assert c["pybullet"] < c["pybullet_no_damping"], "Bullet's damping slows the slide"
    assert max(c["analytic"] for c in a["cases"]) > 10 and min(c["analytic"] for c in a["cases"]) < -0.5


def test_push_along_the_object_axis_has_the_same_sign_and_size(mirror):
    """Pushes -1, -0.5, 0, +0.5, +1 from the same state: in both simulators a positive push
    (along the object's z axis, down the slope in bulb's start pose) lengthens the slide and a
    negative one shortens it, by amounts within 10% of each other."""
    pushes = np.array([-1.0, -0.5, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0])
    base = pbi.InclineParams(mass=0.3, friction=0.3, theta=0.35, texture=0, eps=0.0, start_x=0.1)
    params = [base] * CFG.worlds
    steps = 6
    acts = np.repeat(pushes[None], CFG.steps, 0)
    state = mirror.reset(params)
    mj = mirror.play(state, acts)
    side = par.BulletSide(CFG, bullet_damping=False)
    pb = side.play(params, acts[:steps], mirror.raw(state)[:, :13])
    side.close()
    d_mj = (mj[steps, :5, par.DIST] - mj[0, :5, par.DIST])
    d_pb = (pb[steps, :5, par.DIST] - pb[0, :5, par.DIST])
    assert (np.diff(d_mj) > 0.01).all() and (np.diff(d_pb) > 0.01).all(), (d_mj, d_pb)
    effect_mj, effect_pb = d_mj - d_mj[2], d_pb - d_pb[2]
    np.testing.assert_allclose(effect_mj[[0, 1, 3, 4]], effect_pb[[0, 1, 3, 4]], rtol=0.1)


def test_friction_and_pitch_sweeps_move_both_slides_the_same_way(mirror):
    """Distance after 8 steps over bulb's friction and pitch ranges: same ordering in both
    simulators (more friction: shorter; steeper: longer) and within 2 cm."""
    res = par.sweeps(mirror, par.BulletSide(CFG), CFG)
    for param, sign in (("friction", -1), ("theta", 1)):
        row = res[param]
        d_mj, d_pb = np.array(row["mjx_distance"]), np.array(row["pybullet_distance_same_state"])
        assert (np.sign(np.diff(d_mj)) == sign).all() and (np.sign(np.diff(d_pb)) == sign).all(), param
        assert row["same_state_max_abs_diff"] < 0.02 and row["own_reset_max_abs_diff"] < 0.03, row
    assert res["mass"]["same_trend"] and res["mass"]["spearman_same_state"] > 0.99


# ---------------------------------------------------------------------------------- the PyBullet env
def test_reset_takes_fixed_draws_and_reports_bulbs_state():
    env = pbi.InclineBulletEnv("GeomOnIncline", 0, resolution=32)
    frame, state = env.reset(seed=3, mass=0.3, friction=0.2, theta=0.45, texture=4, eps=0.1, start_x=0.12)
    assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8
    assert state.shape == (5,) and state.dtype == np.float32 and ((state >= 0) & (state <= 1)).all()
    assert env.params == pbi.InclineParams(0.3, 0.2, 0.45, 4, 0.1, 0.12)
    dyn = env.dynamics()
    assert dyn["mass"] == pytest.approx(0.3) and dyn["contact_friction"] == pytest.approx(0.04)
    raw = env.raw_state()
    assert raw[0] > 0.12 and 0 < env.fall_steps <= pbi.FALL_STEPS  # the fall ended past start_x
    np.testing.assert_allclose(state[[0, 1, 2]], [4 / 6, 0, (0.45 - 0.25) / 0.25], atol=1e-6)
    np.testing.assert_allclose(state[3], raw[18] / pbi.CLIP_DIST, atol=1e-6)
    # the object is in its own frame where the camera says (segmentation around the projection)
    col, row = env.project(raw[:3])
    mask = env.object_mask()
    r, c = int(row), int(col)
    assert mask[max(r - 2, 0):r + 3, max(c - 2, 0):c + 3].any()
    # bulb's draws when nothing is fixed: in bulb's ranges, and different per seed
    a = []
    for s in range(6):
        env.reset(seed=s)
        a.append(env.params)
    for p in a:
        assert pbi.MASS[0] <= p.mass <= pbi.MASS[1] and pbi.FRICTION[0] <= p.friction <= pbi.FRICTION[1]
        assert pbi.PITCH[0] <= p.theta <= pbi.PITCH[1] and abs(p.eps) <= pbi.START_EPS
    assert len({p.mass for p in a}) == 6
    r1 = env.step([1.0])
    assert r1.state.shape == (5,) and isinstance(r1.reward, float)
    env.close()


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown Incline domain"):
        pbi.InclineBulletEnv("BlockOnIncline")
    with pytest.raises(ValueError, match="version"):
        pbi.InclineBulletEnv("GeomOnIncline", version=6)
    env = pbi.InclineBulletEnv("GeomOnInclineSm", 3, render=False)
    with pytest.raises(ValueError, match="unknown reset fields"):
        env.reset(pitch=0.3)
    with pytest.raises(ValueError, match="mass"):
        env.reset(mass=0.0)
    with pytest.raises(RuntimeError, match="reset"):
        pbi.InclineBulletEnv("GeomOnIncline", 0, render=False).step([0.0])
    env.close()


def test_same_facts_as_the_mirror():
    """bulb's numbers here equal bulbjax's (copied so that worker processes need no JAX)."""
    from bulbjax.envs.objects import incline as mj

    for name in ("NUM_VERSIONS", "EPISODE_STEPS", "BULLET_DT", "BULLET_SUBSTEPS", "STEPS_PER_ACTION", "MAX_FORCE",
                 "INCLINE_POS", "INCLINE_HALF", "START_POS", "START_EPS", "START_X", "FALL_STEPS", "MASS",
                 "FRICTION", "PITCH", "CLIP_DIST", "CLIP_SPEED", "SCALES", "YCB_OBJECTS", "GEOM_COLOURS",
                 "INCLINE_COLOURS", "GEOM_PLANE_COLOUR", "YCB_PLANE_COLOURS", "YCB_INCLINE_COLOURS"):
        assert getattr(pbi, name) == getattr(mj, name), name
    assert pbi.state_names() == tuple(e.name for e in mj.incline_state_spec(False))
    assert pbi.state_names(True) == tuple(e.name for e in mj.incline_state_spec(True))
    assert pbi.RAW_NAMES == tuple(e.name for e in mj.Incline.raw_state_spec.fget(None))


def test_ycb_object_uses_the_mirrors_processed_meshes():
    if not os.path.isdir(YCB_DIR):
        pytest.skip(f"YCB models not found at {YCB_DIR}")
    from bulbjax.assets import load_ycb_object

    spec = pbi.incline_domain("YcbOnInclineSm")
    shape = pbi.object_shape(spec, 1, ycb_dir=YCB_DIR)
    asset = load_ycb_object("008_pudding_box", scale=1.0, ycb_dir=YCB_DIR)
    assert shape.collision_path == str(asset.collision_path) and shape.visual_path == str(asset.visual_path)
    np.testing.assert_allclose(shape.com, asset.com)
    env = pbi.InclineBulletEnv("YcbOnInclineSm", 1, resolution=32, shape=shape)
    env.reset(seed=0, **{k: v for k, v in asdict(pbi.InclineParams(0.2, 0.3, 0.4, 1, 0.0, 0.1)).items()})
    aabb_lo, aabb_hi = (np.array(v) for v in env.client.getAABB(env.block_id))
    size = np.sort(aabb_hi - aabb_lo)
    box = np.sort(asset.bounds[1] - asset.bounds[0])
    # the collision hull's world box holds the object's extents (rotated on the incline: >=)
    assert (size >= 0.9 * box.min()).all() and size.max() <= 1.5 * np.linalg.norm(box)
    assert env.raw_state()[0] > 0.1
    env.close()
