"""SyntheticMovers: coloured squares moving at constant velocities, generated in JAX.

A check that only sequence models can pass: every episode draws each square's position and
velocity at random, the velocity stays constant (it flips sign on a bounce off a wall), and a
single frame shows positions only. So a frame learner's latent cannot hold the velocity, while
a learner that sees a window of frames can. The true state is every square's position (px, the
top-left corner) and velocity (px per step).

Layout and step convention follow the simulators' rollouts (`bulbjax.data.sequence`): step `t`
stores the state after the `t`-th step; `done[t] = 1` where step `t` ended an episode, and then
frame `t` already shows the next episode's first state. Worlds start at staggered points of their
episodes. Actions are zeros (nothing steers the squares); they keep the `Windows` layout.
Frames are anti-aliased (each pixel is the square's coverage of it), so positions are sub-pixel.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from bulbjax.data.sequence import Trajectories
from bulbjax.eval.spec import StateEntry

NAME = "SyntheticMovers"
# Square colours (RGB in [0, 1]); square i uses colour i.
COLOURS: tuple[tuple[float, float, float], ...] = (
    (1.0, 0.25, 0.2), (0.2, 0.9, 0.3), (0.3, 0.45, 1.0), (1.0, 0.9, 0.2))


@dataclass(frozen=True)
class MoversConfig:
    """Frames of `num_objects` squares of `size` px in `resolution` x `resolution` frames, each
    moving at a constant velocity with components uniform in [-max_speed, max_speed] px/step,
    for episodes of `episode_length` steps."""

    resolution: int = 32
    num_objects: int = 2
    size: float = 6.0
    max_speed: float = 1.5
    episode_length: int = 32

    def __post_init__(self) -> None:
        if not 1 <= self.num_objects <= len(COLOURS):
            raise ValueError(f"num_objects must be in [1, {len(COLOURS)}], got {self.num_objects}")
        if not 0 < self.size < self.resolution:
            raise ValueError(f"size must be in (0, resolution={self.resolution}), got {self.size}")
        if not 0 < self.max_speed < self.resolution - self.size:
            raise ValueError(f"max_speed must be in (0, resolution - size), got {self.max_speed}")
        if self.episode_length < 2:
            raise ValueError(f"episode_length must be >= 2, got {self.episode_length}")

    def replace(self, **kw) -> "MoversConfig":
        return dataclasses.replace(self, **kw)

    @property
    def state_spec(self) -> tuple[StateEntry, ...]:
        """x_i, y_i of every square (position, px), then vx_i, vy_i (velocity, px/step)."""
        pos = [StateEntry(f"{a}{i}", "px", "position") for i in range(self.num_objects) for a in "xy"]
        vel = [StateEntry(f"v{a}{i}", "px/step", "velocity") for i in range(self.num_objects) for a in "xy"]
        return tuple(pos + vel)

    @property
    def frame_shape(self) -> tuple[int, int, int]:
        return (self.resolution, self.resolution, 3)

    @property
    def state_dim(self) -> int:
        return 4 * self.num_objects

    @property
    def action_dim(self) -> int:
        """Width of the (all-zero) actions."""
        return 1


def _new_episode(key: jax.Array, c: MoversConfig, n: int) -> tuple[jax.Array, jax.Array]:
    """Positions [n, K, 2] uniform over the frame and velocities [n, K, 2]."""
    kp, kv = jax.random.split(key)
    pos = jax.random.uniform(kp, (n, c.num_objects, 2), maxval=c.resolution - c.size)
    vel = jax.random.uniform(kv, (n, c.num_objects, 2), minval=-c.max_speed, maxval=c.max_speed)
    return pos, vel


def _move(c: MoversConfig, pos: jax.Array, vel: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One step at constant velocity, reflecting off the walls."""
    hi = c.resolution - c.size
    p = pos + vel
    low, high = p < 0, p > hi
    p = jnp.where(low, -p, jnp.where(high, 2 * hi - p, p))
    return p, jnp.where(low | high, -vel, vel)


def render(c: MoversConfig, pos: jax.Array) -> jax.Array:
    """Positions [..., K, 2] (x, y of the top-left corners) -> uint8 frames [..., R, R, 3];
    a pixel's value is the square's coverage of it (later squares over earlier ones)."""
    grid = jnp.arange(c.resolution, dtype=jnp.float32)

    def coverage(x: jax.Array) -> jax.Array:  # [...] -> [..., R]
        x = x[..., None]
        return jnp.clip(jnp.minimum(grid + 1, x + c.size) - jnp.maximum(grid, x), 0.0, 1.0)

    img = jnp.zeros(pos.shape[:-2] + (c.resolution, c.resolution, 3), jnp.float32)
    for k in range(c.num_objects):
        a = coverage(pos[..., k, 1])[..., :, None] * coverage(pos[..., k, 0])[..., None, :]
        col = jnp.asarray(COLOURS[k], jnp.float32)
        img = img * (1 - a[..., None]) + a[..., None] * col
    return jnp.round(img * 255).astype(jnp.uint8)


def generate(key: jax.Array, config: MoversConfig, steps: int, worlds: int) -> Trajectories:
    """`steps` steps of `worlds` independent worlds -> `Trajectories [steps, worlds, ...]`."""
    c = config
    k0, k_phase, k_run = jax.random.split(key, 3)
    pos, vel = _new_episode(k0, c, worlds)
    age = jax.random.randint(k_phase, (worlds,), 0, c.episode_length)  # staggered episodes

    def step(carry, k):
        pos, vel, age = carry
        pos, vel = _move(c, pos, vel)
        age = age + 1
        done = age >= c.episode_length
        npos, nvel = _new_episode(k, c, worlds)
        pos = jnp.where(done[:, None, None], npos, pos)
        vel = jnp.where(done[:, None, None], nvel, vel)
        age = jnp.where(done, 0, age)
        state = jnp.concatenate([pos.reshape(worlds, -1), vel.reshape(worlds, -1)], -1)
        return (pos, vel, age), (render(c, pos), state, done.astype(jnp.float32))

    _, (frames, states, dones) = jax.lax.scan(step, (pos, vel, age), jax.random.split(k_run, steps))
    actions = jnp.zeros((steps, worlds, c.action_dim), jnp.float32)
    return Trajectories(frames=frames, actions=actions, states=states, dones=dones)
