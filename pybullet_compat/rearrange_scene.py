"""The Rearrange domains' scene for the PyBullet originals (`pybullet_compat.rearrange_env`): bulb's
numbers (the same values as bulbjax's MJX mirror, `bulbjax.envs.objects.rearrange`, copied so that worker
processes never import JAX; tests/test_pybullet_rearrange.py checks them equal), the domains'
specs, and the objects as PyBullet builds them (picklable, prepared in the parent process).
bulb has no licence: every line is ours, only its numbers and behaviour are taken."""

from __future__ import annotations

import importlib.util
import math
import os
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

# ---------------------------------------------------------------------------------- bulb's numbers
# (the same values as bulbjax.envs.objects.rearrange; tests/test_pybullet_rearrange.py checks them)
NUM_VERSIONS = 12
NUM_LISTS = 6
EPISODE_STEPS = 200
BULLET_DT = 0.01
BULLET_SUBSTEPS = 2
SOLVER_ITERATIONS = 5
GRAVITY = 9.81
SETTLE_STEPS = 20
RANDOM_TORQUE_STEPS = 10
OBJ_XYZ_MIN = np.array([-0.45, -0.45, -0.05])
OBJ_XYZ_MAX = np.array([0.45, 0.45, 0.20])
EE_XY_MAX = 0.5
EE_ABOVE_OBJECTS = 0.2
INIT_XY = 0.15
INIT_Z_MAX = 0.075
TARGETS = np.array([[0.2, -0.2], [0.2, 0.2]])  # boxes and cans / everything else
TRAY_SCALE = 0.8
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
TABLE_RGB = np.array([[220, 200, 170], [165, 165, 165], [165, 75, 40], [82, 60, 124],
                      [90, 190, 180], [220, 200, 170]]) / 255.0
PROP_NAMES = ("rgb_r", "rgb_g", "rgb_b", "radius_a", "radius_b", "height", "shape", "mass",
              "restitution", "lateral_friction", "rolling_friction", "spinning_friction")
PROP_MIN = np.array([0, 0, 0, 0.01, 0.01, 0.01, 0, 0.01, 0.0, 0.0, 0.0, 0.0])
PROP_MAX = np.array([1, 1, 1, 0.15, 0.15, 0.15, 3, 1.0, 1.0, 1.0, 0.01, 0.01])
SHAPE_SPHERE, SHAPE_CYLINDER, SHAPE_BOX, SHAPE_MESH = 0, 1, 2, 3
CYLINDER_DEFAULT_DIMS = (0.06, 0.06, 0.06)
YCB_DYNAMICS = (0.0, 0.5, 0.0, 0.0)  # restitution, lateral, rolling, spinning friction
# geom objects: resting half-height z, mass, bulb's reported dims, shape id, dynamics (as the mirror's GEOM_INFO)
GEOM_INFO: dict[str, tuple[float, float, tuple[float, float, float], int, tuple[float, float, float, float]]] = {
    "sphere": (0.04, 0.1, (0.04, 0.04, 0.04), SHAPE_SPHERE, (1.0, 0.5, 0.001, 0.001)),
    "sphere1": (0.06, 0.3, (0.06, 0.06, 0.06), SHAPE_SPHERE, (1.0, 0.5, 0.001, 0.001)),
    "cylinder": (0.06, 0.2, CYLINDER_DEFAULT_DIMS, SHAPE_CYLINDER, (0.0, 0.5, 0.0, 0.0)),
    "cube": (0.075, 0.05, (0.025, 0.05, 0.075), SHAPE_BOX, (0.0, 0.5, 0.0, 0.0)),
}
# their PyBullet shapes (kind, size)
GEOM_SHAPES: dict[str, tuple[str, dict[str, Any]]] = {
    "sphere": ("sphere", {"radius": 0.04}), "sphere1": ("sphere", {"radius": 0.06}),
    "cylinder": ("cylinder", {"radius": 0.06, "half_height": 0.06}),
    "cube": ("box", {"half_extents": (0.025, 0.05, 0.075)})}
BORDER_RESTITUTION = 1.0
REACHER_LIMITS = np.array([31 / 32, 26 / 32]) * math.pi
REACHER_TORQUE = (3.0, 3.0)
REACHER_INIT = 0.75 * math.pi
FRANKA_BASE = (-0.7, 0.0, 0.0)
FRANKA_REST = (-0.0412, 0.5043, 0.0048, -2.6232, -0.1651, 3.1273, 0.9135)
FRANKA_EFFORTS = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
EE_POS_MIN = (-0.5, -0.5, 0.05)
EE_POS_MAX = (0.5, 0.5, 0.35)
IK_TRIES = 10  # bulb draws again while a link touches the floor (no cap); here at most 10, the last kept
IK_ITERATIONS = 100
FINGER_HOLD_FORCE = 100.0  # N, position motors keeping the fingers closed
REACHER_CAMERA = {"distance": 0.40, "yaw": 90.0, "pitch": -89.0, "target": (0.0, 0.0, 0.0)}
FRANKA_CAMERA = {"distance": 0.44, "yaw": 90.0, "pitch": -65.0, "target": (0.05, 0.0, 0.0)}
FOV, NEAR, FAR = 90.0, 0.01, 100.0
REACHER_ELBOW_RGBA = (1.0, 0.6, 0.15, 1.0)
RESET_FIELDS = ("robot_qpos", "obj_pos", "obj_quat", "torques")


# ---------------------------------------------------------------------------------- domains
@dataclass(frozen=True)
class RearrangeSpec:
    """One Rearrange domain: robot, object variant, joints reported in the state (the Franka's
    two fixed fingers included), controlled joints (= action size), episode length."""

    name: str
    robot: str  # "Reacher" or "Franka"
    variant: str  # "Geom", "OneGeom", "Ycb", "OneYcb"
    state_joints: int
    action_size: int
    episode_length: int = EPISODE_STEPS
    discrete: bool = False
    num_actions: int | None = None

    @property
    def num_objects(self) -> int:
        return len(OBJECT_LISTS[self.variant][0])

    @property
    def state_names(self) -> tuple[str, ...]:
        return state_names(self.state_joints, self.num_objects)

    @property
    def state_dim(self) -> int:
        return len(self.state_names)


def state_names(joints: int, objects: int) -> tuple[str, ...]:
    """bulb's Rearrange state names (bulbjax's `rearrange_state_spec` names)."""
    names = [n for j in range(joints) for n in (f"j{j}_sin", f"j{j}_cos")]
    names += [f"obj{i}_{p}" for i in range(objects) for p in PROP_NAMES]
    names += [f"obj{i}_{a}" for i in range(objects) for a in "xyz"]
    names += [f"obj{i}_rot{k}" for i in range(objects) for k in range(9)]
    return tuple(names)


def raw_names(joints: int, objects: int) -> tuple[str, ...]:
    """Names of `raw_state()` (bulbjax's `rearrange_raw_state_spec` names)."""
    names = [f"j{j}_pos" for j in range(joints)] + [f"j{j}_vel" for j in range(joints)]
    for i in range(objects):
        names += [f"obj{i}_pos_{a}" for a in "xyz"] + [f"obj{i}_quat_{a}" for a in "wxyz"]
        names += [f"obj{i}_vel_{a}" for a in "xyz"] + [f"obj{i}_angvel_{a}" for a in "xyz"]
    return tuple(names + [f"ee_{a}" for a in "xyz"])


REARRANGE_DOMAINS: dict[str, RearrangeSpec] = {
    f"{robot}Rearrange{variant}": RearrangeSpec(f"{robot}Rearrange{variant}", robot, variant, joints, act)
    for robot, joints, act in (("Reacher", 2, 2), ("Franka", 9, 7))
    for variant in ("Geom", "OneGeom", "Ycb", "OneYcb")}


def rearrange_domain(name: str) -> RearrangeSpec:
    """The spec of Rearrange domain `name` (ReacherRearrangeGeom, FrankaRearrangeOneYcb, ...)."""
    if name not in REARRANGE_DOMAINS:
        raise ValueError(f"unknown Rearrange domain {name!r}; available: {', '.join(REARRANGE_DOMAINS)}")
    return REARRANGE_DOMAINS[name]


def reacher_mjcf_path() -> str:
    """bulbjax's reacher MJCF (`$BULBJAX_MJCF_DIR`, else the MJCF folder as
    `bulbjax.envs.models.asset_dir` finds it: `bulbjax/mjcf_assets/` in an installed wheel, the
    checkout's top-level `mjcf_assets/` beside `bulbjax/` otherwise), found without importing
    bulbjax: `find_spec` of a top-level package locates it without running it."""
    folder = os.environ.get("BULBJAX_MJCF_DIR")
    if not folder:
        spec = importlib.util.find_spec("bulbjax")
        locations = list(spec.submodule_search_locations or []) if spec else []
        candidates = ([os.path.join(locations[0], "mjcf_assets"),  # an installed wheel
                       os.path.join(os.path.dirname(os.path.abspath(locations[0])), "mjcf_assets")]  # a checkout
                      if locations else ["mjcf_assets"])
        folder = next((c for c in candidates if os.path.isdir(c)), candidates[0])
    path = os.path.join(folder, "reacher_rearrange.xml")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"reacher MJCF {path!r} not found (set BULBJAX_MJCF_DIR to the folder of "
                                "bulbjax's MJCF files, mjcf_assets/ in a checkout)")
    return path


def load_reacher(client: Any, path: str | None = None) -> int:
    """Load the reacher MJCF (`reacher_mjcf_path()` by default) into PyBullet `client` with its base
    welded where it stands, and return its body id. `loadMJCF` makes the root body a free base (the
    0.06 kg base cylinder), which the arm's reaction torques throw about; a base of mass 0 is static
    in Bullet, as bulb's arm mounted on the table."""
    robot = client.loadMJCF(path or reacher_mjcf_path())[0]
    client.changeDynamics(robot, -1, mass=0.0)
    return robot


def check_version(version: Any) -> int:
    if isinstance(version, bool) or not isinstance(version, (int, np.integer)) or not 0 <= int(version) < NUM_VERSIONS:
        raise ValueError(f"version must be an int in 0..{NUM_VERSIONS - 1} (6-11: black background), got {version!r}")
    return int(version)


# ---------------------------------------------------------------------------------- objects
@dataclass(frozen=True)
class RearrangeObject:
    """What PyBullet needs to build one object (picklable, for worker processes).

    kind 'sphere' (radius), 'cylinder' (radius, half_height along z), 'box' (half_extents) or
    'mesh' (the processed `collision_path` hull and `visual_path` mesh, shifted by -`com` so the
    body frame is the centre of mass). `half_z`: bulb's resting half-height times the z scale
    (twice the largest is the tallest object); `props`: bulb's 12 raw properties (un-normalised);
    `target`: the xy target of the object's class."""

    name: str
    kind: str
    mass: float
    rgba: tuple[float, float, float, float]
    half_z: float
    props: tuple[float, ...]
    target: tuple[float, float]
    radius: float | None = None
    half_height: float | None = None
    half_extents: tuple[float, float, float] | None = None
    collision_path: str | None = None
    visual_path: str | None = None
    texture_path: str | None = None
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    restitution: float = 0.0
    lateral_friction: float = 0.5
    rolling_friction: float = 0.0
    spinning_friction: float = 0.0


def _target(name: str) -> tuple[float, float]:
    return tuple(float(t) for t in TARGETS[0 if name.endswith(("_box", "_can")) else 1])


def geom_object(kind: str, rgb: Sequence[float]) -> RearrangeObject:
    """bulb's geometric object `kind` (sphere, sphere1, cylinder, cube) in colour `rgb`."""
    if kind not in GEOM_INFO:
        raise ValueError(f"unknown geom object {kind!r}; known: {sorted(GEOM_INFO)}")
    z, mass, dims, shape, (rest, lat, roll, spin) = GEOM_INFO[kind]
    rgb = tuple(float(c) for c in rgb)
    props = (*rgb, *dims, float(shape), mass, rest, lat, roll, spin)
    shape_kind, geo = GEOM_SHAPES[kind]
    return RearrangeObject(kind, shape_kind, mass, (*rgb, 1.0), z, props, _target(kind), restitution=rest,
                           lateral_friction=lat, rolling_friction=roll, spinning_friction=spin, **geo)


def ycb_object(name: str, ycb_dir: str | None = None, cache_dir: str | None = None) -> RearrangeObject:
    """YCB object `name` at bulb's scale, from bulbjax's asset cache (built on first use; imports
    bulbjax.assets, so call it in the parent process). A missing folder names BULBJAX_YCB_DIR."""
    from bulbjax.assets import YCB_INFO, load_ycb_object

    a = load_ycb_object(name, scale=1.0, ycb_dir=ycb_dir, cache_dir=cache_dir)
    info = YCB_INFO[name]
    rest, lat, roll, spin = YCB_DYNAMICS
    props = (1.0, 1.0, 1.0, *CYLINDER_DEFAULT_DIMS, float(SHAPE_MESH), float(info.mass), rest, lat, roll, spin)
    return RearrangeObject(name, "mesh", float(a.mass), tuple(float(c) for c in a.rgba),
                           float(info.half_height * info.scale[2]), props, _target(name),
                           collision_path=str(a.collision_path), visual_path=str(a.visual_path),
                           texture_path=str(a.texture_path) if a.texture_path is not None else None,
                           com=tuple(float(c) for c in a.com), restitution=rest, lateral_friction=lat,
                           rolling_friction=roll, spinning_friction=spin)


def rearrange_objects(name: str, version: int, ycb_dir: str | None = None,
                      cache_dir: str | None = None) -> tuple[RearrangeObject, ...]:
    """The objects of domain `name` at `version`, in bulb's list order (prepare YCB ones here, in
    the parent, and pass them to worker envs as `objects=`)."""
    spec = rearrange_domain(name)
    v = check_version(version)
    names = OBJECT_LISTS[spec.variant][v % NUM_LISTS]
    if spec.variant in ("Geom", "OneGeom"):
        return tuple(geom_object(n, GEOM_COLOURS[v % NUM_LISTS][i]) for i, n in enumerate(names))
    return tuple(ycb_object(n, ycb_dir, cache_dir) for n in names)


def normalise(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return (x - lo) / (hi - lo) * 2.0 - 1.0


def table_rgb(version: int) -> tuple[float, float, float]:
    """The tray's colour of `version` (the texture's mean colour; 6-11 black)."""
    return tuple(float(c) for c in TABLE_RGB[version]) if version < NUM_LISTS else (0.0, 0.0, 0.0)


def ee_target(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """bulb's random end-effector target for the Franka's reset: position and Euler angles with
    |roll| >= pi/2 (gripper mostly down) and pitch, yaw within +-pi/2."""
    pos = rng.uniform(EE_POS_MIN, EE_POS_MAX)
    rpy = rng.uniform(-math.pi, math.pi, 3)
    half = math.pi / 2
    if abs(rpy[0]) < half:
        rpy[0] = half * (1.0 if rpy[0] >= 0 else -1.0)
    rpy = np.clip(rpy, [-math.pi, -half, -half], [math.pi, half, half])
    return pos, rpy
