"""One `bulbjax run` process per GPU of this host, joined by `jax.distributed` on localhost.

Why processes and not one process driving every GPU: each MJX-Warp operation (step, forward,
render) is a `warp.jax_callable`, and XLA runs it by calling back into Python under the GIL and
one global lock (`_FFI_CALLBACK_LOCK` in `warp/_src/jax/ffi.py`). In one process the GPUs' seed
groups therefore take turns on the host for every physics step and render of an epoch; measured on
two GPUs, one process gave 0.88x one GPU's throughput at 6 seeds (`benchmarks/bench_multigpu.py`,
docs/performance.md). With one process per GPU each has its own interpreter and lock.

This is not a launcher of its own kind: it starts the same command line once per GPU with the
three settings `bulbjax.distributed` reads (`--coordinator localhost:PORT --num-processes N
--process-id I`) and `CUDA_VISIBLE_DEVICES` naming one GPU, exactly what a user would type in N
shells, then waits. Process 0 keeps the console; the others' output is in their log files
(`RUN_DIR/log_process<i>.txt`). Ctrl-C (SIGINT) and SIGTERM are passed on, so every process
checkpoints and stops together; when one process fails the others are stopped.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from typing import Sequence


def visible_gpus() -> list[str]:
    """The NVIDIA GPUs this process may use, as CUDA_VISIBLE_DEVICES entries, without starting a
    JAX backend (which would take GPU memory the worker processes need): CUDA_VISIBLE_DEVICES
    where set, else `nvidia-smi -L`; [] on a machine without NVIDIA GPUs."""
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is not None:
        return [g.strip() for g in env.split(",") if g.strip() and g.strip() != "-1"]
    if os.environ.get("JAX_PLATFORMS", "").strip().lower() in ("cpu",):
        return []
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return []
    return [str(i) for i, line in enumerate(out.stdout.splitlines()) if line.startswith("GPU ")]


def process_count(seeds: int, gpus: int) -> int:
    """Processes for `seeds` seeds on `gpus` GPUs: the most that split the seeds evenly."""
    return max(g for g in range(1, max(1, min(seeds, gpus)) + 1) if seeds % g == 0)


def free_port() -> int:
    """A TCP port free on localhost now (for a coordinator started right after)."""
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return int(s.getsockname()[1])


def _worker_argv(argv: Sequence[str], port: int, count: int, index: int) -> list[str]:
    """`argv` (the `bulbjax` arguments) for worker `index`: seed groups in a process of one GPU,
    joined on localhost. --layout and --devices are this launch's own, so they are replaced."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in ("--layout", "--devices"):
            skip = True
            continue
        if a.startswith(("--layout=", "--devices=")):
            continue
        out.append(a)
    return [sys.executable, "-m", "bulbjax", *out, "--layout", "groups", "--coordinator", f"localhost:{port}",
            "--num-processes", str(count), "--process-id", str(index)]


def run_per_gpu(argv: Sequence[str], gpus: Sequence[str], out_dir: str, poll_s: float = 0.5) -> int:
    """Run `bulbjax <argv>` as one process per GPU of `gpus` and wait for all; returns the first
    non-zero exit code (0 when every process succeeded)."""
    port = free_port()
    n = len(gpus)
    print(f"{n} GPUs: one process per GPU (jax.distributed on localhost:{port}); process 0 reports here, "
          f"the others log to {os.path.join(out_dir, 'log_process<i>.txt')}", flush=True)
    procs: list[subprocess.Popen] = []
    for i, gpu in enumerate(gpus):
        env = dict(os.environ, CUDA_VISIBLE_DEVICES=gpu)
        quiet = {} if i == 0 else {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
        procs.append(subprocess.Popen(_worker_argv(argv, port, n, i), env=env, **quiet))

    def forward(signum, _frame):
        for p in procs:
            if p.poll() is None:
                p.send_signal(signum)

    old = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        failed = None
        while True:
            running = any(p.poll() is None for p in procs)
            bad = [(i, p.returncode) for i, p in enumerate(procs) if p.returncode not in (None, 0)]
            if bad and failed is None:
                failed = bad[0]
                i, rc = failed
                log = os.path.join(out_dir, "log.txt" if i == 0 else f"log_process{i}.txt")
                print(f"process {i} (GPU {gpus[i]}) exited with code {rc} (its log: {log})"
                      + ("; stopping the others" if running else ""),
                      file=sys.stderr, flush=True)
                forward(signal.SIGTERM, None)
                deadline = time.monotonic() + 120  # time to checkpoint, then kill
            if not running:
                break
            if failed is not None and time.monotonic() > deadline:
                for p in procs:
                    if p.poll() is None:
                        p.kill()
            time.sleep(poll_s)
        codes = [p.returncode for p in procs]
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    return next((c for c in codes if c != 0), 0)
