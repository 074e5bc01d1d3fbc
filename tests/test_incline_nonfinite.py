"""Issue 40: Incline worlds with heavy objects went non-finite (GPU soak: 35% of GeomOnInclineSm's
episodes). The per-world masses must reach MuJoCo's subtree masses, or the float32 mass matrix of
an object (built about a subtree COM at mass/mass0 times its position) factors to NaN. CPU, about
a minute: the subtree masses against C MuJoCo's, and heavy objects of every version falling and
sliding with no non-finite reset."""

from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import bulbjax
from bulbjax.envs.objects.incline import NUM_VERSIONS, START_X

N = NUM_VERSIONS  # one world per version
HEAVY = 0.45  # kg: every version's first step was NaN at this mass before the fix


@pytest.fixture(scope="module")
def env():
    return bulbjax.make("GeomOnInclineSm", num_envs=N, render=False, version="random")


def test_world_model_subtree_masses_are_mujocos(env):
    mass = np.linspace(0.05, 0.5, N)
    params = {"mass": jnp.asarray(mass, jnp.float32), "friction": jnp.full(N, 0.3), "theta": jnp.full(N, 0.3),
              "texture": jnp.zeros(N, jnp.int32), "version": jnp.arange(N, dtype=jnp.int32)}
    mx = env._world_model(params)
    for w in range(N):
        m = copy.deepcopy(env.mj_model)
        m.body_mass[:] = np.asarray(mx.body_mass[w])
        m.body_inertia[:] = np.asarray(mx.body_inertia[w])
        mujoco.mj_setConst(m, mujoco.MjData(m))
        np.testing.assert_allclose(np.asarray(mx.body_subtreemass[w]), m.body_subtreemass, rtol=1e-6)


def test_heavy_objects_fall_and_slide_without_nonfinite_resets(env):
    state = jax.jit(lambda k: env.reset_with(k, version=jnp.arange(N), mass=HEAVY, friction=0.3, theta=0.4,
                                             start_x=START_X[0]))(jax.random.PRNGKey(0))
    # the initial fall ran to its end: a fall gone non-finite restarts at the placement, x = -0.05
    x = np.asarray(state.info["lowdim_raw"][:, 0])
    assert np.isfinite(x).all() and (x > START_X[0]).all(), f"the fall did not finish: x = {x}"
    step = jax.jit(env.step)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (8, N, 1), minval=-1.0, maxval=1.0)
    for a in actions:
        state = step(state, a)
    assert int(np.asarray(state.counts["nonfinite_resets"]).sum()) == 0
    assert np.isfinite(np.asarray(state.data.qvel)).all()
