"""What PPO observes: one small class per observation mode (`--rl-input`, `--rl-frames`),
chosen once by `observation_for` when the `Policy` is built.

- `State`: the true state (`EnvState.obs`); nothing is rendered.
- `Pixels`: the world's current frame, through a conv encoder PPO trains end to end.
- `FrameLatent`: a frame learner's latent of the current frame (`encode`), or, for a sequential
  learner whose latent is one frame's (ST-DIM: `Registration.frame_latent`), its
  `frame_features`; each seed's current parameters, no gradient into the learner.
- `StackedFrames`: `Pixels` or `FrameLatent` of the last K frames (`rl_frames` K > 1: the frames
  stacked along the channels, or their latents concatenated), so that PPO can see velocities;
  the frames are kept in a `PolicyHistory` of K steps.
- `WindowLatent`: a sequential learner's latent of the current step in the window of its last L
  steps ending at it (`PolicyHistory` with the frames' features, `PolicyWindow`).

Each mode answers what a rollout asks of it: the PPO it feeds (`ppo`: sized for what it
observes), what a rollout carries from step to step (`view`, a `PolicyView`: None, the current
frames, a `PolicyHistory` or a `PolicyWindow`), PPO's observation of every world per seed
(`obs`), and that carry moved on to the next env state (`advance`). Why classes: the forms used
to be branches in every method of `Policy`; here a new `--rl-input` form is one class and one
line of `observation_for`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax
import jax.numpy as jnp

from bulbjax.config import ExperimentConfig
from bulbjax.envs.base import EnvState
from bulbjax.epoch.devices import Devices
from bulbjax.epoch.seeds import Team
from bulbjax.epoch.state import PolicyHistory, PolicyView, PolicyWindow
from bulbjax.learners import is_sequential, registration
from bulbjax.rl.ppo import PPO, PPOConfig


def push_window(x: jax.Array, new: jax.Array, count: jax.Array, fresh: jax.Array,
                pad_with_new: bool) -> jax.Array:
    """One step of a rolling window in training-window layout (see `PolicyHistory`).

    `x [S, N, L, ...]` holds `count [S, N]` steps then padding; `new [S, N, ...]` is the next
    step; `fresh [S, N]` says it starts a new episode (the window restarts at it). Returns the
    window with `new` appended after the steps held (the oldest step dropped once L are held)
    and the steps after it padded with `new` (`pad_with_new`: frames, features) or zeros
    (actions)."""
    l = x.shape[2]
    full = (count >= l) & ~fresh
    shifted = jnp.concatenate([x[:, :, 1:], new[:, :, None]], axis=2)
    pos = jnp.where(fresh, 0, jnp.minimum(count, l - 1))  # where `new` goes

    def expand(a: jax.Array) -> jax.Array:  # [S, N, L] -> x's rank
        return a.reshape(a.shape + (1,) * (x.ndim - a.ndim))

    i = jnp.arange(l)[None, None, :]
    base = jnp.where(expand(full[..., None]), shifted, x)
    after = new[:, :, None] if pad_with_new else jnp.zeros_like(new)[:, :, None]
    out = jnp.where(expand(i == pos[..., None]), new[:, :, None], base)
    return jnp.where(expand(i > pos[..., None]), after, out).astype(x.dtype)


def push_history(h: PolicyHistory, frames: jax.Array, act: jax.Array,
                 fresh: jax.Array) -> PolicyHistory:
    """The history after an env step: the new frames `[S, N, H, W, 3]` appended with the action
    features that led into them `[S, N, A]`; a world whose step ended an episode (`fresh [S, N]`:
    its frame is the next episode's first) starts its window over."""
    count = jnp.where(fresh, 1, jnp.minimum(h.count + 1, h.frames.shape[2])).astype(jnp.int32)
    return PolicyHistory(frames=push_window(h.frames, frames, h.count, fresh, True),
                         actions=push_window(h.actions, act, h.count, fresh, False), count=count)


def current_frames(dev: Devices, es: EnvState) -> jax.Array:
    """Every world's current frame, per seed `[S, N, H, W, 3]` uint8 (rendered here)."""
    ri = jax.tree.map(lambda x: x[None], es.render_input)
    return dev.per_seed(dev.render_sequence(ri)[0])


def _num_actions(dev: Devices) -> int | None:
    """PPO's discrete action count, None for a continuous action."""
    return dev.env.num_actions if dev.env.discrete else None


def _abstract_params(team: Team, dev: Devices, name: str) -> Any:
    """Shapes of one seed's params of learner `name` (to size PPO's input)."""
    learner = team.learners[name]
    init = lambda k: learner.init(k, dev.env.frame_shape)  # noqa: E731
    return jax.eval_shape(init, jax.random.PRNGKey(0)).params


def _need_learners(learners: dict | None) -> dict:
    """`learners`, refused where a latent is asked for without them."""
    if learners is None:
        raise ValueError("PPO observes a learner's latent: pass the learners' states")
    return learners


@dataclasses.dataclass(frozen=True, eq=False)
class Observation:
    """An observation mode: what a rollout asks of it. The defaults are those of a mode that
    renders nothing and carries nothing from step to step (`State`)."""

    dev: Devices
    team: Team
    renders: ClassVar[bool] = False  # whether rollouts render (and keep) every step's frame

    @property
    def history_length(self) -> int:
        """Steps of the `PolicyHistory` the worlds carry in the run state (0: none)."""
        return 0

    def ppo(self, config: PPOConfig) -> PPO:
        """PPO sized for what this mode observes."""
        raise NotImplementedError

    def view(self, es: EnvState, learners: dict | None,
             history: PolicyHistory | None) -> PolicyView:
        """What a rollout from `es` starts with (see `PolicyView`); `history`: the worlds'
        `PolicyHistory` in the run state, for a mode that keeps one."""
        return None

    def obs(self, es: EnvState, learners: dict | None, view: PolicyView) -> jax.Array:
        """PPO's observation of every world, per seed `[S, N, ...]`; `learners`: the learners'
        states, for a mode that reads a latent."""
        raise NotImplementedError

    def advance(self, learners: dict | None, view: PolicyView, es: EnvState, frames: jax.Array,
                act: jax.Array) -> PolicyView:
        """`view` moved on to the env state `es` after a step: `frames` its frames `[S, N, H, W,
        3]` (rendered by the policy once per step), `act` the step's action features `[S, N,
        A]`."""
        return view


@dataclasses.dataclass(frozen=True, eq=False)
class State(Observation):
    """The true state (`EnvState.obs` per seed), PPO sized for the env's observation."""

    def ppo(self, config: PPOConfig) -> PPO:
        return PPO.for_env(config, self.dev.env)

    def obs(self, es: EnvState, learners: dict | None, view: PolicyView) -> jax.Array:
        return self.dev.per_seed(es.obs)


@dataclasses.dataclass(frozen=True, eq=False)
class FrameObservation(Observation):
    """PPO reads the current frame (`Pixels`, `FrameLatent`): the view is every world's current
    frame `[S, N, H, W, 3]`; `read` / `read_stack` turn one frame or the last K frames into
    PPO's input, `ppo(config, frames=K)` sizes PPO for K frames."""

    renders: ClassVar[bool] = True

    def read(self, learners: dict | None, frames: jax.Array) -> jax.Array:
        """PPO's input from every world's current frame `[S, N, H, W, 3]`."""
        raise NotImplementedError

    def read_stack(self, learners: dict | None, frames: jax.Array) -> jax.Array:
        """PPO's input from every world's last K frames `[S, N, K, H, W, 3]`, oldest first."""
        raise NotImplementedError

    def view(self, es: EnvState, learners: dict | None,
             history: PolicyHistory | None) -> PolicyView:
        return current_frames(self.dev, es)

    def obs(self, es: EnvState, learners: dict | None, view: PolicyView) -> jax.Array:
        """PPO's input from the current frame (`view`, or rendered here)."""
        return self.read(learners, current_frames(self.dev, es) if view is None else view)

    def advance(self, learners: dict | None, view: PolicyView, es: EnvState, frames: jax.Array,
                act: jax.Array) -> PolicyView:
        return frames


@dataclasses.dataclass(frozen=True, eq=False)
class Pixels(FrameObservation):
    """The frames themselves (uint8): one `[S, N, H, W, 3]`, or K stacked along the channels."""

    def ppo(self, config: PPOConfig, frames: int = 1) -> PPO:
        env = self.dev.env
        h, w, ch = env.frame_shape
        return PPO(config, 0, _num_actions(self.dev), env.action_size,
                   frame_shape=(h, w, ch * frames))

    def read(self, learners: dict | None, frames: jax.Array) -> jax.Array:
        return frames

    def read_stack(self, learners: dict | None, frames: jax.Array) -> jax.Array:
        """`[S, N, K, H, W, 3]` -> `[S, N, H, W, 3K]`, oldest first along the channels."""
        s, n, k = frames.shape[:3]
        shape = (s, n) + frames.shape[3:-1] + (k * frames.shape[-1],)
        return jnp.moveaxis(frames, 2, -2).reshape(shape)


@dataclasses.dataclass(frozen=True, eq=False)
class FrameLatent(FrameObservation):
    """Learner `learner`'s latent of a frame, each seed's current params, no gradient into it:
    `encode` for a frame learner, `frame_features` for a sequential learner whose latent is one
    frame's (ST-DIM). K frames' latents are concatenated `[S, N, K*Z]`."""

    learner: str

    def encode(self, params: Any, frames: jax.Array) -> jax.Array:
        """The latent of uint8 frames `[B, H, W, 3]` (one seed)."""
        learner = self.team.learners[self.learner]
        encode = learner.frame_features if is_sequential(learner) else learner.encode
        return encode(jax.lax.stop_gradient(params), frames)

    def ppo(self, config: PPOConfig, frames: int = 1) -> PPO:
        params = _abstract_params(self.team, self.dev, self.learner)
        one = jax.ShapeDtypeStruct((1,) + self.dev.env.frame_shape, jnp.uint8)
        z = jax.eval_shape(self.encode, params, one)
        return PPO(config, z.shape[-1] * frames, _num_actions(self.dev), self.dev.env.action_size)

    def read(self, learners: dict | None, frames: jax.Array) -> jax.Array:
        params = _need_learners(learners)[self.learner].params
        return self.team.over_seeds(self.encode, params, frames, learner=self.learner)

    def read_stack(self, learners: dict | None, frames: jax.Array) -> jax.Array:
        """`[S, N, K, H, W, 3]` -> the K latents concatenated, oldest first `[S, N, K*Z]`."""
        s, n, k = frames.shape[:3]
        params = _need_learners(learners)[self.learner].params
        z = self.team.over_seeds(self.encode, params, frames.reshape((s, n * k) + frames.shape[3:]),
                                 learner=self.learner)
        return z.reshape(s, n, -1)


@dataclasses.dataclass(frozen=True, eq=False)
class StackedFrames(Observation):
    """`frame` (`Pixels` or `FrameLatent`) of the last `k` frames of every world's episode, the
    episode's first frame repeated until k are held; the frames are kept in a `PolicyHistory`
    of k steps (the view, carried in the run state)."""

    frame: FrameObservation
    k: int
    renders: ClassVar[bool] = True

    @property
    def history_length(self) -> int:
        return self.k

    def ppo(self, config: PPOConfig) -> PPO:
        return self.frame.ppo(config, self.k)

    def frames(self, h: PolicyHistory) -> jax.Array:
        """The last k frames of every world, oldest first, the newest last `[S, N, k, H, W, 3]`:
        the window's steps before `count` read back from the end, its first step repeated where
        fewer than k are held (an episode's start)."""
        k = self.k
        count = h.count[..., None]
        idx = jnp.clip(count - k + jnp.arange(k), 0, count - 1)  # [S, N, k]
        idx = idx.reshape(idx.shape + (1,) * (h.frames.ndim - 3))
        return jnp.take_along_axis(h.frames, idx, axis=2)

    def view(self, es: EnvState, learners: dict | None,
             history: PolicyHistory | None) -> PolicyView:
        if history is None:
            raise ValueError("PPO observes a sequential learner's latent or the last rl_frames "
                             "frames: pass the worlds' PolicyHistory")
        return history

    def obs(self, es: EnvState, learners: dict | None, view: PolicyView) -> jax.Array:
        if not isinstance(view, PolicyHistory):
            raise ValueError(f"PPO observes the last {self.k} frames: pass the worlds' "
                             "PolicyHistory")
        return self.frame.read_stack(learners, self.frames(view))

    def advance(self, learners: dict | None, view: PolicyView, es: EnvState, frames: jax.Array,
                act: jax.Array) -> PolicyView:
        return push_history(view, frames, act, self.dev.per_seed(es.done) > 0)


@dataclasses.dataclass(frozen=True, eq=False)
class WindowLatent(Observation):
    """Sequential learner `learner`'s per-step latent of the current step in the window of the
    last L steps ending at it (its `sequence_length`; a `PolicyHistory` carried in the run
    state), each seed's current params, no gradient into it. The view is a `PolicyWindow`: the
    history with its frames' `frame_features`, computed for the whole window once per rollout
    (the params changed since) and for each new frame once per step."""

    learner: str
    action_dim: int  # the action features' width (one-hot for discrete actions)
    renders: ClassVar[bool] = True

    @property
    def history_length(self) -> int:
        return self.team.learners[self.learner].sequence_length

    def ppo(self, config: PPOConfig) -> PPO:
        learner, l = self.team.learners[self.learner], self.history_length

        def latents(params: Any, frames: jax.Array, actions: jax.Array) -> jax.Array:
            return learner.encode_features(params, learner.frame_features(params, frames), actions)

        z = jax.eval_shape(latents, _abstract_params(self.team, self.dev, self.learner),
                           jax.ShapeDtypeStruct((1, l) + self.dev.env.frame_shape, jnp.uint8),
                           jax.ShapeDtypeStruct((1, l, self.action_dim), jnp.float32))
        return PPO(config, z.shape[-1], _num_actions(self.dev), self.dev.env.action_size)

    def features(self, learners: dict, frames: jax.Array) -> jax.Array:
        """The learner's `frame_features` of per-seed frames `[S, N, T, H, W, 3]` -> `[S, N, T,
        F]`, each seed's current params, no gradient into the learner."""
        learner = self.team.learners[self.learner]
        fn = lambda p, f: learner.frame_features(jax.lax.stop_gradient(p), f)  # noqa: E731
        return self.team.over_seeds(fn, learners[self.learner].params, frames,
                                    learner=self.learner)

    def window(self, learners: dict, history: PolicyHistory) -> PolicyWindow:
        """`history` with the features of its frames under the learners' current params: L conv
        passes per world, once per rollout."""
        return PolicyWindow(history, self.features(learners, history.frames))

    def view(self, es: EnvState, learners: dict | None,
             history: PolicyHistory | None) -> PolicyView:
        if history is None:
            raise ValueError("PPO observes a sequential learner's latent or the last rl_frames "
                             "frames: pass the worlds' PolicyHistory")
        return self.window(learners, history)

    def obs(self, es: EnvState, learners: dict | None, view: PolicyView) -> jax.Array:
        """The latent at the window's current step (`count - 1`) `[S, N, Z]`."""
        if learners is None or not isinstance(view, PolicyWindow):
            raise ValueError("PPO observes a sequential learner's latent: pass the learners' "
                             "states and the worlds' PolicyWindow")
        learner = self.team.learners[self.learner]

        def one_seed(params: Any, feats: jax.Array, actions: jax.Array,
                     count: jax.Array) -> jax.Array:
            z = learner.encode_features(jax.lax.stop_gradient(params), feats, actions)  # [N, L, Z]
            return jnp.take_along_axis(z, (count - 1)[:, None, None], axis=1)[:, 0]

        h = view.history
        return self.team.over_seeds(one_seed, learners[self.learner].params, view.features,
                                    h.actions, h.count, learner=self.learner)

    def advance(self, learners: dict | None, view: PolicyView, es: EnvState, frames: jax.Array,
                act: jax.Array) -> PolicyView:
        """The history pushed (`push_history`) and the new frames' features (one conv pass
        each) appended alike."""
        h = view.history
        feats = self.features(learners, frames[:, :, None])[:, :, 0]
        fresh = self.dev.per_seed(es.done) > 0
        return PolicyWindow(push_history(h, frames, act, fresh),
                            push_window(view.features, feats, h.count, fresh, True))


def observation_for(config: ExperimentConfig, dev: Devices, team: Team,
                    action_dim: int) -> Observation:
    """The mode of `config.rl_input` and `config.rl_frames` (checked by `ExperimentConfig`): the
    state, pixels, a learner's latent of one frame or of a window, and K > 1 frames stacked."""
    name = config.rl_learner
    if config.rl_input == "pixels":
        frame: FrameObservation = Pixels(dev, team)
    elif name is None:
        return State(dev, team)
    elif is_sequential(team.learners[name]) and not registration(name).frame_latent:
        return WindowLatent(dev, team, name, action_dim)
    else:
        frame = FrameLatent(dev, team, name)
    return frame if config.rl_frames == 1 else StackedFrames(dev, team, frame, config.rl_frames)
