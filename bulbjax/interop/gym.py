"""gymnasium adapters for bulbjax environments: `make_vec` (a `gymnasium.vector.VectorEnv` over
one batched bulbjax env) and `GymEnv` / `make_env` (a single-world `gymnasium.Env`).

Why: most RL code (Stable-Baselines3, CleanRL, hand-written loops) speaks gymnasium. The bulbjax
env stays one jitted, batched program; the adapter moves one pytree of numpy arrays to the host
per step (`jax.device_get` of the observation, the other view, rewards and flags).

Observations: `obs="pixels"` (uint8 frames `[H, W, 3]` per world; the true state in
`info["state"]`) or `obs="state"` (float32 true state `[D]`; frames in `info["pixels"]` when the
env renders them).

Auto-reset. A bulbjax env resets a world inside the step that ends its episode, so the state it
returns already shows the next episode. The adapter recovers the last observation of the ended
episode by replaying that world's physics step (`env.physics`, the first half of `env.step`,
deterministic for the same inputs) in a second jitted call made only on steps where some episode
ended, and renders its frame with `env.render_frames`. Two modes (`metadata["autoreset_mode"]`):
- `"next_step"` (gymnasium 1.x's default, `AutoresetMode.NEXT_STEP`): the step that ends an
  episode returns its last observation with `terminated`/`truncated`; the next `step` returns the
  new episode's first observation with reward 0 and both flags False, ignoring that world's action
  (the world is held at its reset state for that call, so the episode that follows is exactly the
  one bulbjax would have played).
- `"same_step"` (`AutoresetMode.SAME_STEP`, bulbjax's own): the step that ends an episode returns
  the new episode's first observation; the last one is in `info["final_obs"]` (an object array,
  None where no episode ended) and the ended episode's info in `info["final_info"]`.

Actions: shape and dtype as `action_space` says (the vector env also takes `[N]` for a
one-dimensional Box); an action outside the space, NaN included, is refused with `InvalidAction`
(gymnasium's `gymnasium.error.InvalidAction`, also a ValueError), naming the space.

Info (vector env; every key `k` comes with a boolean mask `_k`, gymnasium's convention): the
other view (`state` or `pixels`), and where an episode ended `episode_return` / `episode_length`.

Registration: importing this module (or `bulbjax.gym`) registers every domain with gymnasium as
`bulbjax/<Name>-v0` (`register_envs`).

Seeding: `reset(seed=s)` starts every world from `jax.random.PRNGKey(s)` exactly as
`env.reset(jax.random.PRNGKey(s))` would (one key for all worlds: a list of per-world seeds is
refused); `reset()` without a seed draws the key from the adapter's `np_random`, itself seeded
by the last seed given.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

try:
    import gymnasium
    from gymnasium import spaces
    from gymnasium.utils import seeding
    from gymnasium.vector import AutoresetMode, VectorEnv
    from gymnasium.vector.utils import batch_space
except ImportError as e:  # pragma: no cover - depends on the install
    raise ImportError("bulbjax.gym needs gymnasium: pip install 'bulbjax[gym]' (or pip install gymnasium)") from e

import bulbjax
from bulbjax.envs.base import EnvState, MjxPixelEnv, RenderInput
from bulbjax.envs.batch import where_tree
from bulbjax.envs.registry import env_class

OBS_KINDS = ("pixels", "state")
AUTORESET_MODES = {"next_step": AutoresetMode.NEXT_STEP, "same_step": AutoresetMode.SAME_STEP}
_OTHER = {"pixels": "state", "state": "pixels"}
_MAX_SEED = 2**31 - 1


@dataclass(frozen=True)
class AdapterConfig:
    """What the adapter reports: observation kind and autoreset mode."""

    obs: str = "pixels"
    autoreset_mode: str = "next_step"

    def __post_init__(self) -> None:
        if self.obs not in OBS_KINDS:
            raise ValueError(f"obs must be one of {OBS_KINDS}, got {self.obs!r}")
        if self.autoreset_mode not in AUTORESET_MODES:
            raise ValueError(f"autoreset_mode must be one of {tuple(AUTORESET_MODES)}, got {self.autoreset_mode!r}")


class _Core:
    """Jitted reset / step / last-observation functions over one bulbjax env, and the host-side
    action checks shared by the vector and the single env."""

    def __init__(self, env: MjxPixelEnv, obs: str, single: bool = False):
        if obs not in OBS_KINDS:
            raise ValueError(f"obs must be one of {OBS_KINDS}, got {obs!r}")
        self.env = env
        self.obs = obs
        self.frames = bool(env.config.render and env.config.render_steps
                           and env.config.observation in ("rgb", "depth"))
        if obs == "pixels" and not self.frames:
            raise ValueError(f'obs="pixels" needs an env that renders frames every step (render=True or "rgb"/"depth"); '
                             f'{env.name} was made with render={env.config.render!r}, observation='
                             f'{env.config.observation!r}: use obs="state" or make it with render=True')
        self.num_envs = env.num_envs
        self.single = single  # a `GymEnv`: messages name no world
        self.reset = jax.jit(env.reset)
        self.step = jax.jit(self._step)
        self.last = jax.jit(self._last)
        self.select = jax.jit(lambda mask, a, b: where_tree(mask, a, b))

    # ----- spaces -----
    def single_observation_space(self) -> spaces.Box:
        if self.obs == "pixels":
            return spaces.Box(0, 255, self.env.frame_shape, np.uint8)
        return spaces.Box(-np.inf, np.inf, (self.env.state_dim,), np.float32)

    def single_action_space(self) -> spaces.Space:
        if self.env.discrete:
            return spaces.Discrete(int(self.env.num_actions))
        return spaces.Box(-1.0, 1.0, (self.env.action_size,), np.float32)

    # ----- jitted pieces -----
    def views(self, s: EnvState) -> dict[str, jax.Array]:
        out = {"state": s.lowdim}
        if self.frames:
            out["pixels"] = s.pixels
        return out

    def _step(self, state: EnvState, action: jax.Array, hold: jax.Array) -> tuple[EnvState, dict[str, Any]]:
        """`env.step` for every world except those in `hold`, which keep their state (NEXT_STEP:
        a world whose episode ended last call shows its reset observation now)."""
        new = self.env.step(state, action)
        new = where_tree(hold, state, new)
        zero = jnp.zeros_like(new.reward)
        out = self.views(new)
        out.update(reward=jnp.where(hold, zero, new.reward), done=jnp.where(hold, zero, new.done),
                   truncated=jnp.where(hold, zero, new.truncated),
                   episode_return=new.info["episode_return"], episode_length=new.info["episode_length"])
        return new, out

    def _last(self, state: EnvState, action: jax.Array) -> dict[str, jax.Array]:
        """The observations `env.step(state, action)` would show without its auto-reset: the
        physics step replayed, its state and (if rendering) its frame. A world whose physics went
        non-finite in that step (`env.step` reset it) shows its observation before the step
        instead: NaN never reaches the caller."""
        data = self.env.physics(state.data, self.env._repair_action(action)[0], state.params)
        lowdim = self.env._lowdim_batch(data, state.params)
        finite = (jnp.isfinite(data.qpos).all(1) & jnp.isfinite(data.qvel).all(1)
                  & jnp.isfinite(lowdim).all(1))
        out = {"state": jnp.where(finite[:, None], lowdim, state.lowdim)}
        if self.frames:
            qpos = jnp.where(finite[:, None], data.qpos, state.data.qpos)
            ri = RenderInput(qpos=qpos, scheme=state.scheme, mocap_pos=data.mocap_pos,
                             mocap_quat=data.mocap_quat)
            out["pixels"] = jnp.where(finite[:, None, None, None], self.env.render_frames(ri), state.pixels)
        return out

    # ----- host side -----
    def action(self, actions: Any) -> np.ndarray:
        """Validated batch of actions as the bulbjax env takes them (int32 `[N]` or float32 `[N, A]`)."""
        a = np.asarray(actions)
        n, env = self.num_envs, self.env
        if env.discrete:
            if a.shape == (n, 1):
                a = a[:, 0]
            number = np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)
            if a.shape != (n,) or not number:
                shape = "one integer action" if self.single else f"integer actions of shape ({n},)"
                raise ValueError(f"{env.name} takes {shape} in [0, {env.num_actions}); got {a.dtype} "
                                 f"{a.shape}")
            with np.errstate(invalid="ignore"):
                ok = (a >= 0) & (a < env.num_actions) & (np.mod(a, 1) == 0)  # NaN fails each
            if not ok.all():
                rule = f"not an integer in [0, {env.num_actions})"
                fix = f"{env.name}'s actions are integers in [0, {env.num_actions})"
                raise InvalidAction(self._invalid(a[~ok][0].item(), np.flatnonzero(~ok), rule, fix))
            return a.astype(np.int32)
        if a.shape == (n,) and env.action_size == 1:
            a = a[:, None]
        if a.shape != (n, env.action_size) or not np.issubdtype(a.dtype, np.number):
            raise ValueError(f"{env.name} takes float actions of shape ({n}, {env.action_size}) in [-1, 1]; "
                             f"got {a.dtype} {a.shape}")
        outside = ~(np.abs(a.astype(np.float64)) <= 1.0)  # NaN too
        if outside.any():
            w = np.flatnonzero(outside.any(axis=1))
            raise InvalidAction(self._invalid(a[w[0]].tolist(), w, "NaN or outside [-1, 1]",
                                              "clip to [-1, 1] before stepping"))
        return a.astype(np.float32)

    def _invalid(self, value: Any, worlds: np.ndarray, rule: str, fix: str) -> str:
        """The one-line message of an action outside the space: the first bad value, its world
        and how many worlds (a vector env), the space and what to do."""
        where = "" if self.single else f" (world {worlds[0]}; {len(worlds)} world(s) {rule})"
        return (f"you passed the invalid action `{value}`{where}. The supported action_space is "
                f"`{self.single_action_space()}`: {fix}")


class InvalidAction(gymnasium.error.InvalidAction, ValueError):
    """An action outside the adapter's action space (NaN included): gymnasium's own error for
    that (`gymnasium.error.InvalidAction`, as CarRacing raises it), also a ValueError like the
    adapter's other input errors. gymnasium's classic-control envs `assert
    action_space.contains(action)` instead; an assert vanishes under `python -O`, this does not.
    (`env.step` itself clips such actions and counts them; the adapters refuse them, so a bug
    upstream is seen rather than silently clipped.)"""


def _key_from(seed: int | None, rng: np.random.Generator) -> jax.Array:
    return jax.random.PRNGKey(int(seed) if seed is not None else int(rng.integers(0, _MAX_SEED)))


def _fps(env: MjxPixelEnv) -> int:
    return int(round(1.0 / (float(env.mj_model.opt.timestep) * env.frame_skip)))


class BulbjaxVectorEnv(VectorEnv):
    """A `gymnasium.vector.VectorEnv` over one batched bulbjax env (see the module docstring)."""

    def __init__(self, env: MjxPixelEnv, obs: str = "pixels", autoreset_mode: str = "next_step",
                 render_mode: str | None = None):
        cfg = AdapterConfig(obs=obs, autoreset_mode=autoreset_mode)
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f'render_mode must be None or "rgb_array", got {render_mode!r}')
        self.core = _Core(env, cfg.obs)
        if render_mode == "rgb_array" and not self.core.frames:
            raise ValueError('render_mode="rgb_array" needs an env made with render=True')
        self.bulbjax_env = env
        self.config = cfg
        self.num_envs = env.num_envs
        self.render_mode = render_mode
        self.metadata = {"autoreset_mode": AUTORESET_MODES[cfg.autoreset_mode], "render_modes": ["rgb_array"],
                         "render_fps": _fps(env)}
        self.single_observation_space = self.core.single_observation_space()
        self.single_action_space = self.core.single_action_space()
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._state: EnvState | None = None
        self._hold = np.zeros(self.num_envs, bool)
        self._last_views: dict[str, np.ndarray] = {}

    @property
    def state(self) -> EnvState:
        """The bulbjax state (device arrays) after the last call."""
        if self._state is None:
            raise RuntimeError("call reset() first")
        return self._state

    def reset(self, *, seed: int | Sequence[int] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset every world (or those in `options["reset_mask"]`, a bool array `[N]`)."""
        if seed is not None and not isinstance(seed, (int, np.integer)):
            raise ValueError("a bulbjax vector env draws all worlds from one key: pass one int seed, "
                             f"not {type(seed).__name__}")
        if seed is not None:
            self._np_random, self._np_random_seed = seeding.np_random(int(seed))
        fresh = self.core.reset(_key_from(seed, self.np_random))
        mask = (options or {}).get("reset_mask")
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
                raise ValueError(f'options["reset_mask"] must be a bool array of shape ({self.num_envs},)')
            if self._state is None:
                raise RuntimeError("reset_mask needs a previous full reset")
            fresh = self.core.select(jnp.asarray(mask), fresh, self._state)
            self._hold = self._hold & ~mask
        else:
            self._hold = np.zeros(self.num_envs, bool)
        self._state = fresh
        views = jax.device_get(self.core.views(fresh))
        views = {k: np.array(v) for k, v in views.items()}
        self._last_views = views
        return views[self.config.obs], self._view_info(views)

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        a = self.core.action(actions)
        prev = self._state
        hold = self._hold if self.config.autoreset_mode == "next_step" else np.zeros(self.num_envs, bool)
        self._state, out = self.core.step(prev, a, hold)
        out = {k: np.array(v) for k, v in jax.device_get(out).items()}
        done = out["done"] > 0
        truncated = out["truncated"] > 0
        terminated = done & ~truncated
        views = {k: out[k] for k in ("state", "pixels") if k in out}
        info = self._view_info(views)
        if done.any():
            info.update(_masked({"episode_return": np.where(done, out["episode_return"], 0).astype(np.float32),
                                 "episode_length": np.where(done, out["episode_length"], 0).astype(np.int32)},
                                done))
            last = {k: np.array(v) for k, v in jax.device_get(self.core.last(prev, a)).items()}
            if self.config.autoreset_mode == "next_step":
                for k in views:  # the ended episodes' last observation, in obs and info alike
                    views[k][done] = last[k][done]
                info = {**info, **self._view_info(views)}
            else:
                final_obs = np.full(self.num_envs, None, dtype=object)
                for i in np.flatnonzero(done):
                    final_obs[i] = last[self.config.obs][i]
                final_info = _masked({_OTHER[self.config.obs]: last[_OTHER[self.config.obs]]}, done) \
                    if _OTHER[self.config.obs] in last else {}
                final_info.update(_masked({"episode_return": info["episode_return"],
                                           "episode_length": info["episode_length"]}, done))
                info.update(final_obs=final_obs, _final_obs=done.copy(), final_info=final_info,
                            _final_info=done.copy())
        self._hold = done
        self._last_views = views
        return (views[self.config.obs], out["reward"].astype(np.float32), terminated, truncated, info)

    def render(self) -> tuple[np.ndarray, ...] | None:
        """The last frames, one per world (`render_mode="rgb_array"`; without it None and a
        warning, gymnasium's convention)."""
        if self.render_mode is None:
            _warn_no_render_mode("make_vec")
            return None
        return tuple(self._last_views["pixels"])

    def _view_info(self, views: dict[str, np.ndarray]) -> dict[str, Any]:
        other = _OTHER[self.config.obs]
        if other not in views:
            return {}
        return _masked({other: views[other]}, np.ones(self.num_envs, bool))


def _warn_no_render_mode(maker: str) -> None:
    """What gymnasium's own envs do when `render()` is called without a render mode: a warning
    (render() then returns None)."""
    gymnasium.logger.warn('render() returns frames only with render_mode="rgb_array": make the env '
                          f'with {maker}(..., render_mode="rgb_array") (or gymnasium.make(..., '
                          'render_mode="rgb_array"))')


def _masked(values: dict[str, np.ndarray], mask: np.ndarray) -> dict[str, Any]:
    """gymnasium's vector info layout: each key with its boolean mask `_key`."""
    out: dict[str, Any] = {}
    for k, v in values.items():
        out[k] = v
        out["_" + k] = mask.copy()
    return out


class GymEnv(gymnasium.Env):
    """A single-world `gymnasium.Env` over a bulbjax env made with `num_envs=1`.

    A step that ends the episode returns its last observation; the next `reset()` starts a new
    one (stepping on without a reset continues from the episode bulbjax already started)."""

    def __init__(self, env: MjxPixelEnv, obs: str = "pixels", render_mode: str | None = None):
        if env.num_envs != 1:
            raise ValueError(f"GymEnv wraps a bulbjax env with num_envs=1 (got {env.num_envs}); "
                             "use make_vec for batches")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f'render_mode must be None or "rgb_array", got {render_mode!r}')
        self.core = _Core(env, AdapterConfig(obs=obs).obs, single=True)
        if render_mode == "rgb_array" and not self.core.frames:
            raise ValueError('render_mode="rgb_array" needs an env made with render=True')
        self.bulbjax_env = env
        self.obs_kind = obs
        self.render_mode = render_mode
        self.metadata = {"render_modes": ["rgb_array"], "render_fps": _fps(env)}
        self.observation_space = self.core.single_observation_space()
        self.action_space = self.core.single_action_space()
        self._state: EnvState | None = None
        self._views: dict[str, np.ndarray] = {}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self._state = self.core.reset(_key_from(seed, self.np_random))
        self._views = {k: np.array(v)[0] for k, v in jax.device_get(self.core.views(self._state)).items()}
        return self._views[self.obs_kind].copy(), self._info(self._views)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action)
        if self.core.env.discrete:
            if a.shape not in ((), (1,)):
                raise ValueError(f"{self.core.env.name} takes one integer action, got shape {a.shape}")
        elif a.shape not in ((self.core.env.action_size,), ()) or (a.shape == () and self.core.env.action_size != 1):
            raise ValueError(f"{self.core.env.name} takes an action of shape ({self.core.env.action_size},), "
                             f"got {a.shape}")
        a = self.core.action(a.reshape((1, -1)) if not self.core.env.discrete else a.reshape((1,)))
        prev = self._state
        self._state, out = self.core.step(prev, a, np.zeros(1, bool))
        out = {k: np.array(v)[0] for k, v in jax.device_get(out).items()}
        done, truncated = bool(out["done"] > 0), bool(out["truncated"] > 0)
        views = {k: out[k] for k in ("state", "pixels") if k in out}
        info: dict[str, Any] = {}
        if done:
            views = {k: np.array(v)[0] for k, v in jax.device_get(self.core.last(prev, a)).items()}
            info = {"episode_return": float(out["episode_return"]), "episode_length": int(out["episode_length"])}
        self._views = views
        return (views[self.obs_kind].copy(), float(out["reward"]), done and not truncated, truncated,
                {**self._info(views), **info})

    def render(self) -> np.ndarray | None:
        """The current frame (`render_mode="rgb_array"`; without it None and a warning,
        gymnasium's convention)."""
        if self.render_mode is None:
            _warn_no_render_mode("make_env")
            return None
        if "pixels" not in self._views:
            raise RuntimeError("call reset() before render()")
        return self._views["pixels"].copy()

    def _info(self, views: dict[str, np.ndarray]) -> dict[str, Any]:
        other = _OTHER[self.obs_kind]
        return {other: views[other].copy()} if other in views else {}


def make_vec(name: str, num_envs: int, obs: str = "pixels", autoreset_mode: str = "next_step",
             render_mode: str | None = None, **make_kwargs: Any) -> BulbjaxVectorEnv:
    """A gymnasium vector env of `num_envs` worlds of bulbjax domain `name`.

    `obs`: "pixels" (frames) or "state" (true state); the other view is in `info`. With
    `obs="state"`, `render=False` among `make_kwargs` skips rendering altogether (faster).
    `make_kwargs` go to `bulbjax.make` (resolution, render, multicolour, version, ...)."""
    AdapterConfig(obs=obs, autoreset_mode=autoreset_mode)  # fail before building the env
    return BulbjaxVectorEnv(bulbjax.make(name, num_envs=num_envs, **make_kwargs), obs=obs,
                            autoreset_mode=autoreset_mode, render_mode=render_mode)


def make_env(name: str, obs: str = "pixels", render_mode: str | None = None, **make_kwargs: Any) -> GymEnv:
    """A single-world `gymnasium.Env` of bulbjax domain `name` (`make_kwargs` as in `make_vec`)."""
    AdapterConfig(obs=obs)
    return GymEnv(bulbjax.make(name, num_envs=1, **make_kwargs), obs=obs, render_mode=render_mode)


def register_envs(prefix: str = "bulbjax") -> list[str]:
    """Register every bulbjax domain with gymnasium as `<prefix>/<Name>-v0` (single env through
    `gymnasium.make`, vector env through `gymnasium.make_vec(...,
    vectorization_mode="vector_entry_point")`), with the domain's episode length as the spec's `max_episode_steps`. Importing this module
    (or `bulbjax.gym`) already did it with the default prefix."""
    ids = []
    for name in bulbjax.env_names():
        env_id = f"{prefix}/{name}-v0"
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point=_entry(name), vector_entry_point=_vector_entry(name),
                               max_episode_steps=env_class(name).episode_length,
                               nondeterministic=False)
        ids.append(env_id)
    return ids


def _entry(name: str):
    def make(**kwargs: Any) -> GymEnv:
        return make_env(name, **kwargs)
    return make


def _vector_entry(name: str):
    def make(num_envs: int = 1, max_episode_steps: int | None = None,
             **kwargs: Any) -> BulbjaxVectorEnv:
        # gymnasium.make_vec hands over the spec's max_episode_steps: a bulbjax env truncates its
        # episodes itself, at the domain's length, and a vector env has no TimeLimit to wrap it in
        length = env_class(name).episode_length
        if max_episode_steps not in (None, length):
            raise ValueError(f"bulbjax/{name} vector envs truncate episodes at the domain's "
                             f"{length} steps; max_episode_steps={max_episode_steps} is not "
                             "supported (leave it out)")
        return make_vec(name, num_envs, **kwargs)
    return make


register_envs()
