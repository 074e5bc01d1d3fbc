"""PyBullet originals of bulb's Incline domains (GeomOnIncline, YcbOnIncline, Md/Sm), built here
from the facts of bulb's `BlockOnInclineEnv` (`../shared/reference/bulb-multiobject.md`), since
bulb itself cannot be installed: it has no licence, so every line is ours, only its numbers and
behaviour are taken.

The scene, as bulb builds it:
- a plane at z = 0; the incline, a fixed box centred at (0, 0, 0.55) pitched by theta about y
  (its top face descends towards +x). bulb's `incline.urdf` is not in its stored repository, so
  the box is bulbjax's: 2.4 x 0.6 x 0.04 m (the slide range 0 <= x <= 1 lies on it at every pitch).
- the object of `version`: Geom -- block (box 0.05 x 0.10 x 0.15 m, 0.05 kg; restitution 0.1),
  block, block, cylinder (r 0.06, h 0.12), cylinder_large (r 0.06, h 0.13, 0.2 kg; restitution 1,
  rolling friction 0.001), cylinder_short (r 0.06, h 0.06), every size times the scale (2.5, Md
  1.5, Sm 1.0), one colour per version; Ycb -- bulb's six YCB objects at bulb's scale times the
  env's, from bulbjax's asset pipeline (`bulbjax.assets.load_ycb_object`): the SAME processed
  files the MJX mirror loads (the <=200-face convex hull collides, the decimated textured mesh is
  drawn), with the body frame at the mesh's centre of mass as in the mirror.
- Bullet's settings of bulb: gravity -9.81, `setTimeStep(0.01)`, `numSubSteps=2`,
  `numSolverIterations=5`; an env step is 4 `stepSimulation` calls with the push applied before
  each (`applyExternalForce` in the object's link frame along its z axis; Bullet keeps it over
  both substeps); episode 50 steps.
- reset (bulb's `randomize=True`): mass U[0.05, 0.5] kg, lateral friction U[0.1, 0.5] given to
  both the object and the incline (Bullet multiplies the two: the contact's coefficient is
  friction^2), pitch U[0.25, 0.5] rad, texture id in 0..5; the object placed at (-0.05, 0, 0.7)
  with roll pi/2, pitch and yaw pi/2 + e (e in +-pi/16, the same draw twice as in bulb); then
  single `stepSimulation`s until its x passes U[0.05, 0.15] (at most 50). `reset(seed, **fixed)`
  sets any of mass/friction/theta/texture/eps/start_x explicitly (the MJX side's `reset_with`).
- action a in [-1, 1] (bulbjax's convention, clipped) is bulb's force 2a N; state: bulb's scaled
  low-dim state (texture/6, version/6, (friction,) pitch, distance from the start, speed), and
  `raw_state()` in the layout of the MJX mirror's `info["lowdim_raw"]`.

What Bullet does on its own (kept, because bulb ran with it; switches for the parity study):
- `changeDynamics(mass=...)` recomputes the inertia from the collision shape (a box's exact one,
  a cylinder's exact one, a convex hull's from its bounding box) -- not the URDF's numbers.
  `inertia="mirror"` sets the MJX mirror's (diagonal) inertia after each mass change instead.
- multibody bases get velocity damping 0.04: a deceleration of 0.04 |v| (1 + |v|) (0.08 m/s^2 at
  1 m/s, 0.48 at 3 m/s). `bullet_damping=False` sets it to 0, as in MuJoCo.

Frames: 64 x 64 RGB from `getCameraImage` (ER_TINY_RENDERER) with bulb's camera (distance 0.8,
yaw 35, pitch -45, target (0.5, 0.2, 0.1), FOV 90, near 0.01, far 100). Plane/incline colours are
bulbjax's (bulb's textures as mean colours). This module imports neither JAX nor bulbjax at
import time (it runs in worker processes); YCB objects are prepared by `object_shape`, which
imports `bulbjax.assets` -- prepare them in the parent and pass `shape=` to workers.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from pybullet_compat import _loader
from pybullet_compat.envs import StepResult

# ---------------------------------------------------------------------------------- bulb's numbers
NUM_VERSIONS = 6
NUM_TEXTURES = 6
EPISODE_STEPS = 50
BULLET_DT = 0.01
BULLET_SUBSTEPS = 2
SOLVER_ITERATIONS = 5
STEPS_PER_ACTION = 4
MAX_FORCE = 2.0
GRAVITY = 9.81
INCLINE_POS = (0.0, 0.0, 0.55)
INCLINE_HALF = (1.2, 0.3, 0.02)
START_POS = (-0.05, 0.0, 0.7)
START_EPS = math.pi / 16
START_X = (0.05, 0.15)
FALL_STEPS = 50
TARGET_X, MIN_X, MAX_X, MAX_Y = 0.5, 0.0, 1.0, 0.1
MASS = (0.05, 0.5)
FRICTION = (0.1, 0.5)
PITCH = (0.25, 0.5)
CLIP_DIST, CLIP_SPEED = 1.27, 3.10
SCALES = {"": 2.5, "Md": 1.5, "Sm": 1.0}
BULLET_DAMPING = 0.04  # btMultiBody's default linear and angular damping
YCB_OBJECTS = ("004_sugar_box", "008_pudding_box", "009_gelatin_box", "005_tomato_soup_can",
               "007_tuna_fish_can", "002_master_chef_can")
GEOM_COLOURS = ((1, 1, 0.5), (0.2, 0.2, 0.2), (1, 0, 0), (1, 0, 1), (0, 0.5, 1), (0, 0, 1))
INCLINE_COLOURS = ((1, 0.5, 0), (0.8, 0.8, 0.8), (0.9, 0.4, 0.4), (0, 1, 0), (0.5, 0.15, 0.15), (1, 0.6, 0))
GEOM_PLANE_COLOUR = (0.72, 0.72, 0.75)
YCB_PLANE_COLOURS = ((0.62, 0.28, 0.25), (0.2, 0.45, 0.9), (0.45, 0.3, 0.6), (0.62, 0.44, 0.27),
                     (0.16, 0.16, 0.18), (0.92, 0.55, 0.2))
YCB_INCLINE_COLOURS = ((0.62, 0.22, 0.16), (0.86, 0.86, 0.83), (0.86, 0.78, 0.67), (0.2, 0.7, 0.25),
                       (0.5, 0.3, 0.6), (0.66, 0.46, 0.28))
CAMERA = {"distance": 0.8, "yaw": 35.0, "pitch": -45.0, "target": (0.5, 0.2, 0.1), "fov": 90.0,
          "near": 0.01, "far": 100.0}
# block.urdf's inertia (at 0.05 kg, unscaled) and cylinder_large.urdf's (0.2 kg): the MJX mirror's
BLOCK_URDF_INERTIA = (1.041666667e-4, 5.208333333e-5, 1.354166667e-4)
CYLINDER_LARGE_URDF_INERTIA = (3.267e-4, 3.267e-4, 9e-5)
RAW_NAMES = ("pos_x", "pos_y", "pos_z", "quat_w", "quat_x", "quat_y", "quat_z", "vel_x", "vel_y", "vel_z",
             "angvel_x", "angvel_y", "angvel_z", "texture_id", "version", "mass", "friction", "theta",
             "distance", "speed")
RESET_FIELDS = ("mass", "friction", "theta", "texture", "eps", "start_x")


def state_names(report_friction: bool = False) -> tuple[str, ...]:
    """bulb's low-dim state names (bulbjax's state spec names)."""
    return ("texture_id", "version") + (("friction",) if report_friction else ()) + ("theta", "distance", "speed")


@dataclass(frozen=True)
class InclineSpec:
    """One Incline domain: family (Geom/Ycb), object scale, episode length, actions, state."""

    name: str
    variant: str
    scale: float
    episode_length: int = EPISODE_STEPS
    report_friction: bool = False
    discrete: bool = False
    num_actions: int | None = None
    action_size: int = 1

    @property
    def state_names(self) -> tuple[str, ...]:
        return state_names(self.report_friction)

    @property
    def state_dim(self) -> int:
        return len(self.state_names)


INCLINE_DOMAINS: dict[str, InclineSpec] = {
    f"{fam}OnIncline{sz}": InclineSpec(f"{fam}OnIncline{sz}", fam, s) for fam in ("Geom", "Ycb") for sz, s in SCALES.items()}


def incline_domain(name: str) -> InclineSpec:
    """The spec of Incline domain `name` (GeomOnIncline, YcbOnInclineMd, ...)."""
    if name not in INCLINE_DOMAINS:
        raise ValueError(f"unknown Incline domain {name!r}; available: {', '.join(INCLINE_DOMAINS)}")
    return INCLINE_DOMAINS[name]


# ---------------------------------------------------------------------------------- objects
@dataclass(frozen=True)
class ObjectShape:
    """What PyBullet needs to build one object (picklable, for worker processes).

    kind 'box' (half_extents), 'cylinder' (radius, half_height along z) or 'mesh' (the
    processed, already scaled `collision_path` hull and `visual_path` mesh, shifted by -`com`
    so the body frame is the centre of mass). `mirror_inertia`: the MJX mirror's diagonal
    inertia at `mass` (used with `inertia='mirror'`)."""

    kind: str
    mass: float
    rgba: tuple[float, float, float, float]
    mirror_inertia: tuple[float, float, float]
    half_extents: tuple[float, float, float] | None = None
    radius: float | None = None
    half_height: float | None = None
    collision_path: str | None = None
    visual_path: str | None = None
    texture_path: str | None = None
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    restitution: float = 0.0
    rolling_friction: float = 0.0
    name: str = ""
    info: dict[str, Any] = field(default_factory=dict, compare=False)


def geom_shape(version: int, scale: float) -> ObjectShape:
    """bulb's geometric object of `version` at `scale` (sizes x scale, inertia x scale^2)."""
    _check_version(version)
    rgba = (*map(float, GEOM_COLOURS[version]), 1.0)
    if version < 3:
        half = tuple(float(h * scale) for h in (0.025, 0.05, 0.075))
        inertia = tuple(float(i * scale ** 2) for i in BLOCK_URDF_INERTIA)
        return ObjectShape("box", 0.05, rgba, inertia, half_extents=half, restitution=0.1, name="block")
    radius, hh = {3: (0.06, 0.06), 4: (0.06, 0.065), 5: (0.06, 0.03)}[version]
    radius, hh = radius * scale, hh * scale
    if version == 4:
        inertia = tuple(float(i * scale ** 2) for i in CYLINDER_LARGE_URDF_INERTIA)
        return ObjectShape("cylinder", 0.2, rgba, inertia, radius=radius, half_height=hh, restitution=1.0,
                           rolling_friction=0.001, name="cylinder_large")
    ixx = 0.2 * (3 * radius ** 2 + (2 * hh) ** 2) / 12
    return ObjectShape("cylinder", 0.2, rgba, (ixx, ixx, 0.2 * radius ** 2 / 2), radius=radius, half_height=hh,
                       name="cylinder" if version == 3 else "cylinder_short")


def object_shape(spec: InclineSpec, version: int, ycb_dir: str | None = None,
                 cache_dir: str | None = None) -> ObjectShape:
    """The object of `version` in domain `spec`; YCB objects come from `bulbjax.assets` (built
    and cached on first use; `ycb_dir` / $BULBJAX_YCB_DIR, `cache_dir` / $BULBJAX_CACHE_DIR)."""
    _check_version(version)
    if spec.variant == "Geom":
        return geom_shape(version, spec.scale)
    from bulbjax.assets import load_ycb_object

    a = load_ycb_object(YCB_OBJECTS[version], scale=spec.scale, ycb_dir=ycb_dir, cache_dir=cache_dir)
    rgba = tuple(float(c) for c in a.rgba)
    return ObjectShape("mesh", float(a.mass), rgba, tuple(float(x) for x in np.diag(a.inertia)),
                       collision_path=str(a.collision_path), visual_path=str(a.visual_path),
                       texture_path=str(a.texture_path) if a.texture_path is not None else None,
                       com=tuple(float(c) for c in a.com), name=a.name,
                       info={"from_cache": a.from_cache, "build_seconds": a.build_seconds})


def _check_version(version: Any) -> None:
    if not isinstance(version, (int, np.integer)) or not 0 <= int(version) < NUM_VERSIONS:
        raise ValueError(f"version must be an int in 0..{NUM_VERSIONS - 1}, got {version!r}")


# ---------------------------------------------------------------------------------- episode draws
@dataclass(frozen=True)
class InclineParams:
    """One episode's draws: object mass (kg), lateral friction (object and incline), incline pitch
    (rad), texture id, orientation noise e (rad) and the x where the initial fall ends (m)."""

    mass: float
    friction: float
    theta: float
    texture: int
    eps: float
    start_x: float

    def check(self) -> "InclineParams":
        if not self.mass > 0:
            raise ValueError(f"mass must be > 0, got {self.mass}")
        if not self.friction >= 0:
            raise ValueError(f"friction must be >= 0, got {self.friction}")
        if not 0 <= self.theta < math.pi / 2:
            raise ValueError(f"theta must be in [0, pi/2), got {self.theta}")
        if not 0 <= self.texture < NUM_TEXTURES:
            raise ValueError(f"texture must be in 0..{NUM_TEXTURES - 1}, got {self.texture}")
        return self


def draw_params(rng: np.random.Generator) -> InclineParams:
    """bulb's reset distributions (randomize=True)."""
    mass, fric, theta = (rng.uniform(lo, hi) for lo, hi in (MASS, FRICTION, PITCH))
    return InclineParams(float(mass), float(fric), float(theta), int(rng.integers(0, NUM_TEXTURES)),
                         float(rng.uniform(-START_EPS, START_EPS)), float(rng.uniform(*START_X)))


def rpy_quat_xyzw(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """PyBullet's quaternion (x, y, z, w) of Euler angles R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])


def quat_matrix_wxyz(q: np.ndarray) -> np.ndarray:
    w, x, y, z = (float(v) for v in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# ---------------------------------------------------------------------------------- the env
class InclineBulletEnv:
    """One Incline episode in PyBullet with bulb's frame, state and reset; no auto-reset.

    `render=False` skips `getCameraImage`. `shape` (from `object_shape`) avoids importing
    bulbjax here; without it Geom objects are built from the numbers above and YCB objects are
    loaded through `bulbjax.assets`. `inertia`: 'bullet' (what bulb simulates) or 'mirror' (the
    MJX mirror's); `bullet_damping`: keep Bullet's default base damping (bulb) or set it to 0."""

    def __init__(self, name: str, version: int = 0, resolution: int = 64, render: bool = True,
                 shape: ObjectShape | None = None, ycb_dir: str | None = None, cache_dir: str | None = None,
                 inertia: str = "bullet", bullet_damping: bool = True, seed: int | None = None):
        if not isinstance(resolution, int) or resolution < 8:
            raise ValueError(f"resolution must be an integer >= 8, got {resolution!r}")
        if inertia not in ("bullet", "mirror"):
            raise ValueError(f"inertia must be 'bullet' or 'mirror', got {inertia!r}")
        _check_version(version)
        self.spec = incline_domain(name)
        self.name, self.version = name, int(version)
        self.resolution, self.render_frames = resolution, render
        self.inertia_mode, self.bullet_damping = inertia, bullet_damping
        self.shape = shape if shape is not None else object_shape(self.spec, self.version, ycb_dir, cache_dir)
        self._rng = np.random.default_rng(seed)
        self._pb = _loader.pybullet()
        from pybullet_utils import bullet_client

        with _loader.quiet_c_stdout():
            self.client = bullet_client.BulletClient(connection_mode=self._pb.DIRECT)
        self._build()
        self.params: InclineParams | None = None
        self.step_count, self.episode_return = 0, 0.0
        self.fall_steps = 0
        self._proj = None

    @property
    def state_names(self) -> tuple[str, ...]:
        return self.spec.state_names

    # ------------------------------------------------------------------ scene
    def _build(self) -> None:
        p, pb, sh = self.client, self._pb, self.shape
        p.setGravity(0, 0, -GRAVITY)
        p.setTimeStep(BULLET_DT)
        p.setPhysicsEngineParameter(numSolverIterations=SOLVER_ITERATIONS, numSubSteps=BULLET_SUBSTEPS)
        plane_col = p.createCollisionShape(pb.GEOM_PLANE)
        plane_vis = p.createVisualShape(pb.GEOM_BOX, halfExtents=[5, 5, 0.005], visualFramePosition=[0, 0, -0.005],
                                        rgbaColor=[*GEOM_PLANE_COLOUR, 1])
        self.plane_id = p.createMultiBody(0, plane_col, plane_vis)
        inc_col = p.createCollisionShape(pb.GEOM_BOX, halfExtents=list(INCLINE_HALF))
        inc_vis = p.createVisualShape(pb.GEOM_BOX, halfExtents=list(INCLINE_HALF), rgbaColor=[*INCLINE_COLOURS[0], 1])
        self.incline_id = p.createMultiBody(0, inc_col, inc_vis, basePosition=list(INCLINE_POS))
        shift = [-c for c in sh.com]
        if sh.kind == "box":
            col = p.createCollisionShape(pb.GEOM_BOX, halfExtents=list(sh.half_extents))
            vis = p.createVisualShape(pb.GEOM_BOX, halfExtents=list(sh.half_extents), rgbaColor=list(sh.rgba))
        elif sh.kind == "cylinder":
            col = p.createCollisionShape(pb.GEOM_CYLINDER, radius=sh.radius, height=2 * sh.half_height)
            vis = p.createVisualShape(pb.GEOM_CYLINDER, radius=sh.radius, length=2 * sh.half_height,
                                      rgbaColor=list(sh.rgba))
        elif sh.kind == "mesh":
            for path in (sh.collision_path, sh.visual_path):
                if not path or not os.path.isfile(path):
                    raise FileNotFoundError(f"{self.name}: processed mesh {path!r} is missing (rebuild the YCB cache)")
            col = p.createCollisionShape(pb.GEOM_MESH, fileName=sh.collision_path, collisionFramePosition=shift)
            vis = p.createVisualShape(pb.GEOM_MESH, fileName=sh.visual_path, visualFramePosition=shift,
                                      rgbaColor=list(sh.rgba))
        else:
            raise ValueError(f"unknown object kind {sh.kind!r}")
        self.block_id = p.createMultiBody(sh.mass, col, vis, basePosition=[0.5, 0.2, 5.0])
        if sh.kind == "mesh" and sh.texture_path:
            p.changeVisualShape(self.block_id, -1, textureUniqueId=p.loadTexture(sh.texture_path))
        p.changeDynamics(self.block_id, -1, restitution=sh.restitution, rollingFriction=sh.rolling_friction)
        if not self.bullet_damping:
            p.changeDynamics(self.block_id, -1, linearDamping=0.0, angularDamping=0.0)

    def dynamics(self) -> dict[str, Any]:
        """Mass, inertia, friction, restitution and damping PyBullet simulates for the object."""
        info = self.client.getDynamicsInfo(self.block_id, -1)
        inc = self.client.getDynamicsInfo(self.incline_id, -1)
        return {"mass": info[0], "lateral_friction": info[1], "inertia": tuple(info[2]), "restitution": info[5],
                "rolling_friction": info[6], "incline_friction": inc[1],
                "contact_friction": info[1] * inc[1], "damping": BULLET_DAMPING if self.bullet_damping else 0.0}

    # ------------------------------------------------------------------ episode API
    def reset(self, seed: int | None = None, **fixed: float) -> tuple[np.ndarray, np.ndarray]:
        """bulb's reset: draw (or take from `fixed`) the episode's parameters, place the object,
        let it fall until x passes start_x -> (frame, state). `seed` reseeds the env's generator."""
        unknown = set(fixed) - set(RESET_FIELDS)
        if unknown:
            raise ValueError(f"unknown reset fields {sorted(unknown)}; known: {RESET_FIELDS}")
        if seed is not None:
            self._rng = np.random.default_rng(int(seed))
        params = draw_params(self._rng)
        params = replace(params, **{k: (int(v) if k == "texture" else float(v)) for k, v in fixed.items()}).check()
        self.place(params)
        p = self.client
        self.fall_steps = 0
        while self.fall_steps < FALL_STEPS:  # the initial fall, one stepSimulation at a time
            p.stepSimulation()
            self.fall_steps += 1
            if p.getBasePositionAndOrientation(self.block_id)[0][0] > params.start_x:
                break
        self.step_count, self.episode_return = 0, 0.0
        return self.render(), self.state()

    def place(self, params: InclineParams) -> None:
        """Apply an episode's parameters (dynamics, pitch, colours) and put the object at bulb's
        start pose, at rest (no fall)."""
        p, pb = self.client, self._pb
        self.params = params
        p.changeDynamics(self.block_id, -1, mass=params.mass, lateralFriction=params.friction)
        if self.inertia_mode == "mirror":
            ratio = params.mass / self.shape.mass
            p.changeDynamics(self.block_id, -1, localInertiaDiagonal=[i * ratio for i in self.shape.mirror_inertia])
        p.changeDynamics(self.incline_id, -1, lateralFriction=params.friction)
        p.resetBasePositionAndOrientation(self.incline_id, list(INCLINE_POS),
                                          pb.getQuaternionFromEuler([0, params.theta, 0]))
        ycb = self.spec.variant == "Ycb"
        plane = YCB_PLANE_COLOURS[params.texture] if ycb else GEOM_PLANE_COLOUR
        incline = (YCB_INCLINE_COLOURS if ycb else INCLINE_COLOURS)[params.texture]
        p.changeVisualShape(self.plane_id, -1, rgbaColor=[*plane, 1])
        p.changeVisualShape(self.incline_id, -1, rgbaColor=[*incline, 1])
        half = math.pi / 2
        quat = rpy_quat_xyzw(half, half + params.eps, half + params.eps)
        p.resetBasePositionAndOrientation(self.block_id, list(START_POS), quat.tolist())
        p.resetBaseVelocity(self.block_id, [0, 0, 0], [0, 0, 0])

    def step(self, action: Any) -> StepResult:
        """Push 2a N (a in [-1, 1], clipped) along the object's own z axis at each of bulb's 4
        stepSimulation calls."""
        if self.params is None:
            raise RuntimeError("call reset() before step()")
        a = float(np.clip(np.asarray(action, np.float64).reshape(-1)[0], -1.0, 1.0))
        self.physics(a)
        pos = self.client.getBasePositionAndOrientation(self.block_id)[0]
        reward = 1.0 - abs(pos[0] - TARGET_X)
        terminated = pos[0] >= MAX_X or pos[0] <= MIN_X or abs(pos[1]) >= MAX_Y
        self.step_count += 1
        self.episode_return += reward
        truncated = self.step_count >= self.spec.episode_length and not terminated
        info = {"episode_return": self.episode_return, "episode_length": self.step_count}
        return StepResult(self.render(), self.state(), float(reward), bool(terminated), bool(truncated), info)

    def physics(self, a: float) -> None:
        """The physics of one env step (no termination): force MAX_FORCE * a, 4 stepSimulations."""
        p = self.client
        for _ in range(STEPS_PER_ACTION):
            p.applyExternalForce(self.block_id, -1, [0, 0, MAX_FORCE * a], [0, 0, 0], self._pb.LINK_FRAME)
            p.stepSimulation()

    # ------------------------------------------------------------------ state
    def pose_velocity(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(position, quaternion w-x-y-z, linear velocity (world), angular velocity (object frame,
        as MuJoCo's free joint)) of the object's centre of mass."""
        p = self.client
        pos, q = p.getBasePositionAndOrientation(self.block_id)
        lin, ang = p.getBaseVelocity(self.block_id)
        quat = np.array([q[3], q[0], q[1], q[2]])
        return np.array(pos), quat, np.array(lin), quat_matrix_wxyz(quat).T @ np.array(ang)

    def set_pose_velocity(self, pos: Any, quat_wxyz: Any, lin: Any, ang_body: Any) -> None:
        """Put the object in a physical state (layout of `pose_velocity`)."""
        q = np.asarray(quat_wxyz, np.float64)
        q = q / np.linalg.norm(q)
        ang_world = quat_matrix_wxyz(q) @ np.asarray(ang_body, np.float64)
        self.client.resetBasePositionAndOrientation(self.block_id, np.asarray(pos, np.float64).tolist(),
                                                    [q[1], q[2], q[3], q[0]])
        self.client.resetBaseVelocity(self.block_id, np.asarray(lin, np.float64).tolist(), ang_world.tolist())

    def raw_state(self) -> np.ndarray:
        """[20] float64 in the MJX mirror's `lowdim_raw` layout (`RAW_NAMES`)."""
        pos, quat, lin, ang = self.pose_velocity()
        dist = 0.0 if pos[0] < MIN_X else float(np.linalg.norm(pos - np.asarray(START_POS)))
        pr = self.params
        static = [pr.texture, self.version, pr.mass, pr.friction, pr.theta, dist, float(np.linalg.norm(lin))]
        return np.concatenate([pos, quat, lin, ang, np.asarray(static, np.float64)])

    def state(self) -> np.ndarray:
        """bulb's low-dim state, each entry scaled to [0, 1] by bulb's range (float32)."""
        raw = self.raw_state()
        pr = self.params
        vals, lo, hi = [pr.texture, self.version], [0.0, 0.0], [float(NUM_TEXTURES), float(NUM_VERSIONS)]
        if self.spec.report_friction:
            vals, lo, hi = vals + [pr.friction], lo + [FRICTION[0]], hi + [FRICTION[1]]
        vals += [pr.theta, raw[18], raw[19]]
        lo, hi = np.array(lo + [PITCH[0], MIN_X, 0.0]), np.array(hi + [PITCH[1], CLIP_DIST, CLIP_SPEED])
        return ((np.clip(np.array(vals, np.float64), lo, hi) - lo) / (hi - lo)).astype(np.float32)

    # ------------------------------------------------------------------ frames
    def render(self) -> np.ndarray:
        """bulb's frame, [H, W, 3] uint8 ([0, 0, 3] when rendering is off)."""
        if not self.render_frames:
            return np.zeros((0, 0, 3), np.uint8)
        return self._camera_image()[0]

    def object_mask(self) -> np.ndarray:
        """[H, W] bool: pixels showing the object (PyBullet's segmentation)."""
        seg = self._camera_image()[1]
        return (seg >= 0) & ((seg & ((1 << 24) - 1)) == self.block_id)

    def _camera_image(self) -> tuple[np.ndarray, np.ndarray]:
        p, res = self.client, self.resolution
        view = p.computeViewMatrixFromYawPitchRoll(cameraTargetPosition=list(CAMERA["target"]),
                                                   distance=CAMERA["distance"], yaw=CAMERA["yaw"],
                                                   pitch=CAMERA["pitch"], roll=0, upAxisIndex=2)
        if self._proj is None:
            self._proj = p.computeProjectionMatrixFOV(fov=CAMERA["fov"], aspect=1.0, nearVal=CAMERA["near"],
                                                      farVal=CAMERA["far"])
        _, _, px, _, seg = p.getCameraImage(width=res, height=res, viewMatrix=view, projectionMatrix=self._proj,
                                            renderer=self._pb.ER_TINY_RENDERER)
        frame = np.asarray(px, np.uint8).reshape(res, res, 4)[:, :, :3].copy()
        return frame, np.asarray(seg, np.int64).reshape(res, res)

    def project(self, point: Any) -> tuple[float, float]:
        """Pixel (column, row) of a world point in bulb's camera."""
        p = self.client
        view = np.array(p.computeViewMatrixFromYawPitchRoll(
            cameraTargetPosition=list(CAMERA["target"]), distance=CAMERA["distance"], yaw=CAMERA["yaw"],
            pitch=CAMERA["pitch"], roll=0, upAxisIndex=2)).reshape(4, 4).T
        proj = np.array(p.computeProjectionMatrixFOV(fov=CAMERA["fov"], aspect=1.0, nearVal=CAMERA["near"],
                                                     farVal=CAMERA["far"])).reshape(4, 4).T
        clip = proj @ view @ np.append(np.asarray(point, np.float64), 1.0)
        ndc = clip[:3] / clip[3]
        return (ndc[0] + 1) / 2 * self.resolution, (1 - ndc[1]) / 2 * self.resolution

    def close(self) -> None:
        try:
            self.client.disconnect()
        except Exception:  # already disconnected
            pass

    # pybullet_compat vector API (get/set of the physical state as flat arrays)
    def get_qpos_qvel(self) -> tuple[np.ndarray, np.ndarray]:
        """The object's free-joint (qpos [7], qvel [6]) in MuJoCo's layout."""
        pos, quat, lin, ang = self.pose_velocity()
        return np.concatenate([pos, quat]), np.concatenate([lin, ang])

    def set_qpos_qvel(self, qpos: Any, qvel: Any) -> tuple[np.ndarray, np.ndarray]:
        """Put the object at the free-joint state (qpos, qvel); a new episode from there."""
        if self.params is None:
            self.reset()
        qpos, qvel = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)
        self.set_pose_velocity(qpos[:3], qpos[3:7], qvel[:3], qvel[3:6])
        self.step_count, self.episode_return = 0, 0.0
        return self.render(), self.state()
