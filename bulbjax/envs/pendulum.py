"""CartPole and InvertedPendulum, mirroring pybullet_envs' CartPoleBulletEnv(-v1) and
InvertedPendulumBulletEnv-v0 (pybullet 3.2.7): same model, timestep, forces, reward,
termination, episode length and reset noise; state names and order as bulb reports them."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from mujoco import mjx

from bulbjax.envs.base import MjxPixelEnv
from bulbjax.envs.camera import CameraConfig
from bulbjax.eval.spec import StateEntry


class CartPole(MjxPixelEnv):
    """CartPoleBulletEnv: push the cart left/right (+-10 N) to keep the pole within 12 degrees
    and the cart within 0.4 m; reward 1 per step, 200 steps, reset uniform in +-0.05 on all four
    state entries. Camera: distance 2, yaw 0, pitch 0.3, target the cart."""

    name = "CartPole"
    xml_file = "cartpole.xml"
    camera = CameraConfig(distance=2.0, yaw=0.0, pitch=0.3, body="cart")
    state_spec = (
        StateEntry("theta", "rad", "position"),
        StateEntry("theta_vel", "rad/s", "velocity"),
        StateEntry("x", "m", "position"),
        StateEntry("x_vel", "m/s", "velocity"),
    )
    episode_length = 200
    solved_return = 190.0
    discrete = True
    num_actions = 2
    action_size = 1
    colour_roles = {"cart": "base", "pole": "pole"}
    pointcloud_exclude = ("slidebar",)
    force_mag = 10.0
    theta_threshold = 12 * 2 * math.pi / 360
    x_threshold = 0.4

    def _reset_qpos_qvel(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        theta, theta_vel, x, x_vel = jax.random.uniform(key, (4,), minval=-0.05, maxval=0.05)
        return jnp.stack([x, theta]), jnp.stack([x_vel, theta_vel])

    def _lowdim(self, data: mjx.Data) -> jax.Array:
        return jnp.stack([data.qpos[1], data.qvel[1], data.qpos[0], data.qvel[0]]).astype(jnp.float32)

    def _ctrl(self, action: jax.Array) -> jax.Array:
        # As CartPoleBulletEnv: 1 pushes right, any other value pushes left.
        force = jnp.where(action == 1, self.force_mag, -self.force_mag)
        return jnp.reshape(force, (1,)).astype(jnp.float32)

    def _reward_terminated(self, data, lowdim, action, prev_data):
        theta, x = lowdim[0], lowdim[2]
        terminated = (jnp.abs(x) > self.x_threshold) | (jnp.abs(theta) > self.theta_threshold)
        return jnp.float32(1.0), terminated


class CartPoleContinuous(CartPole):
    """CartPoleContinuousBulletEnv: the force is the action in [-1, 1] times 10 N."""

    name = "CartPoleContinuous"
    discrete = False
    num_actions = None

    def _ctrl(self, action: jax.Array) -> jax.Array:
        return (jnp.clip(action, -1.0, 1.0) * self.force_mag).reshape((1,))


class InvertedPendulum(MjxPixelEnv):
    """InvertedPendulumBulletEnv: torque 100 * clip(a, -1, 1) on the slider; reward 1 per step,
    done when |theta| > 0.2; 1000 steps; reset: hinge uniform in +-0.1 rad, all else 0.
    Camera: distance 2.2, yaw 0, pitch -30, target the cart."""

    name = "InvertedPendulum"
    xml_file = "inverted_pendulum.xml"
    camera = CameraConfig(distance=2.2, yaw=0.0, pitch=-30.0, body="cart")
    state_spec = (
        StateEntry("x", "m", "position"),
        StateEntry("x_vel", "m/s", "velocity"),
        StateEntry("theta_cos", "1", "position"),
        StateEntry("theta_sin", "1", "position"),
        StateEntry("theta_vel", "rad/s", "velocity"),
    )
    episode_length = 1000
    solved_return = 950.0
    discrete = False
    action_size = 1
    colour_roles = {"cart": "base", "cpole": "pole"}
    pointcloud_exclude = ("rail",)

    def _reset_qpos_qvel(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        theta = jax.random.uniform(key, (), minval=-0.1, maxval=0.1)
        return jnp.stack([0.0, theta]), jnp.zeros(2)

    def _lowdim(self, data: mjx.Data) -> jax.Array:
        x, theta = data.qpos[0], data.qpos[1]
        return jnp.stack([x, data.qvel[0], jnp.cos(theta), jnp.sin(theta), data.qvel[1]]).astype(jnp.float32)

    def _ctrl(self, action: jax.Array) -> jax.Array:
        return jnp.clip(action, -1.0, 1.0).reshape((1,))

    def _reward_terminated(self, data, lowdim, action, prev_data):
        theta = data.qpos[1]
        return jnp.float32(1.0), jnp.abs(theta) > 0.2
