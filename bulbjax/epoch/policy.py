"""The policy side of an experiment: what PPO observes, its rollouts, and its training phase.

PPO observes the true state, the current frame, or a learner's latent of the current frame
(`ExperimentConfig.rl_input`); for a sequential learner, the latent of the current step in the
window of the last L steps ending at it (`PolicyHistory`, kept per world in the run state), unless
its latent is one frame's (ST-DIM), which PPO reads as a frame learner's. With
`rl_frames` K > 1, PPO on pixels or a latent of one frame observes the last K frames (stacked
along the channels) or their latents (concatenated), read from a `PolicyHistory` of K steps. A
rollout stores every step as (render input, true state, action features, done); a policy that
rendered its frames keeps them in place of the render inputs (`Rendered`), so the data side
gathers them instead of rendering the steps again.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from bulbjax.config import ExperimentConfig
from bulbjax.envs.base import EnvState
from bulbjax.epoch.devices import Devices
from bulbjax.epoch.seeds import Team
from bulbjax.epoch.state import PolicyHistory, PolicyView, PolicyWindow, Rendered, history_of
from bulbjax.learners import is_sequential, registration
from bulbjax.rl.ppo import PPO, PPOState, Transition


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
    expand = lambda a: a.reshape(a.shape + (1,) * (x.ndim - a.ndim))  # noqa: E731  [S, N, L] -> x's rank
    i = jnp.arange(l)[None, None, :]
    base = jnp.where(expand(full[..., None]), shifted, x)
    after = new[:, :, None] if pad_with_new else jnp.zeros_like(new)[:, :, None]
    out = jnp.where(expand(i == pos[..., None]), new[:, :, None], base)
    return jnp.where(expand(i > pos[..., None]), after, out).astype(x.dtype)


class Policy:
    """PPO over the worlds of `dev` (its network sized for what it observes), with the
    observations, rollouts and training phase of `config`; a learner's latent is read with that
    learner of `team`, each seed's current parameters, no gradient into it."""

    def __init__(self, config: ExperimentConfig, dev: Devices, team: Team):
        self.config, self.dev, self.team, self.env = config, dev, team, dev.env
        c, env = config, dev.env
        # Actions as the sequential learners see them: one-hot for discrete, the clipped vector else.
        self.action_dim = env.num_actions if env.discrete else env.action_size
        # PPO observes the true state, the frame (rl_input "pixels") or a learner's latent of it.
        self.rl_learner = c.rl_learner
        self.rl_pixels = c.rl_input == "pixels"
        # A sequential learner's latent is read from a window of the last L steps (PolicyHistory),
        # unless it is one frame's (ST-DIM: `Registration.frame_latent`), read as a frame learner's.
        self.rl_sequential = (self.rl_learner is not None and is_sequential(team.learners[self.rl_learner])
                              and not registration(self.rl_learner).frame_latent)
        # PPO on pixels or a frame learner's latent observes the last `rl_frames` frames
        self.rl_frames = c.rl_frames
        num_actions = env.num_actions if env.discrete else None
        if self.rl_pixels:
            h, w, ch = env.frame_shape
            self.ppo = PPO(c.ppo, 0, num_actions, env.action_size, frame_shape=(h, w, ch * self.rl_frames))
        elif self.rl_learner is None:
            self.ppo = PPO.for_env(c.ppo, env)
        else:
            params = self._abstract_learner_params(self.rl_learner)
            if self.rl_sequential:
                l = team.learners[self.rl_learner].sequence_length
                z = jax.eval_shape(self._window_latents, params,
                                   jax.ShapeDtypeStruct((1, l) + env.frame_shape, jnp.uint8),
                                   jax.ShapeDtypeStruct((1, l, self.action_dim), jnp.float32))
            else:
                z = jax.eval_shape(self._encode_frames, params,
                                   jax.ShapeDtypeStruct((1,) + env.frame_shape, jnp.uint8))
            self.ppo = PPO(c.ppo, z.shape[-1] * self.rl_frames, num_actions, env.action_size)

    @property
    def S(self) -> int:
        return self.dev.S

    @property
    def N(self) -> int:
        return self.dev.N

    @property
    def renders(self) -> bool:
        """Whether PPO observes frames (pixels or a learner's latent): its rollouts render every
        step's frame, and keep it for replay, windows and probes (`Rendered`)."""
        return self.rl_pixels or self.rl_learner is not None

    @property
    def keeps_history(self) -> bool:
        """Whether the worlds carry a `PolicyHistory` in the run state: PPO observes a sequential
        learner's latent (a window of L steps) or the last `rl_frames` > 1 frames."""
        return self.rl_sequential or self.rl_frames > 1

    def rl_learners(self, learners: dict) -> dict | None:
        """The learner states PPO's policy reads (its `rl_input` learner's), None when it reads none."""
        return None if self.rl_learner is None else {self.rl_learner: learners[self.rl_learner]}

    # ------------------------------------------------------------------ PPO's observation
    def _abstract_learner_params(self, name: str) -> Any:
        """Shapes of one seed's params of learner `name` (to size PPO's input)."""
        l = self.team.learners[name]
        return jax.eval_shape(lambda k: l.init(k, self.env.frame_shape), jax.random.PRNGKey(0)).params

    def _encode_frames(self, params: Any, frames: jax.Array) -> jax.Array:
        """The RL learner's latent of uint8 frames `[B, H, W, 3]` (one seed), without gradient
        into the learner: `encode` for a frame learner, `frame_features` for a sequential learner
        whose latent is one frame's (ST-DIM)."""
        learner = self.team.learners[self.rl_learner]
        encode = learner.frame_features if is_sequential(learner) else learner.encode
        return encode(jax.lax.stop_gradient(params), frames)

    def _window_latents(self, params: Any, frames: jax.Array, actions: jax.Array) -> jax.Array:
        """The sequential RL learner's per-step latents `[B, L, Z]` of windows given as frames
        `[B, L, H, W, 3]` and actions (one seed; sizes PPO's input)."""
        learner = self.team.learners[self.rl_learner]
        return learner.encode_features(params, learner.frame_features(params, frames), actions)

    def current_frames(self, es: EnvState) -> jax.Array:
        """Every world's current frame, per seed `[S, N, H, W, 3]` uint8 (rendered here)."""
        ri = jax.tree.map(lambda x: x[None], es.render_input)
        return self.dev.per_seed(self.dev.render_sequence(ri)[0])

    def history_start(self, es: EnvState) -> PolicyHistory:
        """The `PolicyHistory` of freshly reset worlds: their current frame alone (count 1), in a
        window of the sequential learner's L steps or of `rl_frames`."""
        frames = self.current_frames(es)
        l = self.team.learners[self.rl_learner].sequence_length if self.rl_sequential else self.rl_frames
        return PolicyHistory(
            frames=jnp.broadcast_to(frames[:, :, None], frames.shape[:2] + (l,) + frames.shape[2:]),
            actions=jnp.zeros((self.S, self.N, l, self.action_dim), jnp.float32),
            count=jnp.ones((self.S, self.N), jnp.int32))

    def _frame_features(self, learners: dict, frames: jax.Array) -> jax.Array:
        """The sequential RL learner's `frame_features` of per-seed frames `[S, N, T, H, W, 3]`
        -> `[S, N, T, F]`, each seed's current params, no gradient into the learner."""
        learner = self.team.learners[self.rl_learner]
        fn = lambda p, f: learner.frame_features(jax.lax.stop_gradient(p), f)  # noqa: E731
        return self.team.over_seeds(fn, learners[self.rl_learner].params, frames, learner=self.rl_learner)

    def window(self, learners: dict, history: PolicyHistory) -> PolicyWindow:
        """`history` with the features of its frames under the learners' current params: L conv
        passes per world, once per rollout (the params changed since the history was built)."""
        return PolicyWindow(history, self._frame_features(learners, history.frames))

    def _history_push(self, h: PolicyHistory, es: EnvState, frames: jax.Array, action: jax.Array) -> PolicyHistory:
        """The history after an env step: `es`'s frames `[S, N, H, W, 3]` appended with the
        actions that led into them `[S, N(, A)]`; a world whose step ended an episode (`es.done`:
        its frame is the next episode's first) starts its window over."""
        act = self.dev.per_seed(self.action_features(action))
        fresh = self.dev.per_seed(es.done) > 0
        return PolicyHistory(frames=push_window(h.frames, frames, h.count, fresh, True),
                             actions=push_window(h.actions, act, h.count, fresh, False),
                             count=jnp.where(fresh, 1, jnp.minimum(h.count + 1, h.frames.shape[2])).astype(jnp.int32))

    def _window_push(self, learners: dict, window: PolicyWindow, es: EnvState, frames: jax.Array,
                     action: jax.Array) -> PolicyWindow:
        """`_history_push` with the new frames' features (one conv pass each) appended alike."""
        h = window.history
        feats = self._frame_features(learners, frames[:, :, None])[:, :, 0]
        fresh = self.dev.per_seed(es.done) > 0
        return PolicyWindow(self._history_push(h, es, frames, action),
                            push_window(window.features, feats, h.count, fresh, True))

    def stacked_frames(self, h: PolicyHistory) -> jax.Array:
        """The last `rl_frames` K frames of every world, oldest first, the newest last `[S, N, K,
        H, W, 3]`: the window's steps before `count` read back from the end, its first step
        repeated where fewer than K are held (an episode's start)."""
        k = self.rl_frames
        idx = jnp.clip(h.count[..., None] - k + jnp.arange(k), 0, h.count[..., None] - 1)  # [S, N, K]
        idx = idx.reshape(idx.shape + (1,) * (h.frames.ndim - 3))
        return jnp.take_along_axis(h.frames, idx, axis=2)

    def _stacked_obs(self, learners: dict | None, h: PolicyHistory) -> jax.Array:
        """PPO's observation from the last K frames: stacked along the channels `[S, N, H, W,
        3K]` for pixels, else the frame learner's latents of them concatenated `[S, N, K*Z]`."""
        frames = self.stacked_frames(h)
        s, n, k = frames.shape[:3]
        if self.rl_pixels:
            return jnp.moveaxis(frames, 2, -2).reshape((s, n) + frames.shape[3:-1] + (k * frames.shape[-1],))
        if learners is None:
            raise ValueError("PPO observes a learner's latent: pass the learners' states")
        z = self.team.over_seeds(self._encode_frames, learners[self.rl_learner].params,
                                 frames.reshape((s, n * k) + frames.shape[3:]), learner=self.rl_learner)
        return z.reshape(s, n, -1)

    def _window_obs(self, learners: dict, window: PolicyWindow) -> jax.Array:
        """PPO's latent of every world `[S, N, Z]`: the sequential learner's per-step latent of
        its window at the current step (`count - 1`), each seed's current params."""
        learner = self.team.learners[self.rl_learner]

        def one_seed(params: Any, feats: jax.Array, actions: jax.Array, count: jax.Array) -> jax.Array:
            z = learner.encode_features(jax.lax.stop_gradient(params), feats, actions)  # [N, L, Z]
            return jnp.take_along_axis(z, (count - 1)[:, None, None], axis=1)[:, 0]

        h = window.history
        return self.team.over_seeds(one_seed, learners[self.rl_learner].params, window.features, h.actions,
                                    h.count, learner=self.rl_learner)

    def view(self, es: EnvState, learners: dict | None, history: PolicyHistory | None,
             random: bool) -> PolicyView:
        """What a rollout from `es` starts with (`PolicyView`): for a sequential learner the
        worlds' `history` with its features, for pixels or a frame learner the current frames
        (rendered here), None for the true state or the random policy."""
        if random or not self.renders:
            return None
        if self.keeps_history:
            if history is None:
                raise ValueError("PPO observes a sequential learner's latent or the last rl_frames frames: "
                                 "pass the worlds' PolicyHistory")
            return self.window(learners, history) if self.rl_sequential else history
        return self.current_frames(es)

    def obs(self, es: EnvState, learners: dict | None, view: PolicyView = None) -> jax.Array:
        """PPO's observation of every world, per seed `[S, N, ...]`: the true state; with
        `rl_input="pixels"` the world's current frame (uint8; `view`, or rendered here); with
        `rl_input="latent:<name>"` that learner's latent of the current frame, encoded with the
        seed's current parameters; for a sequential learner, its latent of the current step of
        the `view`'s window (the last L steps up to the current one, `PolicyHistory`)."""
        if self.rl_learner is None and not self.rl_pixels:
            return self.dev.per_seed(es.obs)
        if self.rl_sequential:
            if learners is None or not isinstance(view, PolicyWindow):
                raise ValueError("PPO observes a sequential learner's latent: pass the learners' "
                                 "states and the worlds' PolicyWindow")
            return self._window_obs(learners, view)
        if self.rl_frames > 1:
            if not isinstance(view, PolicyHistory):
                raise ValueError(f"PPO observes the last {self.rl_frames} frames: pass the worlds' PolicyHistory")
            return self._stacked_obs(learners, view)
        frames = self.current_frames(es) if view is None else view  # [S, N, H, W, 3]
        if self.rl_pixels:
            return frames
        if learners is None:
            raise ValueError("PPO observes a learner's latent: pass the learners' states")
        return self.team.over_seeds(self._encode_frames, learners[self.rl_learner].params, frames,
                                    learner=self.rl_learner)

    # ------------------------------------------------------------------ rollouts
    def step(self, ppo_state: PPOState, es: EnvState, key: jax.Array, random: bool,
             learners: dict | None = None, view: PolicyView = None):
        """One step of all worlds: PPO's observation, its action (or a random one), the env step.
        Returns `(next env state, obs, action, logp, value, view, stored)`: the `PolicyView`
        moved on to the next env state (its frames rendered here, once per step) and the step
        as rollouts store it (`_stored`)."""
        keys = self.team.seed_keys(key)
        if random:  # the random policy observes nothing: no frame is rendered for it
            obs = self.dev.per_seed(es.obs)
            action = jax.vmap(lambda k: self.ppo.random_act(k, self.N))(keys)
            logp = value = jnp.zeros((self.S, self.N))
        else:
            obs = self.obs(es, learners, view)
            action, logp, value = jax.vmap(self.ppo.act)(ppo_state, obs, keys)
        nes = self.dev.env_step(es, self.dev.flat(self.ppo.env_action(action)))
        frames = None
        if view is not None:
            frames = self.current_frames(nes)
            if self.rl_sequential:
                view = self._window_push(learners, view, nes, frames, action)
            elif self.rl_frames > 1:
                view = self._history_push(view, nes, frames, action)
            else:
                view = frames
        return nes, obs, action, logp, value, view, self._stored(nes, action, frames)

    def _stored(self, es: EnvState, action: jax.Array, frames: jax.Array | None) -> tuple:
        """A step as rollouts store it: (render input, or the `Rendered` frames where the policy
        rendered them, true state, action features, done), each `[S*N, ...]`."""
        ri = es.render_input if frames is None else Rendered(self.dev.flat(frames))
        return ri, es.lowdim, self.action_features(action), es.done

    def action_features(self, action: jax.Array) -> jax.Array:
        """Per-seed policy actions `[S, N(, A)]` -> float features `[S*N, A]` (one-hot if discrete)."""
        if self.env.discrete:
            return self.dev.flat(jax.nn.one_hot(action, self.action_dim, dtype=jnp.float32))
        return self.dev.flat(self.ppo.env_action(action).astype(jnp.float32))

    def rollout(self, ppo_state: PPOState, es: EnvState, key: jax.Array, steps: int, random: bool,
                learners: dict | None = None, history: PolicyHistory | None = None):
        """Run `steps` steps, storing (render inputs, true states, action features, dones), each
        `[steps, S*N, ...]`, unrendered (the random policy, PPO on the state). `learners`: for a
        policy that observes a latent; `history`: the worlds' `PolicyHistory` for one that
        observes a sequential learner's. A policy that observes frames keeps them in place of
        the render inputs (`Rendered`). Returns `((env state, history after the steps or None),
        stored)`."""
        view = self.view(es, learners, history, random)

        def body(carry, k):
            es, view = carry
            nes, _, _, _, _, view, stored = self.step(ppo_state, es, k, random, learners, view)
            return (nes, view), stored

        (es, view), stored = jax.lax.scan(body, (es, view), jax.random.split(key, steps))
        return (es, history_of(view)), stored

    # ------------------------------------------------------------------ PPO's training
    def rl_phase(self, ppo_state: PPOState, env_state: EnvState, key: jax.Array,
                 learners: dict | None = None, history: PolicyHistory | None = None):
        """PPO on the true state (or on a learner's latent, `learners` given; a sequential
        learner's also needs the worlds' `history`): rollouts of all seeds' worlds at once,
        per-seed updates.
        Returns the new PPO state, env state, update metrics, per-seed finished-episode return
        sum and count, the stored steps (render inputs, or the policy's frames: `_stored`; true
        states, action features, dones) `[U*T, S*N, ...]`, and the worlds' new `PolicyHistory`
        (None without one)."""
        c, per_seed = self.config, self.dev.per_seed
        view = self.view(env_state, learners, history, False)

        def rl_update(carry, k):
            ppo_state, es, view = carry
            k_roll, k_upd = jax.random.split(k)

            def step(carry, kk):
                es, view = carry
                nes, obs, action, logp, value, view, stored = self.step(ppo_state, es, kk, False,
                                                                        learners, view)
                tr = Transition(obs, action, per_seed(nes.reward), per_seed(nes.done),
                                per_seed(nes.truncated), logp, value)
                ep = (per_seed(nes.info["episode_return"] * nes.done).sum(1),
                      per_seed(nes.done).sum(1))
                return (nes, view), (tr, ep, stored)

            (es, view), (traj, ep, stored) = jax.lax.scan(step, (es, view),
                                                          jax.random.split(k_roll, c.ppo.num_steps))
            traj = jax.tree.map(lambda x: x.swapaxes(0, 1), traj)  # [S, T, N, ...]
            ppo_state, m = jax.vmap(self.ppo.update)(ppo_state, traj, self.obs(es, learners, view),
                                                    self.team.seed_keys(k_upd))
            return (ppo_state, es, view), (m, ep, stored)

        (ppo_state, env_state, view), (m, ep, stored) = jax.lax.scan(
            rl_update, (ppo_state, env_state, view), jax.random.split(key, c.ppo_updates_per_epoch))
        total = c.ppo_updates_per_epoch * c.ppo.num_steps
        steps = jax.tree.map(lambda x: x.reshape((total,) + x.shape[2:]), stored)
        return (ppo_state, env_state, jax.tree.map(lambda x: x.mean(0), m), ep[0].sum((0, 1)),
                ep[1].sum((0, 1)), steps, history_of(view))
