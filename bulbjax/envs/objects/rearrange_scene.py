"""The Rearrange domains' constants and scene parts: bulb's numbers (episode, physics steps, bounds,
targets), the object lists and colours of versions 0-11, the geom objects, the per-object property
table and the state specs. Kept apart from the env classes (`rearrange_base`, `reacher_rearrange`,
`franka_rearrange`) so that each reads on its own; facts: `../shared/reference/bulb-multiobject.md`."""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass

import numpy as np

from bulbjax.envs.objects.incline_scene import geom_object
from bulbjax.eval.spec import StateEntry

os.environ.setdefault("MUJOCO_GL", "disable")  # dm_control needs no GL context to build models
from dm_control import mjcf  # noqa: E402


NUM_VERSIONS = 12  # 0-5, and 6-11 the same with a black background
NUM_LISTS = 6
EPISODE_STEPS = 200
BULLET_DT = 0.01
BULLET_SUBSTEPS = 2
SETTLE_STEPS = 20  # bulb: stepSimulation x 20 "to let the objects emerge from problematic poses"
RANDOM_TORQUE_STEPS = 10  # then 10 steps of random torques in +-max_torque / 2
SETTLE_MAX_SPEED = 1.0  # m/s, objects' speed cap during the settle (see `_cap_speeds`)
SETTLE_MAX_SPIN = 10.0  # rad/s
OBJ_XYZ_MIN = np.array([-0.45, -0.45, -0.05])
OBJ_XYZ_MAX = np.array([0.45, 0.45, 0.20])
EE_XY_MAX = 0.5
EE_ABOVE_OBJECTS = 0.2
INIT_XY = 0.15
INIT_Z_MAX = 0.075
TARGETS = np.array([[0.2, -0.2], [0.2, 0.2]])  # boxes and cans / everything else
# `show_targets`: discs on the tray floor at TARGETS (bulb's markers -- 1 cm spheres in rgba
# (0.6, 0.6, 0.9, 0.7) and (0.9, 0.9, 0.9, 0.7), left commented out -- would be a pixel wide at
# 64 x 64, and the renderer has no transparency). Opaque violet / lime, at least 0.5 (in their most
# different channel) from every tray, geom-object and arm colour: the marks never blend in.
TARGET_RADIUS = 0.05
TARGET_HALF_HEIGHT = 0.001
TARGET_RGBA = ((0.5, 0.1, 1.0, 1.0), (0.5, 0.9, 0.1, 1.0))
TRAY_SCALE = 0.8
PARK_HEIGHT = 50.0
NAN_RETRIES = 2

OBJECT_LISTS: dict[str, tuple[tuple[str, ...], ...]] = {
    "Ycb": (("002_master_chef_can", "009_gelatin_box", "013_apple", "016_pear"),
            ("007_tuna_fish_can", "009_gelatin_box", "014_lemon", "017_orange"),
            ("002_master_chef_can", "004_sugar_box", "016_pear", "014_lemon"),
            ("005_tomato_soup_can", "004_sugar_box", "014_lemon", "013_apple"),
            ("002_master_chef_can", "008_pudding_box", "017_orange", "018_plum"),
            ("004_sugar_box", "017_orange", "018_plum", "008_pudding_box")),
    "OneYcb": (("005_tomato_soup_can",), ("004_sugar_box",), ("002_master_chef_can",),
               ("008_pudding_box",), ("016_pear",), ("008_pudding_box",)),
    "Geom": (("cylinder", "cube", "sphere", "sphere1"),) * 5 + (("cube", "sphere", "sphere", "cube"),),
    "OneGeom": (("cylinder",), ("cube",), ("cylinder",), ("cube",), ("sphere1",), ("cube",)),
}
GEOM_COLOURS = (((0, 0, 1), (1, 0, 1), (1, 0, 0), (1, 1, 0)),
                ((1, 1, 0), (0, 1, 1), (1, 0, 1), (0, 1, 0)),
                ((0, 1, 0), (0, 0, 1), (1, 1, 0), (0, 1, 1)),
                ((1, 0, 0), (1, 1, 0), (0, 1, 0), (1, 0, 1)),
                ((1, 0, 1), (1, 1, 0), (1, 0, 0), (0.9, 0.9, 0.9)),
                ((0, 1, 1), (0, 1, 0), (1, 1, 0), (0, 0, 1)))
# table textures birch, gray, orange, blue, purple, birch as their mean colours; 6-11 black
TABLE_RGB = np.array([[220, 200, 170], [165, 165, 165], [165, 75, 40], [82, 60, 124],
                      [90, 190, 180], [220, 200, 170]]) / 255.0
# bulb's object properties [rgb, dims (3), shape, mass, restitution, lateral, rolling, spinning
# friction] and their normalisation ranges (SIM_PARAM_OBJ_MINS / MAXS)
PROP_NAMES = ("rgb_r", "rgb_g", "rgb_b", "radius_a", "radius_b", "height", "shape", "mass",
              "restitution", "lateral_friction", "rolling_friction", "spinning_friction")
PROP_MIN = np.array([0, 0, 0, 0.01, 0.01, 0.01, 0, 0.01, 0.0, 0.0, 0.0, 0.0])
PROP_MAX = np.array([1, 1, 1, 0.15, 0.15, 0.15, 3, 1.0, 1.0, 1.0, 0.01, 0.01])
SHAPE_SPHERE, SHAPE_CYLINDER, SHAPE_BOX, SHAPE_MESH = 0, 1, 2, 3
CYLINDER_DEFAULT_DIMS = (0.06, 0.06, 0.06)  # bulb reports these for cylinders and meshes


@dataclass(frozen=True)
class GeomInfo:
    """A geometric object: bulb's resting half-height z, mass, reported dims, shape id and
    dynamics (restitution, lateral, rolling, spinning friction, as PyBullet reports them)."""

    z: float
    mass: float
    dims: tuple[float, float, float]
    shape: int
    dynamics: tuple[float, float, float, float]


GEOM_INFO = {
    "sphere": GeomInfo(0.04, 0.1, (0.04, 0.04, 0.04), SHAPE_SPHERE, (1.0, 0.5, 0.001, 0.001)),
    "sphere1": GeomInfo(0.06, 0.3, (0.06, 0.06, 0.06), SHAPE_SPHERE, (1.0, 0.5, 0.001, 0.001)),
    "cylinder": GeomInfo(0.06, 0.2, CYLINDER_DEFAULT_DIMS, SHAPE_CYLINDER, (0.0, 0.5, 0.0, 0.0)),
    "cube": GeomInfo(0.075, 0.05, (0.025, 0.05, 0.075), SHAPE_BOX, (0.0, 0.5, 0.0, 0.0)),
}
YCB_DYNAMICS = (0.0, 0.5, 0.0, 0.0)  # createMultiBody defaults

# Contact bits: the floor and tray collide with objects (bit 1); objects also with the robot
# (bit 2). Robots set contype 2 and conaffinity 0 (the Franka adds the floor).
OBJECT_CONAFFINITY = 3
FRICTION = (0.5, 0.005, 0.0001)


def _sphere_object(radius: float, mass: float) -> mjcf.RootElement:
    model = mjcf.RootElement(model="sphere")
    body = model.worldbody.add("body", name="object")
    body.add("geom", name="visual", type="sphere", size=[radius], rgba=(1, 1, 1, 1))
    body.add("inertial", pos=[0, 0, 0], mass=mass, diaginertia=[0.4 * mass * radius ** 2] * 3)
    return model


def geom_model(kind: str) -> mjcf.RootElement:
    """bulb's geometric object `kind` (sphere, sphere1, cylinder, cube) as a sub-model with one
    body `object` (white; each version's colour is set at render time)."""
    if kind == "sphere":
        return _sphere_object(0.04, 0.1)
    if kind == "sphere1":
        return _sphere_object(0.06, 0.3)
    if kind == "cylinder":
        return geom_object(3, 1.0)  # incline's cylinder: r 0.06, half-height 0.06, 0.2 kg
    if kind == "cube":
        return geom_object(0, 1.0)  # bulb's block: 0.05 x 0.10 x 0.15 m, 0.05 kg
    raise ValueError(f"unknown geom object {kind!r}; known: {sorted(GEOM_INFO)}")


def is_box_or_can(name: str) -> bool:
    return name.endswith(("_box", "_can"))


def object_half_height(name: str) -> float:
    """bulb's resting half-height times the z scale (its `max_object_z` is twice the largest)."""
    if name in GEOM_INFO:
        return GEOM_INFO[name].z
    from bulbjax.assets import YCB_INFO

    info = YCB_INFO[name]
    return info.half_height * info.scale[2]


def _slots(lists: tuple[tuple[str, ...], ...], versions: tuple[int, ...]) -> tuple[list[str], np.ndarray]:
    """The model's object bodies (each object as often as the most any used version needs) and
    `[NUM_VERSIONS, M]` the body slot of each version's i-th object (0 for unused versions)."""
    need: dict[str, int] = {}
    for v in versions:
        for name, k in Counter(lists[v % NUM_LISTS]).items():
            need[name] = max(need.get(name, 0), k)
    slots = [n for n in need for _ in range(need[n])]
    m = len(lists[0])
    table = np.zeros((NUM_VERSIONS, m), np.int32)
    for v in range(NUM_VERSIONS):
        if v not in versions:
            continue
        seen: Counter = Counter()
        for i, name in enumerate(lists[v % NUM_LISTS]):
            table[v, i] = [j for j, s in enumerate(slots) if s == name][seen[name]]
            seen[name] += 1
    return slots, table


def rearrange_state_spec(joints: int, objects: int) -> tuple[StateEntry, ...]:
    """bulb's Rearrange state: joint sin/cos, object properties, positions, rotation matrices."""
    spec = []
    for j in range(joints):
        spec += [StateEntry(f"j{j}_sin", "1", "robot"), StateEntry(f"j{j}_cos", "1", "robot")]
    for i in range(objects):
        spec += [StateEntry(f"obj{i}_{p}", "[-1,1] of bulb's range", "object_static") for p in PROP_NAMES]
    for i in range(objects):
        spec += [StateEntry(f"obj{i}_{a}", "[-1,1] of [-0.45,0.45] m (z [-0.05,0.2])", "object_position")
                 for a in "xyz"]
    for i in range(objects):
        spec += [StateEntry(f"obj{i}_rot{k}", "1", "object_orientation") for k in range(9)]
    return tuple(spec)


def rearrange_raw_state_spec(joints: int, objects: int) -> tuple[StateEntry, ...]:
    spec = [StateEntry(f"j{j}_pos", "rad", "robot") for j in range(joints)]
    spec += [StateEntry(f"j{j}_vel", "rad/s", "robot_velocity") for j in range(joints)]
    for i in range(objects):
        spec += [StateEntry(f"obj{i}_pos_{a}", "m", "object_position") for a in "xyz"]
        spec += [StateEntry(f"obj{i}_quat_{a}", "1", "object_orientation") for a in "wxyz"]
        spec += [StateEntry(f"obj{i}_vel_{a}", "m/s", "object_velocity") for a in "xyz"]
        spec += [StateEntry(f"obj{i}_angvel_{a}", "rad/s", "object_angular_velocity") for a in "xyz"]
    spec += [StateEntry(f"ee_{a}", "m", "robot") for a in "xyz"]
    return tuple(spec)


def _normalise(x, lo, hi):
    return (x - lo) / (hi - lo) * 2.0 - 1.0


ANGLE_GROUP = "object_angle"
ANGLE_UNIT = "1 (cos 2θ, sin 2θ; θ the major axis's angle mod π)"


def angle_target_spec(spec: tuple[StateEntry, ...]) -> tuple[StateEntry, ...]:
    """The major-axis angle targets derived from a Rearrange state (`angle_targets`): per object
    of `spec` (entries `obj<i>_rot0..8`), `obj<i>_axis_cos2` and `obj<i>_axis_sin2` in group
    `object_angle`; () for a spec without rotation matrices."""
    out = []
    for i in range(_count_objects(spec)):
        out += [StateEntry(f"obj{i}_axis_{t}", ANGLE_UNIT, ANGLE_GROUP) for t in ("cos2", "sin2")]
    return tuple(out)


def _count_objects(spec: tuple[StateEntry, ...]) -> int:
    names = {e.name for e in spec}
    i = 0
    while f"obj{i}_rot0" in names and f"obj{i}_shape" in names:
        i += 1
    return i


def angle_targets(spec: tuple[StateEntry, ...]):
    """`states [..., D] -> [..., 2M]`: per object, (cos 2θ, sin 2θ) of its major axis's angle θ in
    the table plane (`bulbjax.eval.angles`), read off the state itself: the rotation matrix
    (`obj<i>_rot*`), the shape id and bulb's dims (`obj<i>_shape`, `_radius_a`, `_radius_b`,
    `_height`: the half-extents along body x, y, z of the block, radius and half-height of the
    cylinder), so it holds for every version, random ones included. Spheres and YCB meshes
    (shape id 3: their dims are bulb's defaults, not the mesh's) have no axis: (0, 0), excluded
    by the reference spread where constant over the run. Not part of the env's state: bulb's
    state layout (and its parity tests) stays as it is; the probes add these (`angle_target_spec`)."""
    import jax.numpy as jnp

    from bulbjax.eval.angles import major_axis_c2s2

    names = [e.name for e in spec]
    m = _count_objects(spec)
    rot_idx = np.array([[names.index(f"obj{i}_rot{k}") for k in range(9)] for i in range(m)])
    shape_idx = np.array([names.index(f"obj{i}_shape") for i in range(m)])
    dim_idx = np.array([[names.index(f"obj{i}_{p}") for p in ("radius_a", "radius_b", "height")] for i in range(m)])
    k = PROP_NAMES.index("shape")
    lo, hi = PROP_MIN[3:6], PROP_MAX[3:6]

    def fn(states):
        rot = states[..., rot_idx].reshape(states.shape[:-1] + (m, 3, 3))
        shape = jnp.round((states[..., shape_idx] + 1.0) / 2.0 * (PROP_MAX[k] - PROP_MIN[k]) + PROP_MIN[k])
        dims = (states[..., dim_idx] + 1.0) / 2.0 * (hi - lo) + lo
        c2s2 = major_axis_c2s2(rot, shape.astype(jnp.int32), dims)  # [..., M, 2]
        return c2s2.reshape(states.shape[:-1] + (2 * m,)).astype(states.dtype)

    return fn
