"""FrankaRearrange (Geom, OneGeom, Ycb, OneYcb): the Panda among the objects, with bulb's IK reset pose; the domain itself in `rearrange_base`."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from bulbjax.envs.camera import CameraConfig
from bulbjax.envs.env_config import EnvConfig
from bulbjax.envs.objects.incline import _quat_mat

os.environ.setdefault("MUJOCO_GL", "disable")  # dm_control needs no GL context to build models
from dm_control import mjcf  # noqa: E402

from bulbjax.envs.objects.rearrange_base import Rearrange, _VARIANT_DOCS, _variant_class


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
    forward_after_step = True  # `_torque` reads qfrc_bias: the forward pass at the new state
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

    @classmethod
    def check_sources(cls, ycb_dir: str | None = None) -> None:
        """The Panda comes from pybullet's pybullet_data: pybullet must be installed
        (`PybulletNotInstalled`, a one-line ValueError, says how)."""
        super().check_sources(ycb_dir)
        from bulbjax.assets.franka import panda_urdf_dir

        panda_urdf_dir()

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
