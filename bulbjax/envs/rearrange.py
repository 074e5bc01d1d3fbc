"""ReacherRearrange and FrankaRearrange (Geom, OneGeom, Ycb, OneYcb): a torque-controlled robot
among four objects (one for `One*`) in a bordered table tray, mirroring bulb's `RearrangeEnv`
(facts: `../shared/reference/bulb-multiobject.md`; numbers and behaviour of contactrika/bulb).

The scene is composed with `dm_control.mjcf`: a floor plane, the tray (bulb's `borders.urdf` at
scale 0.8: four border boxes 0.84 x 0.04 x 0.08 m around a 0.8 x 0.8 m visual bottom), the robot
and the objects attached as sub-models (objects with free joints; `bulbjax.assets` for YCB).
What is mirrored:
- versions 0-11: the object list is bulb's list number `version % 6`, geom colours bulb's
  `GEOM_COLORS[version]`, the tray the version's texture as its mean colour (versions 6-11
  black). `version="random"` draws one per world and episode: the model then holds every
  object any version needs (a union with multiplicity) and parks the unused ones far above the
  scene with per-world gravity compensation (as the incline domains do).
- episode 200 steps; one env step is one of bulb's `stepSimulation` calls (dt 0.01 s, 2 solver
  substeps): MuJoCo steps 0.005 s, 2 per env step, the torque held.
- action a in [-1, 1] per controlled joint (bulbjax's convention; bulb's [0, 1] action is
  (a + 1) / 2): torque = clip(a, -1, 1) * max_torque. Reacher: 3 N m per joint. Franka: the
  URDF's efforts (87 x 4, 12 x 3 N m) plus gravity compensation (MuJoCo's bias force, bulb's
  inverse dynamics at zero acceleration), the sum clipped to the efforts; fingers fixed.
- joint limits as bulb enforces them after every step: Reacher joints beyond (31/32, 26/32) pi
  are put back on the limit with their velocity reversed; Franka joints outside the URDF's
  range are put back with zero velocity.
- reset: random robot pose (Reacher: U(+-0.75 pi) per joint; Franka: see `FrankaRearrange`),
  each object at x, y ~ U[-0.15, 0.15], z ~ U[0.03 (Ycb) or 0.04 (Geom), 0.075] with bulb's
  orientation draw (a uniform 4-vector in [0, 1]^4, normalised, as PyBullet's x, y, z, w);
  20 steps of free physics to let the objects settle; then 10 steps of random torques in
  +-max_torque / 2 (a ~ U[-0.5, 0.5]).
- done when an object leaves [-0.45, 0.45]^2 x [-0.05, 0.20] m, the end effector (the COM of
  bulb's end-effector link, as PyBullet's `getLinkState`) is more than 0.2 m above the tallest
  object (twice bulb's z times its z scale) or outside |x|, |y| <= 0.5; reward per step
  (1 - mean over objects of min(1, xy distance to its target)) / 200, targets (0.2, -0.2) for
  boxes and cans and (0.2, 0.2) for everything else.
- state (bulb's order, in [-1, 1]): sin and cos of every robot joint (the Franka's fixed fingers
  included, as bulb's `get_qpos` reports them); 12 properties per object (rgb, bulb's dims,
  shape id, mass, restitution, lateral/rolling/spinning friction, normalised by bulb's ranges;
  static); x, y, z per object (clipped to the box above, normalised); the rotation matrix per
  object (row-major). Groups `robot`, `object_static`, `object_position`,
  `object_orientation`. `state.info["lowdim_raw"]`: joint angles and speeds, each object's
  position (m), quaternion (w, x, y, z), linear velocity (m/s, world) and angular velocity
  (rad/s, body frame, MuJoCo's free joint), and the end effector's position.
- cameras: Reacher top-down (distance 0.40, yaw 90, pitch -89, target (0, 0, 0)); Franka
  distance 0.44, yaw 90, pitch -65, target (0.05, 0, 0); vertical FOV 90.

Known differences from bulb:
- bulb's `reacher.xml`, `cube.urdf`, `cylinder.urdf` and table textures are not in the stored
  repository: the reacher is written from the reference's numbers (heights, hand sizes and
  mass assumed, see `mjcf_assets/reacher_rearrange.xml`); cube = bulb's block (box 0.05 x 0.10 x
  0.15 m, 0.05 kg), cylinder radius 0.06, half-height 0.06, 0.2 kg; its contact parameters
  (restitution 0, lateral friction 0.5) assumed; tray colours are the textures' mean colours.
- The reacher follows the reference's numbers (2 kg links, armature 1, damping 1: a slow arm,
  ~0.4 rad in 0.6 s at full torque). bulb loaded its `reacher.xml` with PyBullet's `loadMJCF`,
  which ignores geom masses, joint damping and armature (measured on this file:
  `pybullet_compat/rearrange.py`, `docs/parity/rearrange_report.json`), so bulb's arm may have
  been far lighter and faster than the numbers say.
- The Panda is `pybullet_data`'s (bulb used its own `franka_small_fingers.urdf`, not stored):
  its fingers are longer, and at bulb's rest pose their tips touch the floor.
- bulb's rotation-matrix entries come from `quat2mat` applied to PyBullet's (x, y, z, w)
  quaternion, which that function reads as (w, x, y, z): bulb's nine numbers are the matrix of a
  permuted quaternion. Here they are the object's true rotation matrix.
- bulb's code leaves the target markers commented out (`create_visual_area` "impacts
  physics"), so by default no targets are drawn here either. `show_targets=True`
  (`bulbjax.make(..., show_targets=True)`, `bulbjax render --show-targets`) draws them as
  visual-only discs on the tray floor (radius 5 cm; violet at (0.2, -0.2) for boxes and cans,
  lime at (0.2, 0.2) for everything else; bulb's would-be markers were 1 cm translucent
  spheres); the physics is unchanged by them.
- YCB objects' body frames are their centres of mass (as in the incline domains; bulb places
  the mesh origin); positions in the state are COM positions.
- Contacts are MuJoCo's soft contacts with friction 0.5 everywhere (Bullet multiplies the two
  coefficients, 0.5-1.0 each); restitution (1.0 for spheres and borders in bulb) and the
  spheres' rolling/spinning friction (0.001) are left out; the robot does not collide with
  the tray's borders or with itself (bulb: self-collision on); the Reacher does not touch the
  floor, the Franka does.
- bulb's Franka skips `stepSimulation` entirely when the commanded torque is all zeros (an
  `allclose(torque, 0)` early return); here physics always steps.
- During the reset's settle, object speeds are capped at 1 m/s and 10 rad/s (MuJoCo pushes
  objects that start inside each other apart faster than Bullet; uncapped, light spheres could
  be thrown off the table).
- Every reset of a batch runs the settle (30 env steps of physics) for all worlds whenever any
  world resets, as MJX steps all worlds together.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from bulbjax.envs.base import EnvConfig, EnvState, MjxPixelEnv, _finite_rows, _where_tree, asset_dir
from bulbjax.envs.camera import CameraConfig
from bulbjax.envs.incline import _quat_mat, geom_object
from bulbjax.envs.locomotion import _quiet_solver_limits
from bulbjax.envs.render import SCENERY_GROUP
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


class Rearrange(MjxPixelEnv):
    """bulb's RearrangeEnv on MJX; subclasses pick the robot (`_robot_model`, joints, torques,
    end effector, camera) and the object variant."""

    num_versions = NUM_VERSIONS

    variant: str = "Geom"
    # robot: joints in state order (controlled ones first), their torque limits, the end-effector
    # body, the floor colour
    joint_names: tuple[str, ...] = ()
    controlled: int = 0
    max_torque: tuple[float, ...] = ()
    ee_body: str = ""
    robot_pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # joints bulb reports in the state that do not move here (the Franka's fingers): their angles
    fixed_joint_qpos: tuple[float, ...] = ()
    floor_rgba: tuple[float, float, float, float] = (0, 0, 0, 1)
    floor_conaffinity: int = 1
    episode_length = EPISODE_STEPS
    solved_return = 1.0
    discrete = False
    frame_skip = BULLET_SUBSTEPS
    kinematics_after_step = True
    always_recolour = True  # tray and geom colours follow each world's version
    naconmax_per_world = 48
    njmax = 256
    pointcloud_box = 0.5  # bulb's PTCLOUD_BOX_SIZE for Rearrange
    pointcloud_exclude = ("floor", "tray_bottom", "border0", "border1", "border2", "border3")
    supports_multicolour = False
    supports_targets = True

    def __init__(self, config: EnvConfig):
        version = config.version
        if version == "random":
            self.versions = tuple(range(NUM_VERSIONS))
        elif isinstance(version, (int, np.integer)) and 0 <= version < NUM_VERSIONS:
            self.versions = (int(version),)
        else:
            raise ValueError(f"{self.name}: version must be an int in 0..{NUM_VERSIONS - 1} (6-11: black "
                             f"background) or 'random', got {version!r}")
        self.random_version = version == "random"
        self.lists = OBJECT_LISTS[self.variant]
        self.num_objects = len(self.lists[0])
        self.slot_names, version_slots = _slots(self.lists, self.versions)
        super().__init__(config)
        m = self.mj_model
        self._slot_bodies = np.array([m.body(f"o{k}/object").id for k in range(len(self.slot_names))])
        frames = m.body_parentid[self._slot_bodies]
        self._slot_qadr = jnp.asarray(m.jnt_qposadr[m.body_jntadr[frames]])
        self._slot_vadr = jnp.asarray(m.jnt_dofadr[m.body_jntadr[frames]])
        jids = [m.joint(self._robot_prefix + j).id for j in self.joint_names]
        self._robot_qadr = jnp.asarray(m.jnt_qposadr[jids])
        self._robot_vadr = jnp.asarray(m.jnt_dofadr[jids])
        self._ee = m.body(self._robot_prefix + self.ee_body).id
        self._version_slots = jnp.asarray(version_slots)
        self._max_torque = jnp.asarray(self.max_torque, jnp.float32)
        self._tables()
        park = np.zeros(m.nq)
        park[:] = m.qpos0
        for k in range(len(self.slot_names)):
            a = int(self._slot_qadr[k])
            park[a:a + 7] = [2.0 + 1.0 * k, 3.0, PARK_HEIGHT, 1, 0, 0, 0]
        self._qpos_park = jnp.asarray(park, jnp.float32)

    # ----- what subclasses provide -----
    _robot_prefix = "robot/"

    def _robot_model(self) -> mjcf.RootElement:
        raise NotImplementedError

    def _draw_robot_qpos(self, key: jax.Array) -> jax.Array:
        raise NotImplementedError

    def _obey_limits(self, data: mjx.Data) -> mjx.Data:
        """bulb's joint-limit handling after a step (one world)."""
        return data

    # ----- static tables -----
    def _tables(self) -> None:
        """Per-version (all 12) object properties, targets and tallest object height."""
        props = np.zeros((NUM_VERSIONS, self.num_objects, len(PROP_NAMES)))
        targets = np.zeros((NUM_VERSIONS, self.num_objects, 2))
        max_z = np.zeros(NUM_VERSIONS)
        for v in range(NUM_VERSIONS):
            for i, name in enumerate(self.lists[v % NUM_LISTS]):
                if name in GEOM_INFO:
                    g = GEOM_INFO[name]
                    row = [*GEOM_COLOURS[v % NUM_LISTS][i], *g.dims, g.shape, g.mass, *g.dynamics]
                else:
                    from bulbjax.assets import YCB_INFO
                    row = [1, 1, 1, *CYLINDER_DEFAULT_DIMS, SHAPE_MESH, YCB_INFO[name].mass, *YCB_DYNAMICS]
                props[v, i] = _normalise(np.asarray(row, float), PROP_MIN, PROP_MAX)
                targets[v, i] = TARGETS[0 if is_box_or_can(name) else 1]
                max_z[v] = max(max_z[v], 2 * object_half_height(name))
        self._props = jnp.asarray(props, jnp.float32)
        self._targets = jnp.asarray(targets, jnp.float32)
        self._max_object_z = jnp.asarray(max_z, jnp.float32)

    # ----- model -----
    def _build_spec(self) -> mujoco.MjSpec:
        root = mjcf.RootElement(model=self.name)
        root.compiler.angle = "radian"
        root.option.timestep = BULLET_DT / BULLET_SUBSTEPS
        root.option.gravity = [0, 0, -9.81]
        root.option.solver = "Newton"
        root.option.iterations = 10
        root.option.ls_iterations = 10
        root.option.integrator = "Euler"
        root.visual.headlight.ambient = [0.45, 0.45, 0.45]
        root.visual.headlight.diffuse = [0.5, 0.5, 0.5]
        root.worldbody.add("light", name="key", directional=True, pos=[0, 0, 3], dir=[0.2, 0.3, -1],
                           diffuse=[0.4, 0.4, 0.4])
        self._add_floor(root)
        self._add_tray(root)
        robot = self._robot_model()
        robot.model = self._robot_prefix.rstrip("/")
        root.worldbody.attach(robot).pos = self.robot_pos
        for k, name in enumerate(self.slot_names):
            model = self._object_model(name)
            model.model = f"o{k}"
            for geom in model.find_all("geom"):
                if geom.contype is None or geom.contype:
                    geom.conaffinity, geom.friction = OBJECT_CONAFFINITY, FRICTION
            frame = root.worldbody.attach(model)
            frame.add("freejoint")
            if self.random_version:
                model.find("body", "object").gravcomp = 1e-6  # compiled in, set per world to park
            frame.pos = [2.0 + 1.0 * k, 3.0, PARK_HEIGHT]
        if self.config.show_targets:
            self._add_targets(root)
        return mujoco.MjSpec.from_string(root.to_xml_string(), assets=root.get_assets())

    def _add_targets(self, root: mjcf.RootElement) -> None:
        """bulb's two target areas as flat discs on the tray floor, drawn only: no contacts, no
        mass, in a static body added last so that every other body's and geom's id is unchanged
        (physics is the same with and without them). In the scenery group: point clouds leave
        them out, as they leave out the tray."""
        body = root.worldbody.add("body", name="targets")
        top = 0.0005 + 2 * TARGET_HALF_HEIGHT  # on the tray bottom's top face (z 0.0005)
        for i, ((x, y), rgba) in enumerate(zip(TARGETS, TARGET_RGBA)):
            body.add("geom", name=f"target{i}", type="cylinder", size=[TARGET_RADIUS, TARGET_HALF_HEIGHT],
                     pos=[x, y, top - TARGET_HALF_HEIGHT], rgba=rgba, contype=0, conaffinity=0, mass=0,
                     group=SCENERY_GROUP)

    def _add_floor(self, root: mjcf.RootElement) -> None:
        root.worldbody.add("geom", name="floor", type="plane", size=[5, 5, 0.1], rgba=self.floor_rgba,
                           friction=FRICTION, contype=1, conaffinity=self.floor_conaffinity)

    def _add_tray(self, root: mjcf.RootElement) -> None:
        """bulb's borders.urdf at scale 0.8: the borders collide, the bottom is drawn only."""
        s = TRAY_SCALE
        tray = root.worldbody.add("body", name="tray")
        rgb = (*TABLE_RGB[0], 1)
        # a thin visual slab whose top sits just above the floor (objects rest on the floor)
        tray.add("geom", name="tray_bottom", type="box", size=[0.5 * s, 0.5 * s, 0.002], pos=[0, 0, -0.0015],
                 rgba=rgb, contype=0, conaffinity=0)
        long, thick, height = 1.05 * s / 2, 0.05 * s / 2, 0.10 * s / 2
        for i, (pos, size) in enumerate((((0.5 * s, 0, height), (thick, long, height)),
                                         ((-0.5 * s, 0, height), (thick, long, height)),
                                         ((0, 0.5 * s, height), (long, thick, height)),
                                         ((0, -0.5 * s, height), (long, thick, height)))):
            tray.add("geom", name=f"border{i}", type="box", size=size, pos=pos, rgba=rgb,
                     friction=FRICTION, contype=1, conaffinity=1)

    def _object_model(self, name: str) -> mjcf.RootElement:
        if name in GEOM_INFO:
            return geom_model(name)
        from bulbjax.assets import load_ycb_object, ycb_mjcf

        asset = load_ycb_object(name, scale=1.0, ycb_dir=self.config.ycb_dir)
        return ycb_mjcf(asset, "object", origin="com")

    def _post_put(self, mx: mjx.Model) -> mjx.Model:
        return _quiet_solver_limits(mx)

    def _scheme_colours(self) -> tuple[np.ndarray, np.ndarray]:
        """Colour scheme = version: the tray's colour, and each geom object's colour where the
        version uses its slot."""
        tray = [self._geom_id(g) for g in ("tray_bottom", "border0", "border1", "border2", "border3")]
        objs = []
        if self.variant in ("Geom", "OneGeom"):
            objs = [self._geom_id(f"o{k}/visual") for k in range(len(self.slot_names))]
        rgb = np.full((NUM_VERSIONS, len(tray) + len(objs), 3), 0.5)
        _, table = _slots(self.lists, self.versions)
        for v in range(NUM_VERSIONS):
            rgb[v, :len(tray)] = TABLE_RGB[v] if v < NUM_LISTS else 0.0
            if objs and v in self.versions:
                for i, slot in enumerate(table[v]):
                    rgb[v, len(tray) + slot] = GEOM_COLOURS[v % NUM_LISTS][i]
        return np.array(tray + objs, np.int32), rgb.astype(np.float32)

    # ----- state -----
    @property
    def raw_state_spec(self) -> tuple[StateEntry, ...]:
        return rearrange_raw_state_spec(len(self.joint_names), self.num_objects)

    def _objects(self, data: mjx.Data, version: jax.Array) -> dict[str, jax.Array]:
        """One world's objects (the version's, in its list order): qpos `[M, 7]`, qvel `[M, 6]`."""
        slots = self._version_slots[version]
        q = data.qpos[self._slot_qadr[slots][:, None] + jnp.arange(7)]
        v = data.qvel[self._slot_vadr[slots][:, None] + jnp.arange(6)]
        return {"pos": q[:, :3], "quat": q[:, 3:], "vel": v}

    def _lowdim_batch(self, data: mjx.Data, params: dict[str, jax.Array]) -> jax.Array:
        lo, hi = jnp.asarray(OBJ_XYZ_MIN, jnp.float32), jnp.asarray(OBJ_XYZ_MAX, jnp.float32)

        def one(d, version):
            qpos = d.qpos[self._robot_qadr]
            qpos = jnp.concatenate([qpos, jnp.asarray(self.fixed_joint_qpos, qpos.dtype)])
            sincos = jnp.stack([jnp.sin(qpos), jnp.cos(qpos)], axis=1).reshape(-1)
            ob = self._objects(d, version)
            pos = _normalise(jnp.clip(ob["pos"], lo, hi), lo, hi)
            rot = jax.vmap(_quat_mat)(ob["quat"] / jnp.linalg.norm(ob["quat"], axis=1, keepdims=True))
            return jnp.concatenate([sincos, self._props[version].reshape(-1), pos.reshape(-1), rot.reshape(-1)])
        return jax.vmap(one)(data, params["version"]).astype(jnp.float32)

    def raw_state(self, data: mjx.Data, params: dict[str, jax.Array] | None = None) -> jax.Array:
        if params is None:
            raise ValueError(f"{self.name}.raw_state needs the worlds' params (state.params)")

        def one(d, version):
            ob = self._objects(d, version)
            per_obj = jnp.concatenate([ob["pos"], ob["quat"], ob["vel"]], axis=1).reshape(-1)
            return jnp.concatenate([d.qpos[self._robot_qadr], d.qvel[self._robot_vadr], per_obj,
                                    d.xipos[self._ee]])
        return jax.vmap(one)(data, params["version"]).astype(jnp.float32)

    def _reward_terminated_batch(self, data, lowdim, action, prev_data, params):
        lo, hi = jnp.asarray(OBJ_XYZ_MIN, jnp.float32), jnp.asarray(OBJ_XYZ_MAX, jnp.float32)

        def one(d, version):
            pos = self._objects(d, version)["pos"]
            dist = jnp.minimum(jnp.linalg.norm(pos[:, :2] - self._targets[version], axis=1), 1.0)
            finite = jnp.isfinite(d.qpos).all()
            reward = jnp.where(finite, (1.0 - dist.mean()) / EPISODE_STEPS, 0.0)
            ee = d.xipos[self._ee]
            outside = ((pos < lo) | (pos > hi)).any()
            too_high = ee[2] > EE_ABOVE_OBJECTS + self._max_object_z[version]
            away = (jnp.abs(ee[:2]) > EE_XY_MAX).any()
            return reward, outside | too_high | away | ~finite
        return jax.vmap(one)(data, params["version"])

    # ----- dynamics -----
    def _world_model(self, params: dict[str, jax.Array]) -> mjx.Model:
        if not params or not self.random_version:
            return self.mx
        n = params["version"].shape[0]
        slots = self._version_slots[params["version"]]  # [N, M]
        active = (jnp.arange(len(self.slot_names))[None, :, None] == slots[:, None, :]).any(-1)
        gravcomp = jnp.broadcast_to(self.mx.body_gravcomp, (n, *self.mx.body_gravcomp.shape))
        gravcomp = gravcomp.at[:, self._slot_bodies].set(1.0 - active.astype(jnp.float32))
        return self.mx.tree_replace({"body_gravcomp": gravcomp})

    def _torque(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        """Joint torques of one world's controlled joints from an action in [-1, 1]."""
        return jnp.clip(action, -1.0, 1.0) * self._max_torque

    def _apply_action(self, data: mjx.Data, action: jax.Array) -> mjx.Data:
        return data.replace(ctrl=self._torque(data, action))

    def physics(self, data: mjx.Data, action: jax.Array, params: dict[str, jax.Array] | None = None) -> mjx.Data:
        """One env step: one of bulb's stepSimulation calls (2 MuJoCo steps, the torque held),
        bulb's joint-limit handling, then kinematics."""
        mx = self._world_model(params or {})

        def substep(d: mjx.Data, _):
            d = jax.vmap(self._apply_action)(d, action)
            return jax.vmap(mjx.step, in_axes=(None, 0))(mx, d), None

        data = jax.lax.scan(substep, data, None, length=self.frame_skip)[0]
        data = jax.vmap(self._obey_limits)(data)
        return jax.vmap(mjx.kinematics, in_axes=(None, 0))(mx, data)

    # ----- reset -----
    RESET_FIELDS = ("version", "robot_qpos", "obj_pos", "obj_quat", "torques")
    _fixed: dict[str, jax.Array] = {}

    def reset_with(self, key: jax.Array, **fixed: jax.Array) -> EnvState:
        """`reset(key)` with some per-world draws fixed (arrays with a leading `num_envs` axis,
        or broadcastable): `version` (with `version="random"`), `robot_qpos [N, J]`, `obj_pos
        [N, M, 3]` and `obj_quat [N, M, 4]` (MuJoCo's w, x, y, z; before the settle), `torques
        [N, 10, A]` (the actions of the random-torque steps). Later automatic resets draw as usual."""
        unknown = set(fixed) - set(self.RESET_FIELDS)
        if unknown:
            raise ValueError(f"unknown reset fields {sorted(unknown)}; known: {self.RESET_FIELDS}")
        if "version" in fixed and not self.random_version:
            raise ValueError(f"{self.name} was made with version={self.versions[0]}; make it with "
                             f"version='random' to set versions per world")
        shapes = {"version": (), "robot_qpos": (len(self.joint_names),), "obj_pos": (self.num_objects, 3),
                  "obj_quat": (self.num_objects, 4), "torques": (RANDOM_TORQUE_STEPS, self.controlled)}
        fixed = {k: jnp.broadcast_to(jnp.asarray(v), (self.num_envs, *shapes[k])) for k, v in fixed.items()}
        saved, self._fixed = self._fixed, fixed
        try:
            return self.reset(key)
        finally:
            self._fixed = saved

    def _draws(self, key: jax.Array) -> dict[str, jax.Array]:
        """One world's reset draws (bulb's distributions) and its advanced key."""
        key, k = jax.random.split(key)
        kv, kr, kp, kq, kt = jax.random.split(k, 5)
        version = (jax.random.randint(kv, (), 0, NUM_VERSIONS) if self.random_version
                   else jnp.asarray(self.versions[0]))
        z_min = 0.03 if "Ycb" in self.variant else 0.04
        lo = jnp.array([-INIT_XY, -INIT_XY, z_min])
        hi = jnp.array([INIT_XY, INIT_XY, INIT_Z_MAX])
        pos = jax.random.uniform(kp, (self.num_objects, 3), minval=lo, maxval=hi)
        xyzw = jax.random.uniform(kq, (self.num_objects, 4))
        xyzw = xyzw / jnp.linalg.norm(xyzw, axis=1, keepdims=True)
        torques = jax.random.uniform(kt, (RANDOM_TORQUE_STEPS, self.controlled), minval=-0.5, maxval=0.5)
        return {"version": version.astype(jnp.int32), "robot_qpos": self._draw_robot_qpos(kr), "obj_pos": pos,
                "obj_quat": xyzw[:, jnp.array([3, 0, 1, 2])], "torques": torques, "key": key}

    def _draws_fixed(self, keys: jax.Array) -> dict[str, jax.Array]:
        draws = jax.vmap(self._draws)(keys)
        return {**draws, **{k: v.astype(draws[k].dtype) for k, v in self._fixed.items()}}

    def _place(self, draws: dict[str, jax.Array]) -> mjx.Data:
        """One world before the settle: the robot at its drawn pose, the version's objects at
        their drawn poses, the other objects parked."""
        qpos = self._qpos_park.at[self._robot_qadr].set(draws["robot_qpos"])
        slots = self._version_slots[draws["version"]]
        idx = self._slot_qadr[slots][:, None] + jnp.arange(7)
        qpos = qpos.at[idx].set(jnp.concatenate([draws["obj_pos"], draws["obj_quat"]], axis=1))
        return self._data0.replace(qpos=qpos, qvel=jnp.zeros(self.mj_model.nv))

    def _settle(self, data: mjx.Data, draws: dict[str, jax.Array]) -> mjx.Data:
        """bulb's 20 free steps, then 10 steps of the drawn random torques (one scan)."""
        params = {"version": draws["version"]}
        mx = self._world_model(params)
        data = jax.vmap(mjx.forward, in_axes=(None, 0))(mx, data)  # bias forces for the first torques
        zero = jnp.zeros((SETTLE_STEPS, self.num_envs, self.controlled))
        actions = jnp.concatenate([zero, jnp.swapaxes(draws["torques"], 0, 1)])  # [30, N, A]
        return jax.lax.scan(lambda d, a: (self._cap_speeds(self.physics(d, a, params)), None), data, actions)[0]

    def _cap_speeds(self, data: mjx.Data) -> mjx.Data:
        """Objects' speeds capped during the settle: MuJoCo's soft contacts push objects that
        start deep in each other (or in the arm) apart faster than Bullet's capped penetration
        recovery does, and a light sphere could fly off the table."""
        idx = self._slot_vadr[:, None] + jnp.arange(6)  # [S, 6]

        def cap(v):  # [..., S, 6]
            lin, ang = v[..., :3], v[..., 3:]
            scale = lambda x, m: x * jnp.minimum(1.0, m / jnp.maximum(jnp.linalg.norm(x, axis=-1, keepdims=True), 1e-9))
            return jnp.concatenate([scale(lin, SETTLE_MAX_SPEED), scale(ang, SETTLE_MAX_SPIN)], axis=-1)
        qvel = data.qvel.at[:, idx].set(cap(data.qvel[:, idx]))
        return data.replace(qvel=qvel)

    def _reset_batch(self, keys: jax.Array, done: jax.Array, forward: bool = True):
        """bulb's reset of the worlds in `done`: draws, placement, settle; a world whose settle
        went non-finite (objects started deep in each other) is drawn again (at most
        `NAN_RETRIES` times). One settle in the graph (a while loop), none run when no world
        is done."""
        draws = self._draws_fixed(keys)
        data = jax.vmap(self._place)(draws)

        def attempt(carry):
            i, draws, data, todo = carry
            settled = self._settle(jax.vmap(self._place)(draws), draws)
            data = _where_tree(todo, settled, data)
            bad = todo & ~jnp.isfinite(data.qpos).all(axis=1)
            draws = _where_tree(bad, self._draws_fixed(draws["key"]), draws)
            return i + 1, draws, data, bad

        def more(carry):
            i, _, _, todo = carry
            return (i <= NAN_RETRIES) & todo.any()

        _, draws, data, _ = jax.lax.while_loop(more, attempt, (jnp.int32(0), draws, data, done))
        # Still non-finite after the redraws: the world starts from its placement before the
        # settle (finite by construction; a step that goes NaN from it is reset and counted).
        data = _where_tree(done & ~_finite_rows(data), jax.vmap(self._place)(draws), data)
        params = {"version": draws["version"]}
        if forward:
            data = jax.vmap(mjx.forward, in_axes=(None, 0))(self._world_model(params), data)
        return data, draws["version"], params, draws["key"]


# ----------------------------------------------------------------------------- Reacher
REACHER_CAMERA = CameraConfig(distance=0.40, yaw=90.0, pitch=-89.0, body="world", fovy=90.0)
REACHER_LIMITS = np.array([31 / 32, 26 / 32]) * math.pi  # bulb's clamp of |q|


class ReacherRearrange(Rearrange):
    """bulb's ReacherRearrangeEnv: the planar 2-link reacher (`mjcf_assets/reacher_rearrange.xml`)
    at the tray's centre, 3 N m per joint, black floor, top-down camera."""

    joint_names = ("joint0", "joint1")
    controlled = 2
    action_size = 2
    max_torque = (3.0, 3.0)
    ee_body = "hand_link"
    floor_rgba = (0.0, 0.0, 0.0, 1.0)
    camera = REACHER_CAMERA
    robot_file = "reacher_rearrange.xml"

    def _robot_model(self) -> mjcf.RootElement:
        return mjcf.from_path(os.path.join(asset_dir(), self.robot_file))

    def _draw_robot_qpos(self, key: jax.Array) -> jax.Array:
        return jax.random.uniform(key, (2,), minval=-0.75 * math.pi, maxval=0.75 * math.pi)

    def _obey_limits(self, data: mjx.Data) -> mjx.Data:
        """bulb's ReacherBulletSimulation: a joint past (31/32, 26/32) pi is put on that limit
        with its velocity reversed."""
        q, v = data.qpos[self._robot_qadr], data.qvel[self._robot_vadr]
        lim = jnp.asarray(REACHER_LIMITS, q.dtype)
        over = jnp.abs(q) > lim
        q = jnp.where(over, lim * jnp.sign(q), q)
        v = jnp.where(over, -v, v)
        return data.replace(qpos=data.qpos.at[self._robot_qadr].set(q), qvel=data.qvel.at[self._robot_vadr].set(v))


def _variant_class(base: type, robot: str, variant: str, doc: str) -> type:
    name = f"{robot}Rearrange{variant}"
    n_obj = len(OBJECT_LISTS[variant][0])
    cls = type(name, (base,), {
        "name": name, "variant": variant, "__doc__": doc,
        "state_spec": rearrange_state_spec(len(base.joint_names) + len(base.fixed_joint_qpos), n_obj)})
    cls.__module__ = __name__
    return cls


_VARIANT_DOCS = {
    "Geom": "four geometric objects (cylinder, cube, two spheres) in each version's colours",
    "OneGeom": "one geometric object per version",
    "Ycb": "four YCB objects per version (meshes from `ycb_dir` / $BULBJAX_YCB_DIR)",
    "OneYcb": "one YCB object per version (meshes from `ycb_dir` / $BULBJAX_YCB_DIR)",
}
ReacherRearrangeGeom = _variant_class(ReacherRearrange, "Reacher", "Geom", f"ReacherRearrange: {_VARIANT_DOCS['Geom']}.")
ReacherRearrangeOneGeom = _variant_class(ReacherRearrange, "Reacher", "OneGeom", f"ReacherRearrange: {_VARIANT_DOCS['OneGeom']}.")
ReacherRearrangeYcb = _variant_class(ReacherRearrange, "Reacher", "Ycb", f"ReacherRearrange: {_VARIANT_DOCS['Ycb']}.")
ReacherRearrangeOneYcb = _variant_class(ReacherRearrange, "Reacher", "OneYcb", f"ReacherRearrange: {_VARIANT_DOCS['OneYcb']}.")


# ----------------------------------------------------------------------------- Franka
FRANKA_CAMERA = CameraConfig(distance=0.44, yaw=90.0, pitch=-65.0, body="world", target_offset=(0.05, 0.0, 0.0),
                             fovy=90.0)
FRANKA_BASE = (-0.7, 0.0, 0.0)
FRANKA_REST = (-0.0412, 0.5043, 0.0048, -2.6232, -0.1651, 3.1273, 0.9135)
FRANKA_EFFORTS = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)  # panda.urdf's <limit effort>
EE_POS_MIN = (-0.5, -0.5, 0.05)  # bulb's region for the random end-effector pose
EE_POS_MAX = (0.5, 0.5, 0.35)
IK_ITERATIONS = 60
IK_CANDIDATES = 4
IK_DAMPING = 1e-2
IK_ROT_WEIGHT = 0.3  # metres per unit of rotation-matrix error
IK_MIN_LINK_Z = 0.01  # a pose is kept when every link frame past the base is this far above the floor
FINGERTIP_OFFSET = 0.11  # m along the hand's z axis (panda.urdf: fingers at 0.0584, 0.054 long)


def _axis_angle_mat(axis: jax.Array, angle: jax.Array) -> jax.Array:
    x, y, z = axis[0], axis[1], axis[2]
    c, s, t = jnp.cos(angle), jnp.sin(angle), 1 - jnp.cos(angle)
    return jnp.array([[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
                      [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
                      [t * x * z - s * y, t * y * z + s * x, t * z * z + c]])


def _euler_quat_mat(rpy: jax.Array) -> jax.Array:
    """PyBullet's getQuaternionFromEuler as a matrix: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = jnp.cos(rpy[0]), jnp.sin(rpy[0])
    cp, sp = jnp.cos(rpy[1]), jnp.sin(rpy[1])
    cy, sy = jnp.cos(rpy[2]), jnp.sin(rpy[2])
    rx = jnp.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = jnp.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = jnp.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


class FrankaRearrange(Rearrange):
    """bulb's FrankaRearrangeEnv: the Panda (`pybullet_data`'s panda.urdf converted by MuJoCo,
    `bulbjax.assets.franka`) based at (-0.7, 0, 0), 7 torque-controlled joints with gravity
    compensation, fingers fixed (closed), camera at distance 0.44, yaw 90, pitch -65.

    Reset pose: bulb draws an end-effector target (x, y in [-0.5, 0.5], z in [0.05, 0.35], roll
    pushed to |roll| >= pi/2 and pitch, yaw clipped to +-pi/2: the gripper points mostly down)
    and solves PyBullet's IK from the rest pose, retrying while a link touches the floor. Here:
    damped least squares on the hand's position and orientation in JAX (60 iterations from the
    rest pose, joint ranges enforced), 4 targets per world, the first whose link frames and
    fingertips all clear the floor kept (else the last). pybullet_data's fingers are longer than
    bulb's `franka_small_fingers.urdf`: at bulb's rest pose their tips touch the floor."""

    joint_names = tuple(f"panda_joint{i}" for i in range(1, 8))
    fixed_joint_qpos = (0.0, 0.0)  # the fingers, closed
    controlled = 7
    action_size = 7
    max_torque = FRANKA_EFFORTS
    ee_body = "panda_hand"
    robot_pos = FRANKA_BASE
    floor_rgba = (0.55, 0.6, 0.68, 1.0)  # PyBullet's plane.urdf checker, as one colour
    floor_conaffinity = 3  # the Franka touches the floor
    camera = FRANKA_CAMERA

    def __init__(self, config: EnvConfig):
        super().__init__(config)
        m = self.mj_model
        jids = [m.joint(self._robot_prefix + j).id for j in self.joint_names]
        self._jnt_lo = jnp.asarray(m.jnt_range[jids, 0], jnp.float32)
        self._jnt_hi = jnp.asarray(m.jnt_range[jids, 1], jnp.float32)
        efforts = np.array([m.actuator(self._robot_prefix + j).ctrlrange[1] for j in self.joint_names])
        if not np.allclose(efforts, self.max_torque):
            raise ValueError(f"converted Panda's efforts {efforts} differ from bulb's {self.max_torque}")
        # the kinematic chain from the base to the hand, for the reset's IK
        chain = [self._ee]
        while m.body_parentid[chain[-1]] != 0:
            chain.append(int(m.body_parentid[chain[-1]]))
        chain = chain[::-1]
        self._chain_pos = np.asarray(m.body_pos[chain])
        self._chain_quat = np.asarray(m.body_quat[chain])
        self._chain_joint = [int(np.nonzero(np.array(jids) == m.body_jntadr[b])[0][0]) if m.body_jntnum[b] else -1
                             for b in chain]
        self._chain_axis = [np.asarray(m.jnt_axis[m.body_jntadr[b]]) if m.body_jntnum[b] else None for b in chain]
        self._first_jointed = min(i for i, j in enumerate(self._chain_joint) if j >= 0)
        self._rest = jnp.asarray(FRANKA_REST, jnp.float32)

    def _robot_model(self) -> mjcf.RootElement:
        from bulbjax.assets.franka import franka_mjcf

        return mjcf.from_path(str(franka_mjcf()))

    # ----- control -----
    def _torque(self, data: mjx.Data, action: jax.Array) -> jax.Array:
        """bulb's torque plus gravity compensation (inverse dynamics at zero acceleration:
        MuJoCo's bias force of the latest forward pass), clipped to the efforts."""
        bias = data.qfrc_bias[self._robot_vadr]
        return jnp.clip(jnp.clip(action, -1.0, 1.0) * self._max_torque + bias, -self._max_torque, self._max_torque)

    def _obey_limits(self, data: mjx.Data) -> mjx.Data:
        """bulb's `obey_joint_limits`: a joint outside its range is put on the bound, at rest."""
        q, v = data.qpos[self._robot_qadr], data.qvel[self._robot_vadr]
        out = (q < self._jnt_lo) | (q > self._jnt_hi)
        q = jnp.clip(q, self._jnt_lo, self._jnt_hi)
        v = jnp.where(out, 0.0, v)
        return data.replace(qpos=data.qpos.at[self._robot_qadr].set(q), qvel=data.qvel.at[self._robot_vadr].set(v))

    # ----- reset pose -----
    def hand_pose(self, q: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """World position and rotation of the hand's frame at arm angles `q` [7], and the z of
        every link frame of the chain and of the fingertips (pure JAX forward kinematics of the
        compiled model)."""
        pos, rot = jnp.zeros(3), jnp.eye(3)
        zs = []
        for p, quat, j, axis in zip(self._chain_pos, self._chain_quat, self._chain_joint, self._chain_axis):
            pos = pos + rot @ jnp.asarray(p, jnp.float32)
            rot = rot @ _quat_mat(jnp.asarray(quat, jnp.float32))
            if j >= 0:
                rot = rot @ _axis_angle_mat(jnp.asarray(axis, jnp.float32), q[j])
            zs.append(pos[2])
        zs.append(pos[2] + rot[2, 2] * FINGERTIP_OFFSET)  # the fingertips, below the hand
        return pos, rot, jnp.stack(zs)

    def solve_ik(self, target_pos: jax.Array, target_rot: jax.Array) -> jax.Array:
        """Arm angles that put the hand at `target_pos` with rotation `target_rot` (damped least
        squares from the rest pose, clipped to the joint ranges; a best effort when out of reach)."""
        def residual(q):
            pos, rot, _ = self.hand_pose(q)
            # the matrix difference, not the cross-product form (zero at half-turns as well)
            return jnp.concatenate([pos - target_pos, IK_ROT_WEIGHT * (rot - target_rot).reshape(-1)])

        def body(q, _):
            r = residual(q)
            jac = jax.jacfwd(residual)(q)
            dq = jac.T @ jnp.linalg.solve(jac @ jac.T + IK_DAMPING * jnp.eye(12), r)
            return jnp.clip(q - dq, self._jnt_lo, self._jnt_hi), None

        return jax.lax.scan(body, self._rest, None, length=IK_ITERATIONS)[0]

    def _ee_target(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """bulb's random end-effector target: position and the restricted Euler angles."""
        kp, ko = jax.random.split(key)
        pos = jax.random.uniform(kp, (3,), minval=jnp.asarray(EE_POS_MIN), maxval=jnp.asarray(EE_POS_MAX))
        rpy = jax.random.uniform(ko, (3,), minval=-jnp.pi, maxval=jnp.pi)
        almost_down = jnp.pi / 2
        roll = jnp.where(jnp.abs(rpy[0]) < almost_down, almost_down * jnp.sign(rpy[0]), rpy[0])
        rpy = jnp.clip(rpy.at[0].set(roll), -jnp.array([jnp.pi, jnp.pi / 2, jnp.pi / 2]),
                       jnp.array([jnp.pi, jnp.pi / 2, jnp.pi / 2]))
        return pos, _euler_quat_mat(rpy)

    def _draw_robot_qpos(self, key: jax.Array) -> jax.Array:
        keys = jax.random.split(key, IK_CANDIDATES)

        def candidate(k):
            pos, rot = self._ee_target(k)
            q = self.solve_ik(pos, rot)
            ok = (self.hand_pose(q)[2][self._first_jointed:] > IK_MIN_LINK_Z).all()
            return q, ok

        qs, ok = jax.vmap(candidate)(keys)
        first = jnp.where(ok.any(), jnp.argmax(ok), IK_CANDIDATES - 1)
        return qs[first]


FrankaRearrangeGeom = _variant_class(FrankaRearrange, "Franka", "Geom", f"FrankaRearrange: {_VARIANT_DOCS['Geom']}.")
FrankaRearrangeOneGeom = _variant_class(FrankaRearrange, "Franka", "OneGeom", f"FrankaRearrange: {_VARIANT_DOCS['OneGeom']}.")
FrankaRearrangeYcb = _variant_class(FrankaRearrange, "Franka", "Ycb", f"FrankaRearrange: {_VARIANT_DOCS['Ycb']}.")
FrankaRearrangeOneYcb = _variant_class(FrankaRearrange, "Franka", "OneYcb", f"FrankaRearrange: {_VARIANT_DOCS['OneYcb']}.")

REARRANGE_CLASSES: tuple[type[Rearrange], ...] = (
    ReacherRearrangeGeom, ReacherRearrangeOneGeom, ReacherRearrangeYcb, ReacherRearrangeOneYcb,
    FrankaRearrangeGeom, FrankaRearrangeOneGeom, FrankaRearrangeYcb, FrankaRearrangeOneYcb)
