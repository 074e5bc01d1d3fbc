"""Brax / MuJoCo Playground-style wrapper: `reset(rng) -> State`, `step(state, action) -> State`
over a `State(pipeline_state, obs, reward, done, metrics, info)` pytree, with the attributes
Brax's training code reads (`observation_size`, `action_size`, `backend`, `dt`, `unwrapped`).

Why: JAX RL code (Brax's PPO/SAC trainers, Playground-style loops) takes this shape; a bulbjax env
is already a pure, jittable, batched `reset`/`step` and only needs renaming.

Batch semantics. Brax's trainers normally wrap a single-world env with `VmapWrapper`,
`EpisodeWrapper` and `AutoResetWrapper`. A bulbjax env is batched (`num_envs` worlds), has its
own time limit and auto-resets inside `step`, so `BraxEnv` is the *already wrapped* env: pass it
with `wrap_env=False` and `num_envs=env.num_envs` (and an `eval_env` of `num_eval_envs` worlds).
It fills the `info` entries those wrappers would: `truncation` (ended by the time limit),
`steps` (steps into the episode, the ended episode's length on the step that ends it),
`episode_done` and `episode_metrics` (`sum_reward`, `length`; the ended episode's on its last
step), which Brax's PPO logs and bootstraps from. As with Brax's `AutoResetWrapper`, the state
returned by the step that ends an episode already holds the next episode's first observation
(`state.pipeline_state` is the bulbjax `EnvState`; its `lowdim`/`pixels` are the new episode's).

`reset(rng)` takes one key `[2]`, or a batch `[num_envs, 2]` as Brax's trainers pass (the first
key then seeds all worlds: bulbjax splits one key over its worlds).

Actions: float `[N, action_size]` in [-1, 1]. For discrete domains `action_size = num_actions`
and the world takes `argmax` of its row (so a Gaussian policy's output can drive CartPole). Any
other shape is a ValueError naming `(num_envs, action_size)` when traced; NaN and out-of-range
values go to `env.step`, which treats NaN as 0, clips to [-1, 1] and counts them
(`state.pipeline_state.counts["actions_fixed"]`).
Observations: `obs="state"` -> float32 `[N, D]` true state; `obs="pixels"` -> the dict
`{"pixels/view_0": float32 [N, H, W, 3] in [0, 1]}` (Brax's vision networks read `pixels/` keys).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from bulbjax.envs.base import EnvState, MjxPixelEnv

try:  # Brax's own classes where installed, so its wrappers' isinstance checks and `replace` hold
    from brax.envs.base import Env as _BraxEnvBase
    from brax.envs.base import State
    HAVE_BRAX = True
except ImportError:  # pragma: no cover - depends on the install
    HAVE_BRAX = False

    class _BraxEnvBase:  # type: ignore[no-redef]
        """Stand-in for `brax.envs.base.Env` when Brax is not installed."""

    @struct.dataclass
    class State:  # type: ignore[no-redef]
        """Same fields as `brax.envs.base.State`."""

        pipeline_state: Any
        obs: Any
        reward: jax.Array
        done: jax.Array
        metrics: dict[str, jax.Array] = struct.field(default_factory=dict)
        info: dict[str, Any] = struct.field(default_factory=dict)

BRAX_OBS_KINDS = ("state", "pixels")
PIXELS_KEY = "pixels/view_0"
_OWN_INFO = ("truncation", "steps", "episode_done", "episode_metrics")


class BraxEnv(_BraxEnvBase):
    """A batched bulbjax env as a Brax `Env` (already vmapped, time-limited and auto-resetting)."""

    def __init__(self, env: MjxPixelEnv, obs: str = "state"):
        if obs not in BRAX_OBS_KINDS:
            raise ValueError(f"obs must be one of {BRAX_OBS_KINDS}, got {obs!r}")
        if obs == "pixels" and not (env.config.render and env.config.render_steps
                                    and env.config.observation in ("rgb", "depth")):
            raise ValueError('obs="pixels" needs a bulbjax env made with render=True')
        self.env = env
        self.obs_kind = obs
        self.num_envs = env.num_envs
        self.episode_length = env.episode_length

    # ----- Brax's Env attributes -----
    @property
    def observation_size(self) -> int | dict[str, tuple[int, ...]]:
        if self.obs_kind == "pixels":
            return {PIXELS_KEY: self.env.frame_shape}
        return self.env.state_dim

    @property
    def action_size(self) -> int:
        return int(self.env.num_actions) if self.env.discrete else int(self.env.action_size)

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def dt(self) -> float:
        """Seconds per env step."""
        return float(self.env.mj_model.opt.timestep) * self.env.frame_skip

    @property
    def unwrapped(self) -> "BraxEnv":
        return self

    # Playground-style names for the models
    @property
    def mj_model(self) -> Any:
        return self.env.mj_model

    @property
    def mjx_model(self) -> Any:
        return self.env.mx

    # ----- reset / step -----
    def reset(self, rng: jax.Array) -> State:
        """All worlds' first state; `rng` one key `[2]` or Brax's batch `[num_envs, 2]`."""
        key = self._key(rng)
        s = self.env.reset(key)
        zeros = jnp.zeros(self.num_envs, jnp.float32)
        info = {"truncation": zeros, "steps": zeros, "episode_done": zeros,
                "episode_metrics": {"sum_reward": zeros, "length": zeros}}
        return State(pipeline_state=s, obs=self._obs(s), reward=s.reward, done=s.done, metrics={}, info=info)

    def step(self, state: State, action: jax.Array) -> State:
        """Step every world with `action` `[num_envs, action_size]` (auto-reset where one ends)."""
        action = jnp.asarray(action)
        if action.shape != (self.num_envs, self.action_size):
            raise ValueError(f"{self.env.name} (Brax wrapper) takes actions of shape "
                             f"({self.num_envs}, {self.action_size}); got {action.shape}")
        if self.env.discrete:
            action = jnp.argmax(action, axis=-1).astype(jnp.int32)
        else:
            action = action.astype(jnp.float32)
        s: EnvState = self.env.step(state.pipeline_state, action)
        done = s.done > 0
        length = jnp.where(done, s.info["episode_length"], s.step_count).astype(jnp.float32)
        info = {k: v for k, v in state.info.items() if k not in _OWN_INFO}  # outer wrappers' entries
        info.update(truncation=s.truncated, steps=length, episode_done=s.done,
                    episode_metrics={"sum_reward": jnp.where(done, s.info["episode_return"], s.episode_return),
                                     "length": length})
        return state.replace(pipeline_state=s, obs=self._obs(s), reward=s.reward, done=s.done, metrics={},
                             info=info)

    def _obs(self, s: EnvState) -> jax.Array | dict[str, jax.Array]:
        if self.obs_kind == "pixels":
            return {PIXELS_KEY: s.pixels.astype(jnp.float32) / 255.0}
        return s.lowdim

    def _key(self, rng: jax.Array) -> jax.Array:
        rng = jnp.asarray(rng)
        if jnp.issubdtype(rng.dtype, jax.dtypes.prng_key):
            rng = jax.random.key_data(rng)
        if rng.shape == (2,):
            return rng
        if rng.ndim == 2 and rng.shape[1] == 2:
            if rng.shape[0] != self.num_envs:
                raise ValueError(f"a batch of {rng.shape[0]} keys for an env of {self.num_envs} worlds: make the "
                                 f"bulbjax env with num_envs={rng.shape[0]} (Brax: num_envs / num_eval_envs)")
            return rng[0]
        raise ValueError(f"reset takes one PRNG key [2] or a batch [{self.num_envs}, 2]; got shape {rng.shape}")


def make(name: str, num_envs: int, obs: str = "state", **make_kwargs: Any) -> BraxEnv:
    """`BraxEnv` over `bulbjax.make(name, num_envs, **make_kwargs)`. From state, pass
    `render=False` (no renderer, much faster)."""
    import bulbjax

    if obs not in BRAX_OBS_KINDS:
        raise ValueError(f"obs must be one of {BRAX_OBS_KINDS}, got {obs!r}")
    return BraxEnv(bulbjax.make(name, num_envs=num_envs, **make_kwargs), obs=obs)
