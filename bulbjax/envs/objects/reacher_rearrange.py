"""ReacherRearrange (Geom, OneGeom, Ycb, OneYcb): bulb's planar 2-link reacher among the objects; the domain itself in `rearrange_base`."""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from bulbjax.envs.models import asset_dir
from bulbjax.envs.camera import CameraConfig

os.environ.setdefault("MUJOCO_GL", "disable")  # dm_control needs no GL context to build models
from dm_control import mjcf  # noqa: E402

from bulbjax.envs.objects.rearrange_base import Rearrange, _VARIANT_DOCS, _variant_class


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


ReacherRearrangeGeom = _variant_class(ReacherRearrange, "Reacher", "Geom", f"ReacherRearrange: {_VARIANT_DOCS['Geom']}.")
ReacherRearrangeOneGeom = _variant_class(ReacherRearrange, "Reacher", "OneGeom", f"ReacherRearrange: {_VARIANT_DOCS['OneGeom']}.")
ReacherRearrangeYcb = _variant_class(ReacherRearrange, "Reacher", "Ycb", f"ReacherRearrange: {_VARIANT_DOCS['Ycb']}.")
ReacherRearrangeOneYcb = _variant_class(ReacherRearrange, "Reacher", "OneYcb", f"ReacherRearrange: {_VARIANT_DOCS['OneYcb']}.")
