"""A run's init and epoch executables: traced in one fixed order, compiled side by side, then
only called (`Programs`); an epoch as one program or as several (`Stages`)."""

from __future__ import annotations

import functools
import os
import threading
import time
from concurrent.futures import Future
from typing import Any, Callable, Sequence

import jax

from jax.sharding import Mesh

from bulbjax.config import PROGRAM_FORMS
from bulbjax.epoch.loop import Experiment
from bulbjax.epoch.probe_variants import common_set
from bulbjax.epoch.state import RunState


def resolve_programs(choice: str, mesh: Mesh) -> str:
    """How init and the epoch are compiled (`ExperimentConfig.programs`), checked against the
    mesh: split programs run on one device (a sharded run's layouts are set on the fused
    programs' outputs)."""
    if choice not in PROGRAM_FORMS:
        raise ValueError(f"programs must be one of {PROGRAM_FORMS}, got {choice!r}")
    if choice == "split" and mesh.size > 1:
        raise ValueError("programs='split' runs on one device; this run's mesh has "
                         f"{mesh.size} devices: use 'fused'")
    return choice


class Stages:
    """Init and the epoch as several programs, run one after another with nothing fetched to the
    host in between, the same steps in the same order as the fused programs (`Experiment._init`,
    `Experiment._epoch`) and so the same numbers up to floating-point reassociation.

    Why: XLA runs one program's HLO passes on one thread, so the parts as programs of their own
    might compile side by side (`Programs.prepare` starts each in a thread). The parts: init's
    environment half and each learner's init; the epoch's environment work
    (`Experiment.env_stage`), one update program per unit (`Team.units`: the VAE group, each
    other learner; `Learning.learn_unit`), the held-out rollouts (`Experiment.eval_stage`) and
    one probe program per unit (`Probing.probe_unit`),
    the last two only in epochs that probe (a Python choice: no `lax.cond`). Measured on an H100
    (fig2-invpend, 6 learners x 6 seeds, 2026-11-25) it does not start sooner: on one machine
    the first epoch came after 223 s against the fused programs' 205 s (195 s on another).
    XLA's autotuning does not run side by side on one GPU: two VAE updates compiled in threads
    took 58.8 s, one after the other 20.0 s (`diag_parallel_compile.py`: benchmarks/diagnostics/README.md).
    Kept as an option (`ExperimentConfig.programs="split"`). One device only: the sharded run's
    layouts are set on the fused programs' outputs."""

    def __init__(self, exp: Experiment) -> None:
        if exp.sharded:
            raise ValueError("split programs run on one device; a run over several devices uses "
                             "the fused programs (programs='fused')")
        self.exp = exp
        self.units = exp.team.units()
        opts = exp.compiler_options or None
        jit = functools.partial(jax.jit, compiler_options=opts)
        self.jits: dict[str, Any] = {"init/env": jit(exp.init_env)}
        for n in exp.learners:
            self.jits[f"init/learner/{n}"] = jit(functools.partial(exp.learning.init_learner, n))
        # donated: what the stage replaces (its outputs take their buffers)
        self.jits["epoch/env"] = jit(exp.env_stage, donate_argnums=(0, 1, 2, 3, 4))
        for u in self.units:
            self.jits[self.learn_name(u)] = jit(functools.partial(exp.learning.learn_unit, u), donate_argnums=0)
        self.jits["epoch/eval"] = jit(exp.eval_stage, donate_argnums=(1, 2, 4))
        for u in self.units:
            self.jits[self.probe_name(u)] = jit(functools.partial(exp.probing.probe_unit, u))

    def common(self, probe_set: Any, fresh: Any, abstract: bool = False) -> Any:
        """The common probe set of an epoch (`probe_variants.common_set`; None without the
        variant), or its shapes (`abstract`)."""
        if not self.exp.common_probes:
            return None
        if abstract:
            return jax.eval_shape(common_set, probe_set, fresh)
        return common_set(probe_set, fresh)

    @staticmethod
    def learn_name(unit: Sequence[str]) -> str:
        return "epoch/learn/" + "+".join(unit)

    @staticmethod
    def probe_name(unit: Sequence[str]) -> str:
        return "epoch/probe/" + "+".join(unit)

    def trace(self, probes: bool) -> dict[str, Any]:
        """Every program traced on abstract arguments, in one fixed order (see `Programs`); the
        eval and probe programs only if some epoch `probes`."""
        exp, rl_learners = self.exp, self.exp.policy.rl_learners
        rs, key = exp.abstract_state(), exp.abstract_key()
        hist = rs.policy_history
        t: dict[str, Any] = {"init/env": self.jits["init/env"].trace(key)}
        for n in exp.learners:
            t[f"init/learner/{n}"] = self.jits[f"init/learner/{n}"].trace(key)
        t["epoch/env"] = self.jits["epoch/env"].trace(rs.ppo, rs.train_env, rs.buffers, rs.windows,
                                                      hist.get("train"), rl_learners(rs.learners),
                                                      rs.ref_spread, rs.epoch, key)
        for u in self.units:
            t[self.learn_name(u)] = self.jits[self.learn_name(u)].trace(_members(rs.learners, u), rs.buffers,
                                                                        key, rs.windows)
        if probes:
            t["epoch/eval"] = self.jits["epoch/eval"].trace(rs.ppo, rs.curr_env, rs.rand_env,
                                                            rl_learners(rs.learners), hist.get("curr"), key)
            held = t["epoch/eval"].out_info[2]
            common = self.common(rs.probe_set, t["epoch/env"].out_info.fresh, abstract=True)
            for u in self.units:
                probe = self.jits[self.probe_name(u)]
                t[self.probe_name(u)] = probe.trace(_members(rs.learners, u), rs.buffers, held, key,
                                                    rs.windows, common)
        return t

    def init(self, run: Callable[[str], Callable], key: jax.Array) -> RunState:
        """`Experiment.init` from the programs (`run(name)`: the named executable)."""
        rs = run("init/env")(key)
        return rs.replace(learners={n: run(f"init/learner/{n}")(key) for n in self.exp.learners})

    def epoch(self, run: Callable[[str], Callable], rs: RunState, key: jax.Array, probe: bool
              ) -> tuple[RunState, dict[str, Any]]:
        """`Experiment.epoch` from the programs (`rs` donated); metrics without `probes` when
        not probing."""
        exp, rl_learners = self.exp, self.exp.policy.rl_learners
        hist = dict(rs.policy_history)
        env = run("epoch/env")(rs.ppo, rs.train_env, rs.buffers, rs.windows, hist.get("train"),
                               rl_learners(rs.learners), rs.ref_spread, rs.epoch, key)
        if env.train_hist is not None:
            hist["train"] = env.train_hist
        learners, learn_m = {}, {}
        for u in self.units:
            states, m = run(self.learn_name(u))(_members(rs.learners, u), env.buffers, env.k_learn, env.windows)
            learners.update(states)
            learn_m.update(m)
        learners = {n: learners[n] for n in exp.learners}
        metrics = {**env.metrics, "learners": {n: learn_m[n] for n in exp.learners}}
        curr_env, rand_env = rs.curr_env, rs.rand_env
        if probe:
            curr_env, rand_env, held, curr_hist = run("epoch/eval")(env.ppo, curr_env, rand_env,
                                                                    rl_learners(learners), hist.get("curr"),
                                                                    env.k_eval)
            if curr_hist is not None:
                hist["curr"] = curr_hist
            probes: dict[str, Any] = {}
            common = self.common(rs.probe_set, env.fresh)
            for u in self.units:
                probes.update(run(self.probe_name(u))(_members(learners, u), env.buffers, held, env.k_probe,
                                                      env.windows, common))
            metrics["probes"] = {n: probes[n] for n in exp.learners}
        new = RunState(ppo=env.ppo, learners=learners, buffers=env.buffers, windows=env.windows,
                       train_env=env.train_env, curr_env=curr_env, rand_env=rand_env, policy_history=hist,
                       ref_spread=rs.ref_spread, epoch=env.epoch, probe_set=rs.probe_set)
        return new, metrics


def _members(learners: dict, unit: Sequence[str]) -> dict:
    return {n: learners[n] for n in unit}


class Programs:
    """A run's init and epoch executables, traced in one fixed order and then only called.

    A pipelined run (`ExperimentConfig.overlap`) has a third program, `prime`, traced between init
    and the epoch.

    MuJoCo Warp writes two per-process counters into every program that steps or renders: the
    FFI target's name (`<function>_<n>`, numbered in the order the targets are first traced)
    and each call site's `call_id` (numbered in the order the call sites are traced). Both are
    part of the compiled program and so of its persistent compile-cache key. A process that
    traced anything else first, or traced the same function twice (a jit call whose arguments
    differ in placement from an earlier trace retraces it: on the GPU a fresh run's `init` call
    did, a resumed run never calls `init`), numbers the calls differently and misses the
    cache: minutes of compile for every resumed stretch on the GPU. Here every process, fresh
    or resumed, traces `init` and then the epoch on abstract arguments before anything runs,
    and later calls go to executables compiled from exactly those traces, so nothing is traced
    again.

    Fused (`ExperimentConfig.programs` "fused", `resolve_programs`; or `split=False`): one init
    and one epoch program. A run that probes every epoch (`probes=(True,)`) gets the probing
    epoch, one that probes some epochs (`(True, False)`) gets `Experiment.epoch_flag`, whose
    flag switches the probes on. Split: the programs of `Stages`, named `init/...` and
    `epoch/...`, traced in their fixed order.
    `prepare(names)` compiles (or loads from the compile cache) in background threads, so that
    the programs' compiles overlap each other and a resume's checkpoint restore; a program not
    prepared compiles on first use. A name is a program's or a group's (`"init"`, `"epoch"`:
    all the programs of init or of the epoch)."""

    def __init__(self, exp: Experiment, probes: Sequence[bool], split: bool | None = None) -> None:
        key, rs = exp.abstract_key(), exp.abstract_state()
        self._exp = exp
        self.probes = frozenset(bool(p) for p in probes)
        if not self.probes:
            raise ValueError("Programs needs at least one probe value (True, False or both)")
        self.flag = len(self.probes) == 2
        self.split = resolve_programs(exp.config.programs, exp.mesh) == "split" if split is None else bool(split)
        self._stages: Stages | None = None
        if self.split:
            self._stages = Stages(exp)
            self._traced: dict[str, Any] = self._stages.trace(True in self.probes)
        else:
            self._traced = {"init": exp.init.trace(key)}
            if exp.apart is not None:  # the learners apart: three programs on two devices (`apart.Apart`)
                self._traced.update({f"epoch/{n}": t for n, t in exp.apart.trace().items()})
            else:
                if exp.pipelined:  # the first epoch's environment work on init's state (`Experiment.prime`)
                    self._traced["prime"] = exp.prime.trace(exp.abstract_init_state(), key)
                if self.flag:
                    self._traced["epoch"] = exp.epoch_flag.trace(rs, key, exp.abstract_flag())
                else:
                    self._traced["epoch"] = exp.epoch.trace(rs, key, probe=next(iter(self.probes)))
        self._lowered: dict[str, Any] = {}
        self._compiled: dict[str, Future] = {}
        self._chain: Future | None = None  # the compile started last (`prepare`)
        self._t0 = time.perf_counter()
        # per program: (start, end) of its compile (or cache load), seconds after the programs were
        # traced (lowering, then compiling, begins then: `prepare`)
        self.compile_spans: dict[str, tuple[float, float]] = {}

    @classmethod
    def of(cls, exp: Experiment, probes: Sequence[bool] = (True, False)) -> "Programs":
        """The init and epoch executables of a run of `exp` (`probes`: which epochs it runs),
        traced in one fixed order before anything runs. Kept per `probes` on the experiment
        (`Experiment.programs_cache`), so that several runs of one experiment in a process
        (tests) compile once."""
        probes = tuple(bool(p) for p in probes)
        if probes not in exp.programs_cache:
            exp.programs_cache[probes] = cls(exp, probes)
        return exp.programs_cache[probes]

    @property
    def names(self) -> list[str]:
        """Every program's name, in trace order."""
        return list(self._traced)

    def members(self, which: str) -> list[str]:
        """The programs a name stands for: itself, or a group's (`"epoch"` -> `epoch/...`)."""
        out = [n for n in self._traced if n == which or n.startswith(which + "/")]
        if not out:
            raise KeyError(f"no program {which!r}; these programs: {', '.join(self._traced)}")
        return out

    def lowered(self, which: str) -> Any:
        """The lowered program (e.g. `"init"`, `"epoch"`, or a split program's name): what is
        compiled, e.g. for its text."""
        if which not in self._traced:
            raise KeyError(f"no single program {which!r}; these programs: {', '.join(self._traced)}")
        if which not in self._lowered:
            self._lowered[which] = self._traced[which].lower()
        return self._lowered[which]

    def prepare(self, *which: str) -> "Programs":
        """Start compiling the named programs (or groups): each is lowered here, in trace order,
        then compiled in a background thread of its own, side by side; with
        `BULBJAX_COMPILE_ORDER=sequential` each compile waits for the one started before it."""
        for w in which:
            for n in self.members(w):
                if n not in self._compiled:
                    after = self._chain if compile_order() == "sequential" else None
                    self._compiled[n] = in_thread(functools.partial(self._compile, n, self.lowered(n), after))
                    self._chain = self._compiled[n]
        return self

    def _compile(self, name: str, lowered: Any, after: Future | None = None) -> Any:
        if after is not None:
            after.exception()  # waits; its error is raised where its own result is asked for
        t = time.perf_counter() - self._t0
        out = lowered.compile()
        self.compile_spans[name] = (t, time.perf_counter() - self._t0)
        return out

    def settle(self) -> None:
        """Wait for the compiles still running, their results unused (e.g. a resume of a run that
        has no epoch left): a process that exits while XLA compiles in a daemon thread is aborted
        by the C++ runtime ("FATAL: exception not rethrown", exit -6; benchmarks/kill_resume.py)."""
        for fut in self._compiled.values():
            try:
                fut.result()
            except BaseException:  # noqa: BLE001  (a compile nobody asked for: its error is moot)
                pass

    def compiled(self, which: str) -> Any:
        """The compiled program, waiting for (or starting) its compile; for a group's name, every
        member compiled, as `{name: executable}`."""
        names = self.members(which)
        self.prepare(*names)
        if names == [which]:
            return self._compiled[which].result()
        return {n: self._compiled[n].result() for n in names}

    def init(self, key: jax.Array) -> RunState:
        """`Experiment.init` of a host PRNG key (placed on the mesh here)."""
        if self._stages is not None:
            self.prepare("init")
            return self._stages.init(self.compiled, self._exp.put_key(key))
        return self.compiled("init")(self._exp.put_key(key))

    def prime(self, rs: RunState, key: jax.Array) -> RunState:
        """`Experiment.prime` (`rs`, init's state, donated): a pipelined run's first epoch's
        environment work; the key, that epoch's, is placed on the mesh here. With the learners
        apart, `Apart.prime` from the epoch's programs."""
        if self._exp.apart is not None:
            return self._exp.apart.prime(rs, key, self._apart_program)
        return self.compiled("prime")(rs, self._exp.put_key(key))

    def _apart_program(self, name: str) -> Any:
        return self.compiled(f"epoch/{name}")

    def startup(self, resume: bool) -> tuple[str, ...]:
        """The programs (or groups) a run compiles before its first epoch: init (a fresh run), a
        pipelined run's `prime`, the epoch."""
        prime = ("prime",) if "prime" in self._traced and not resume else ()
        return (*(() if resume else ("init",)), *prime, "epoch")

    def epoch(self, rs: RunState, key: jax.Array, probe: bool = True) -> tuple[RunState, Any]:
        """`Experiment.epoch` (`rs` donated); the key is placed on the mesh here. The metrics of
        an epoch that does not probe have no `probes`, whichever program ran it."""
        probe = bool(probe)
        if probe not in self.probes:
            raise KeyError(f"this run's epoch was traced for probe in {sorted(self.probes)}, not {probe!r}: "
                           "pass every probe value the run uses to Programs.of")
        if self._stages is not None:
            self.prepare("epoch")
            return self._stages.epoch(self.compiled, rs, self._exp.put_key(key), probe)
        if self._exp.apart is not None:
            self.prepare("epoch")
            return self._exp.apart.epoch(rs, key, probe, self._apart_program)
        if not self.flag:
            return self.compiled("epoch")(rs, self._exp.put_key(key))
        rs, m = self.compiled("epoch")(rs, self._exp.put_key(key), self._exp.put_flag(probe))
        return rs, m if probe else without_probes(m)


def without_probes(metrics: dict[str, Any]) -> dict[str, Any]:
    """An `epoch_flag` epoch's metrics as a non-probing epoch has them: no `probes` (its NaN/0
    placeholders dropped)."""
    return {k: v for k, v in metrics.items() if k != "probes"}


COMPILE_ORDERS = ("side-by-side", "sequential")


def compile_order() -> str:
    """`BULBJAX_COMPILE_ORDER`: "side-by-side" (the default: every program in its own thread at
    once) or "sequential" (one after another, in trace order: init, then the epoch). On a GPU
    XLA autotunes the convolutions of programs compiled side by side 2.5-2.9x more slowly, and a
    program compiled after another finds the kernels they share in XLA's per-fusion autotune
    cache (JAX keeps it beside the compile cache), so sequential may start a cold run sooner
    (issue 56; to be measured on a GPU: docs/performance.md, "Start-up")."""
    order = os.environ.get("BULBJAX_COMPILE_ORDER", "side-by-side").strip().lower()
    if order not in COMPILE_ORDERS:
        raise ValueError(f"BULBJAX_COMPILE_ORDER={order!r}: use one of {', '.join(COMPILE_ORDERS)}")
    return order


def in_thread(fn: Callable[[], Any], name: str = "bulbjax-compile") -> Future:
    """`fn()` in a daemon thread (an XLA compile releases the GIL), its result as a Future. Daemon:
    a process that fails meanwhile exits without waiting for a compile it no longer needs."""
    fut: Future = Future()

    def run() -> None:
        try:
            fut.set_result(fn())
        except BaseException as e:  # re-raised by fut.result() in the caller's thread
            fut.set_exception(e)

    threading.Thread(target=run, daemon=True, name=name).start()
    return fut
