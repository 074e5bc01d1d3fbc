"""PyBullet originals of bulb's Rearrange domains (ReacherRearrange*, FrankaRearrange* in the Geom,
OneGeom, Ycb and OneYcb variants), built here from the facts of bulb's `RearrangeEnv`
(`../shared/reference/bulb-multiobject.md`) with the numbers bulbjax's MJX mirror uses
(`bulbjax.envs.objects.rearrange`; copied in `pybullet_compat.rearrange_scene` so that worker processes
never import JAX, and tested equal). bulb has no licence: every line is ours, only its numbers and behaviour are taken.

The scene:
- `plane.urdf` from pybullet_data at z = 0 (drawn black for the Reacher; its checker for the
  Franka); the tray as the mirror has it (bulb's `borders.urdf` at scale 0.8): four fixed border
  boxes 0.84 x 0.04 x 0.08 m around a drawn-only 0.8 x 0.8 m bottom, all in the version's table
  colour (the texture's mean colour; versions 6-11 black); borders with restitution 1.
- the version's objects (list `version % 6`): Geom shapes as bulb's (sphere r 0.04 0.1 kg, sphere1
  r 0.06 0.3 kg, cylinder r 0.06 h 0.12 0.2 kg, cube = bulb's block 0.05 x 0.10 x 0.15 m 0.05 kg)
  in the version's colours, spheres with restitution 1 and rolling/spinning friction 0.001; YCB
  objects from the SAME processed files the mirror loads (`bulbjax.assets.load_ycb_object` at
  scale 1: the <=200-face convex hull collides, the decimated textured mesh is drawn, the body
  frame at the mesh's centre of mass). Prepare them in the parent with `rearrange_objects` and
  pass `objects=` to workers; otherwise the env prepares them (importing bulbjax.assets).
- Reacher: bulbjax's `mjcf_assets/reacher_rearrange.xml` through `loadMJCF` (as
  `pybullet_compat.rearrange.ReacherBullet`), its base made static (`loadMJCF` leaves the root
  body free: a 0.06 kg base that the arm's reaction torques throw around), the elbow drawn orange.
  Franka: `pybullet_data`'s `franka_panda/panda.urdf`, fixed base at (-0.7, 0, 0), link
  inertias Bullet's default (recomputed from the collision meshes; the URDF's are 0.1 kg m^2
  placeholders, which the MJX mirror uses: `inertia_from_file=True` takes those),
  self-collision on (all ancestors excluded; the two fixed fingers not against each other), the
  fingers held closed by position motors (bulb gives them no torque).
- Bullet settings of bulb: gravity -9.81, time step 0.01 s, 2 substeps, 5 solver iterations; the
  arm's motors disabled (torque control). One env step = one `stepSimulation`.
- action a in [-1, 1] per controlled joint (bulbjax's convention; bulb's [0, 1] action is
  (a + 1) / 2): Reacher torque = clip(a) * 3 N m, then bulb's limit handling (a joint past (31/32,
  26/32) pi put on the limit with its velocity reversed); Franka torque = clip(a) * effort plus
  gravity compensation (`calculateInverseDynamics` at zero acceleration), clipped to the URDF's
  efforts (87 x 4, 12 x 3 N m), then a joint outside its range put on the bound at rest. bulb's
  Franka does not step at all when the commanded torque is all zeros (`skip_zero_torque`, on).
- reset: the robot at a random pose (Reacher: U(+-0.75 pi) per joint; Franka: bulb's random
  end-effector target -- x, y in [-0.5, 0.5], z in [0.05, 0.35], roll pushed to |roll| >= pi/2,
  pitch and yaw clipped to +-pi/2 -- solved by PyBullet's IK from the rest pose, drawn again
  while a link other than the base touches the floor, at most `IK_TRIES` times); each object at
  x, y ~ U[-0.15, 0.15], z ~ U[0.03 (Ycb) or 0.04 (Geom), 0.075], orientation a uniform 4-vector
  in [0, 1]^4 normalised as PyBullet's (x, y, z, w); 20 free `stepSimulation`s (no torque); then
  10 steps of random torques a ~ U[-0.5, 0.5] through the robot's control. `reset(seed, **fixed)`
  sets any of robot_qpos / obj_pos / obj_quat (w, x, y, z) / torques explicitly, as the mirror's
  `reset_with`. A seed repeats an episode exactly only in a fresh env: Bullet's contact caches
  outlive `resetBasePositionAndOrientation` (and `restoreState`), so a used env drifts by ~1e-4.
- done when an object leaves [-0.45, 0.45]^2 x [-0.05, 0.20], the end effector (the COM of the
  hand link, `getLinkState`) is more than 0.2 m above the tallest object or outside |x|, |y| <=
  0.5; reward (1 - mean over objects of min(1, xy distance to its target)) / 200; 200 steps.
- state (float32, in [-1, 1], the mirror's layout and length): sin, cos per robot joint (the
  Franka's fingers included), 12 normalised properties per object, x, y, z per object (clipped to
  the box), the rotation matrix per object (row-major; `rotation="bulb"` gives bulb's matrix of
  the permuted quaternion instead). `raw_state()`: the mirror's `info["lowdim_raw"]` layout.
- frames: 64 x 64 RGB from `getCameraImage` (ER_TINY_RENDERER); Reacher camera distance 0.40,
  yaw 90, pitch -89, target (0, 0, 0); Franka distance 0.44, yaw 90, pitch -65, target
  (0.05, 0, 0); vertical FOV 90, near 0.01, far 100.

Differences from the MJX mirror (measured: `python -m pybullet_compat.parity_rearrange`,
docs/parity/README.md, Rearrange): where objects settle agrees (mean heights within 3 mm, the
same shares on their side), but the arms move more here during the reset -- the reacher has
`loadMJCF`'s density-1000 masses and no damping or armature, the Panda Bullet's recomputed link
inertias (the mirror: the URDF's 0.1 kg m^2 placeholders) and no gravity compensation during the
free settle (the mirror holds it) -- so objects start episodes faster here. The mirror leaves out
restitution and rolling friction and caps object speeds during its reset; objects' body frames
are their centres of mass on both sides.

    env = RearrangeBulletEnv("FrankaRearrangeGeom", version=2)
    frame, state = env.reset(seed=0)
    r = env.step(np.zeros(7))
"""

from __future__ import annotations

import os
from typing import Any, Sequence

import numpy as np

from pybullet_compat import _loader
from pybullet_compat.envs import StepResult
from pybullet_compat.incline import quat_matrix_wxyz
from pybullet_compat.rearrange_scene import (  # the scene's numbers, domains and objects
    NUM_LISTS, EPISODE_STEPS, BULLET_DT, BULLET_SUBSTEPS, SOLVER_ITERATIONS, GRAVITY, SETTLE_STEPS,
    RANDOM_TORQUE_STEPS, OBJ_XYZ_MIN, OBJ_XYZ_MAX, EE_XY_MAX, EE_ABOVE_OBJECTS, INIT_XY, INIT_Z_MAX,
    TRAY_SCALE, OBJECT_LISTS, PROP_MIN, PROP_MAX, BORDER_RESTITUTION,
    REACHER_LIMITS, REACHER_TORQUE, REACHER_INIT, FRANKA_BASE, FRANKA_REST, FRANKA_EFFORTS, IK_TRIES,
    IK_ITERATIONS, FINGER_HOLD_FORCE, REACHER_CAMERA, FRANKA_CAMERA, FOV, NEAR, FAR, REACHER_ELBOW_RGBA,
    RESET_FIELDS, raw_names, rearrange_domain,
    load_reacher, check_version, RearrangeObject, rearrange_objects, normalise, table_rgb, ee_target)


# ---------------------------------------------------------------------------------- the env
class RearrangeBulletEnv:
    """One Rearrange episode in PyBullet with bulb's scene, reset, reward, frame and state; no
    auto-reset. `objects` (from `rearrange_objects`) avoids importing bulbjax here.
    `render=False` skips `getCameraImage`; `rotation` 'true' (bulbjax's state) or 'bulb'
    (bulb's matrix of the permuted quaternion); `skip_zero_torque`: bulb's Franka does not step
    when the commanded torque is all zeros; `inertia_from_file`: the Panda's link inertias from
    panda.urdf (0.1 kg m^2 placeholders, as the MJX mirror has them) instead of Bullet's default,
    which recomputes them from the collision meshes (5-200x smaller)."""

    def __init__(self, name: str, version: int = 0, resolution: int = 64, render: bool = True,
                 ycb_dir: str | None = None, cache_dir: str | None = None,
                 objects: Sequence[RearrangeObject] | None = None, rotation: str = "true",
                 skip_zero_torque: bool = True, inertia_from_file: bool = False, seed: int | None = None):
        if not isinstance(resolution, int) or resolution < 8:
            raise ValueError(f"resolution must be an integer >= 8, got {resolution!r}")
        if rotation not in ("true", "bulb"):
            raise ValueError(f"rotation must be 'true' or 'bulb', got {rotation!r}")
        self.spec = rearrange_domain(name)
        self.name, self.version = name, check_version(version)
        self.resolution, self.render_frames = resolution, render
        self.rotation, self.skip_zero_torque = rotation, skip_zero_torque
        self.inertia_from_file = inertia_from_file
        self.objects = tuple(objects) if objects is not None else rearrange_objects(name, self.version, ycb_dir, cache_dir)
        expected = OBJECT_LISTS[self.spec.variant][self.version % NUM_LISTS]
        if tuple(o.name for o in self.objects) != expected:
            raise ValueError(f"{name} v{self.version} needs objects {expected}, got {tuple(o.name for o in self.objects)}")
        self.franka = self.spec.robot == "Franka"
        self.camera = FRANKA_CAMERA if self.franka else REACHER_CAMERA
        self._rng = np.random.default_rng(seed)
        self._pb = _loader.pybullet()
        from pybullet_utils import bullet_client

        with _loader.quiet_c_stdout():
            self.client = bullet_client.BulletClient(connection_mode=self._pb.DIRECT)
        self._build()
        lo, hi = PROP_MIN, PROP_MAX
        self._props = np.concatenate([normalise(np.asarray(o.props, np.float64), lo, hi) for o in self.objects])
        self._targets = np.array([o.target for o in self.objects])
        self.max_object_z = max(2 * o.half_z for o in self.objects)
        self.step_count, self.episode_return, self._started = 0, 0.0, False
        self.ik_tries = 0
        self.last_draws: dict[str, np.ndarray] = {}
        self._view = self._proj = None

    @property
    def state_names(self) -> tuple[str, ...]:
        return self.spec.state_names

    @property
    def raw_names(self) -> tuple[str, ...]:
        return raw_names(self.spec.action_size, self.spec.num_objects)

    # ------------------------------------------------------------------ scene
    def _build(self) -> None:
        import pybullet_data

        p = self.client
        p.setAdditionalSearchPath(pybullet_data.getDataPath())
        p.setGravity(0, 0, -GRAVITY)
        p.setTimeStep(BULLET_DT)
        # deterministicOverlappingPairs: Bullet otherwise orders contact pairs by memory address, so
        # the same seed gave different resets in every other env created in a process
        p.setPhysicsEngineParameter(numSolverIterations=SOLVER_ITERATIONS, numSubSteps=BULLET_SUBSTEPS,
                                    deterministicOverlappingPairs=1)
        self.plane_id = p.loadURDF("plane.urdf", [0, 0, 0])
        if not self.franka:
            p.changeVisualShape(self.plane_id, -1, rgbaColor=[0, 0, 0, 1])
        self._build_tray()
        self._build_robot()
        self.object_ids = [self._build_object(o, k) for k, o in enumerate(self.objects)]

    def _build_tray(self) -> None:
        """The mirror's tray: a drawn-only bottom whose top is 0.5 mm above the floor, four borders."""
        p, pb, s = self.client, self._pb, TRAY_SCALE
        rgba = [*table_rgb(self.version), 1.0]
        vis = p.createVisualShape(pb.GEOM_BOX, halfExtents=[0.5 * s, 0.5 * s, 0.002], rgbaColor=rgba)
        self.tray_ids = [p.createMultiBody(0, -1, vis, basePosition=[0, 0, -0.0015])]
        long, thick, height = 1.05 * s / 2, 0.05 * s / 2, 0.10 * s / 2
        for pos, half in (((0.5 * s, 0, height), (thick, long, height)), ((-0.5 * s, 0, height), (thick, long, height)),
                          ((0, 0.5 * s, height), (long, thick, height)), ((0, -0.5 * s, height), (long, thick, height))):
            col = p.createCollisionShape(pb.GEOM_BOX, halfExtents=list(half))
            vis = p.createVisualShape(pb.GEOM_BOX, halfExtents=list(half), rgbaColor=rgba)
            body = p.createMultiBody(0, col, vis, basePosition=list(pos))
            p.changeDynamics(body, -1, restitution=BORDER_RESTITUTION)
            self.tray_ids.append(body)

    def _build_robot(self) -> None:
        p, pb = self.client, self._pb
        if self.franka:
            flags = pb.URDF_USE_SELF_COLLISION | pb.URDF_USE_SELF_COLLISION_EXCLUDE_ALL_PARENTS
            if self.inertia_from_file:
                flags |= pb.URDF_USE_INERTIA_FROM_FILE
            self.robot_id = p.loadURDF("franka_panda/panda.urdf", list(FRANKA_BASE), useFixedBase=True, flags=flags)
            names = {p.getJointInfo(self.robot_id, j)[1].decode(): j for j in range(p.getNumJoints(self.robot_id))}
            self.joints = [names[f"panda_joint{i}"] for i in range(1, 8)]
            self.fingers = [names["panda_finger_joint1"], names["panda_finger_joint2"]]
            links = {p.getJointInfo(self.robot_id, j)[12].decode(): j for j in range(p.getNumJoints(self.robot_id))}
            self.ee_link = links["panda_hand"]
            info = [p.getJointInfo(self.robot_id, j) for j in self.joints]
            self.joint_lo = np.array([i[8] for i in info])
            self.joint_hi = np.array([i[9] for i in info])
            efforts = np.array([i[10] for i in info])
            if not np.allclose(efforts, FRANKA_EFFORTS):
                raise ValueError(f"pybullet_data's Panda efforts {efforts} differ from bulb's {FRANKA_EFFORTS}")
            self.max_torque = np.asarray(FRANKA_EFFORTS)
            p.setCollisionFilterPair(self.robot_id, self.robot_id, self.fingers[0], self.fingers[1], 0)
            self.dofs = self.joints + self.fingers  # every movable joint, for IK and inverse dynamics
            finger_info = [p.getJointInfo(self.robot_id, j) for j in self.fingers]
            self._ik_lo = list(self.joint_lo) + [i[8] for i in finger_info]
            self._ik_hi = list(self.joint_hi) + [i[9] for i in finger_info]
            p.setJointMotorControlArray(self.robot_id, self.fingers, pb.POSITION_CONTROL, targetPositions=[0.0, 0.0],
                                        forces=[FINGER_HOLD_FORCE] * 2)
        else:
            self.robot_id = load_reacher(p)  # loadMJCF leaves the base free: welded there
            names = {p.getJointInfo(self.robot_id, j)[1].decode(): j for j in range(p.getNumJoints(self.robot_id))}
            links = {p.getJointInfo(self.robot_id, j)[12].decode(): j for j in range(p.getNumJoints(self.robot_id))}
            self.joints = [names["joint0"], names["joint1"]]
            self.fingers = []
            self.dofs = list(self.joints)
            self.ee_link = links["hand_link"]
            self.max_torque = np.asarray(REACHER_TORQUE)
            p.changeVisualShape(self.robot_id, links["elbow_link"], rgbaColor=list(REACHER_ELBOW_RGBA))
        p.setJointMotorControlArray(self.robot_id, self.joints, pb.VELOCITY_CONTROL, forces=[0.0] * len(self.joints))

    def _build_object(self, o: RearrangeObject, k: int) -> int:
        p, pb = self.client, self._pb
        rgba = list(o.rgba)
        if o.kind == "sphere":
            col = p.createCollisionShape(pb.GEOM_SPHERE, radius=o.radius)
            vis = p.createVisualShape(pb.GEOM_SPHERE, radius=o.radius, rgbaColor=rgba)
        elif o.kind == "cylinder":
            col = p.createCollisionShape(pb.GEOM_CYLINDER, radius=o.radius, height=2 * o.half_height)
            vis = p.createVisualShape(pb.GEOM_CYLINDER, radius=o.radius, length=2 * o.half_height, rgbaColor=rgba)
        elif o.kind == "box":
            col = p.createCollisionShape(pb.GEOM_BOX, halfExtents=list(o.half_extents))
            vis = p.createVisualShape(pb.GEOM_BOX, halfExtents=list(o.half_extents), rgbaColor=rgba)
        elif o.kind == "mesh":
            for path in (o.collision_path, o.visual_path):
                if not path or not os.path.isfile(path):
                    raise FileNotFoundError(f"{self.name}: processed mesh {path!r} of {o.name} is missing "
                                            f"(rebuild the YCB cache: bulbjax.assets.load_ycb_object)")
            shift = [-c for c in o.com]
            col = p.createCollisionShape(pb.GEOM_MESH, fileName=o.collision_path, collisionFramePosition=shift)
            vis = p.createVisualShape(pb.GEOM_MESH, fileName=o.visual_path, visualFramePosition=shift, rgbaColor=rgba)
        else:
            raise ValueError(f"unknown object kind {o.kind!r}")
        body = p.createMultiBody(o.mass, col, vis, basePosition=[2.0 + k, 3.0, 0.5])
        if o.kind == "mesh" and o.texture_path:
            p.changeVisualShape(body, -1, textureUniqueId=p.loadTexture(o.texture_path))
        p.changeDynamics(body, -1, restitution=o.restitution, lateralFriction=o.lateral_friction,
                         rollingFriction=o.rolling_friction, spinningFriction=o.spinning_friction)
        return body

    def dynamics(self) -> list[dict[str, Any]]:
        """Mass, inertia, friction and restitution PyBullet simulates for each object."""
        out = []
        for o, b in zip(self.objects, self.object_ids):
            d = self.client.getDynamicsInfo(b, -1)
            out.append({"name": o.name, "mass": d[0], "lateral_friction": d[1], "inertia": tuple(d[2]),
                        "restitution": d[5], "rolling_friction": d[6], "spinning_friction": d[7]})
        return out

    # ------------------------------------------------------------------ robot
    def joint_states(self) -> tuple[np.ndarray, np.ndarray]:
        """Angles and speeds of every movable robot joint (controlled ones, then the fingers)."""
        s = self.client.getJointStates(self.robot_id, self.dofs)
        return np.array([x[0] for x in s]), np.array([x[1] for x in s])

    def set_robot(self, q: Sequence[float], qd: Sequence[float] | None = None) -> None:
        """Put the controlled joints at `q` (speeds `qd`, default 0); the fingers closed, at rest."""
        qd = np.zeros(len(self.joints)) if qd is None else np.asarray(qd, np.float64)
        for j, a, v in zip(self.joints, np.asarray(q, np.float64), qd):
            self.client.resetJointState(self.robot_id, j, targetValue=float(a), targetVelocity=float(v))
        for j in self.fingers:
            self.client.resetJointState(self.robot_id, j, targetValue=0.0, targetVelocity=0.0)

    def _draw_robot_qpos(self) -> np.ndarray:
        if not self.franka:
            return self._rng.uniform(-REACHER_INIT, REACHER_INIT, 2)
        return self._franka_pose()

    def _franka_pose(self) -> np.ndarray:
        """bulb's random end-effector target solved by PyBullet's IK from the rest pose, drawn
        again while a link other than the base touches the floor (at most IK_TRIES)."""
        p = self.client
        rest = list(FRANKA_REST) + [0.0, 0.0]
        ranges = [h - lo for lo, h in zip(self._ik_lo, self._ik_hi)]
        for self.ik_tries in range(1, IK_TRIES + 1):
            self.set_robot(FRANKA_REST)
            pos, rpy = ee_target(self._rng)
            q = p.calculateInverseKinematics(self.robot_id, self.ee_link, pos.tolist(),
                                             p.getQuaternionFromEuler(rpy.tolist()), lowerLimits=self._ik_lo,
                                             upperLimits=self._ik_hi, jointRanges=ranges, restPoses=rest,
                                             maxNumIterations=IK_ITERATIONS)
            q = np.clip(np.asarray(q[:len(self.joints)]), self.joint_lo, self.joint_hi)
            self.set_robot(q)
            touching = [c for c in p.getClosestPoints(self.robot_id, self.plane_id, 0.0) if c[3] >= 0]
            if not touching:
                break
        return q

    def _control(self, action: Any) -> None:
        """One env step of the robot: bulb's torque, one stepSimulation, bulb's limit handling."""
        a = np.clip(np.asarray(action, np.float64).reshape(-1), -1.0, 1.0)
        if a.shape != (len(self.joints),):
            raise ValueError(f"{self.name} takes {len(self.joints)} actions in [-1, 1], got shape {np.shape(action)}")
        torque = a * self.max_torque
        p, pb = self.client, self._pb
        if self.franka:
            if self.skip_zero_torque and np.allclose(torque, 0.0):
                return  # bulb's Franka returns before stepSimulation
            q, qd = self.joint_states()
            grav = np.asarray(p.calculateInverseDynamics(self.robot_id, q.tolist(), qd.tolist(), [0.0] * len(q)))
            torque = np.clip(torque + grav[:len(self.joints)], -self.max_torque, self.max_torque)
        p.setJointMotorControlArray(self.robot_id, self.joints, pb.TORQUE_CONTROL, forces=torque.tolist())
        p.stepSimulation()
        self._obey_limits()

    def _obey_limits(self) -> None:
        """Reacher: a joint past (31/32, 26/32) pi back on the limit, velocity reversed. Franka: a
        joint outside the URDF's range back on the bound, at rest."""
        s = self.client.getJointStates(self.robot_id, self.joints)
        for i, (j, (q, v)) in enumerate(zip(self.joints, ((x[0], x[1]) for x in s))):
            if self.franka:
                if q < self.joint_lo[i] or q > self.joint_hi[i]:
                    self.client.resetJointState(self.robot_id, j, float(np.clip(q, self.joint_lo[i], self.joint_hi[i])), 0.0)
            elif abs(q) > REACHER_LIMITS[i]:
                self.client.resetJointState(self.robot_id, j, float(REACHER_LIMITS[i] * np.sign(q)), float(-v))

    # ------------------------------------------------------------------ episode API
    def reset(self, seed: int | None = None, **fixed: Any) -> tuple[np.ndarray, np.ndarray]:
        """bulb's reset -> (frame, state): robot pose, objects dropped, 20 free steps, 10 steps of
        random torques. `fixed` sets draws: robot_qpos [A], obj_pos [M, 3], obj_quat [M, 4]
        (w, x, y, z, before the settle), torques [10, A] (actions in [-1, 1]). The episode's
        draws are kept in `last_draws` (the same fields, for the mirror's `reset_with`)."""
        unknown = set(fixed) - set(RESET_FIELDS)
        if unknown:
            raise ValueError(f"unknown reset fields {sorted(unknown)}; known: {RESET_FIELDS}")
        if seed is not None:
            self._rng = np.random.default_rng(int(seed))
        m, n = len(self.objects), len(self.joints)
        if "robot_qpos" in fixed:
            q = np.broadcast_to(np.asarray(fixed["robot_qpos"], np.float64), (n,))
        else:
            q = self._draw_robot_qpos()
        z_min = 0.03 if "Ycb" in self.spec.variant else 0.04
        pos = self._rng.uniform([-INIT_XY, -INIT_XY, z_min], [INIT_XY, INIT_XY, INIT_Z_MAX], (m, 3))
        xyzw = self._rng.uniform(0.0, 1.0, (m, 4))
        xyzw /= np.linalg.norm(xyzw, axis=1, keepdims=True)
        torques = self._rng.uniform(-0.5, 0.5, (RANDOM_TORQUE_STEPS, n))
        if "obj_pos" in fixed:
            pos = np.broadcast_to(np.asarray(fixed["obj_pos"], np.float64), (m, 3))
        if "obj_quat" in fixed:
            wxyz = np.broadcast_to(np.asarray(fixed["obj_quat"], np.float64), (m, 4))
            xyzw = wxyz[:, [1, 2, 3, 0]] / np.linalg.norm(wxyz, axis=1, keepdims=True)
        if "torques" in fixed:
            torques = np.broadcast_to(np.asarray(fixed["torques"], np.float64), (RANDOM_TORQUE_STEPS, n))
        self.last_draws = {"robot_qpos": np.array(q, np.float64), "obj_pos": np.array(pos),
                           "obj_quat": np.array(xyzw[:, [3, 0, 1, 2]]), "torques": np.array(torques)}
        p = self.client
        self.set_robot(q)
        for b, xyz, quat in zip(self.object_ids, pos, xyzw):
            p.resetBasePositionAndOrientation(b, xyz.tolist(), quat.tolist())
            p.resetBaseVelocity(b, [0, 0, 0], [0, 0, 0])
        for _ in range(SETTLE_STEPS):  # let the objects emerge from each other, no torque
            p.stepSimulation()
        for a in torques:
            self._control(a)
        self.step_count, self.episode_return, self._started = 0, 0.0, True
        return self.render(), self.state()

    def step(self, action: Any) -> StepResult:
        """One env step: torques from `action` [A] in [-1, 1], one stepSimulation; reward and
        bulb's termination; truncated after 200 steps."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        self._control(action)
        reward, terminated = self.reward_terminated()
        self.step_count += 1
        self.episode_return += reward
        truncated = self.step_count >= self.spec.episode_length and not terminated
        info = {"episode_return": self.episode_return, "episode_length": self.step_count}
        return StepResult(self.render(), self.state(), float(reward), bool(terminated), bool(truncated), info)

    def reward_terminated(self) -> tuple[float, bool]:
        pos = self.object_poses()[0]
        ee = self.ee_position()
        if not (np.isfinite(pos).all() and np.isfinite(ee).all()):
            return 0.0, True
        dist = np.minimum(np.linalg.norm(pos[:, :2] - self._targets, axis=1), 1.0)
        reward = (1.0 - dist.mean()) / EPISODE_STEPS
        outside = bool(((pos < OBJ_XYZ_MIN) | (pos > OBJ_XYZ_MAX)).any())
        too_high = ee[2] > EE_ABOVE_OBJECTS + self.max_object_z
        away = bool((np.abs(ee[:2]) > EE_XY_MAX).any())
        return float(reward), bool(outside or too_high or away)

    # ------------------------------------------------------------------ state
    def ee_position(self) -> np.ndarray:
        """The end effector: the hand link's centre of mass (`getLinkState`)."""
        return np.array(self.client.getLinkState(self.robot_id, self.ee_link)[0])

    def object_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Objects' positions [M, 3] (centres of mass) and quaternions [M, 4] (w, x, y, z)."""
        poses = [self.client.getBasePositionAndOrientation(b) for b in self.object_ids]
        pos = np.array([x[0] for x in poses])
        quat = np.array([[x[1][3], x[1][0], x[1][1], x[1][2]] for x in poses])
        return pos, quat

    def object_velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """Linear (world) [M, 3] and angular (body frame, as MuJoCo's free joint) [M, 3] velocities."""
        vel = [self.client.getBaseVelocity(b) for b in self.object_ids]
        quat = self.object_poses()[1]
        lin = np.array([v[0] for v in vel])
        ang = np.array([quat_matrix_wxyz(q).T @ np.array(v[1]) for q, v in zip(quat, vel)])
        return lin, ang

    def state(self) -> np.ndarray:
        """bulb's low-dim state in [-1, 1] (float32), bulbjax's layout (`state_names`)."""
        q, _ = self.joint_states()
        sincos = np.stack([np.sin(q), np.cos(q)], axis=1).reshape(-1)
        pos, quat = self.object_poses()
        pos = normalise(np.clip(pos, OBJ_XYZ_MIN, OBJ_XYZ_MAX), OBJ_XYZ_MIN, OBJ_XYZ_MAX)
        if self.rotation == "bulb":  # bulb's quat2mat reads PyBullet's (x, y, z, w) as (w, x, y, z)
            quat = quat[:, [1, 2, 3, 0]]
        rot = np.stack([quat_matrix_wxyz(qq / np.linalg.norm(qq)) for qq in quat]).reshape(-1)
        return np.concatenate([sincos, self._props, pos.reshape(-1), rot]).astype(np.float32)

    def raw_state(self) -> np.ndarray:
        """float64 in the MJX mirror's `info["lowdim_raw"]` layout (`raw_names`): controlled joint
        angles and speeds, per object position, quaternion (w, x, y, z), linear and body angular
        velocity, then the end effector's position."""
        q, qd = self.joint_states()
        n = len(self.joints)
        pos, quat = self.object_poses()
        lin, ang = self.object_velocities()
        per_obj = np.concatenate([pos, quat, lin, ang], axis=1).reshape(-1)
        return np.concatenate([q[:n], qd[:n], per_obj, self.ee_position()])

    def get_qpos_qvel(self) -> tuple[np.ndarray, np.ndarray]:
        """(qpos, qvel): controlled joint angles then per object position + quaternion (w, x, y, z);
        joint speeds then per object linear + body angular velocity (bulb's object order)."""
        q, qd = self.joint_states()
        n = len(self.joints)
        pos, quat = self.object_poses()
        lin, ang = self.object_velocities()
        return (np.concatenate([q[:n], np.concatenate([pos, quat], 1).reshape(-1)]),
                np.concatenate([qd[:n], np.concatenate([lin, ang], 1).reshape(-1)]))

    def set_qpos_qvel(self, qpos: Any, qvel: Any) -> tuple[np.ndarray, np.ndarray]:
        """Put robot and objects in the state (qpos, qvel) of `get_qpos_qvel`; a new episode from there."""
        n, m = len(self.joints), len(self.objects)
        qpos, qvel = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)
        if qpos.shape != (n + 7 * m,) or qvel.shape != (n + 6 * m,):
            raise ValueError(f"{self.name}: qpos must be [{n + 7 * m}] and qvel [{n + 6 * m}], got "
                             f"{qpos.shape} and {qvel.shape}")
        self.set_robot(qpos[:n], qvel[:n])
        for k, b in enumerate(self.object_ids):
            qp, qv = qpos[n + 7 * k:n + 7 * k + 7], qvel[n + 6 * k:n + 6 * k + 6]
            wxyz = qp[3:] / np.linalg.norm(qp[3:])
            self.client.resetBasePositionAndOrientation(b, qp[:3].tolist(), wxyz[[1, 2, 3, 0]].tolist())
            self.client.resetBaseVelocity(b, qv[:3].tolist(), (quat_matrix_wxyz(wxyz) @ qv[3:]).tolist())
        self.step_count, self.episode_return, self._started = 0, 0.0, True
        return self.render(), self.state()

    # ------------------------------------------------------------------ frames
    def render(self) -> np.ndarray:
        """bulb's frame, [H, W, 3] uint8 ([0, 0, 3] when rendering is off)."""
        if not self.render_frames:
            return np.zeros((0, 0, 3), np.uint8)
        p, res, cam = self.client, self.resolution, self.camera
        if self._view is None:
            self._view = p.computeViewMatrixFromYawPitchRoll(cameraTargetPosition=list(cam["target"]),
                                                             distance=cam["distance"], yaw=cam["yaw"],
                                                             pitch=cam["pitch"], roll=0, upAxisIndex=2)
            self._proj = p.computeProjectionMatrixFOV(fov=FOV, aspect=1.0, nearVal=NEAR, farVal=FAR)
        px = p.getCameraImage(width=res, height=res, viewMatrix=self._view, projectionMatrix=self._proj,
                              renderer=self._pb.ER_TINY_RENDERER)[2]
        return np.asarray(px, np.uint8).reshape(res, res, 4)[:, :, :3].copy()

    def close(self) -> None:
        try:
            self.client.disconnect()
        except Exception:  # already disconnected
            pass
