"""Two real processes on the CPU: `bulbjax.distributed.allgather` and `broadcast_flags`, and the
checkpoints each process of a multi-process run writes (`checkpoint.ProcessFiles`).

Two Python processes join a local `jax.distributed` coordinator (Gloo collectives) and gather a
tree of mixed dtypes and ranks, packed as one byte array: every leaf must come back with its
dtype, its process-order concatenation (0-d leaves stacked) and its exact bytes; the flags must
be process 0's on both.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import numpy as np
import pytest

WORKER = r"""
import json, sys
import numpy as np
import pytest
from bulbjax import distributed
i, port = int(sys.argv[1]), int(sys.argv[2])
distributed.initialize(distributed.DistributedConfig(coordinator=f"127.0.0.1:{port}", num_processes=2, process_id=i))
tree = {"f": np.arange(6, dtype=np.float32).reshape(2, 3) + 10 * i + 0.25,
        "i": np.array([7, -3], np.int32) * (i + 1),
        "b": np.array([[True], [bool(i)]]),
        "s": np.float64(1.5 + i),
        "h": np.array([0.1 * (i + 1)], np.float16)}
out = distributed.allgather(tree)
flags = distributed.broadcast_flags(i == 0, i == 1)
print("RESULT", json.dumps({k: [str(v.dtype), list(v.shape), v.tolist()] for k, v in out.items()} | {"flags": flags}))
distributed.shutdown()
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_allgather_two_processes():
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONUNBUFFERED": "1"}
    port = _free_port()
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, str(i), str(port)], env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT) for i in range(2)]
    logs = [p.communicate(timeout=300)[0] for p in procs]
    results = []
    for p, log in zip(procs, logs):
        assert p.returncode == 0, log[-3000:]
        results.append(json.loads(next(line for line in log.splitlines() if line.startswith("RESULT"))[7:]))
    assert results[0] == results[1]
    r = results[0]
    f = np.concatenate([np.arange(6, dtype=np.float32).reshape(2, 3) + 10 * i + 0.25 for i in range(2)])
    assert r["f"] == ["float32", [4, 3], f.tolist()]
    assert r["i"] == ["int32", [4], [7, -3, 14, -6]]
    assert r["b"] == ["bool", [4, 1], [[True], [False], [True], [True]]]
    assert r["s"] == ["float64", [2], [1.5, 2.5]]
    assert r["h"] == ["float16", [2], np.array([0.1, 0.2], np.float16).tolist()]
    assert r["flags"] == [True, False]  # process 0's flags on both


CHECKPOINT_WORKER = r"""
import sys
import jax, jax.numpy as jnp, numpy as np
from bulbjax import distributed
from bulbjax.run.checkpoint import Checkpointer
i, port, d = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
distributed.initialize(distributed.DistributedConfig(coordinator=f"127.0.0.1:{port}", num_processes=2, process_id=i))
state = {"a": jnp.arange(6.0).reshape(2, 3) + 100 * i, "b": jnp.zeros((0,)), "k": jax.random.PRNGKey(3 + i)}
ck = Checkpointer(d, process=i, cleanup_tmp=True)
ck.save(4, state, {"epoch": 4, "process": i})
ck.close()
distributed.barrier("saved")
got, host, epoch = Checkpointer(d, process=i).restore(jax.tree.map(jnp.zeros_like, state))
assert epoch == 4 and host == {"epoch": 4, "process": i}, (epoch, host)
for k in state:
    np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(state[k]))
print("RESTORED", i, flush=True)
distributed.shutdown()
"""


def test_each_process_checkpoints_and_restores_its_own_state(tmp_path):
    """Every process of a multi-process run writes its own checkpoint with its data and restores
    it (with orbax, process 1's checkpoints held commit markers and no data: its numpy handler
    writes on process 0 only)."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONUNBUFFERED": "1"}
    port = _free_port()
    procs = [subprocess.Popen([sys.executable, "-c", CHECKPOINT_WORKER, str(i), str(port), str(tmp_path)], env=env,
                              text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT) for i in range(2)]
    logs = [p.communicate(timeout=300)[0] for p in procs]
    for i, (p, log) in enumerate(zip(procs, logs)):
        assert p.returncode == 0 and f"RESTORED {i}" in log, log[-3000:]
    for i in range(2):
        assert sorted(os.listdir(tmp_path / "checkpoints" / f"process_{i}" / "4")) == ["arrays.npz", "meta.json"]


def test_process_files_keep_k_partial_and_dtypes(tmp_path):
    """`ProcessFiles`: the newest `keep` kept, a half-written `<epoch>.partial` never read and
    removed by the next writer, every dtype (bfloat16, uint32 keys, 0-d) back bit for bit."""
    import jax.numpy as jnp

    from bulbjax.run.checkpoint import ProcessFiles

    d = str(tmp_path / "p1")
    files = ProcessFiles(d, keep=2)
    flat = {"00000": np.asarray(jnp.arange(5, dtype=jnp.bfloat16) / 3), "00001": np.array([7, 9], np.uint32),
            "00002": np.float32(2.5), "00003": np.arange(6, dtype=np.int64).reshape(2, 3)}
    for step in (1, 2, 3):
        files.save(step, flat, {"epoch": step})
    os.makedirs(os.path.join(d, "4.partial"))  # a kill during the write of epoch 4
    assert files.steps() == [2, 3]
    got, meta = files.restore(3)
    assert meta["epoch"] == 3
    for k, v in flat.items():
        assert got[k].dtype == np.asarray(v).dtype and got[k].shape == np.shape(v)
        assert got[k].tobytes() == np.asarray(v).tobytes()
    ProcessFiles(d, keep=2, cleanup_tmp=True)
    assert sorted(os.listdir(d)) == ["2", "3"]


def test_process_files_background_write_and_its_error(tmp_path):
    """`ProcessFiles(background=True)`: `save` returns before the files exist, `wait` finishes
    them (the same bytes back); a write that fails is raised by the next `wait` as
    `CheckpointWriteError` naming its epoch, once, and leaves only a partial folder behind."""
    from bulbjax.run.checkpoint import CheckpointWriteError, ProcessFiles

    d = str(tmp_path / "p0")
    files = ProcessFiles(d, keep=2, background=True)
    flat = {"00000": np.arange(2_000_000, dtype=np.float32), "00001": np.array([3, 4], np.uint32)}
    files.save(1, flat, {"epoch": 1})
    files.wait()
    got, meta = files.restore(1)
    assert files.steps() == [1] and meta["epoch"] == 1
    assert all(got[k].tobytes() == v.tobytes() for k, v in flat.items())
    files.save(2, {"00000": object()}, {"epoch": 2})  # not an array: np.savez fails in the thread
    with pytest.raises(CheckpointWriteError, match="epoch 2") as err:
        files.wait()
    assert err.value.epoch == 2
    files.wait()  # raised once
    assert files.steps() == [1] and os.path.isdir(os.path.join(d, "2.partial"))
