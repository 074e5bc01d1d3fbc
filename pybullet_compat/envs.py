"""The original PyBullet domains (pybullet_envs 3.2.7) reporting a frame and the true state.

Like bulb's `AuxBulletEnv`: every reset/step returns the 64x64 RGB frame from `getCameraImage`
with bulb's camera (the env's own `_cam_dist`/`_cam_yaw`/`_cam_pitch`, target = the robot's
base, so it follows walking robots; vertical FOV 60, aspect 1, near 0.1, far 100; the CPU
`ER_TINY_RENDERER`, no GUI) as H x W x 3 uint8, beside the low-dimensional state with the names
and order of bulbjax's state spec. The env classes are constructed directly (no `gym.make`), the
time limit (gym's `max_episode_steps`) is applied here, and the step API is the old 4-tuple one
of the wrapped env, returned here as (frame, state, reward, terminated, truncated, info).

`get_qpos_qvel`/`set_qpos_qvel` read and write the full physical state in the generalised
coordinates of the MJX mirror (MuJoCo's qpos/qvel layout), so both simulators can start from the
same state. This module does not import JAX (it runs in worker processes).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from pybullet_compat import _loader

PENDULUM_STATE: dict[str, tuple[str, ...]] = {
    "CartPole": ("theta", "theta_vel", "x", "x_vel"),
    "InvertedPendulum": ("x", "x_vel", "theta_cos", "theta_sin", "theta_vel"),
}
LOCOMOTION_HEAD = ("z_delta", "tgt_theta_sin", "tgt_theta_cos", "x_vel", "y_vel", "z_vel",
                   "body_roll", "body_pitch")


def locomotion_state_names(num_joints: int, num_feet: int) -> tuple[str, ...]:
    """bulb's names for `WalkerBase.calc_state()`: 8 body entries, (pos, vel) per joint, contacts."""
    joints = tuple(n for i in range(num_joints) for n in (f"j{i}_pos", f"j{i}_vel"))
    return LOCOMOTION_HEAD + joints + tuple(f"ft{k}_contact" for k in range(num_feet))


@dataclass(frozen=True)
class DomainSpec:
    """One original domain: its class, gym id, camera, episode length, actions and state names."""

    name: str  # bulbjax name
    env_id: str  # gym id in pybullet_envs' registry
    cls_name: str
    cam_dist: float
    cam_yaw: float
    cam_pitch: float
    episode_length: int
    state_names: tuple[str, ...]
    discrete: bool = False
    num_actions: int | None = None
    action_size: int = 1
    mobile: bool = False  # camera target is the torso (walking robots) instead of the cart

    @property
    def state_dim(self) -> int:
        return len(self.state_names)


DOMAINS: dict[str, DomainSpec] = {
    "CartPole": DomainSpec("CartPole", "CartPoleBulletEnv-v1", "CartPoleBulletEnv", 2.0, 0.0, 0.3, 200,
                           PENDULUM_STATE["CartPole"], discrete=True, num_actions=2),
    "InvertedPendulum": DomainSpec("InvertedPendulum", "InvertedPendulumBulletEnv-v0", "InvertedPendulumBulletEnv",
                                   2.2, 0.0, -30.0, 1000, PENDULUM_STATE["InvertedPendulum"]),
    "HalfCheetah": DomainSpec("HalfCheetah", "HalfCheetahBulletEnv-v0", "HalfCheetahBulletEnv", 3.0, 0.0, -30.0,
                              1000, locomotion_state_names(6, 6), action_size=6, mobile=True),
    "Ant": DomainSpec("Ant", "AntBulletEnv-v0", "AntBulletEnv", 3.0, 0.0, -30.0, 1000,
                      locomotion_state_names(8, 4), action_size=8, mobile=True),
}
# bulb colours CartPole's cart yellow and its pole blue (PyBullet's URDF has a blue cart, white pole)
CARTPOLE_RGBA = {0: (1.0, 1.0, 0.0, 1.0), 1: (0.0, 0.0, 1.0, 1.0)}


def domain(name: str) -> DomainSpec:
    """The spec of domain `name` (bulbjax naming: CartPole, InvertedPendulum, HalfCheetah, Ant)."""
    if name not in DOMAINS:
        raise ValueError(f"unknown PyBullet domain {name!r}; available: {', '.join(DOMAINS)}")
    return DOMAINS[name]


class StepResult(NamedTuple):
    """One step: frame [H, W, 3] uint8 (or [0, 0, 3]), state [D] float32, reward, flags, info."""

    frame: np.ndarray
    state: np.ndarray
    reward: float
    terminated: bool
    truncated: bool
    info: dict[str, Any]


class BulletPixelEnv:
    """One original PyBullet env with bulb's frame and true state; no auto-reset.

    `render=False` skips `getCameraImage` (frames are [0, 0, 3]) for fast state-only rollouts."""

    def __init__(self, name: str, resolution: int = 64, render: bool = True):
        if not isinstance(resolution, int) or resolution < 8:
            raise ValueError(f"resolution must be an integer >= 8, got {resolution!r}")
        self.spec = domain(name)
        self.name = name
        self.resolution = resolution
        self.render_frames = render
        self._pb = _loader.pybullet()
        cls = _loader.env_class(self.spec.cls_name)
        with _loader.quiet_c_stdout():
            self.env = cls()
        self._connected = False
        self.step_count = 0
        self.episode_return = 0.0
        self._proj = None

    # ------------------------------------------------------------------ properties
    @property
    def state_names(self) -> tuple[str, ...]:
        return self.spec.state_names

    @property
    def client(self) -> Any:
        """The env's `BulletClient` (valid after the first reset)."""
        return self.env._p

    # ------------------------------------------------------------------ episode API
    def reset(self, seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Start an episode (reseeding the env's own generator when `seed` is given) -> (frame, state)."""
        if seed is not None:
            self.env.seed(int(seed))
        with _loader.quiet_c_stdout():
            state = self.env.reset()
        if not self._connected:
            self._on_connect()
        self.step_count, self.episode_return = 0, 0.0
        return self.render(), self._state(state)

    def step(self, action: Any) -> StepResult:
        """Apply one action (int for CartPole, float array [action_size] in [-1, 1] otherwise)."""
        if self.spec.discrete:
            act: Any = int(np.asarray(action).reshape(()))
        else:
            act = np.asarray(action, np.float64).reshape(self.spec.action_size)
        state, reward, terminated, _ = self.env.step(act)
        self.step_count += 1
        self.episode_return += float(reward)
        truncated = (self.step_count >= self.spec.episode_length) and not terminated
        info = {"episode_return": self.episode_return, "episode_length": self.step_count}
        return StepResult(self.render(), self._state(state), float(reward), bool(terminated), bool(truncated), info)

    def render(self) -> np.ndarray:
        """bulb's frame of the current state, [H, W, 3] uint8 ([0, 0, 3] when rendering is off)."""
        if not self.render_frames:
            return np.zeros((0, 0, 3), np.uint8)
        return self._camera_image()[0]

    def robot_mask(self) -> np.ndarray:
        """[H, W] bool: pixels of bulb's frame that show the robot (PyBullet's segmentation)."""
        seg = self._camera_image()[1]
        return (seg >= 0) & ((seg & ((1 << 24) - 1)) == self.body_uid())

    def _camera_image(self) -> tuple[np.ndarray, np.ndarray]:
        p, res = self.client, self.resolution
        view = p.computeViewMatrixFromYawPitchRoll(
            cameraTargetPosition=self.camera_target(), distance=self.spec.cam_dist, yaw=self.spec.cam_yaw,
            pitch=self.spec.cam_pitch, roll=0, upAxisIndex=2)
        if self._proj is None:
            self._proj = p.computeProjectionMatrixFOV(fov=60, aspect=1.0, nearVal=0.1, farVal=100.0)
        _, _, px, _, seg = p.getCameraImage(width=res, height=res, viewMatrix=view, projectionMatrix=self._proj,
                                            renderer=self._pb.ER_TINY_RENDERER)
        frame = np.asarray(px, np.uint8).reshape(res, res, 4)[:, :, :3].copy()
        return frame, np.asarray(seg, np.int64).reshape(res, res)

    def camera_target(self) -> list[float]:
        """The robot's base: the cart `[x, 0, 0]` for pendulums, the torso for walking robots."""
        if self.spec.mobile:
            return list(self.env.robot.robot_body.pose().xyz())
        qpos, _ = self.get_qpos_qvel()
        return [float(qpos[0]), 0.0, 0.0]

    def close(self) -> None:
        self.env.close()
        self._connected = False

    # ------------------------------------------------------------------ physical state
    def joint_names(self) -> list[str]:
        """Names of the coordinates in `get_qpos_qvel` order (hinges/slides; the free base first)."""
        if self.name == "CartPole":
            return ["slider_to_cart", "cart_to_pole"]
        if self.name == "InvertedPendulum":
            return ["slider", "hinge"]
        names = [j.joint_name for j in self.env.robot.ordered_joints]
        if self.name == "HalfCheetah":
            return ["ignorex", "ignorez", "ignorey"] + names
        return ["root"] + names

    def get_qpos_qvel(self) -> tuple[np.ndarray, np.ndarray]:
        """Full physical state in the MJX mirror's layout (float64).

        CartPole / InvertedPendulum: qpos = [x, theta], qvel = [x_vel, theta_vel].
        HalfCheetah: the planar root (x, z, pitch) then the six leg joints.
        Ant: free root (position, quaternion w-x-y-z; linear velocity in the world frame, angular
        velocity in the torso frame, as MuJoCo's free joint) then the eight leg joints."""
        p = self.client
        if self.name == "CartPole":
            body = self.env.cartpole
            (x, xv), (th, thv) = (p.getJointState(body, j)[:2] for j in (0, 1))
            return np.array([x, th]), np.array([xv, thv])
        if self.name == "InvertedPendulum":
            (x, xv), (th, thv) = self.env.robot.slider.get_state(), self.env.robot.j1.get_state()
            return np.array([x, th]), np.array([xv, thv])
        joints = self._all_joints()
        js = [j.get_state() for j in joints]
        jq, jv = np.array([s[0] for s in js]), np.array([s[1] for s in js])
        if self.name == "HalfCheetah":
            return jq, jv
        body = self._base_body()
        pos, quat_xyzw = p.getBasePositionAndOrientation(body)
        lin, ang = p.getBaseVelocity(body)
        rot = np.array(p.getMatrixFromQuaternion(quat_xyzw)).reshape(3, 3)
        quat_wxyz = [quat_xyzw[3], *quat_xyzw[:3]]
        return (np.concatenate([pos, quat_wxyz, jq]), np.concatenate([lin, rot.T @ np.asarray(ang), jv]))

    def set_qpos_qvel(self, qpos: Any, qvel: Any) -> tuple[np.ndarray, np.ndarray]:
        """Put the simulator in the given physical state (layout of `get_qpos_qvel`); returns
        (frame, state) there. The step counter restarts (a new episode from that state)."""
        qpos, qvel = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)
        if not self._connected:
            self.reset()
        p = self.client
        if self.name == "CartPole":
            body = self.env.cartpole
            p.resetJointState(body, 0, qpos[0], qvel[0])
            p.resetJointState(body, 1, qpos[1], qvel[1])
            state = np.array(p.getJointState(body, 1)[0:2] + p.getJointState(body, 0)[0:2])
            self.env.state = tuple(state)
        elif self.name == "InvertedPendulum":
            r = self.env.robot
            r.slider.reset_current_position(float(qpos[0]), float(qvel[0]))
            r.j1.reset_current_position(float(qpos[1]), float(qvel[1]))
            state = r.calc_state()
        else:
            joints = self._all_joints()
            nj = len(joints)
            if self.name == "Ant":
                body = self._base_body()
                pos, quat = qpos[:3], qpos[3:7]
                rot = np.array(p.getMatrixFromQuaternion([quat[1], quat[2], quat[3], quat[0]])).reshape(3, 3)
                p.resetBasePositionAndOrientation(body, pos.tolist(), [quat[1], quat[2], quat[3], quat[0]])
                p.resetBaseVelocity(body, qvel[:3].tolist(), (rot @ qvel[3:6]).tolist())
                jq, jv = qpos[7:], qvel[6:]
            else:
                jq, jv = qpos, qvel
            if len(jq) != nj or len(jv) != nj:
                raise ValueError(f"{self.name}: expected {nj} joint coordinates, got {len(jq)}/{len(jv)}")
            for j, q, v in zip(joints, jq, jv):
                j.reset_current_position(float(q), float(v))
            state = self.env.robot.calc_state()
            self.env.potential = self.env.robot.calc_potential()
        self.step_count, self.episode_return = 0, 0.0
        return self.render(), self._state(state)

    def body_uid(self) -> int:
        """PyBullet unique id of the robot's multibody."""
        if self.name == "CartPole":
            return int(self.env.cartpole)
        j = self.env.robot.ordered_joints[0]
        return int(j.bodies[j.bodyIndex])

    def link_inertias(self) -> dict[str, tuple[float, tuple[float, float, float]]]:
        """Mass and principal moments of inertia PyBullet uses for each massive link (by link
        name; the base under its body name): what it actually simulates, which can differ from
        the model file (URDF inertia ignored, capsule inertia from a margin-inflated box)."""
        p, b = self.client, self.body_uid()
        out = {}
        base = p.getDynamicsInfo(b, -1)
        if base[0] > 0:
            out[p.getBodyInfo(b)[0].decode()] = (float(base[0]), tuple(float(x) for x in base[2]))
        for j in range(p.getNumJoints(b)):
            info = p.getDynamicsInfo(b, j)
            if info[0] > 0:
                out[p.getJointInfo(b, j)[12].decode()] = (float(info[0]), tuple(float(x) for x in info[2]))
        return out

    def joint_damping(self) -> dict[str, float]:
        """Joint damping PyBullet applies per named joint (`getJointInfo`); its MJCF importer
        does not always keep the file's value (e.g. InvertedPendulum's default-class damping)."""
        p, b = self.client, self.body_uid()
        return {p.getJointInfo(b, j)[1].decode(): float(p.getJointInfo(b, j)[6]) for j in range(p.getNumJoints(b))}

    # ------------------------------------------------------------------ internals
    def _on_connect(self) -> None:
        self._connected = True
        if self.name == "CartPole":
            for link, rgba in CARTPOLE_RGBA.items():
                self.client.changeVisualShape(self.env.cartpole, link, rgbaColor=list(rgba))

    def _all_joints(self) -> list[Any]:
        """PyBullet `Joint` objects for the mirror's hinge/slide coordinates (locomotion)."""
        robot = self.env.robot
        joints = list(robot.ordered_joints)
        if self.name == "HalfCheetah":
            rb = robot_bases()
            body = robot.robot_body
            ignore = {}
            p = self.client
            bid = body.bodies[body.bodyIndex]
            for j in range(p.getNumJoints(bid)):
                nm = p.getJointInfo(bid, j)[1].decode()
                if nm.startswith("ignore"):
                    ignore[nm] = rb.Joint(p, nm, body.bodies, body.bodyIndex, j)
            joints = [ignore["ignorex"], ignore["ignorez"], ignore["ignorey"]] + joints
        return joints

    def _base_body(self) -> int:
        body = self.env.robot.robot_body
        if body.bodyPartIndex != -1:
            raise RuntimeError(f"{self.name}: expected the torso to be the multibody's base")
        return body.bodies[body.bodyIndex]

    def _state(self, state: Any) -> np.ndarray:
        s = np.asarray(state, np.float32).reshape(-1)
        if s.shape[0] != self.spec.state_dim:  # pragma: no cover - guards pybullet version drift
            raise RuntimeError(f"{self.name}: PyBullet state has {s.shape[0]} entries, expected {self.spec.state_dim}")
        return s


def robot_bases() -> Any:
    """pybullet_envs' `robot_bases` module (for `Joint`)."""
    _loader.env_class("InvertedPendulumBulletEnv")
    import importlib
    return importlib.import_module("robot_bases")

