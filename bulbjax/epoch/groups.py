"""A run's seeds over several GPUs and processes: seed groups, one program per device.

The seeds of a run are independent but for one number, the reference spread pooled over all
their random-policy worlds (`Experiment.init_env`). So a run over D devices is D experiments of
S/D seeds each (a *seed group*), one per device, each compiled as a one-device program and
dispatched side by side (JAX runs them asynchronously, one stream per GPU). Every random draw of
a group is its seeds' share of the whole run's draw (`Experiment(seed_group=...)`,
`seeds.SeedGroup`), and the reference spread is pooled over all groups, so the metrics are the ones
a single device computes for all S seeds, up to floating-point reassociation (tested on the CPU).

Why not one program sharded over a mesh (`shard_map` for the simulators, XLA's partitioner for the
rest, the form `Experiment` still has): on GPUs XLA segfaults while compiling any multi-device
program that holds an MJX-Warp FFI call. `benchmarks/diagnostics/diag_multigpu.py` (two H200s, jax 0.11.2,
mujoco-warp 4.0.0, warp-lang 1.19.0) shows it for a lone env reset under `shard_map` in every Warp
graph mode (WARP, NONE, WARP_STAGED_EX), under `jax.pmap` (in this JAX a shard_map), and with
one GPU per process under `jax.distributed`; the same reset, render and six-learner init run on
either GPU alone and on both side by side. With several processes (`bulbjax.distributed`), each
process runs the groups of its own devices and the metrics and reference states are gathered
over processes (`distributed.allgather`: one packed all-gather, a program without Warp).

`form`: "groups" (the default wherever more than one device is given), "sharded" (one program over
a mesh of the devices: the CPU's host devices in tests; on GPUs it is refused in one line and the
run uses groups) or "single" (the first device only).
"""

from __future__ import annotations

import dataclasses
import functools
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from bulbjax import compile_cache, distributed
from bulbjax.config import ExperimentConfig
from bulbjax.epoch.loop import Experiment
from bulbjax.epoch.programs import Programs, in_thread
from bulbjax.epoch.state import RunState
from bulbjax.eval import probe

FORMS = ("auto", "groups", "sharded", "single")


def group_count(seeds: int, devices: int, processes: int = 1) -> int:
    """Seed groups of a run: the largest divisor of `seeds` that fits in `devices` and gives every
    process as many groups as the others (a multiple of `processes`)."""
    fits = [g for g in range(1, min(seeds, devices) + 1) if seeds % g == 0 and g % processes == 0]
    if not fits:
        raise ValueError(f"{seeds} seeds cannot be split evenly over {processes} processes: give --seeds a "
                         f"multiple of {processes} (each process runs the same number of seeds)")
    return max(fits)


class SeedGroups:
    """The experiments of one run on this process's devices, as one object the run loop drives:
    `init`, `epoch` (metrics of all the run's seeds, in seed order), `abstract_state` (for
    checkpoints: one RunState, or a tuple of them with several local groups)."""

    def __init__(self, cfg: ExperimentConfig, devices: Sequence[jax.Device] | None = None,
                 compiler_options: dict[str, Any] | None = None, form: str = "auto",
                 log: Callable[[str], None] = print):
        if form not in FORMS:
            raise ValueError(f"form must be one of {FORMS}, got {form!r}")
        devices = list(devices) if devices is not None else jax.devices()
        me = jax.process_index()
        local = [d for d in devices if d.process_index == me]
        processes = len({d.process_index for d in devices})
        if not local:
            raise ValueError(f"none of the devices given belongs to this process ({me})")
        if processes > 1 and form in ("sharded", "single"):
            raise ValueError(f"form {form!r} runs in one process; a run over {processes} processes uses seed groups")
        if form == "sharded" and local[0].platform == "gpu" and len(local) > 1:
            log("one program sharded over several GPUs does not compile with MJX-Warp (XLA segfaults; "
                "benchmarks/diagnostics/diag_multigpu.py): running one seed group per GPU instead")
            form = "groups"
        # a group's devices: one, or two with the learners apart (the environment's, the learners')
        k = 2 if cfg.overlap == "apart" else 1
        if form == "auto":
            form = "groups" if len(devices) > k else "single"
        self.form = form
        self.processes = processes
        self.config = cfg
        if form in ("sharded", "single"):
            devs = local if form == "sharded" else local[:k]
            self.exps = [Experiment(cfg, devices=devs, compiler_options=compiler_options)]
            self.groups, self.offsets = 1, [0]
        else:
            per_process = {p: sum(d.process_index == p for d in devices) // k for p in range(processes)}
            g = group_count(cfg.seeds, min(per_process.values()) * processes, processes)
            self.groups = g
            sg, gl = cfg.seeds // g, g // processes
            rank = sorted(per_process).index(me)
            first = rank * gl
            self.offsets = [(first + i) * sg for i in range(gl)]
            sub = cfg if g == 1 else dataclasses.replace(cfg, seeds=sg)
            self.exps = [Experiment(sub, devices=local[k * i:k * (i + 1)], compiler_options=compiler_options,
                                    seed_group=None if g == 1 else (self.offsets[i], cfg.seeds))
                         for i in range(gl)]
        self.exp = self.exps[0]
        self.spec = self.exp.spec
        self.env = self.exp.env
        self._programs: list[Any] = []

    @classmethod
    def of(cls, exp: Experiment) -> "SeedGroups":
        """A built experiment (one device, or sharded over a mesh) as the run loop drives it."""
        self = cls.__new__(cls)
        self.form = "sharded" if exp.sharded else "single"
        self.processes, self.config, self.groups, self.offsets = 1, exp.config, 1, [0]
        self.exps, self.exp, self.spec, self.env = [exp], exp, exp.spec, exp.env
        self._programs = []
        return self

    # ------------------------------------------------------------------ description
    @property
    def devices(self) -> list[jax.Device]:
        """This process's devices that compute (one per local group, or the sharded mesh's; and each
        group's learners' device with the learners apart)."""
        return [d for e in self.exps
                for d in [*e.devices.local_mesh_devices(), *([e.apart.learner_device] if e.apart else [])]]

    def describe(self) -> str:
        """One line: how the seeds lie over devices and processes."""
        kind = self.exp.devices.local_mesh_devices()[0].device_kind
        if self.form == "groups" and self.groups > 1:
            where = f"{self.groups} seed groups of {self.config.seeds // self.groups} seeds, one per {kind}"
            if self.processes > 1:
                where += f", over {self.processes} processes ({len(self.exps)} here)"
            return where
        if self.form == "sharded":
            return f"one program sharded over {self.exp.mesh.size} x {kind} (mesh {dict(self.exp.mesh.shape)})"
        return f"1 x {kind}" + (" and 1 for the learners (--overlap apart)" if self.exp.apart else "")

    def provenance(self) -> dict[str, Any]:
        return {"layout": self.form, "seed_groups": self.groups, "processes": self.processes,
                "devices_used": len(self.devices) * self.processes, "mesh": dict(self.exp.mesh.shape)}

    # ------------------------------------------------------------------ programs
    def programs(self, probes: Sequence[bool]) -> "SeedGroups":
        """Trace every group's init and epoch (group by group, in one fixed order: see `Programs`)."""
        self._programs = [Programs.of(e, probes) for e in self.exps]
        return self

    def startup(self, resume: bool) -> tuple[str, ...]:
        """The programs a stretch compiles before its first epoch (`Programs.startup`)."""
        return self._programs[0].startup(resume)

    def prepare(self, *which: str) -> "SeedGroups":
        for p in self._programs:
            p.prepare(*which)
        return self

    def warm_physics(self, key: jax.Array) -> Future | None:
        """Every local group's `Devices.warm_physics` in a background thread (the groups one after
        another: the first builds MuJoCo Warp's kernels, the others find them loaded), started
        once the run's programs are traced and compiling; the run waits for it before init runs.
        None (nothing started) with `BULBJAX_WARM_PHYSICS=0`, the measurement's "before"."""
        if not compile_cache.env_on("BULBJAX_WARM_PHYSICS"):
            return None
        exps = list(self.exps)

        def warm() -> None:
            for e in exps:
                e.devices.warm_physics(key)

        return in_thread(warm, name="bulbjax-warm-physics")

    def settle(self) -> None:
        """Wait for every group's compiles still running (`Programs.settle`)."""
        for p in self._programs:
            p.settle()

    def compiled(self, which: str) -> list[Any]:
        """Every group's compiled program `which` (`Programs.compiled`: waits for its compile)."""
        return [p.compiled(which) for p in self._programs]

    def _unwrap(self, state: Any) -> list[RunState]:
        return [state] if len(self.exps) == 1 else list(state)

    def _wrap(self, states: list[RunState]) -> Any:
        return states[0] if len(self.exps) == 1 else tuple(states)

    def abstract_state(self) -> Any:
        return self._wrap([e.abstract_state() for e in self.exps])

    def abstract_key(self) -> jax.ShapeDtypeStruct:
        return self.exp.abstract_key()

    def put_key(self, key: jax.Array) -> jax.Array:
        return self.exp.put_key(key)

    # ------------------------------------------------------------------ running
    def init(self, key: jax.Array) -> Any:
        """Every local group's initial state; with several groups the reference spread is pooled
        over all of them (all processes), as one experiment of all the seeds pools it."""
        states = _side_by_side([functools.partial(p.init, key) for p in self._programs])
        if self.groups > 1:
            ref = [jax.jit(e.reference_states)(e.put_key(key)) for e in self.exps]
            ref = np.concatenate([np.asarray(r) for r in jax.device_get(ref)], axis=1)  # [T, Sl*N, D]
            if self.processes > 1:
                ref = distributed.allgather(np.ascontiguousarray(ref.swapaxes(0, 1))).swapaxes(0, 1)
            targets = self.exps[0].targets  # the probes' targets: the states and what derives from them
            spread = jax.jit(lambda r: probe.spread(targets(r)))(jnp.asarray(ref.reshape((-1, ref.shape[-1]))))
            states = [rs.replace(ref_spread=jax.device_put(spread, e.devices.replicated))
                      for rs, e in zip(states, self.exps)]
        return self._wrap(states)

    def prime(self, state: Any, key: jax.Array) -> Any:
        """Every local group's first epoch's environment work on init's state (a pipelined run,
        `ExperimentConfig.overlap`; `state` donated); the state itself otherwise."""
        if not self.exp.pipelined:
            return state
        return self._wrap(_side_by_side([functools.partial(p.prime, rs, key)
                                         for p, rs in zip(self._programs, self._unwrap(state))]))

    def epoch(self, state: Any, key: jax.Array, probe: bool = True) -> tuple[Any, dict[str, Any]]:
        """One epoch of every local group (dispatched together, run side by side on their devices;
        `state` donated). Returns the new state and the metrics of all the run's seeds (host
        arrays, seed axis first, in seed order)."""
        outs = _side_by_side([functools.partial(p.epoch, rs, key, probe=probe)
                              for p, rs in zip(self._programs, self._unwrap(state))])
        metrics = [jax.device_get(m) for _, m in outs]
        m = metrics[0] if len(metrics) == 1 else jax.tree.map(lambda *xs: np.concatenate(xs, 0), *metrics)
        if self.processes > 1:
            m = jax.tree.map(np.asarray, m)
            m = distributed.allgather(m)
        return self._wrap([rs for rs, _ in outs]), m

    def group_state(self, state: Any, index: int = 0) -> RunState:
        """The RunState of local group `index` (e.g. for the reconstruction figures of seed 0)."""
        return self._unwrap(state)[index]


def _side_by_side(calls: list[Callable[[], Any]]) -> list[Any]:
    """Each call in a thread of its own, results in order. A GPU program with MJX-Warp holds the
    thread that runs it until its last kernel is launched (its loops and FFI calls are driven
    from the host), so groups called one after another from one thread run one after another."""
    if len(calls) == 1:
        return [calls[0]()]
    with ThreadPoolExecutor(len(calls), thread_name_prefix="bulbjax-group") as pool:
        return list(pool.map(lambda c: c(), calls))
