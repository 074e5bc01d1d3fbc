"""`bulbjax.distributed.allgather` and `broadcast_flags` across two real processes on the CPU.

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

WORKER = r"""
import json, sys
import numpy as np
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
