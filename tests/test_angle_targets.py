"""Major-axis angle targets (issue 37): the in-plane angle of an object's major axis modulo its
symmetry, as (cos 2θ, sin 2θ) probe targets derived from a Rearrange state (not part of the env's
state, whose layout mirrors bulb's), their symmetry, exclusion of spheres, and the angle error.
CPU only; no environment is built."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.envs.objects.rearrange_scene import (GEOM_COLOURS, GEOM_INFO, OBJECT_LISTS, PROP_MAX, PROP_MIN, _normalise,
                                          rearrange_state_spec)
from bulbjax.epoch.probing import fit_and_score, probe_targets
from bulbjax.eval import angles
from bulbjax.eval.probe import ProbeConfig, summarise


def _rz(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _rx(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


BLOCK = np.array([0.025, 0.05, 0.075])  # bulb's block, half-extents along body x, y, z


def _c2s2(rot, shape, ext=BLOCK):
    return np.asarray(angles.major_axis_c2s2(jnp.asarray(rot, jnp.float32), jnp.asarray(shape), jnp.asarray(ext, jnp.float32)))


def test_a_box_turned_by_pi_about_z_has_the_same_target_and_by_half_pi_the_opposite():
    # lying on its 10 x 15 cm face (body x up): the major axis is the 15 cm body z, in the plane
    lying = np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]], float)  # about y by -90 deg: body x up, body z along -x
    assert np.allclose(lying @ lying.T, np.eye(3)) and np.isclose(np.linalg.det(lying), 1)
    for t in (0.3, -1.2, 2.0):
        a = _c2s2(_rz(t) @ lying, angles.BOX)
        b = _c2s2(_rz(t + math.pi) @ lying, angles.BOX)
        np.testing.assert_allclose(a, b, atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(a), 1.0, atol=1e-6)
        np.testing.assert_allclose(_c2s2(_rz(t + math.pi / 2) @ lying, angles.BOX), -a, atol=1e-6)
        # the axis is body z, lying along world -x turned by t: theta = t + pi (= t mod pi)
        assert float(angles.angle_error(jnp.asarray(a), jnp.asarray([math.cos(2 * t), math.sin(2 * t)]))) < 1e-5


def test_the_blocks_axis_is_the_long_side_of_its_footprint():
    # standing on its 5 x 10 cm face (body z up): the footprint's long side is the 10 cm body y
    t = 0.4
    got = _c2s2(_rz(t), angles.BOX)
    want = np.array([math.cos(2 * (t + math.pi / 2)), math.sin(2 * (t + math.pi / 2))])
    np.testing.assert_allclose(got, want, atol=1e-6)
    # a box with a square footprint (upright) has none
    np.testing.assert_allclose(_c2s2(_rz(t), angles.BOX, [0.05, 0.05, 0.1]), [0, 0], atol=0)


def test_spheres_standing_cylinders_and_meshes_have_no_axis():
    rot = _rz(0.7) @ _rx(0.3)
    for shape in (angles.SPHERE, 3):
        np.testing.assert_array_equal(_c2s2(rot, shape, [0.04, 0.04, 0.04]), [0, 0])
    cyl = [0.06, 0.06, 0.06]
    np.testing.assert_array_equal(_c2s2(_rz(0.7), angles.CYLINDER, cyl), [0, 0])  # standing: a disc
    lying = _rz(0.7) @ _rx(math.pi / 2)  # axis (body z) along world -y turned by 0.7
    got = _c2s2(lying, angles.CYLINDER, cyl)
    assert np.isclose(np.linalg.norm(got), 1) and bool(angles.defined(jnp.asarray(got)))
    assert float(angles.angle_error(jnp.asarray(got), jnp.asarray([math.cos(2 * (0.7 - math.pi / 2)),
                                                                    math.sin(2 * (0.7 - math.pi / 2))]))) < 1e-5


def test_angle_error_is_zero_for_a_perfect_prediction_and_pi_over_2_at_most():
    t = jnp.linspace(-3, 3, 13)
    pair = jnp.stack([jnp.cos(2 * t), jnp.sin(2 * t)], -1)
    np.testing.assert_allclose(angles.angle_error(pair, pair), 0.0, atol=1e-6)
    np.testing.assert_allclose(angles.angle_error(0.3 * pair, pair), 0.0, atol=1e-6)  # length is not read
    turned = jnp.stack([jnp.cos(2 * t + math.pi), jnp.sin(2 * t + math.pi)], -1)  # axes at 90 degrees
    np.testing.assert_allclose(angles.angle_error(turned, pair), math.pi / 2, atol=1e-5)
    small = jnp.stack([jnp.cos(2 * (t + 0.1)), jnp.sin(2 * (t + 0.1))], -1)
    np.testing.assert_allclose(angles.angle_error(small, pair), 0.1, atol=1e-5)
    # undefined targets are left out; an object with none is NaN
    tgt = jnp.stack([pair[:4], jnp.zeros((4, 2))], 1)  # [B=4, M=2, 2]
    err = angles.mean_angle_error(tgt, tgt)
    assert float(err[0]) == 0.0 and bool(jnp.isnan(err[1]))


def _geom_state(version: int, rots: np.ndarray) -> np.ndarray:
    """A ReacherRearrangeGeom state row of `version` with the objects' rotations `rots [4, 3, 3]`
    (joints and positions zero)."""
    props = []
    for i, name in enumerate(OBJECT_LISTS["Geom"][version % 6]):
        g = GEOM_INFO[name]
        props.append(_normalise(np.array([*GEOM_COLOURS[version % 6][i], *g.dims, g.shape, g.mass, *g.dynamics]),
                                PROP_MIN, PROP_MAX))
    return np.concatenate([np.zeros(4), np.concatenate(props), np.zeros(12), rots.reshape(-1)]).astype(np.float32)


def test_rearrange_probe_targets_add_angles_and_exclude_the_spheres():
    spec = rearrange_state_spec(2, 4)
    targets = probe_targets(spec)
    assert targets.spec[:len(spec)] == spec and len(targets.spec) == len(spec) + 8
    assert {e.group for e in targets.derived} == {"object_angle"}
    assert [p[0] for p in targets.angle_pairs] == ["obj0", "obj1", "obj2", "obj3"]
    assert probe_targets(spec[:4]).spec == spec[:4]  # no objects: the state as it is
    rng = np.random.default_rng(0)
    # version 6: cylinder, block, sphere, sphere1; cylinder and block lying at random angles
    lying_block = np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]], float)
    rows = []
    for t in rng.uniform(-3, 3, 64):
        rots = np.stack([_rz(t) @ _rx(math.pi / 2), _rz(-t) @ lying_block, _rz(t) @ _rx(t), _rz(2 * t)])
        rows.append(_geom_state(6, rots))
    states = jnp.asarray(np.stack(rows))
    out = np.asarray(targets(states))
    np.testing.assert_array_equal(out[:, :len(spec)], np.asarray(states))
    ang = out[:, len(spec):].reshape(64, 4, 2)
    np.testing.assert_allclose(np.linalg.norm(ang[:, :2], axis=-1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(ang[:, 2:], 0.0)  # spheres: no axis
    # the same scene turned by pi about z: the same targets
    turned = np.stack([_geom_state(6, np.stack([_rz(math.pi) @ r.reshape(3, 3) for r in row[-36:].reshape(4, 9)]))
                       for row in rows])
    np.testing.assert_allclose(np.asarray(targets(jnp.asarray(turned)))[:, len(spec):], out[:, len(spec):], atol=1e-5)
    # the reference spread leaves the spheres' (constant) entries out, as object_static on one version
    spread = np.mean(np.abs(out - np.median(out, 0)), 0)
    s = summarise(spread, spread, spread, targets.spec)
    assert {f"obj{i}_axis_{c}" for i in (2, 3) for c in ("cos2", "sin2")} <= set(s["excluded"])
    assert not {f"obj{i}_axis_{c}" for i in (0, 1) for c in ("cos2", "sin2")} & set(s["excluded"])
    assert np.isfinite(s["groups"]["object_angle"]["mae_norm"])


@pytest.mark.parametrize("informative", [True, False])
def test_fit_and_score_reports_angle_errors_per_object(informative):
    """A latent that is the angle targets themselves scores a far smaller angle error than the
    constant predictor; a noise latent does not. Spheres get NaN (no defined angle)."""
    spec = rearrange_state_spec(2, 4)
    targets = probe_targets(spec)
    rng = np.random.default_rng(1)
    lying_block = np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]], float)

    def states(n):
        t = rng.uniform(-3, 3, n)
        return np.stack([_geom_state(6, np.stack([_rz(a) @ _rx(math.pi / 2), _rz(-a) @ lying_block, _rz(a), _rz(a)]))
                         for a in t])

    tr, te = states(512), states(128)
    lat = lambda s: (np.asarray(targets(jnp.asarray(s)))[:, -8:] if informative  # noqa: E731
                     else rng.normal(size=(len(s), 8)).astype(np.float32))
    from bulbjax.data.sequence import Windows
    held = Windows(frames=jnp.zeros((128, 1, 1, 1, 1)), actions=jnp.zeros((128, 1, 1)), states=jnp.asarray(te)[:, None],
                   valid=jnp.ones((128, 1), bool))
    latents = {"tz": jnp.asarray(lat(tr)), "ts": jnp.asarray(tr), "groups": None,
               "held": {"rand": jnp.asarray(lat(te))[:, None]}}
    res = fit_and_score(latents, {"rand": held}, jax.random.PRNGKey(0), ProbeConfig(hidden=(64,), steps=300),
                        targets=targets)["rand"]
    assert res["mae"].shape == (len(targets.spec),)
    mae, base = np.asarray(res["angle"]["mae"]), np.asarray(res["angle"]["baseline"])
    assert np.isnan(mae[2:]).all() and np.isnan(base[2:]).all()
    assert (base[:2] > 0.5).all()  # a constant axis is ~pi/4 off on average for uniform angles
    if informative:
        assert (mae[:2] < 0.25 * base[:2]).all()
    else:
        assert (mae[:2] > 0.7 * base[:2]).all()
