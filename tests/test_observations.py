"""Observation modes of every domain (here CartPole): depth in metres and bulb's point clouds."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import bulbjax


def test_depth_is_metres_to_the_cart():
    env = bulbjax.make("CartPole", num_envs=2, render="depth")
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    assert state.pixels.shape == (2, 64, 64, 3) and state.depth.shape == (2, 64, 64)
    assert state.depth.dtype == jnp.float32
    # the camera is 2 m in front of the cart (pitch 0.3 deg): the cart's front face (0.25 m
    # towards the camera) fills the frame's centre, the pole stands above it
    centre = np.asarray(state.depth[:, 32, 32])
    np.testing.assert_allclose(centre, 1.75, atol=0.03)


def test_point_cloud_is_the_cart_and_pole_without_the_slidebar():
    env = bulbjax.make("CartPole", num_envs=2, render="pointcloud", num_points=512)
    state = jax.jit(env.reset)(jax.random.PRNGKey(1))
    state = jax.jit(env.step)(state, jnp.ones(2, jnp.int32))
    pts = np.asarray(state.points)
    assert pts.shape == (2, 512, 3) and pts.dtype == np.float32
    x = np.asarray(state.data.qpos[:, 0])
    for i in range(2):
        real = pts[i][np.abs(pts[i]).sum(-1) > 0]
        assert len(real) == 512
        assert (np.abs(real[:, 0] - x[i]) < 0.3).all(), "points beyond the cart: the 30 m slidebar leaked in"
        assert (np.abs(real[:, 1]) < 0.26).all() and (real[:, 2] > -0.11).all() and (real[:, 2] < 1.05).all()
        assert real[:, 2].max() > 0.5, "the pole is in the cloud"


def test_bad_observation_is_an_error():
    with pytest.raises(ValueError, match="observation"):
        bulbjax.make("CartPole", num_envs=1, render="lidar")
