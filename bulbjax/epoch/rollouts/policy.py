"""The policy side of an experiment: what PPO observes, its rollouts, and its training phase.

PPO observes the true state, the current frame, or a learner's latent of the current frame
(`ExperimentConfig.rl_input`); for a sequential learner, the latent of the current step in the
window of the last L steps ending at it (`PolicyHistory`, kept per world in the run state), unless
its latent is one frame's (ST-DIM), which PPO reads as a frame learner's. With `rl_frames` K > 1,
PPO on pixels or a latent of one frame observes the last K frames (stacked along the channels) or
their latents (concatenated), read from a `PolicyHistory` of K steps. Each of these modes is one
class of `observations.py`, chosen once when the `Policy` is built; the rollouts here ask it for
PPO's observation and for what a rollout carries from step to step, whatever the mode. A
rollout stores every step as (render input, true state, action features, done); a policy that
rendered its frames keeps them in place of the render inputs (`Rendered`), so the data side
gathers them instead of rendering the steps again.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from bulbjax.config import ExperimentConfig
from bulbjax.envs.base import EnvState
from bulbjax.epoch.devices import Devices
from bulbjax.epoch.rollouts.observations import (Observation, WindowLatent, current_frames,
                                        observation_for, push_window)
from bulbjax.epoch.seeds import Team
from bulbjax.epoch.state import PolicyHistory, PolicyView, PolicyWindow, Rendered, history_of
from bulbjax.rl.ppo import PPOState, Transition

__all__ = ["Policy", "push_window"]  # push_window: the rolling window, kept where tests import it


class Policy:
    """PPO over the worlds of `dev` (its network sized for what it observes), with the
    observations, rollouts and training phase of `config`; a learner's latent is read with that
    learner of `team`, each seed's current parameters, no gradient into it."""

    def __init__(self, config: ExperimentConfig, dev: Devices, team: Team):
        self.config, self.dev, self.team, self.env = config, dev, team, dev.env
        env = dev.env
        # Actions as the sequential learners see them: one-hot for discrete, the clipped vector
        # else.
        self.action_dim = env.num_actions if env.discrete else env.action_size
        # What PPO observes (`observations.py`), chosen once: the state, pixels, a learner's
        # latent of one frame or of a window, or the last `rl_frames` frames of either.
        self.observation: Observation = observation_for(config, dev, team, self.action_dim)
        self.rl_learner = config.rl_learner
        # PPO reads a sequential learner's latent of a window (not one frame's, as ST-DIM's)
        self.rl_sequential = isinstance(self.observation, WindowLatent)
        self.ppo = self.observation.ppo(config.ppo)

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
        return self.observation.renders

    @property
    def keeps_history(self) -> bool:
        """Whether the worlds carry a `PolicyHistory` in the run state: PPO observes a sequential
        learner's latent (a window of L steps) or the last `rl_frames` > 1 frames."""
        return self.observation.history_length > 0

    def rl_learners(self, learners: dict) -> dict | None:
        """The learner states PPO's policy reads (its `rl_input` learner's), None when it reads
        none."""
        return None if self.rl_learner is None else {self.rl_learner: learners[self.rl_learner]}

    # ------------------------------------------------------------------ PPO's observation
    def history_start(self, es: EnvState) -> PolicyHistory:
        """The `PolicyHistory` of freshly reset worlds: their current frame alone (count 1), in a
        window of the sequential learner's L steps or of `rl_frames`."""
        frames = current_frames(self.dev, es)
        l = self.observation.history_length
        return PolicyHistory(
            frames=jnp.broadcast_to(frames[:, :, None], frames.shape[:2] + (l,) + frames.shape[2:]),
            actions=jnp.zeros((self.S, self.N, l, self.action_dim), jnp.float32),
            count=jnp.ones((self.S, self.N), jnp.int32))

    def window(self, learners: dict, history: PolicyHistory) -> PolicyWindow:
        """For PPO on a sequential learner's latent: `history` with the features of its frames
        under the learners' current params (`WindowLatent.window`)."""
        return self.observation.window(learners, history)

    def view(self, es: EnvState, learners: dict | None, history: PolicyHistory | None,
             random: bool) -> PolicyView:
        """What a rollout from `es` starts with (`PolicyView`): for a sequential learner the
        worlds' `history` with its features, for the last `rl_frames` frames the `history`, for
        pixels or a frame learner the current frames (rendered here), None for the true state
        or the random policy."""
        if random or not self.renders:
            return None
        return self.observation.view(es, learners, history)

    def obs(self, es: EnvState, learners: dict | None, view: PolicyView = None) -> jax.Array:
        """PPO's observation of every world, per seed `[S, N, ...]`: the true state; with
        `rl_input="pixels"` the world's current frame (uint8; `view`, or rendered here); with
        `rl_input="latent:<name>"` that learner's latent of the current frame, encoded with the
        seed's current parameters; for a sequential learner, its latent of the current step of
        the `view`'s window (the last L steps up to the current one, `PolicyHistory`)."""
        return self.observation.obs(es, learners, view)

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
        act = self.action_features(action)
        frames = None
        if view is not None:
            frames = current_frames(self.dev, nes)
            view = self.observation.advance(learners, view, nes, frames, self.dev.per_seed(act))
        return nes, obs, action, logp, value, view, self._stored(nes, act, frames)

    def _stored(self, es: EnvState, act: jax.Array, frames: jax.Array | None) -> tuple:
        """A step as rollouts store it: (render input, or the `Rendered` frames where the policy
        rendered them, true state, action features `act`, done), each `[S*N, ...]`."""
        ri = es.render_input if frames is None else Rendered(self.dev.flat(frames))
        return ri, es.lowdim, act, es.done

    def action_features(self, action: jax.Array) -> jax.Array:
        """Per-seed policy actions `[S, N(, A)]` -> float features `[S*N, A]` (one-hot if
        discrete)."""
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
