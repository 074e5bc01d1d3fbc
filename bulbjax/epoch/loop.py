"""The training loop of one experiment: every epoch is one jitted function, vmapped over seeds.

An epoch is: PPO's rollouts and updates (`Policy.rl_phase`), frames of its rollouts into replay
and windows into the window buffers (`Streams.replay_phase`, `.window_phase`), the learners'
updates (`Learning.learn_phase`), then, in an epoch that probes, held-out rollouts
(`Streams.eval_phase`) and the probes (`Probing.probe_phase`). `Experiment` builds those parts
over one `Devices` (mesh, env, per-device rendering) and one `Team` (the learners and their
seed loop), and composes them into `init` and `epoch`; `programs.Programs` compiles them.

Layout of the run state (`state.RunState`): everything a seed owns (PPO, learners, replay
buffers) carries a leading seed axis `[S, ...]` and is updated with `jax.vmap` (or the seed
loop, `seeds`); the simulators of all seeds are one batch of `S * num_envs` worlds (one Warp
physics launch and one render context for all seeds, which is what makes the GPU fast).
"""

from __future__ import annotations

import functools
from typing import Any, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from bulbjax.config import ExperimentConfig
from bulbjax.envs.base import EnvState
from bulbjax.epoch import probe_variants as pv
from bulbjax.epoch.apart import Apart
from bulbjax.epoch.devices import Devices
from bulbjax.epoch.keys import epoch_keys, init_keys, world_keys
from bulbjax.epoch.learning import Learning
from bulbjax.epoch.probing import Probing, object_pixels, probe_targets
from bulbjax.epoch.rollouts.policy import Policy
from bulbjax.epoch.rollouts.streams import Streams
from bulbjax.epoch.seeds import SeedGroup, Team, resolve_seed_loop, with_seed_loop
from bulbjax.epoch.state import EnvBatch, EnvStage, PolicyHistory, RunState
from bulbjax.eval import objects, probe
from bulbjax.learners import make_learner
from bulbjax.rl.ppo import PPOState


class Experiment:
    """Builds the environment, PPO, learners and the jitted `init` and `epoch` functions.

    Its parts, each a module of its own: `devices` (the mesh of `devices`, default the first
    device alone; the env; calls on every device's worlds), `team` (the learners, each seed's,
    and the seed loop), `policy` (PPO: observations, rollouts, its training phase), `streams`
    (replay, windows, held-out windows), `learning` and `probing`. Here: how they make `init`
    and an epoch, and the jitted forms of both (`compiler_options`: XLA options for compiling
    them, how the program runs, not what it computes).

    `seed_group=(offset, total)`: this experiment runs seeds offset..offset+S-1 of a run of `total`
    seeds (`bulbjax.epoch.groups`): every random draw is the one those seeds get in the whole
    run (`seeds.SeedGroup`), so a run's seeds spread over several experiments (devices, processes)
    compute what one experiment of all seeds computes."""

    def __init__(self, config: ExperimentConfig, devices: Sequence[jax.Device] | None = None,
                 compiler_options: Mapping[str, Any] | None = None, seed_group: tuple[int, int] | None = None):
        self.config = c = config
        self.compiler_options = dict(compiler_options or {})
        offset, total = seed_group or (0, c.seeds)
        self.group = group = SeedGroup(c.seeds, c.num_envs, offset, total)
        # the learners apart (`ExperimentConfig.overlap` "apart", `bulbjax.epoch.apart`): the
        # first device is the environment's, the second the learners'
        devices, learner_device = apart_devices(c, devices)
        self.devices = dev = Devices(c, devices, group)
        self.env, self.mesh, self.sharded = dev.env, dev.mesh, dev.sharded
        # what the probes regress: the env's state and targets derived from it (`probe_targets`)
        self.targets = probe_targets(self.env.state_spec)
        self.spec = self.targets.spec
        self.seed_loop = resolve_seed_loop(c.learner_seed_loop, self.mesh)
        latent = c.latent_factor * self.env.state_dim
        action_dim = self.env.num_actions if self.env.discrete else self.env.action_size
        self.learners = {n: with_seed_loop(make_learner(n, latent, c.learner, action_dim), self.seed_loop)
                         for n in c.learners}
        self.team = Team(self.learners, self.seed_loop, group, c.shared_updates)
        self.policy = Policy(c, dev, self.team)
        self.ppo, self.action_dim = self.policy.ppo, self.policy.action_dim
        self.streams = Streams(c, dev, self.team, self.policy)
        self.window_length, self.eval_length = self.streams.window_length, self.streams.eval_length
        self.learning = Learning(self.team, c.learner_batches, self.env.frame_shape)
        # Object-level probe (multi-object domains): names and states -> image positions (px)
        # of the true objects, None for domains without objects in the state (nothing computed).
        self.probing = Probing(self.team, c.probe, c.probe_train_frames, c.resolution,
                               object_pixels(self.env), objects.default_radius(c.resolution),
                               self.targets, c.probe_variants_run)
        self.common_probes = "common" in c.probe_variants  # the common probe set is kept and drawn
        # the pipelined epoch (`ExperimentConfig.overlap`): its state carries the next epoch's
        # environment work (`RunState.pending`), which `prime` does once after init
        self.pipelined = c.overlap != "none"
        opts = self.compiler_options or None
        self.apart = (Apart(self, learner_device, functools.partial(jax.jit, compiler_options=opts))
                      if learner_device is not None else None)
        init_shapes = jax.eval_shape(self._init, jax.random.PRNGKey(0))
        shapes = (jax.eval_shape(self._prime, init_shapes, jax.random.PRNGKey(0)) if self.pipelined
                  else init_shapes)
        self._state_sh = self.apart.state_shardings(shapes) if self.apart else dev.state_shardings(shapes)
        self._init_sh = dev.state_shardings(init_shapes)
        rep = dev.replicated
        # what `programs.Programs.of` keeps of this experiment's programs (per `probes`)
        self.programs_cache: dict[tuple[bool, ...], Any] = {}
        # traced once here: every later use reads this, so that a process's sequence of traces
        # (which numbers MuJoCo Warp's FFI calls, see `Programs`) does not depend on how often
        # it asks for the state's shapes
        self._abstract_state = jax.tree.map(lambda x, sh: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sh),
                                            shapes, self._state_sh)
        self._abstract_init = jax.tree.map(lambda x, sh: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sh),
                                           init_shapes, self._init_sh)
        self.init = jax.jit(self._init, out_shardings=self._init_sh, compiler_options=opts)
        # `prime(rs, key)`: the first epoch's environment work on init's state (pipelined runs)
        self.prime = jax.jit(self._prime, donate_argnums=0, out_shardings=self._state_sh, compiler_options=opts)
        # `epoch(rs, key, probe=False)` skips the held-out rollouts and probes (`--probe-every`).
        # Outputs laid out exactly as the inputs (state as `init` gives it, metrics replicated):
        # an equivalent but differently written sharding (XLA drops size-1 mesh axes) would
        # make the second call compile the epoch again.
        self.epoch = jax.jit(self._epoch, donate_argnums=0, static_argnames="probe",
                             out_shardings=(self._state_sh, rep), compiler_options=opts)
        # `epoch_flag(rs, key, flag)`: one program for probing and non-probing epochs, `flag` a
        # boolean array (`abstract_flag`) that switches the held-out rollouts and probes on
        # (`lax.cond`), so a run probing every k epochs compiles and loads one epoch, not two.
        self.epoch_flag = jax.jit(self._epoch, donate_argnums=0,
                                  out_shardings=(self._state_sh, rep), compiler_options=opts)

    @property
    def S(self) -> int:
        return self.config.seeds

    @property
    def N(self) -> int:
        return self.config.num_envs

    def abstract_state(self) -> RunState:
        """Shapes, dtypes and shardings of the RunState (what a checkpoint is restored into)."""
        return self._abstract_state

    def abstract_init_state(self) -> RunState:
        """What `init` returns: `abstract_state` but for a pipelined run, whose init state has no
        `pending` until `prime` (`ExperimentConfig.overlap`)."""
        return self._abstract_init

    def abstract_key(self) -> jax.ShapeDtypeStruct:
        return self.devices.abstract_key()

    def abstract_flag(self) -> jax.ShapeDtypeStruct:
        """The `flag` argument of `epoch_flag` (a boolean scalar, replicated)."""
        return self.devices.abstract_flag()

    def put_key(self, key: jax.Array) -> jax.Array:
        """A host-side PRNG key placed on the mesh (replicated)."""
        return self.devices.put_key(key)

    def put_flag(self, probe: bool) -> jax.Array:
        return self.devices.put_flag(probe)

    # ------------------------------------------------------------------ init
    def _init(self, key: jax.Array) -> RunState:
        """The run state before the first epoch: `init_env`'s, with every learner's `init_learner`."""
        return self.init_env(key).replace(learners={n: self.learning.init_learner(n, key) for n in self.learners})

    def init_env(self, key: jax.Array) -> RunState:
        """The run state before the first epoch without the learners' states (`learners={}`):
        PPO, the worlds, replay and window buffers filled by the random policy, the reference
        spread."""
        c, dev, policy = self.config, self.devices, self.policy
        keys, worlds = init_keys(key), world_keys(key)
        ppo_state = jax.vmap(self.ppo.init)(self.team.seed_keys(keys.ppo))
        train_env, curr_env, rand_env = (dev.env_reset(k) for k in (worlds.train, worlds.curr, worlds.rand))
        # The reference spread of every state entry, once per run: the random policy's held-out
        # worlds run `reference_steps` steps (pooled over seeds); their π_rand stream goes on from there.
        (rand_env, _), (_, ref_states, _, _) = policy.rollout(ppo_state, rand_env, worlds.reference, c.reference_steps,
                                                              random=True)
        ref_targets = self.targets(ref_states)
        ref_spread = probe.spread(ref_targets.reshape((-1, ref_targets.shape[-1])))
        # Fill replay with frames of the random policy; retained learners keep a share of them.
        frames, states = self.streams.initial_frames(ppo_state, keys.fill)
        buffers = self.streams.fill_buffers(frames, states, keys.keep)
        initial = pv.frames_as_windows(frames, states, self.action_dim)
        # Keys of the window buffers are folded in, so frame-only runs keep their random streams.
        windows = {}
        if self.window_length:
            k_win = jax.random.fold_in(key, 1)
            initial = self.streams.initial_windows(ppo_state, k_win)
            windows = self.streams.fill_windows(initial, k_win)
        # The common probe set's random-policy part: a fixed draw of those steps (`probe_variants`).
        probe_set = (pv.initial_part(initial, self.N, c.probe_train_frames // 2,
                                     jax.random.fold_in(key, pv.COMMON_FOLD), self.eval_length)
                     if self.common_probes else None)
        # PPO on a sequential learner's latent: every policy-driven world's window starts at its first frame.
        history = ({"train": policy.history_start(train_env), "curr": policy.history_start(curr_env)}
                   if policy.keeps_history else {})
        return RunState(ppo=ppo_state, learners={}, buffers=buffers, windows=windows,
                        train_env=train_env, curr_env=curr_env, rand_env=rand_env, policy_history=history,
                        ref_spread=ref_spread, epoch=jnp.zeros((), jnp.int32), probe_set=probe_set)

    def reference_states(self, key: jax.Array) -> jax.Array:
        """The states `[reference_steps, S*N, D]` that init's reference spread is taken over (the
        random policy's held-out worlds, `init_env`), recomputed from the init key: a run of seed
        groups pools them over all its groups (`bulbjax.epoch.groups`)."""
        worlds = world_keys(key)
        ppo_state = jax.vmap(self.ppo.init)(self.team.seed_keys(init_keys(key).ppo))
        _, (_, ref_states, _, _) = self.policy.rollout(ppo_state, self.devices.env_reset(worlds.rand),
                                                       worlds.reference, self.config.reference_steps,
                                                       random=True)
        return ref_states

    # ------------------------------------------------------------------ the epoch
    def env_stage(self, ppo_state: PPOState, train_env: EnvState, buffers: dict, windows: dict,
                  train_hist: PolicyHistory | None, learners: dict | None, ref_spread: jax.Array,
                  epoch: jax.Array, key: jax.Array) -> EnvStage:
        """An epoch's environment work, before any learner updates: PPO (rollouts and updates),
        frames of its rollouts into replay, windows into the window buffers; the epoch's
        metrics of it, its counter moved on, and the keys of the later phases. `learners`: the
        states PPO's policy reads (`Policy.rl_learners`). `env_data`, then `insert_data`."""
        ppo_state, train_env, train_hist, batch = self.env_data(ppo_state, train_env, train_hist, learners, key)
        buffers, windows, pending = self.insert_data(buffers, windows, batch, ref_spread)
        return EnvStage(ppo_state, train_env, buffers, windows, train_hist, pending["metrics"], epoch + 1,
                        batch.k_learn, batch.k_eval, batch.k_probe, pending.get("fresh"))

    def env_data(self, ppo_state: PPOState, train_env: EnvState, train_hist: PolicyHistory | None,
                 learners: dict | None, key: jax.Array) -> tuple[PPOState, EnvState, PolicyHistory | None, EnvBatch]:
        """The environment's half of `env_stage`: PPO's rollouts and updates, then the epoch's
        new frames and windows rendered (`EnvBatch`, with the keys of the later phases)."""
        k = epoch_keys(key)
        resets_before = train_env.counts["nonfinite_resets"]
        # named scopes label each phase's ops in a profiler trace (benchmarks/trace_summary.py)
        with jax.named_scope("bj.rl"):
            ppo_state, train_env, ppo_m, ret_sum, count, steps, train_hist = self.policy.rl_phase(
                ppo_state, train_env, k.rl, learners, train_hist)
        # worlds of this epoch's rollouts reset because their physics went non-finite (`EnvState.counts`)
        nonfinite = self.devices.per_seed(train_env.counts["nonfinite_resets"] - resets_before).sum(1)
        with jax.named_scope("bj.replay"):
            frames, states = self.streams.epoch_frames(steps, k.replay)
        new = index = None
        if self.window_length:
            with jax.named_scope("bj.windows"):
                new, index = self.streams.epoch_windows(steps, jax.random.fold_in(k.replay, 1))
        rl = {"rl_return": jnp.where(count > 0, ret_sum / jnp.maximum(count, 1), jnp.nan),
              "rl_episodes": count, "nonfinite_resets": nonfinite, "ppo": ppo_m}
        return ppo_state, train_env, train_hist, EnvBatch(frames, states, new, index, k.replay, k.learn,
                                                          k.eval, k.probe, rl)

    def insert_data(self, buffers: dict, windows: dict, batch: EnvBatch, ref_spread: jax.Array
                    ) -> tuple[dict, dict, dict[str, Any]]:
        """The learners' half of `env_stage`: the epoch's frames and windows into the buffers.
        Returns the buffers, the window buffers and what the epoch's learning and probing read
        of it (`RunState.pending`'s form: the epoch's metrics, its keys, the common probe set's
        new part)."""
        buffers, windows = self.insert_buffers(buffers, windows, batch)
        fresh = None  # the epoch's new steps: the common probe set's current-policy part
        if self.common_probes and not windows:  # frames (as windows of one step)
            frames = batch.frames
            index = jnp.broadcast_to(jnp.arange(frames.shape[1]), frames.shape[:2])
            new = pv.frames_as_windows(frames, batch.states, self.action_dim)
            fresh = pv.fresh_part(new, index, self.N, 1)
        if windows and self.common_probes:
            with jax.named_scope("bj.windows"):
                fresh = pv.fresh_part(batch.windows, batch.index, self.N, self.eval_length)
        metrics = {
            **batch.rl,
            "ref_spread": jnp.broadcast_to(ref_spread, (self.S,) + ref_spread.shape),
            "replay_dropped": {**{k: b.num_dropped for k, b in buffers.items()},
                               **{f"windows_{k}": b.num_dropped for k, b in windows.items()}},
        }
        out = {"metrics": metrics, "k_learn": batch.k_learn, "k_eval": batch.k_eval, "k_probe": batch.k_probe}
        if fresh is not None:
            out["fresh"] = fresh
        return buffers, windows, out

    def insert_buffers(self, buffers: dict, windows: dict, batch: EnvBatch) -> tuple[dict, dict]:
        """The epoch's frames into `buffers` and its windows into `windows`, any subset of the run's
        (each buffer's insert reads only the batch and its keys): `insert_data`'s, and that of the
        copies kept on the environment's device with the learners apart (`apart.Apart`)."""
        with jax.named_scope("bj.replay"):
            buffers = self.streams.insert_frames(buffers, batch.frames, batch.states, batch.k_rep)
        if windows:
            with jax.named_scope("bj.windows"):
                windows = self.streams.insert_windows(windows, batch.windows, jax.random.fold_in(batch.k_rep, 1))
        return buffers, windows

    def eval_stage(self, ppo_state: PPOState, curr_env: EnvState, rand_env: EnvState,
                   rl_learners: dict | None, curr_hist: PolicyHistory | None, key: jax.Array) -> tuple:
        """A probing epoch's held-out rollouts (`Streams.eval_phase`); `rl_learners`: the updated
        states PPO's policy reads (`Policy.rl_learners`)."""
        with jax.named_scope("bj.eval"):
            return self.streams.eval_phase(ppo_state, curr_env, rand_env, key, rl_learners, curr_hist)

    def _epoch(self, rs: RunState, key: jax.Array, probe: bool | jax.Array = True
               ) -> tuple[RunState, dict[str, Any]]:
        """One epoch; with `probe=False` no held-out rollout or probe (metrics without `probes`).
        A traced boolean `probe` (`epoch_flag`) puts both in one program: the held-out rollouts
        and probes run under `lax.cond`, and the metrics always have `probes` (NaN or 0 where the
        epoch did not probe; `Programs.epoch` drops them). `programs.Stages` runs the same steps
        (`env_stage`, `Learning.learn_unit`, `eval_stage`, `Probing.probe_unit`) as programs of
        their own."""
        if self.pipelined:
            return self._epoch_pipelined(rs, key, probe)
        rl_learners = self.policy.rl_learners
        hist = dict(rs.policy_history)
        env = self.env_stage(rs.ppo, rs.train_env, rs.buffers, rs.windows, hist.get("train"),
                             rl_learners(rs.learners), rs.ref_spread, rs.epoch, key)
        if env.train_hist is not None:
            hist["train"] = env.train_hist
        ppo_state, train_env, buffers, windows = env.ppo, env.train_env, env.buffers, env.windows
        learners, learn_m = self.learning.learn_phase(rs.learners, buffers, env.k_learn, windows)
        metrics = {**env.metrics, "learners": learn_m}
        ops = (rs.curr_env, rs.rand_env, hist.get("curr"), ppo_state, learners, buffers, windows, rs.probe_set,
               env.fresh)
        curr_env, rand_env = self._probe_tail(probe, ops, env.k_eval, env.k_probe, hist, metrics)
        new = RunState(ppo=ppo_state, learners=learners, buffers=buffers, windows=windows,
                       train_env=train_env, curr_env=curr_env, rand_env=rand_env, policy_history=hist,
                       ref_spread=rs.ref_spread, epoch=env.epoch, probe_set=rs.probe_set)
        if self.sharded:  # the next epoch gets the layout this one got
            new = jax.lax.with_sharding_constraint(new, self._state_sh)
        return new, metrics

    # ------------------------------------------------------------------ the pipelined epoch
    # With `ExperimentConfig.overlap` "pipeline", the program of epoch t does epoch
    # t's learner updates (on the frames of t's rollouts, in the buffers since the program before)
    # and, beside them, epoch t+1's environment work: PPO's rollouts and updates and the replay
    # and window inserts, which read the PPO state, worlds and buffers and never the learners when
    # PPO observes the true state or pixels. Then epoch t's held-out rollouts and probes. Every
    # part takes the inputs and keys it takes in the plain epoch (epoch t's learning, held-out and
    # probe keys come from t's key, kept in `RunState.pending` with t's metrics), so an epoch's
    # numbers are the plain epoch's; what changes is what one program holds: the two sides are
    # independent in it, the layout for running them at once (docs/performance.md, "The
    # locomotion epoch on one H200": on one GPU stream XLA runs them one after the other, and its
    # stream annotation does not take a call that holds loops on JAX 0.11.2). `prime` does epoch
    # 0's environment work after init; the last program does one epoch's environment work that
    # no later epoch uses.
    def _prime(self, rs: RunState, key: jax.Array) -> RunState:
        """Init's state with the first epoch's environment work done (`key`: that epoch's key)."""
        hist = dict(rs.policy_history)
        env = self.env_stage(rs.ppo, rs.train_env, rs.buffers, rs.windows, hist.get("train"), None,
                             rs.ref_spread, rs.epoch, key)
        if env.train_hist is not None:
            hist["train"] = env.train_hist
        new = rs.replace(ppo=env.ppo, train_env=env.train_env, buffers=env.buffers, windows=env.windows,
                         policy_history=hist, pending=_pending(env))
        if self.sharded:
            new = jax.lax.with_sharding_constraint(new, self._state_sh)
        return new

    def _epoch_pipelined(self, rs: RunState, key: jax.Array, probe: bool | jax.Array
                         ) -> tuple[RunState, dict[str, Any]]:
        """Epoch t of a pipelined run: `rs` holds t's environment work done (`rs.pending`), `key`
        is epoch t+1's. Returns the state with t's learners updated and t+1's environment work
        done, and epoch t's metrics (as `_epoch` gives them)."""
        p, hist = rs.pending, dict(rs.policy_history)
        learners, learn_m = self.learning.learn_phase(rs.learners, rs.buffers, p["k_learn"], rs.windows)
        env = self.env_stage(rs.ppo, rs.train_env, rs.buffers, rs.windows, hist.get("train"), None,
                             rs.ref_spread, rs.epoch, key)
        metrics = {**p["metrics"], "learners": learn_m}
        ops = (rs.curr_env, rs.rand_env, hist.get("curr"), rs.ppo, learners, rs.buffers, rs.windows, rs.probe_set,
               p.get("fresh"))
        curr_env, rand_env = self._probe_tail(probe, ops, p["k_eval"], p["k_probe"], hist, metrics)
        if env.train_hist is not None:
            hist["train"] = env.train_hist
        new = RunState(ppo=env.ppo, learners=learners, buffers=env.buffers, windows=env.windows,
                       train_env=env.train_env, curr_env=curr_env, rand_env=rand_env, policy_history=hist,
                       ref_spread=rs.ref_spread, epoch=rs.epoch + 1, probe_set=rs.probe_set, pending=_pending(env))
        if self.sharded:
            new = jax.lax.with_sharding_constraint(new, self._state_sh)
        return new, metrics

    def _probe_tail(self, probe: bool | jax.Array, ops: tuple, k_eval: jax.Array, k_probe: jax.Array,
                    hist: dict, metrics: dict) -> tuple[EnvState, EnvState]:
        """An epoch's held-out rollouts and probes (`ops`: the held-out worlds and policy history,
        the PPO state, learners and buffers they read, the common probe set's parts): none when
        `probe` is False, under `lax.switch` when it is traced. Writes `metrics["probes"]` and the
        current-policy history into `hist`; returns the held-out worlds."""
        rl_learners = self.policy.rl_learners
        curr_env, rand_env = ops[0], ops[1]

        def evaluate(ops: tuple) -> tuple:
            curr_env, rand_env, curr_hist, ppo_state, learners, buffers, windows, probe_set, fresh = ops
            common = pv.common_set(probe_set, fresh) if self.common_probes else None
            curr_env, rand_env, held_out, curr_hist = self.eval_stage(ppo_state, curr_env, rand_env,
                                                                      rl_learners(learners), curr_hist, k_eval)
            return curr_env, rand_env, curr_hist, self.probing.probe_phase(learners, buffers, held_out, k_probe,
                                                                           windows, common)

        if isinstance(probe, (bool, np.bool_)):
            if probe:
                curr_env, rand_env, curr_hist, metrics["probes"] = evaluate(ops)
                if curr_hist is not None:
                    hist["curr"] = curr_hist
        else:
            # `skip` returns placeholders shaped like `evaluate`'s probes. `lax.switch` traces its
            # branches in order, so `evaluate`'s own trace gives those shapes: the eval and probe
            # phases are traced once, not twice (an `eval_shape` first; ~1/7 of the epoch's
            # tracing on the CPU). Were the order ever different, `skip` falls back to `eval_shape`.
            shapes: list[Any] = []

            def evaluate_once(ops: tuple) -> tuple:
                out = evaluate(ops)
                shapes.append(jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), out[3]))
                return out

            def skip(ops: tuple) -> tuple:
                probes_shape = shapes[0] if shapes else jax.eval_shape(evaluate, ops)[3]
                return ops[0], ops[1], ops[2], jax.tree.map(_blank, probes_shape)

            curr_env, rand_env, curr_hist, metrics["probes"] = jax.lax.switch(
                jnp.where(probe, 0, 1), [evaluate_once, skip], ops)
            if curr_hist is not None:
                hist["curr"] = curr_hist
        return curr_env, rand_env


def apart_devices(config: ExperimentConfig, devices: Sequence[jax.Device] | None
                  ) -> tuple[Sequence[jax.Device] | None, jax.Device | None]:
    """(the environment's devices, the learners' device) of an experiment: with overlap "apart"
    the first two of `devices` (default this process's first two), else `devices` and None. One
    line when there are fewer than two."""
    if config.overlap != "apart":
        return devices, None
    devs = list(devices) if devices is not None else jax.local_devices()
    if len(devs) < 2:
        raise ValueError(f"--overlap apart puts the learners on a device of their own: this process has "
                         f"{len(devs)} ({devs[0].device_kind if devs else 'none'}); give it two GPUs "
                         "(CUDA_VISIBLE_DEVICES), or use --overlap pipeline")
    return devs[:1], devs[1]


def _pending(env: EnvStage) -> dict[str, Any]:
    """What a pipelined epoch keeps of the next epoch's environment work for that epoch's
    learning and probing (`RunState.pending`)."""
    out = {"metrics": env.metrics, "k_learn": env.k_learn, "k_eval": env.k_eval, "k_probe": env.k_probe}
    if env.fresh is not None:
        out["fresh"] = env.fresh
    return out


def _blank(s: jax.ShapeDtypeStruct) -> jax.Array:
    """NaN (floats) or 0 of a shape: the probes of an epoch that did not probe."""
    return jnp.full(s.shape, jnp.nan if jnp.issubdtype(s.dtype, jnp.inexact) else 0, s.dtype)
