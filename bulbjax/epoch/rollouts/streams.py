"""The data side of an experiment: what the learners and probes see of the policy's rollouts.

Frame learners (vae, vae_rpl, beta_vae) train on frame replay buffers, sequential learners
(svae, pred, dsa) on window buffers (`bulbjax.data.sequence`) cut from the same rollouts;
learners with the same retention share a buffer. Held-out evaluation streams are windows of L
steps (L = 1 without sequential learners), so every learner is probed on the very same
(frame, state) pairs: frame learners encode each frame, sequential learners each window, one
latent per step. Frames are rendered only for the steps stored (or gathered where the policy
rendered them already, `Rendered`).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from bulbjax.config import ExperimentConfig
from bulbjax.data import replay, sequence
from bulbjax.data.sequence import Windows
from bulbjax.envs.base import EnvState
from bulbjax.epoch.devices import Devices
from bulbjax.epoch.rollouts.policy import Policy
from bulbjax.epoch.seeds import Team, buffer_key
from bulbjax.epoch.state import PolicyHistory, Rendered
from bulbjax.rl.ppo import PPOState


class Streams:
    """Replay and window buffers, and held-out windows, of the rollouts of `policy` on the worlds
    of `dev`, for the learners of `team`, sized by `config`."""

    def __init__(self, config: ExperimentConfig, dev: Devices, team: Team, policy: Policy):
        self.config, self.dev, self.team, self.policy = config, dev, team, policy
        self.window_length = config.window_length  # stored windows (0 without sequential learners)
        self.eval_length = config.seq_len if self.window_length else 1  # held-out window length

    @property
    def S(self) -> int:
        return self.dev.S

    @property
    def N(self) -> int:
        return self.dev.N

    # ------------------------------------------------------------------ frames of stored steps
    def frames_at(self, render_inputs: Any) -> jax.Array:
        """Frames `[K, S*N, H, W, 3]` of stored steps `[K, S*N]`: rendered from their render
        inputs, or the policy's own frames where it kept them (`Rendered`): the same pixels,
        rendered once."""
        if isinstance(render_inputs, Rendered):
            return render_inputs.frames
        return self.dev.render_sequence(render_inputs)

    def frames_of_steps(self, render_inputs: Any, lowdim: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Render stored steps `[K, S*N]` -> per-seed frames `[S, K*N, H, W, 3]` and states."""
        frames = self.frames_at(render_inputs)  # [K, S*N, H, W, 3]
        k = frames.shape[0]
        frames = frames.reshape((k, self.S, self.N) + frames.shape[2:]).swapaxes(0, 1)
        lowdim = lowdim.reshape((k, self.S, self.N, -1)).swapaxes(0, 1)
        return (frames.reshape((self.S, k * self.N) + frames.shape[3:]),
                lowdim.reshape((self.S, k * self.N, -1)))

    def collect(self, ppo_state: PPOState, es: EnvState, key: jax.Array, steps: int, random: bool):
        """Run `steps` steps and render every one of them (initial replay frames)."""
        (es, _), (ri, low, _, _) = self.policy.rollout(ppo_state, es, key, steps, random)
        frames, states = self.frames_of_steps(ri, low)
        return es, frames, states

    def windows(self, steps: tuple, starts: jax.Array, length: int) -> Windows:
        """Render windows of `length` steps from stored steps `[T, S*N]` (or gather the policy's
        frames, `Rendered`), one per world and round (`starts [R, S*N]`), cut at episode
        boundaries -> per-seed `Windows [S, R*N, length]`."""
        ri, low, act, done = steps
        r = starts.shape[0]
        src, valid = jax.vmap(lambda st: sequence.window_indices(done, st, length))(starts)
        src, valid = src.reshape((r * length, -1)), valid.reshape((r * length, -1))
        frames = self.frames_at(jax.tree.map(lambda x: sequence.gather_steps(x, src), ri))
        act = sequence.gather_steps(act, src) * valid[..., None]

        def per_seed(x: jax.Array) -> jax.Array:  # [R*L, S*N, ...] -> [S, R*N, L, ...]
            x = x.reshape((r, length, self.S, self.N) + x.shape[2:])
            x = jnp.moveaxis(x, (2, 0, 3, 1), (0, 1, 2, 3))
            return x.reshape((self.S, r * self.N, length) + x.shape[4:])

        return Windows(frames=per_seed(frames), actions=per_seed(act),
                       states=per_seed(sequence.gather_steps(low, src)), valid=per_seed(valid))

    def _world_ids(self, n: int) -> jax.Array:
        """`[n]` world index (0..N-1) of each of a seed's `n` frames as `frames_of_steps` lays
        them out (step-major). Kept in replay so that the probe's validation split keeps one
        world's frames together (`probe.fit`'s `groups`)."""
        return (jnp.arange(n) % self.N).astype(jnp.int32)

    # ------------------------------------------------------------------ the buffers at init
    def init_buffers(self, ppo_state: PPOState, k_fill: jax.Array, k_keep: jax.Array) -> dict:
        """The frame buffers filled with frames of the random policy (fresh worlds reset from
        `k_fill`); retained learners keep a share of them (`k_keep`)."""
        return self.fill_buffers(*self.initial_frames(ppo_state, k_fill), k_keep)

    def initial_frames(self, ppo_state: PPOState, k_fill: jax.Array) -> tuple[jax.Array, jax.Array]:
        """`init_buffers`' frames `[S, C, H, W, 3]` and states of the random policy (fresh worlds
        reset from `k_fill`); frame i of a seed came from world `i % N`."""
        c = self.config
        steps = -(-c.replay_capacity // self.N)
        k_fill_reset, k_fill_roll = jax.random.split(k_fill)
        _, frames, states = self.collect(ppo_state, self.dev.env_reset(k_fill_reset), k_fill_roll, steps,
                                         random=True)
        return frames[:, : c.replay_capacity], states[:, : c.replay_capacity]

    def fill_buffers(self, frames: jax.Array, states: jax.Array, k_keep: jax.Array) -> dict:
        """The frame buffers filled with `initial_frames`; retained learners keep a share."""
        env = self.dev.env
        c = self.config
        rcfg = replay.ReplayConfig(capacity=c.replay_capacity)
        buffers = {}
        for frac in sorted(set(self.team.retention.values())):
            def fill(f, s, k, frac=frac):
                buf = replay.init(rcfg, env.frame_shape, env.state_dim,
                                  extras={"world": jax.ShapeDtypeStruct((), jnp.int32)})
                buf = replay.insert(buf, k, f, s, {"world": self._world_ids(f.shape[0])})
                return replay.retain_initial(buf, k, frac) if frac > 0 else buf
            buffers[buffer_key(frac)] = jax.vmap(fill)(frames, states, self.team.seed_keys(k_keep))
        return buffers

    def init_windows(self, ppo_state: PPOState, key: jax.Array) -> dict[str, sequence.WindowBuffer]:
        """Fill the window buffers with windows of a random-policy rollout (consecutive,
        non-overlapping windows per world), then retain a share of them for the sequential
        learners that ask for it (all of them by default: the paper's fix applied to all)."""
        return self.fill_windows(self.initial_windows(ppo_state, key), key)

    def initial_windows(self, ppo_state: PPOState, key: jax.Array) -> Windows:
        """`init_windows`' windows `[S, C, window_length]` of a random-policy rollout; window i of
        a seed came from world `i % N`."""
        c, lw = self.config, self.window_length
        cap = sequence.capacity_in_windows(c.replay_capacity, lw)
        rounds = -(-cap // self.N)
        k_reset, k_roll, _ = jax.random.split(key, 3)
        _, st = self.policy.rollout(ppo_state, self.dev.env_reset(k_reset), k_roll, rounds * lw, random=True)
        starts = jnp.broadcast_to((jnp.arange(rounds) * lw)[:, None], (rounds, self.S * self.N))
        return jax.tree.map(lambda x: x[:, :cap], self.windows(st, starts, lw))

    def fill_windows(self, w: Windows, key: jax.Array) -> dict[str, sequence.WindowBuffer]:
        """The window buffers filled with `initial_windows` (`key`: `init_windows`' own)."""
        c, lw, env = self.config, self.window_length, self.dev.env
        cap = sequence.capacity_in_windows(c.replay_capacity, lw)
        k_keep = jax.random.split(key, 3)[2]
        out = {}
        fracs = {self.team.retention[n] for n, seq in self.team.sequential.items() if seq}
        for frac in sorted(fracs):
            def fill(w, k, frac=frac):
                buf = sequence.init(cap, lw, env.frame_shape, env.state_dim, self.policy.action_dim)
                buf = sequence.insert(buf, k, w)
                return sequence.retain_initial(buf, k, frac) if frac > 0 else buf
            out[buffer_key(frac)] = jax.vmap(fill)(w, self.team.seed_keys(k_keep))
        return out

    # ------------------------------------------------------------------ epoch phases
    def replay_phase(self, buffers: dict, steps: tuple, key: jax.Array) -> dict:
        """Render a random subset of the epoch's stored steps (all worlds of each chosen step;
        the policy's own frames where it kept them, `Rendered`) and write those frames of the
        current policy into every replay buffer."""
        return self.insert_frames(buffers, *self.epoch_frames(steps, key), key)

    def epoch_frames(self, steps: tuple, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """`replay_phase`'s frames `[S, F, H, W, 3]` and states: a random subset of the epoch's
        stored steps (all worlds of each), frame i of a seed from world `i % N`."""
        c = self.config
        ri, low = steps[:2]
        k_pick = jax.random.split(key)[0]
        pick = jax.random.choice(k_pick, low.shape[0], (c.frames_per_epoch // self.N,), replace=False)
        return self.frames_of_steps(jax.tree.map(lambda x: x[pick], ri), low[pick])

    def insert_frames(self, buffers: dict, frames: jax.Array, states: jax.Array,
                      key: jax.Array) -> dict:
        """`epoch_frames` written into every replay buffer (`key`: `replay_phase`'s own)."""
        keys = self.team.seed_keys(jax.random.split(key)[1])
        world = {"world": jnp.broadcast_to(self._world_ids(frames.shape[1]), frames.shape[:2])}
        return {k: jax.vmap(replay.insert)(b, keys, frames, states, world) for k, b in buffers.items()}

    def window_phase(self, windows: dict, steps: tuple, key: jax.Array) -> dict:
        """Cut windows of the epoch's stored steps at random starts (one per world and round, cut
        at episode boundaries), render them, and write `frames_per_epoch // window_length` of them
        per seed (a random subset) into every window buffer: the frame buffers' frame budget."""
        if not windows:
            return windows
        return self.insert_windows(windows, self.epoch_windows(steps, key)[0], key)

    def epoch_windows(self, steps: tuple, key: jax.Array) -> tuple[Windows, jax.Array]:
        """`window_phase`'s windows `[S, P, window_length]` and each one's index `[S, P]` among
        the epoch's cuts (its world: index % N)."""
        c, lw = self.config, self.window_length
        per_epoch = max(1, c.frames_per_epoch // lw)
        rounds = -(-per_epoch // self.N)
        k_start, k_pick, _ = jax.random.split(key, 3)
        total = steps[1].shape[0]
        group = self.team.group
        # starts drawn for all of the run's worlds, this group's share kept (`SeedGroup`)
        starts = group.seed_columns(jax.random.randint(k_start, (rounds, group.total * self.N), 0, total - lw + 1))
        w = self.windows(steps, starts, lw)
        picks = jax.vmap(lambda k: jax.random.permutation(k, rounds * self.N)[:per_epoch])(
            group.seed_keys(k_pick))
        return jax.vmap(lambda ws, p: jax.tree.map(lambda x: x[p], ws))(w, picks), picks

    def insert_windows(self, windows: dict, w: Windows, key: jax.Array) -> dict:
        """`epoch_windows` written into every window buffer (`key`: `window_phase`'s own)."""
        keys = self.team.group.seed_keys(jax.random.split(key, 3)[2])
        return {k: jax.vmap(sequence.insert)(b, keys, w) for k, b in windows.items()}

    def eval_phase(self, ppo_state: PPOState, curr_env: EnvState, rand_env: EnvState, key: jax.Array,
                   learners: dict | None = None, history: PolicyHistory | None = None):
        """Held-out windows (never in replay) from the current and from a random policy: each
        world's rollout of `ceil(eval_frames / N)` steps, rounded up to whole windows of
        `eval_length` steps, cut into consecutive windows (and at episode boundaries).
        `history`: the current-policy worlds' `PolicyHistory` (PPO on a sequential learner's
        latent). Returns both env states, the windows and the new history (None without one)."""
        le = self.eval_length
        rounds = -(-self.config.eval_frames // (self.N * le))
        starts = jnp.broadcast_to((jnp.arange(rounds) * le)[:, None], (rounds, self.S * self.N))
        k_curr, k_rand = jax.random.split(key)
        (curr_env, history), cst = self.policy.rollout(ppo_state, curr_env, k_curr, rounds * le, random=False,
                                                       learners=learners, history=history)
        (rand_env, _), rst = self.policy.rollout(ppo_state, rand_env, k_rand, rounds * le, random=True)
        return curr_env, rand_env, {"curr": self.windows(cst, starts, le),
                                    "rand": self.windows(rst, starts, le)}, history
