"""The learners apart: the pipelined epoch as programs on two devices, so that they run at once.

With `ExperimentConfig.overlap` "apart" an experiment uses two devices of its process: the
environment's (PPO, the worlds, their rendering) and the learners' (the learners' states, the
replay and window buffers, the probes). Epoch t is three programs:

- "learn", on the learners' device: epoch t's learner updates on the buffers as epoch t's frames
  left them (`Learning.learn_phase`);
- "env", on the environment's device, beside it: epoch t's held-out rollouts (in an epoch that
  probes) and epoch t+1's environment work up to its new frames and windows
  (`Experiment.env_data`: PPO's rollouts and updates, the frames rendered);
- "finish", on the learners' device, once both are done and the new frames and held-out windows
  have moved over (~12 MB of frames an epoch of 1,024): epoch t's probes, then epoch t+1's frames
  and windows into the buffers (`Experiment.insert_data`).

Each part takes the inputs and keys it takes in the plain epoch (`loop.Experiment._epoch`), so an
epoch's numbers are the plain epoch's (tested); the state is the pipelined run's
(`RunState.pending` holds epoch t's metrics and keys), each array on the device of the side that
owns it (`state_shardings`). Why: on one GPU XLA runs a program's work on one stream, and PPO's
phase of a locomotion epoch (0.66 s of 1.8 s on an H200) keeps the GPU busy only half its time
(MuJoCo Warp's chains of small kernels) while the learners' updates (1.09 s) fill it; on two
devices an epoch should take about the longer side (docs/performance.md, "The locomotion epoch").
"env" and "learn" are dispatched from two threads: a program with MJX-Warp holds the thread that
runs it until its last kernel is launched (`groups._side_by_side`).

The learners of `ExperimentConfig.apart_env_learners` ("near"; pred by default) are updated by a
fourth program, "near", on the environment's device after "env": epoch t's updates on copies of
their buffers kept there, then epoch t+1's frames into the copies (the batch and keys "finish"
inserts: the same contents), so that the two devices' shares even out (an H200: PPO ~0.7 s, the
learners ~1.0 s of a locomotion epoch). Their states lie on the environment's device; "finish"
probes them from a copy moved over. The copies are not in the run state: they are made again from
the buffers at the first epoch and after a resume. (Updated inside "env" instead, pred took 0.48 s
there against 0.22 s among the learners: `results/apart_sides_fig2-ant_*_20261130_080320.json`;
so, a fig2-ant seed ran 1.37-1.40 s an epoch against 0.997 s as now.)
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct
from jax.sharding import SingleDeviceSharding

from bulbjax.epoch import probe_variants as pv
from bulbjax.epoch.seeds import buffer_key
from bulbjax.epoch.state import EnvBatch, RunState

# the parts of the run state on the learners' device; the rest lie on the environment's
LEARNER_SIDE = ("learners", "buffers", "windows", "ref_spread", "probe_set", "pending")
# in trace order (`programs.Programs`); "near": with near learners
PROGRAMS = ("env", "learn", "near", "finish")


@struct.dataclass
class EnvOut:
    """What the "env" program hands on: PPO's state and the worlds after epoch t+1's environment
    work, epoch t's held-out rollouts (blanks where it does not probe), the policy histories of the
    train and current-policy streams, and epoch t+1's frames (`batch`: "near" and "finish" insert
    them)."""
    ppo: Any
    train_env: Any
    curr_env: Any
    rand_env: Any
    held_out: Any
    histories: dict
    batch: EnvBatch


class Apart:
    """The programs of an apart epoch of `exp` (an `Experiment` with overlap "apart", whose
    mesh is its environment's device) and how the run state lies over the two devices. `jit`:
    how each program is jitted (the experiment's compiler options)."""

    def __init__(self, exp: Any, learner_device: jax.Device, jit: Callable[..., Any]):
        self.exp = exp
        self.env_device = exp.mesh.devices.flat[0]
        self.learner_device = learner_device
        self.on_env = SingleDeviceSharding(self.env_device)
        self.on_learners = SingleDeviceSharding(learner_device)
        units = exp.team.units()
        self.near = near_units(units, exp.config.apart_env_learners)
        self.far = [u for u in units if u not in self.near]
        self.near_names = [n for u in self.near for n in u]
        team = exp.team
        # the buffers the near learners read, copied on the environment's device (frames, windows)
        self.mirror_keys = tuple(sorted({buffer_key(team.retention[n]) for n in self.near_names
                                         if team.sequential[n] == seq}) for seq in (False, True))
        self._mirror: tuple[dict, dict] | None = None
        self._mirror_of: Any = None  # the learners' buffer leaf the copies equal
        # a diagnosis (benchmarks/profile_epoch.py --overlap apart): where a dict, each epoch runs
        # its programs one after another and appends each one's seconds under its name
        self.timings: dict[str, list[float]] | None = None
        # donated: what a program replaces (the environment's state; the buffers inserted into)
        self.jits = {
            "env": jit(self._env_side, donate_argnums=(0, 1, 2, 3, 4, 5),
                       out_shardings=self.on_env),
            "learn": jit(self._learn_side, out_shardings=self.on_learners),
            "near": jit(self._near_side, donate_argnums=(1,), out_shardings=self.on_env),
            "finish": jit(self._finish, donate_argnums=(1, 2), out_shardings=self.on_learners)}

    # ------------------------------------------------------------------ the state's layout
    def state_shardings(self, rs: RunState) -> RunState:
        """The shardings of `rs` (a state or its shapes): `LEARNER_SIDE` on the learners' device,
        the rest on the environment's."""
        def side(f: str, tree: Any) -> Any:
            if f == "learners":
                return {n: jax.tree.map(lambda _, s=self._learner_side(n): s, t)
                        for n, t in tree.items()}
            where = self.on_learners if f in LEARNER_SIDE else self.on_env
            return jax.tree.map(lambda _: where, tree)
        return RunState(**{f: side(f, getattr(rs, f)) for f in RunState.__dataclass_fields__})

    def _learner_side(self, name: str) -> SingleDeviceSharding:
        return self.on_env if name in self.near_names else self.on_learners

    def trace(self) -> dict[str, Any]:
        """The programs traced on the abstract state, in `PROGRAMS` order ("near" where the run
        has near learners)."""
        exp = self.exp
        rs, hist = exp.abstract_state(), exp.abstract_state().policy_history
        sides = (self.on_env, self.on_learners)
        k_env, k_learn = (jax.ShapeDtypeStruct((2,), jnp.uint32, sharding=s) for s in sides)
        f_env, f_learn = (jax.ShapeDtypeStruct((), jnp.bool_, sharding=s) for s in sides)
        near, far = self._parts(rs.learners)
        mirror = _on(self._mirror_part(rs.buffers, rs.windows), self.on_env)
        env = self.jits["env"].trace(rs.ppo, rs.train_env, rs.curr_env, rs.rand_env,
                                     hist.get("train"), hist.get("curr"), k_env, k_env, f_env)
        out = {"env": env, "learn": self.jits["learn"].trace(far, rs.buffers, rs.windows, k_learn)}
        if self.near:
            out["near"] = self.jits["near"].trace(near, mirror, k_env, env.out_info.batch)
        held, batch = (_on(x, self.on_learners) for x in (env.out_info.held_out,
                                                         env.out_info.batch))
        out["finish"] = self.jits["finish"].trace(
            _on(rs.learners, self.on_learners), rs.buffers, rs.windows, held, rs.pending,
            rs.probe_set, batch, rs.ref_spread, f_learn)
        return out

    # ------------------------------------------------------------------ the programs
    def _parts(self, learners: dict) -> tuple[dict, dict]:
        """The near learners' states and the others'."""
        return ({n: learners[n] for n in self.near_names},
                {n: s for n, s in learners.items() if n not in self.near_names})

    def _mirror_part(self, buffers: dict, windows: dict) -> tuple[dict, dict]:
        """The buffers the near learners read (frames, windows)."""
        frames, seqs = self.mirror_keys
        return {k: buffers[k] for k in frames}, {k: windows[k] for k in seqs}

    def _units(self, units: list, learners: dict, buffers: dict, windows: dict, key: jax.Array
               ) -> tuple[dict, dict]:
        """`Learning.learn_unit` of each unit of `units`: their new states and metrics."""
        out: tuple[dict, dict] = ({}, {})
        learn_unit = self.exp.learning.learn_unit
        for unit in units:
            for d, part in zip(out, learn_unit(unit, learners, buffers, key, windows)):
                d.update(part)
        return out

    def _env_side(self, ppo: Any, train_env: Any, curr_env: Any, rand_env: Any, train_hist: Any,
                  curr_hist: Any, key: jax.Array, k_eval: jax.Array, flag: jax.Array) -> EnvOut:
        """Epoch t's held-out rollouts where `flag` (`lax.cond`; blanks and the worlds unmoved
        else), with PPO's state of epoch t; then epoch t+1's environment work (`key`: its key)
        up to its frames."""
        exp = self.exp

        def evaluate(ops: tuple) -> tuple:
            return exp.eval_stage(ppo, ops[0], ops[1], None, ops[2], k_eval)

        ops = (curr_env, rand_env, curr_hist)
        shapes = jax.eval_shape(evaluate, ops)[2]

        def skip(ops: tuple) -> tuple:
            return ops[0], ops[1], jax.tree.map(_blank, shapes), ops[2]

        curr_env, rand_env, held_out, curr_hist = jax.lax.cond(flag, evaluate, skip, ops)
        ppo, train_env, train_hist, batch = exp.env_data(ppo, train_env, train_hist, None, key)
        return EnvOut(ppo=ppo, train_env=train_env, curr_env=curr_env, rand_env=rand_env,
                      held_out=held_out, histories={"train": train_hist, "curr": curr_hist},
                      batch=batch)

    def _near_side(self, near: dict, mirror: tuple[dict, dict], k_learn: jax.Array, batch: EnvBatch
                   ) -> tuple:
        """Epoch t's updates of the near learners on the copies of their buffers (`k_learn`:
        epoch t's learning key), then epoch t+1's `batch` into the copies: (near, its metrics,
        the copies)."""
        near, near_m = self._units(self.near, near, *mirror, k_learn)
        return near, near_m, self.exp.insert_buffers(*mirror, batch)

    def _learn_side(self, learners: dict, buffers: dict, windows: dict, k_learn: jax.Array
                    ) -> tuple:
        """Epoch t's updates of the learners other than the near ones."""
        return self._units(self.far, learners, buffers, windows, k_learn)

    def _finish(self, learners: dict, buffers: dict, windows: dict, held_out: Any, pending: dict,
                probe_set: Any, batch: EnvBatch, ref_spread: jax.Array, flag: jax.Array) -> tuple:
        """Epoch t's probes where `flag` (blanks else), then epoch t+1's frames and windows into
        the buffers: (probes, buffers, windows, epoch t+1's `pending`)."""
        exp = self.exp
        common = pv.common_set(probe_set, pending.get("fresh")) if exp.common_probes else None

        def probes(_: Any) -> Any:
            return exp.probing.probe_phase(learners, buffers, held_out, pending["k_probe"], windows,
                                           common)

        shapes = jax.eval_shape(probes, None)
        out = jax.lax.cond(flag, probes, lambda _: jax.tree.map(_blank, shapes), None)
        buffers, windows, nxt = exp.insert_data(buffers, windows, batch, ref_spread)
        return out, buffers, windows, nxt

    # ------------------------------------------------------------------ running
    def prime(self, rs: RunState, key: jax.Array, run: Callable[[str], Callable]) -> RunState:
        """Init's state (all on the environment's device) over both devices, with the first
        epoch's environment work done and inserted (`key`: that epoch's key). `run(name)`: the
        named executable (`PROGRAMS`)."""
        rs = rs.replace(**{f: jax.device_put(getattr(rs, f), self.on_learners) for f in LEARNER_SIDE
                           if f not in ("pending", "learners")})
        rs = rs.replace(learners={n: jax.device_put(s, self._learner_side(n))
                                  for n, s in rs.learners.items()})
        blank = jax.tree.map(_blank, self.exp.abstract_state().pending)
        blank = jax.device_put(blank, self.on_learners)
        return self._step(rs.replace(pending=blank), key, False, run, learn=False)[0]

    def epoch(self, rs: RunState, key: jax.Array, probe: bool, run: Callable[[str], Callable]
              ) -> tuple[RunState, dict[str, Any]]:
        """Epoch t of an apart run (`rs`: epoch t's environment work done, `key`: epoch t+1's):
        the state after it and epoch t's metrics (no `probes` where it does not probe)."""
        return self._step(rs, key, probe, run, learn=True)

    def _step(self, rs: RunState, key: jax.Array, probe: bool, run: Callable[[str], Callable],
              learn: bool) -> tuple[RunState, dict[str, Any]]:
        p, hist = rs.pending, dict(rs.policy_history)
        flag_env, flag_learn = (jax.device_put(jnp.asarray(bool(probe)), s)
                                for s in (self.on_env, self.on_learners))
        near, far = self._parts(rs.learners)
        env_args = (rs.ppo, rs.train_env, rs.curr_env, rs.rand_env, hist.get("train"),
                    hist.get("curr"), jax.device_put(key, self.on_env),
                    jax.device_put(p["k_eval"], self.on_env), flag_env)
        clock = _Clock(self.timings if learn else None)

        def env_side() -> tuple:
            """"env", then "near" on its batch (an epoch, near learners): the environment's device's
            work, dispatched from one thread: (env's `EnvOut`, near's states, their metrics, the
            copies)."""
            outs = clock("env", run("env"), *env_args)
            if not (learn and self.near):
                return outs, near, {}, None
            k = jax.device_put(p["k_learn"], self.on_env)
            return outs, *clock("near", run("near"), near, self._mirror_for(rs), k, outs.batch)

        if learn and self.timings is None:
            with ThreadPoolExecutor(2, thread_name_prefix="bulbjax-apart") as pool:
                learned = pool.submit(run("learn"), far, rs.buffers, rs.windows, p["k_learn"])
                env = pool.submit(env_side)
                far, far_m = learned.result()
                outs, near, near_m, mirror = env.result()
        elif learn:  # a diagnosis: each program alone, timed
            far, far_m = clock("learn", run("learn"), far, rs.buffers, rs.windows, p["k_learn"])
            outs, near, near_m, mirror = env_side()
        else:  # prime: the first epoch's environment work alone
            outs, near, near_m, mirror = env_side()
            far_m = {}
        learn_m = {n: {**far_m, **near_m}[n] for n in rs.learners} if learn else {}
        learners = {n: near[n] if n in near else far[n] for n in rs.learners}
        probes, buffers, windows, pending = clock(
            "finish", run("finish"), {**learners, **jax.device_put(near, self.on_learners)},
            rs.buffers, rs.windows, jax.device_put(outs.held_out, self.on_learners), p,
            rs.probe_set, jax.device_put(outs.batch, self.on_learners), rs.ref_spread, flag_learn)
        self._keep_mirror(mirror, buffers, windows)
        metrics = {**p["metrics"], "learners": learn_m}
        if probe:
            metrics["probes"] = probes
        hist = {k: v for k, v in outs.histories.items() if v is not None}
        new = RunState(ppo=outs.ppo, learners=learners, buffers=buffers, windows=windows,
                       train_env=outs.train_env, curr_env=outs.curr_env, rand_env=outs.rand_env,
                       policy_history=hist, ref_spread=rs.ref_spread,
                       epoch=rs.epoch + 1 if learn else rs.epoch, probe_set=rs.probe_set,
                       pending=pending)
        return new, metrics

    def _mirror_for(self, rs: RunState) -> tuple[dict, dict]:
        """The copies of the near learners' buffers on the environment's device, equal to
        `rs`'s: those the last epoch left where they were made beside `rs`'s buffers, else
        new copies (the first epoch, a resume)."""
        part = self._mirror_part(rs.buffers, rs.windows)
        leaves = jax.tree.leaves(part)
        if self._mirror is None or not leaves or self._mirror_of is not leaves[0]:
            self._mirror = jax.device_put(part, self.on_env)
        mirror, self._mirror = self._mirror, None  # donated to "near"
        return mirror

    def _keep_mirror(self, mirror: tuple[dict, dict] | None, buffers: dict, windows: dict) -> None:
        """Keep "near"'s copies as equal to `buffers` and `windows` (None: no copies; the next
        epoch makes them)."""
        leaves = jax.tree.leaves(self._mirror_part(buffers, windows))
        self._mirror = mirror
        self._mirror_of = leaves[0] if leaves and mirror is not None else None


class _Clock:
    """Calls a program; with `timings` (a dict) waits for it and appends its seconds there."""

    def __init__(self, timings: dict[str, list[float]] | None):
        self.timings = timings

    def __call__(self, name: str, fn: Callable, *args: Any) -> Any:
        if self.timings is None:
            return fn(*args)
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        self.timings.setdefault(name, []).append(time.perf_counter() - t0)
        return out


def near_units(units: list[tuple[str, ...]], setting: str) -> list[tuple[str, ...]]:
    """The units (`Team.units`) of `ExperimentConfig.apart_env_learners` ("auto": pred's where
    it is alone and three units besides; "none"; names joined by commas, a unit's all or none)."""
    if setting == "none":
        return []
    if setting == "auto":
        return [("pred",)] if ("pred",) in units and len(units) >= 4 else []
    names = set(setting.split(","))
    partial = [u for u in units if names & set(u) and not set(u) <= names]
    if partial:
        raise ValueError(f"--apart-env-learners {setting}: {', '.join(partial[0])} share one "
                         "update program (update_groups): name all of them or none")
    return [u for u in units if set(u) <= names]


def _on(tree: Any, sharding: SingleDeviceSharding) -> Any:
    """Abstract arrays of `tree` as they lie after a move to `sharding`."""
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), tree)


def _blank(s: Any) -> jax.Array:
    """NaN (floats) or 0 of a shape: what a program that did not probe returns in its place."""
    return jnp.full(s.shape, jnp.nan if jnp.issubdtype(s.dtype, jnp.inexact) else 0, s.dtype)
