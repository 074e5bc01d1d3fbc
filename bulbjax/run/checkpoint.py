"""Checkpoints of a whole run with orbax: the `RunState` (PPO, learners, optimisers, replay and
window buffers, env states with their mjx.Data, keys, epoch counter, reference spread) and the
host-side PRNG key chain of the run loop, written atomically, the last K kept. Each process of
a multi-process run keeps its own groups' states in plain files instead (`ProcessFiles`).

The pytree is saved as a flat dict of its leaves, named by their index in `jax.tree.flatten`
order, because orbax refuses zero-size arrays (mjx.Data has many, e.g. `act` of a model
without activations): those are left out and rebuilt as zeros on restore. The leaves' tree paths
go into the checkpoint's JSON metadata, so a checkpoint of a different run layout (other learners,
env, seeds or device count) is refused with a clear error instead of being misread.

A checkpoint is only taken between jitted calls (after an epoch, or after a chunk of epochs once
several run in one call), so every saved state is a state the run loop itself held.

`background=True` (the run loop's): checkpoints are written while the loop goes on, by orbax's
asynchronous save (one process) or a thread of `ProcessFiles` (each process of a multi-process
run); the loop waits only for the host copy of the state (the next epoch reuses the device
buffers: they are donated, and on the CPU a fetched array may share them) and, at its next
checkpoint or at the end, for the previous write. A write that failed raises
`CheckpointWriteError` there, naming its epoch. Checkpoints saved from host copies restore into
device arrays as before (orbax reads them by the restore target's shapes and shardings).
"""

from __future__ import annotations

import json
import os
import shutil
import threading
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

CHECKPOINT_DIR = "checkpoints"
_FORMAT = 1


class CheckpointWriteError(Exception):
    """A checkpoint written in the background failed (`epoch`: its epoch; `__cause__`: why)."""

    def __init__(self, epoch: int, cause: BaseException):
        super().__init__(f"the checkpoint of epoch {epoch}: {type(cause).__name__}: {cause}")
        self.epoch = epoch


def _host_copies(xs: list[Any]) -> list[np.ndarray]:
    """`xs` on the host, each in memory of its own, fetched by one `jax.device_get` of the list:
    it starts every device-to-host copy before waiting for the first, where a fetch per array
    waited for each in turn (a run state is ~1,000 arrays; a checkpoint held the loop for 1.4-3.3
    s on two H200s, fig2-invpend, 3 seeds per GPU). A CPU device's array fetched to numpy may
    share the device buffer, which the next epoch (its state donated) overwrites while a
    background write still reads it: those are copied; a GPU's come back in fresh host memory."""
    fetched = jax.device_get(list(xs))

    def own(x: Any, host: Any) -> np.ndarray:
        host = np.asarray(host)
        on_cpu = isinstance(x, jax.Array) and any(d.platform == "cpu" for d in x.devices())
        return host.copy() if on_cpu or not isinstance(x, jax.Array) else host

    return [own(x, h) for x, h in zip(xs, fetched)]


def _paths(tree: Any) -> list[str]:
    return [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(tree)]


class Checkpointer:
    """Saves and restores `{"run": RunState, "key": host key}` under `run_dir/checkpoints/<epoch>`,
    keeping the newest `keep`. Steps are the number of epochs done. `cleanup_tmp`: remove the
    unfinished checkpoint folders a killed process left (only for the one process that writes
    the run: a reader must not remove a running run's checkpoint in progress)."""

    def __init__(self, run_dir: str, keep: int = 2, process: int | None = None, cleanup_tmp: bool = False,
                 background: bool = False):
        if keep < 1:
            raise ValueError(f"--keep must be >= 1 (checkpoints kept), got {keep}")
        self.directory = os.path.abspath(os.path.join(run_dir, CHECKPOINT_DIR))
        self.keep = keep
        self._files: ProcessFiles | None = None
        self._mngr: Any = None
        # one process of a multi-process run saves the states of its own devices' seed groups in
        # a folder of its own, as host copies in plain files (`ProcessFiles`: orbax writes numpy
        # arrays on process 0 only and refuses one process's device arrays there)
        # a background write reads host copies (the device buffers are donated to the next epoch)
        self.host_arrays = process is not None or background
        self.background = background
        self._pending: int | None = None  # the epoch orbax is still writing (background)
        self._reported = False  # a background write's failure was raised by `wait`
        if process is not None:
            self.directory = os.path.join(self.directory, f"process_{process}")
            self._files = ProcessFiles(self.directory, keep, cleanup_tmp, background=background)
            return
        # background: orbax's asynchronous save (its write and rename in orbax's thread)
        opts = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, cleanup_tmp_directories=cleanup_tmp,
                                            enable_async_checkpointing=background)
        self._mngr = ocp.CheckpointManager(self.directory, options=opts)

    def steps(self) -> list[int]:
        """Epoch counts of the checkpoints on disk, oldest first."""
        return self._files.steps() if self._files else sorted(self._mngr.all_steps())

    def latest(self) -> int | None:
        steps = self.steps()
        return steps[-1] if steps else None

    def save(self, epoch: int, state: Any, host: dict[str, Any] | None = None) -> None:
        """Write the checkpoint of `epoch` epochs done (atomically: orbax writes a temporary
        folder and renames it once complete) and drop the oldest beyond `keep`. `state` is any
        pytree of arrays; `host` is JSON-able metadata stored beside it."""
        leaves = jax.tree.leaves(state)
        flat = {f"{i:05d}": x for i, x in enumerate(leaves) if np.size(x)}
        if self.host_arrays:  # host copies (on the CPU a fetched array may share the donated buffer)
            flat = dict(zip(flat, _host_copies(list(flat.values()))))
        meta = {"format": _FORMAT, "epoch": int(epoch), "paths": _paths(state),
                "shapes": [list(np.shape(x)) for x in leaves],
                "dtypes": [str(x.dtype) for x in leaves],
                "host": host or {}}
        if self._files:
            self._files.save(int(epoch), flat, meta)
            return
        self.wait()  # the previous write ended (its error raised, naming its epoch)
        self._mngr.save(int(epoch), args=ocp.args.Composite(state=ocp.args.StandardSave(flat),
                                                            meta=ocp.args.JsonSave(meta)), force=True)
        if self.background:
            self._pending = int(epoch)
        else:
            self._mngr.wait_until_finished()

    def restore(self, like: Any, epoch: int | None = None) -> tuple[Any, dict[str, Any], int]:
        """The checkpoint of `epoch` (default the newest) as a pytree shaped like `like` (arrays
        or `jax.ShapeDtypeStruct`s, with shardings where the state is sharded), its host
        metadata and its epoch. Raises ValueError when none exists or the layout differs."""
        epoch = self.latest() if epoch is None else epoch
        if epoch is None:
            raise ValueError(f"no checkpoint in {self.directory}: the run was never checkpointed "
                             "(start it again without --resume)")
        if self._files:
            got, meta = self._files.restore(epoch)
        else:
            meta = self._mngr.restore(epoch, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        leaves, treedef = jax.tree.flatten(like)
        paths = _paths(like)
        shapes = [list(x.shape) for x in leaves]
        if meta.get("paths") != paths or meta.get("shapes") != shapes:
            diff = _first_difference(meta.get("paths", []), meta.get("shapes", []), paths, shapes)
            raise ValueError(f"checkpoint {self.directory}/{epoch} does not fit this run's state "
                             f"({diff}); it was written with another configuration, code version or "
                             "device count. Resume with the run's own config.json on the same number "
                             "of devices, or start a new run")
        if self._files:  # numpy on the host, then onto the devices the state lives on
            got = {k: jax.device_put(v, getattr(leaves[int(k)], "sharding", None)) for k, v in got.items()}
        else:
            abstract = {f"{i:05d}": jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None))
                        for i, x in enumerate(leaves) if int(np.prod(x.shape))}
            got = self._mngr.restore(epoch, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))["state"]

        def leaf(i: int, x: Any) -> jax.Array:
            if f"{i:05d}" in got:
                return got[f"{i:05d}"]
            z = jnp.zeros(x.shape, x.dtype)
            sh = getattr(x, "sharding", None)
            return jax.device_put(z, sh) if sh is not None else z

        return jax.tree.unflatten(treedef, [leaf(i, x) for i, x in enumerate(leaves)]), meta["host"], epoch

    def wait(self) -> None:
        """Wait for a checkpoint still being written (`background`); raises `CheckpointWriteError`
        if it failed."""
        if self._files:
            self._files.wait()
        elif self._pending is not None:
            epoch, self._pending = self._pending, None
            try:
                self._mngr.wait_until_finished()
            except Exception as err:  # noqa: BLE001  (OSError, tensorstore's errors: a full disk)
                self._reported = True
                raise CheckpointWriteError(epoch, err) from err

    def close(self) -> None:
        """Wait for a write in progress (its error, if any, is raised by `wait`, not here) and
        close the manager."""
        try:
            self.wait()
        except CheckpointWriteError:
            pass
        if self._mngr is not None:
            try:
                self._mngr.close()
            except Exception:  # noqa: BLE001  (orbax raises a failed write's error again)
                if not self._reported:
                    raise


class ProcessFiles:
    """One process's checkpoints in a multi-process run, as plain files: `<dir>/<epoch>/arrays.npz`
    (each array's bytes) and `meta.json` (the checkpoint's metadata, with every leaf's dtype and
    shape), written under `<epoch>.partial` and renamed once complete and synced, so a kill
    mid-write leaves the previous checkpoints and a partial folder that is never read. With
    `background`, `save` hands the (host) arrays to a thread that writes them, and returns.

    Why not orbax here (orbax-checkpoint 0.12.8, checked on two CPU processes, issue 56): it
    refuses arrays of one process's devices in a multi-process run ("Cannot serialize host local
    jax.Array"), and it writes host (numpy) arrays and JSON metadata on process 0 only, even with
    `MultiprocessingOptions(primary_host=None, active_processes={i})` (every process primary, a
    manager per process): process 1's checkpoint held commit markers and no data, and its restore
    failed ("Individual parameter subdirectory not found"). Each process writes only its own
    folder here, so no coordination is needed; the background write is a thread of our own."""

    PARTIAL = ".partial"

    def __init__(self, directory: str, keep: int, cleanup_tmp: bool = False, background: bool = False):
        self.directory, self.keep, self.background = directory, keep, background
        self._thread: threading.Thread | None = None
        self._failed: CheckpointWriteError | None = None
        os.makedirs(directory, exist_ok=True)
        if cleanup_tmp:
            for name in os.listdir(directory):
                if name.endswith(self.PARTIAL):
                    shutil.rmtree(os.path.join(directory, name), ignore_errors=True)

    def steps(self) -> list[int]:
        return sorted(int(n) for n in os.listdir(self.directory)
                      if n.isdigit() and os.path.exists(os.path.join(self.directory, n, "meta.json")))

    def save(self, step: int, flat: dict[str, Any], meta: dict[str, Any]) -> None:
        """Write the checkpoint `step` of the host arrays `flat` (not to be changed afterwards: a
        background write reads them later); in the background, after the previous write ended."""
        self.wait()
        if not self.background:
            self._write(step, flat, meta)
            return

        def write() -> None:
            try:
                self._write(step, flat, meta)
            except BaseException as err:  # noqa: BLE001  (raised in the loop's thread by `wait`)
                self._failed = CheckpointWriteError(step, err)
                self._failed.__cause__ = err

        self._thread = threading.Thread(target=write, name=f"bulbjax-checkpoint-{step}", daemon=False)
        self._thread.start()

    def wait(self) -> None:
        """Wait for the write in progress; raise `CheckpointWriteError` (once) if it failed."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._failed is not None:
            failed, self._failed = self._failed, None
            raise failed

    def _write(self, step: int, flat: dict[str, Any], meta: dict[str, Any]) -> None:
        final = os.path.join(self.directory, str(step))
        tmp = final + self.PARTIAL
        shutil.rmtree(tmp, ignore_errors=True)
        os.makedirs(tmp)
        arrays = {k: np.ascontiguousarray(np.asarray(v)).reshape(-1).view(np.uint8) for k, v in flat.items()}
        meta = {**meta, "arrays": {k: [str(np.asarray(v).dtype), list(np.shape(v))] for k, v in flat.items()}}
        for name, write in (("arrays.npz", lambda f: np.savez(f, **arrays)),
                            ("meta.json", lambda f: f.write(json.dumps(meta).encode()))):
            with open(os.path.join(tmp, name), "wb") as f:
                write(f)
                f.flush()
                os.fsync(f.fileno())
        if os.path.exists(final):  # the same epoch saved again (force)
            shutil.rmtree(final)
        os.rename(tmp, final)
        for old in self.steps()[:-self.keep]:
            shutil.rmtree(os.path.join(self.directory, str(old)), ignore_errors=True)

    def restore(self, step: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        folder = os.path.join(self.directory, str(step))
        with open(os.path.join(folder, "meta.json")) as f:
            meta = json.load(f)
        with np.load(os.path.join(folder, "arrays.npz")) as z:
            arrays = {k: z[k].view(jnp.dtype(dtype)).reshape(shape) for k, (dtype, shape) in meta["arrays"].items()}
        return arrays, meta


def _first_difference(p0: list, s0: list, p1: list, s1: list) -> str:
    if len(p0) != len(p1):
        return f"{len(p0)} arrays saved, {len(p1)} expected"
    for a, sa, b, sb in zip(p0, s0, p1, s1):
        if a != b:
            return f"saved {a}, expected {b}"
        if sa != sb:
            return f"{a}: saved shape {tuple(sa)}, expected {tuple(sb)}"
    return "layout differs"
