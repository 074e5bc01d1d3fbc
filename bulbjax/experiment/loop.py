"""The training loop of one experiment: every epoch is one jitted function, vmapped over seeds.

Layout of the run state: everything a seed owns (PPO, learners, replay buffers) carries a leading
seed axis `[S, ...]` and is updated with `jax.vmap`; the simulators of all seeds are one batch of
`S * num_envs` worlds (one Warp physics launch and one render context for all seeds, which is
what makes the GPU fast), reshaped to `[S, num_envs]` wherever a per-seed function needs them.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

import bulbjax
from bulbjax.data import replay
from bulbjax.envs.base import EnvState, MjxPixelEnv
from bulbjax.eval import probe
from bulbjax.experiment.config import ExperimentConfig
from bulbjax.learners import make_learner
from bulbjax.rl.ppo import PPO, PPOState, Transition


@struct.dataclass
class RunState:
    """Carry of the jitted epoch."""

    ppo: PPOState  # [S]
    learners: dict[str, Any]  # name -> LearnerState [S]
    buffers: dict[str, replay.ReplayBuffer]  # retention key -> buffer [S]
    train_env: EnvState  # [S*N] worlds driven by PPO; frames for replay come from here
    curr_env: EnvState  # [S*N] held-out worlds under the current policy (never in replay)
    rand_env: EnvState  # [S*N] held-out worlds under the random policy (never in replay)
    epoch: jax.Array


def learner_unroll() -> bool | int:
    """How far to unroll the scan over learner updates: fully on CPU, where XLA runs the conv
    net ~8x slower inside a rolled loop (measured: 3.7 s vs 0.45 s per update), not on GPU."""
    return True if jax.default_backend() == "cpu" else 1


def buffer_key(fraction: float) -> str:
    """Learners with the same replay retention share one buffer."""
    return f"retain_{fraction:g}"


class Experiment:
    """Builds the environment, PPO, learners and the jitted `init` and `epoch` functions."""

    def __init__(self, config: ExperimentConfig):
        self.config = c = config
        self.env: MjxPixelEnv = bulbjax.make(c.env, num_envs=c.seeds * c.num_envs,
                                             resolution=c.resolution, render=True,
                                             render_steps=False, multicolour=c.multicolour)
        self.spec = self.env.state_spec
        self.ppo = PPO.for_env(c.ppo, self.env)
        latent = c.latent_factor * self.env.state_dim
        self.learners = {n: make_learner(n, latent, c.learner) for n in c.learners}
        self.retention = {n: l.retain_fraction for n, l in self.learners.items()}
        self.init = jax.jit(self._init)
        self.epoch = jax.jit(self._epoch, donate_argnums=0)

    # ------------------------------------------------------------------ helpers
    @property
    def S(self) -> int:
        return self.config.seeds

    @property
    def N(self) -> int:
        return self.config.num_envs

    def _per_seed(self, x: jax.Array) -> jax.Array:
        """[S*N, ...] -> [S, N, ...]."""
        return x.reshape((self.S, self.N) + x.shape[1:])

    def _flat(self, x: jax.Array) -> jax.Array:
        """[S, N, ...] -> [S*N, ...]."""
        return x.reshape((self.S * self.N,) + x.shape[2:])

    def _policy_step(self, ppo_state: PPOState, es: EnvState, key: jax.Array, random: bool):
        obs = self._per_seed(es.obs)
        keys = jax.random.split(key, self.S)
        if random:
            action = jax.vmap(lambda k: self.ppo.random_act(k, self.N))(keys)
            logp = value = jnp.zeros((self.S, self.N))
        else:
            action, logp, value = jax.vmap(self.ppo.act)(ppo_state, obs, keys)
        nes = self.env.step(es, self._flat(self.ppo.env_action(action)))
        return nes, obs, action, logp, value

    def _frames_of_steps(self, render_inputs: Any, lowdim: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Render stored steps `[K, S*N]` -> per-seed frames `[S, K*N, H, W, 3]` and states."""
        frames = self.env.render_sequence(render_inputs)  # [K, S*N, H, W, 3]
        k = frames.shape[0]
        frames = frames.reshape((k, self.S, self.N) + frames.shape[2:]).swapaxes(0, 1)
        lowdim = lowdim.reshape((k, self.S, self.N, -1)).swapaxes(0, 1)
        return (frames.reshape((self.S, k * self.N) + frames.shape[3:]),
                lowdim.reshape((self.S, k * self.N, -1)))

    def _collect(self, ppo_state: PPOState, es: EnvState, key: jax.Array, steps: int, random: bool):
        """Run `steps` steps and render every one of them (held-out evaluation and initial frames)."""
        def body(es, k):
            nes = self._policy_step(ppo_state, es, k, random)[0]
            return nes, (nes.render_input, nes.lowdim)
        es, (ri, low) = jax.lax.scan(body, es, jax.random.split(key, steps))
        frames, states = self._frames_of_steps(ri, low)
        return es, frames, states

    # ------------------------------------------------------------------ init
    def _init(self, key: jax.Array) -> RunState:
        c = self.config
        k_ppo, k_learn, k_env, k_fill, k_keep = jax.random.split(key, 5)
        ppo_state = jax.vmap(self.ppo.init)(jax.random.split(k_ppo, self.S))
        learners = {}
        for i, (name, learner) in enumerate(self.learners.items()):
            keys = jax.random.split(jax.random.fold_in(k_learn, i), self.S)
            learners[name] = jax.vmap(lambda k, l=learner: l.init(k, self.env.frame_shape))(keys)
        ke = jax.random.split(k_env, 3)
        train_env, curr_env, rand_env = (self.env.reset(k) for k in ke)
        # Fill replay with frames of the random policy; retained learners keep a share of them.
        steps = -(-c.replay_capacity // self.N)
        k_fill_reset, k_fill_roll = jax.random.split(k_fill)
        _, frames, states = self._collect(ppo_state, self.env.reset(k_fill_reset), k_fill_roll, steps,
                                          random=True)
        frames, states = frames[:, : c.replay_capacity], states[:, : c.replay_capacity]
        rcfg = replay.ReplayConfig(capacity=c.replay_capacity)
        buffers = {}
        for frac in sorted(set(self.retention.values())):
            def fill(f, s, k, frac=frac):
                buf = replay.init(rcfg, self.env.frame_shape, self.env.state_dim)
                buf = replay.insert(buf, k, f, s)
                return replay.retain_initial(buf, k, frac) if frac > 0 else buf
            buffers[buffer_key(frac)] = jax.vmap(fill)(frames, states, jax.random.split(k_keep, self.S))
        return RunState(ppo=ppo_state, learners=learners, buffers=buffers, train_env=train_env,
                        curr_env=curr_env, rand_env=rand_env, epoch=jnp.zeros((), jnp.int32))

    # ------------------------------------------------------------------ epoch phases
    def rl_phase(self, ppo_state: PPOState, env_state: EnvState, key: jax.Array):
        """PPO on the true state: rollouts of all seeds' worlds at once, per-seed updates.
        Returns the new PPO state, env state, update metrics, per-seed finished-episode return
        sum and count, and the stored steps (render inputs, true states) `[U*T, S*N]`."""
        c = self.config

        def rl_update(carry, k):
            ppo_state, es = carry
            k_roll, k_upd = jax.random.split(k)

            def step(es, kk):
                nes, obs, action, logp, value = self._policy_step(ppo_state, es, kk, random=False)
                tr = Transition(obs, action, self._per_seed(nes.reward), self._per_seed(nes.done),
                                self._per_seed(nes.truncated), logp, value)
                ep = (self._per_seed(nes.info["episode_return"] * nes.done).sum(1),
                      self._per_seed(nes.done).sum(1))
                return nes, (tr, ep, nes.render_input, nes.lowdim)

            es, (traj, ep, ri, low) = jax.lax.scan(step, es, jax.random.split(k_roll, c.ppo.num_steps))
            traj = jax.tree.map(lambda x: x.swapaxes(0, 1), traj)  # [S, T, N, ...]
            ppo_state, m = jax.vmap(self.ppo.update)(ppo_state, traj, self._per_seed(es.obs),
                                                    jax.random.split(k_upd, self.S))
            return (ppo_state, es), (m, ep, ri, low)

        (ppo_state, env_state), (m, ep, ri, low) = jax.lax.scan(
            rl_update, (ppo_state, env_state), jax.random.split(key, c.ppo_updates_per_epoch))
        total = c.ppo_updates_per_epoch * c.ppo.num_steps
        flat = lambda x: x.reshape((total,) + x.shape[2:])
        steps = (jax.tree.map(flat, ri), flat(low))
        return ppo_state, env_state, jax.tree.map(lambda x: x.mean(0), m), ep[0].sum((0, 1)), ep[1].sum((0, 1)), steps

    def replay_phase(self, buffers: dict, steps: tuple, key: jax.Array) -> dict:
        """Render a random subset of the epoch's stored steps (all worlds of each chosen step)
        and write those frames of the current policy into every replay buffer."""
        c = self.config
        ri, low = steps
        k_pick, k_ins = jax.random.split(key)
        pick = jax.random.choice(k_pick, low.shape[0], (c.frames_per_epoch // self.N,), replace=False)
        frames, states = self._frames_of_steps(jax.tree.map(lambda x: x[pick], ri), low[pick])
        keys = jax.random.split(k_ins, self.S)
        return {k: jax.vmap(replay.insert)(b, keys, frames, states) for k, b in buffers.items()}

    def learn_phase(self, learners: dict, buffers: dict, key: jax.Array) -> tuple[dict, dict]:
        """`learner_batches` updates of every learner on batches sampled from its replay buffer."""
        c = self.config
        out, metrics = {}, {}
        for i, (name, learner) in enumerate(self.learners.items()):
            def train_seed(state, b, k, learner=learner):
                def one(state, kk):
                    k_s, k_u = jax.random.split(kk)
                    frames, _ = replay.sample(b, k_s, c.learner.batch_size)
                    return learner.update(state, frames, k_u)
                return jax.lax.scan(one, state, jax.random.split(k, c.learner_batches),
                                    unroll=learner_unroll())

            keys = jax.random.split(jax.random.fold_in(key, i), self.S)
            buf = buffers[buffer_key(self.retention[name])]
            out[name], m = jax.vmap(train_seed)(learners[name], buf, keys)
            metrics[name] = jax.tree.map(lambda x: x.mean(-1), m)
        return out, metrics

    def eval_phase(self, ppo_state: PPOState, curr_env: EnvState, rand_env: EnvState, key: jax.Array):
        """Held-out frames (never in replay) from the current and from a random policy."""
        steps = self.config.eval_frames // self.N
        k_curr, k_rand = jax.random.split(key)
        curr_env, cf, cs = self._collect(ppo_state, curr_env, k_curr, steps, random=False)
        rand_env, rf, rsx = self._collect(ppo_state, rand_env, k_rand, steps, random=True)
        return curr_env, rand_env, {"curr": (cf, cs), "rand": (rf, rsx)}

    def probe_phase(self, learners: dict, buffers: dict, held_out: dict, key: jax.Array) -> dict:
        """Alignment probes: fit latents -> true state on replay frames, evaluate on held-out ones."""
        c = self.config
        out = {}
        for i, (name, learner) in enumerate(self.learners.items()):
            def probe_seed(lstate, b, held, k, learner=learner):
                k_s, k_f = jax.random.split(k)
                tf, ts = replay.sample(b, k_s, c.probe_train_frames)
                enc = lambda f: learner.encode(lstate.params, f)
                p = probe.fit(k_f, enc(tf), ts, c.probe)
                return {stream: {"mae": probe.mae(probe.predict(p, enc(f)), s),
                                 "baseline": probe.constant_baseline(ts, s),
                                 "spread": probe.spread(s)} for stream, (f, s) in held.items()}

            keys = jax.random.split(jax.random.fold_in(key, i), self.S)
            buf = buffers[buffer_key(self.retention[name])]
            out[name] = jax.vmap(probe_seed)(learners[name], buf, held_out, keys)
        return out

    def _epoch(self, rs: RunState, key: jax.Array) -> tuple[RunState, dict[str, Any]]:
        k_rl, k_rep, k_learn, k_eval, k_probe = jax.random.split(key, 5)
        ppo_state, train_env, ppo_m, ret_sum, count, steps = self.rl_phase(rs.ppo, rs.train_env, k_rl)
        buffers = self.replay_phase(rs.buffers, steps, k_rep)
        learners, learn_m = self.learn_phase(rs.learners, buffers, k_learn)
        curr_env, rand_env, held_out = self.eval_phase(ppo_state, rs.curr_env, rs.rand_env, k_eval)
        probes = self.probe_phase(learners, buffers, held_out, k_probe)
        metrics = {
            "rl_return": jnp.where(count > 0, ret_sum / jnp.maximum(count, 1), jnp.nan),
            "rl_episodes": count,
            "ppo": ppo_m,
            "learners": learn_m,
            "probes": probes,
            "replay_dropped": {k: b.num_dropped for k, b in buffers.items()},
        }
        new = RunState(ppo=ppo_state, learners=learners, buffers=buffers, train_env=train_env,
                       curr_env=curr_env, rand_env=rand_env, epoch=rs.epoch + 1)
        return new, metrics
