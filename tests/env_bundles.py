"""The environments the env tests build, each with its jitted entry points (`Bundle`), and what
the tests step and look at them with: constant actions, rollouts, a state set by hand, MuJoCo C's
trajectory for comparison, colour checks of a frame's pixels, and the shapes and dtypes of a
state's fields."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

import bulbjax
from bulbjax.envs import EnvState, MjxPixelEnv, RenderInput

N = 4  # worlds per env
RES = 64


@dataclass
class Bundle:
    """An env with its jitted entry points (compiled once per module)."""

    env: MjxPixelEnv
    reset: Callable[[jax.Array], EnvState]
    step: Callable[[EnvState, jax.Array], EnvState]
    render: Callable[[RenderInput], jax.Array] | None


def _bundle(name: str, num_envs: int = N, render: bool = True) -> Bundle:
    env = bulbjax.make(name, num_envs=num_envs, resolution=RES, render=render)
    return Bundle(env, jax.jit(env.reset), jax.jit(env.step),
                  jax.jit(env.render_frames) if render else None)


def _action(env: MjxPixelEnv, value: float | int) -> jax.Array:
    """A constant action for every world: discrete index or continuous value."""
    if env.discrete:
        return jnp.full((env.num_envs,), int(value), jnp.int32)
    return jnp.full((env.num_envs, env.action_size), float(value), jnp.float32)


def _push_right(env: MjxPixelEnv) -> jax.Array:
    return _action(env, 1)


def _rollout(b: Bundle, key: jax.Array, actions: list[jax.Array]) -> list[EnvState]:
    s = b.reset(key)
    states = [s]
    for a in actions:
        s = b.step(s, a)
        states.append(s)
    return jax.device_get(states)


def _set_state(s: EnvState, qpos: np.ndarray, qvel: np.ndarray) -> EnvState:
    """Place every world at the given joint positions/velocities (fresh episode)."""
    data = s.data.replace(qpos=jnp.asarray(qpos, s.data.qpos.dtype), qvel=jnp.asarray(qvel, s.data.qvel.dtype))
    return s.replace(data=data, step_count=jnp.zeros_like(s.step_count),
                     episode_return=jnp.zeros_like(s.episode_return))


def _mujoco_reference(model: mujoco.MjModel, qpos0: np.ndarray, qvel0: np.ndarray, ctrl: np.ndarray,
                      steps: int) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo C (CPU, float64) trajectory of one world under a constant control: qpos/qvel [steps, nq]."""
    d = mujoco.MjData(model)
    d.qpos[:], d.qvel[:], d.ctrl[:] = qpos0, qvel0, ctrl
    qs, vs = [], []
    for _ in range(steps):
        mujoco.mj_step(model, d)
        qs.append(d.qpos.copy())
        vs.append(d.qvel.copy())
    return np.array(qs), np.array(vs)


def _rgb(px: np.ndarray) -> np.ndarray:
    return np.asarray(px).astype(np.int32)


def _is_blue(px: np.ndarray) -> bool:
    r, g, b = _rgb(px)
    return b > 150 and b > r + 100 and b > g + 100


def _matches_colour(px: np.ndarray, colour: np.ndarray) -> bool:
    """Shaded pixel has the colour's dominant channels: high (>150) where the colour is 1,
    low (<110) where it is 0."""
    px = _rgb(px)
    return all((p > 150) if c > 0.5 else (p < 110) for p, c in zip(px, colour))


def _check_fields(env: MjxPixelEnv, s: EnvState, res: int) -> None:
    n, d = env.num_envs, env.state_dim
    assert s.obs.shape == (n, env.obs_size) and s.obs.dtype == jnp.float32
    assert s.lowdim.shape == (n, d) and s.lowdim.dtype == jnp.float32
    assert s.pixels.shape == (n, res, res, 3) and s.pixels.dtype == jnp.uint8
    for f in ("reward", "done", "truncated", "episode_return"):
        arr = getattr(s, f)
        assert arr.shape == (n,) and arr.dtype == jnp.float32, (f, arr.shape, arr.dtype)
    assert s.step_count.shape == (n,) and s.step_count.dtype == jnp.int32
    assert s.scheme.shape == (n,) and s.scheme.dtype == jnp.int32
    assert s.key.shape[0] == n
    assert set(s.info) >= {"episode_return", "episode_length"}
    assert s.info["episode_return"].shape == (n,) and s.info["episode_return"].dtype == jnp.float32
    assert s.info["episode_length"].shape == (n,) and jnp.issubdtype(s.info["episode_length"].dtype, jnp.integer)
    assert s.data.qpos.shape == (n, env.mj_model.nq) and s.data.qvel.shape == (n, env.mj_model.nv)
    assert s.render_input.qpos.shape == (n, env.mj_model.nq)
    np.testing.assert_array_equal(s.obs, s.lowdim)  # policy input is the true state by default
    assert np.all(np.isfinite(np.asarray(s.lowdim)))
