"""Checkpoints of a whole run with orbax: the `RunState` (PPO, learners, optimisers, replay and
window buffers, env states with their mjx.Data, keys, epoch counter, reference spread) and the
host-side PRNG key chain of the run loop, written atomically, the last K kept.

The pytree is saved as a flat dict of its leaves, named by their index in `jax.tree.flatten`
order, because orbax refuses zero-size arrays (mjx.Data has many, e.g. `act` of a model
without activations): those are left out and rebuilt as zeros on restore. The leaves' tree paths
go into the checkpoint's JSON metadata, so a checkpoint of a different run layout (other learners,
env, seeds or device count) is refused with a clear error instead of being misread.

A checkpoint is only taken between jitted calls (after an epoch, or after a chunk of epochs once
several run in one call), so every saved state is a state the run loop itself held.
"""

from __future__ import annotations

import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

CHECKPOINT_DIR = "checkpoints"
_FORMAT = 1


def _paths(tree: Any) -> list[str]:
    return [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_leaves_with_path(tree)]


class Checkpointer:
    """Saves and restores `{"run": RunState, "key": host key}` under `run_dir/checkpoints/<epoch>`,
    keeping the newest `keep`. Steps are the number of epochs done."""

    def __init__(self, run_dir: str, keep: int = 2, process: int | None = None):
        if keep < 1:
            raise ValueError(f"--keep must be >= 1 (checkpoints kept), got {keep}")
        self.directory = os.path.abspath(os.path.join(run_dir, CHECKPOINT_DIR))
        mp = ocp.options.MultiprocessingOptions()
        if process is not None:
            # one process of a multi-process run: it saves the states of its own devices' seed
            # groups (single-device arrays) in a folder of its own, coordinating with no other
            self.directory = os.path.join(self.directory, f"process_{process}")
            mp = ocp.options.MultiprocessingOptions(primary_host=process, active_processes={process},
                                                    barrier_sync_key_prefix=f"bulbjax_p{process}")
        self.keep = keep
        opts = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True,
                                            enable_async_checkpointing=False, multiprocessing_options=mp)
        self._mngr = ocp.CheckpointManager(self.directory, options=opts)

    def steps(self) -> list[int]:
        """Epoch counts of the checkpoints on disk, oldest first."""
        return sorted(self._mngr.all_steps())

    def latest(self) -> int | None:
        return self._mngr.latest_step()

    def save(self, epoch: int, state: Any, host: dict[str, Any] | None = None) -> None:
        """Write the checkpoint of `epoch` epochs done (atomically: orbax writes a temporary
        folder and renames it once complete) and drop the oldest beyond `keep`. `state` is any
        pytree of arrays; `host` is JSON-able metadata stored beside it."""
        leaves = jax.tree.leaves(state)
        flat = {f"{i:05d}": x for i, x in enumerate(leaves) if np.size(x)}
        meta = {"format": _FORMAT, "epoch": int(epoch), "paths": _paths(state),
                "shapes": [list(np.shape(x)) for x in leaves],
                "dtypes": [str(x.dtype) for x in leaves],
                "host": host or {}}
        self._mngr.save(int(epoch), args=ocp.args.Composite(state=ocp.args.StandardSave(flat),
                                                            meta=ocp.args.JsonSave(meta)), force=True)
        self._mngr.wait_until_finished()

    def restore(self, like: Any, epoch: int | None = None) -> tuple[Any, dict[str, Any], int]:
        """The checkpoint of `epoch` (default the newest) as a pytree shaped like `like` (arrays
        or `jax.ShapeDtypeStruct`s, with shardings where the state is sharded), its host
        metadata and its epoch. Raises ValueError when none exists or the layout differs."""
        epoch = self.latest() if epoch is None else epoch
        if epoch is None:
            raise ValueError(f"no checkpoint in {self.directory}: the run was never checkpointed "
                             "(start it again without --resume)")
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
        abstract = {f"{i:05d}": jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None))
                    for i, x in enumerate(leaves) if int(np.prod(x.shape))}
        got = self._mngr.restore(epoch, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))
        got = got["state"]

        def leaf(i: int, x: Any) -> jax.Array:
            if f"{i:05d}" in got:
                return got[f"{i:05d}"]
            z = jnp.zeros(x.shape, x.dtype)
            sh = getattr(x, "sharding", None)
            return jax.device_put(z, sh) if sh is not None else z

        return jax.tree.unflatten(treedef, [leaf(i, x) for i, x in enumerate(leaves)]), meta["host"], epoch

    def close(self) -> None:
        self._mngr.close()


def _first_difference(p0: list, s0: list, p1: list, s1: list) -> str:
    if len(p0) != len(p1):
        return f"{len(p0)} arrays saved, {len(p1)} expected"
    for a, sa, b, sb in zip(p0, s0, p1, s1):
        if a != b:
            return f"saved {a}, expected {b}"
        if sa != sb:
            return f"{a}: saved shape {tuple(sa)}, expected {tuple(sb)}"
    return "layout differs"
