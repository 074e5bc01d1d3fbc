"""Several processes (hosts, or one process per GPU) through JAX's multi-controller runtime.

`initialize` starts `jax.distributed` from explicit settings, from the variables JAX itself reads
(`JAX_COORDINATOR_ADDRESS`, `JAX_LOCAL_DEVICE_IDS`, plus `JAX_NUM_PROCESSES` / `JAX_PROCESS_ID`,
which bulbjax reads for JAX), or from a cluster manager JAX detects (SLURM, Open MPI, ...: every
process gets its count and id from there). Each process then runs the same program over the mesh
of all processes' devices: its own devices compute their seeds, and only process 0 writes files
(`is_writer`). Nothing here launches processes: SLURM's `srun`, `mpirun` or a shell loop over hosts
start one `bulbjax run` per host (or per GPU), each with the same arguments.

On the CPU (tests, the CI) the cross-process collectives need Gloo, which `initialize` switches
on before JAX's backends start.

Leaving in order (issue 56). JAX's coordination service runs in process 0, and every process's
backend (the PjRt-IFRT client) watches the other tasks through it with a background `WatchTasks`
RPC for as long as the backend lives, which is until the process exits. When the service goes
away first (process 0's `jax.distributed.shutdown`, or process 0 leaving Python), that watcher
logs `WatchTasksAsync failed for task N: UNAVAILABLE ... Connection refused` and `CANCELLED` about
once a second until its process is gone (on a GPU, seconds of CUDA teardown: a wall of error
lines after a run that ended well). So the service must outlive every backend. The one-process-
per-GPU launcher (`bulbjax.local_processes`) therefore runs the service itself, in the parent
process, and stops it after every worker has exited; a worker told so by `SERVICE_ENV` joins as a
plain client, process 0 included (`initialize`). Processes started by hand or by SLURM keep JAX's
own arrangement (process 0 serves).

The persistent compile cache: JAX writes its entries from process 0 only. A multi-process run's
processes compile programs of their own (each process's seed groups are other constants), so the
programs of processes 1.. were never cached: every rerun and resume compiled them again while
process 0, its own programs loaded from the cache in seconds, waited at the first collective for
them (the silent minute before a resumed epoch on two GPUs; on the CPU, 33 s of a 46-s compile).
`initialize` lets every process write its own entries (`compile_cache.write_from_every_process`).
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from typing import Any, Iterator

import jax

# set by `bulbjax.local_processes` for its workers: the coordination service runs in the launcher
SERVICE_ENV = "BULBJAX_COORDINATION_SERVICE"
SERVICE_EXTERNAL = "launcher"


@dataclass(frozen=True)
class DistributedConfig:
    """How this process joins a multi-process run (all None and `auto` False: a single process).

    `auto`: let JAX detect a cluster manager (SLURM, Open MPI, ...)."""

    coordinator: str | None = None  # "host:port" of process 0's coordinator service
    num_processes: int | None = None
    process_id: int | None = None
    local_device_ids: tuple[int, ...] | None = None  # this process's GPUs (default: all it sees)
    auto: bool = False

    @classmethod
    def from_env(cls, **given: object) -> "DistributedConfig":
        """Explicit settings (`given`, None where not set) completed from the environment."""
        env = os.environ

        def num(name: str) -> int | None:
            v = env.get(name)
            if v is None or v == "":
                return None
            try:
                return int(v)
            except ValueError as err:
                raise ValueError(f"{name}={v!r} must be an integer") from err

        coordinator = given.get("coordinator") or env.get("JAX_COORDINATOR_ADDRESS") or None
        num_processes = given.get("num_processes")
        process_id = given.get("process_id")
        ids = given.get("local_device_ids")
        return cls(coordinator=coordinator,
                   num_processes=num_processes if num_processes is not None else num("JAX_NUM_PROCESSES"),
                   process_id=process_id if process_id is not None else num("JAX_PROCESS_ID"),
                   local_device_ids=tuple(ids) if ids is not None else None,
                   auto=bool(given.get("auto", False)))

    @property
    def wanted(self) -> bool:
        """Whether a multi-process run was asked for."""
        return self.auto or any(v is not None for v in (self.coordinator, self.num_processes, self.process_id))

    def check(self) -> None:
        """Clear errors for settings JAX would reject later and less clearly."""
        if self.auto:
            return
        missing = [flag for flag, v in (("--coordinator", self.coordinator), ("--num-processes", self.num_processes),
                                        ("--process-id", self.process_id)) if v is None]
        if missing:
            raise ValueError("a multi-process run needs --coordinator HOST:PORT, --num-processes N and "
                             f"--process-id I on every process (missing: {', '.join(missing)}); or "
                             "--distributed to take them from SLURM / Open MPI")
        if ":" not in self.coordinator:
            raise ValueError(f"--coordinator {self.coordinator!r} must read HOST:PORT (process 0's host)")
        if self.num_processes < 1 or not 0 <= self.process_id < self.num_processes:
            raise ValueError(f"--process-id {self.process_id} must be in [0, --num-processes "
                             f"{self.num_processes})")


def initialize(cfg: DistributedConfig) -> bool:
    """Join the multi-process run `cfg` asks for (before anything else touches JAX's devices).
    Returns whether this is a multi-process run. A no-op for a single process. With
    `SERVICE_ENV` set (the launcher's workers), process 0 starts no coordination service: the
    launcher runs it (module doc)."""
    if not cfg.wanted:
        return False
    cfg.check()
    # cross-process all-reduces and gathers of the CPU backend (the GPU's go through NCCL; the
    # setting touches only the CPU client, which JAX also makes beside a GPU one)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    kwargs = {} if cfg.auto else dict(coordinator_address=cfg.coordinator, num_processes=cfg.num_processes,
                                      process_id=cfg.process_id)
    if cfg.local_device_ids is not None:
        kwargs["local_device_ids"] = list(cfg.local_device_ids)
    served_elsewhere = os.environ.get(SERVICE_ENV) == SERVICE_EXTERNAL
    with _service_elsewhere() if served_elsewhere else contextlib.nullcontext():
        jax.distributed.initialize(**kwargs)
    from bulbjax import compile_cache

    compile_cache.write_from_every_process()
    return True


class _ServedElsewhere:
    """Stands for the coordination service in process 0 when the launcher runs it: JAX's
    `jax.distributed.shutdown` calls its `shutdown`, which leaves the real one to the launcher."""

    def shutdown(self) -> None:
        pass


@contextlib.contextmanager
def _service_elsewhere() -> Iterator[None]:
    """`jax.distributed.initialize` without starting the coordination service in process 0.
    JAX has no option for it: its `State.initialize` calls `_jax.get_distributed_runtime_service`
    for process 0, so that one call is answered with a stand-in, through the module reference
    JAX's distributed module holds (checked here, so that a JAX that moved it fails clearly)."""
    from jax._src import distributed as jax_distributed

    real = getattr(jax_distributed, "_jax", None)
    if real is None or not hasattr(real, "get_distributed_runtime_service"):
        raise RuntimeError(f"{SERVICE_ENV}={SERVICE_EXTERNAL}: this JAX ({jax.__version__}) has no "
                           "jax._src.distributed._jax.get_distributed_runtime_service to stand in "
                           "for; start the processes by hand (--coordinator ...) instead")

    class _Module:
        def __getattr__(self, name: str) -> Any:
            return getattr(real, name)

        @staticmethod
        def get_distributed_runtime_service(*args: Any, **kwargs: Any) -> _ServedElsewhere:
            return _ServedElsewhere()

    jax_distributed._jax = _Module()
    try:
        yield
    finally:
        jax_distributed._jax = real


def start_service(port: int, num_processes: int) -> Any:
    """JAX's coordination service for `num_processes` processes on `port` (all interfaces, as
    JAX binds it), in this process, without a JAX backend: the launcher's (module doc). Returns
    the service; its `shutdown()` stops it."""
    from jax._src.lib import _jax

    return _jax.get_distributed_runtime_service(f"[::]:{port}", num_processes)


def active() -> bool:
    """Whether this process has joined a multi-process run (`jax.distributed` is up)."""
    from jax._src import distributed as jax_distributed

    return jax_distributed.global_state.client is not None


def process_count() -> int:
    return jax.process_count()


def is_writer() -> bool:
    """Whether this process writes the run's files (metrics, config, reports): process 0."""
    return jax.process_index() == 0


def broadcast_flags(*values: bool) -> tuple[bool, ...]:
    """Process 0's `values` on every process, in one collective (decisions all must share, e.g.
    whether to stop after this epoch: each process's own clock or signal could differ). Free for
    one process."""
    if jax.process_count() == 1:
        return tuple(bool(v) for v in values)
    from jax.experimental import multihost_utils

    import numpy as np

    out = multihost_utils.broadcast_one_to_all(np.asarray(values, np.int32))
    return tuple(bool(v) for v in np.asarray(out))


def broadcast_flag(value: bool) -> bool:
    """Process 0's `value` on every process (`broadcast_flags` of one flag)."""
    return broadcast_flags(value)[0]


def allgather(tree: Any) -> Any:
    """Every process's host arrays (same tree, shapes and dtypes on each), concatenated over
    processes along their first axis (process order; 0-d leaves are stacked).

    One collective for the whole tree: the leaves travel packed as one byte array.
    `multihost_utils.process_allgather` runs a jitted all-gather (and a host sync) per leaf, and
    an epoch's metrics have hundreds of leaves: ~0.1 s an epoch on two GPUs, paid by every
    epoch of a multi-process run."""
    import numpy as np

    leaves, treedef = jax.tree.flatten(tree)
    arrays = [np.ascontiguousarray(np.asarray(x)) for x in leaves]
    if jax.process_count() == 1:
        return jax.tree.unflatten(treedef, [a if a.ndim else a[None] for a in arrays])
    from jax.experimental import multihost_utils

    packed = np.concatenate([a.reshape(-1).view(np.uint8) for a in arrays] + [np.zeros(0, np.uint8)])
    every = np.asarray(multihost_utils.process_allgather(packed, tiled=False))  # [P, bytes]
    out, at = [], 0
    for a in arrays:
        parts = [every[p, at:at + a.nbytes].copy().view(a.dtype).reshape(a.shape) for p in range(every.shape[0])]
        out.append(np.concatenate(parts, 0) if a.ndim else np.stack(parts))
        at += a.nbytes
    return jax.tree.unflatten(treedef, out)


def barrier(name: str) -> None:
    """Wait until every process got here (no-op for one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def shutdown() -> None:
    """Leave the multi-process run in order: JAX's shutdown barrier (every process gets there
    before any client disconnects), then, in a process 0 that serves, the service. A no-op for
    one process. Where the launcher runs the service (module doc), no backend ever sees it go."""
    if active():
        jax.distributed.shutdown()
