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
checkpoints and stops together; when one process fails the others are stopped and one line says
which failed and why. JAX's coordination service runs here, in the launcher, and outlives every
worker (`bulbjax.distributed`'s module doc: a service that goes first leaves each backend's task
watcher logging a wall of "connection refused" errors).
"""

from __future__ import annotations

import collections
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import IO, Sequence


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


def _tail_reader(stream: IO[str], keep: collections.deque) -> threading.Thread:
    """Drain a worker's stderr in a thread (so the worker never blocks on a full pipe), keeping
    its last lines: what the launcher says when that worker fails."""
    def read() -> None:
        for line in stream:
            keep.append(line.rstrip("\n"))
        stream.close()

    t = threading.Thread(target=read, daemon=True, name="bulbjax-worker-stderr")
    t.start()
    return t


def failure_reason(lines: Sequence[str], returncode: int | None) -> str:
    """Why a worker failed, in one phrase: its `bulbjax: error: ...` line, else the last line of
    its traceback (`SomeError: ...`), else the signal that ended it or its exit code."""
    for line in reversed(lines):
        if line.startswith("bulbjax: error: "):
            return line[len("bulbjax: error: "):]
    for line in reversed(lines):
        head = line.split(":", 1)[0].strip()
        if ":" in line and head and " " not in head and (head.endswith(("Error", "Exception", "Interrupt"))
                                                          or head.startswith("jax")):
            return line.strip()
    if returncode is not None and returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exit code {returncode}"


def run_per_gpu(argv: Sequence[str], gpus: Sequence[str], out_dir: str, poll_s: float = 0.2) -> int:
    """Run `bulbjax <argv>` as one process per GPU of `gpus` and wait for all; returns the first
    non-zero exit code (0 when every process succeeded).

    This process runs JAX's coordination service (`bulbjax.distributed`: the workers join it as
    clients, process 0 too) and stops it once every worker has exited, so that no worker's
    backend outlives it; its own C++ log lines go to `RUN_DIR/log_coordinator.txt`. When a worker
    fails the others are stopped at once (each waits in a collective for the failed one, so none
    could finish its epoch or checkpoint) and one line says which failed and why (from its stderr,
    kept here; its whole output is in its log file)."""
    from bulbjax import distributed

    port = free_port()
    n = len(gpus)
    os.makedirs(out_dir, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    console_fd = os.dup(2)
    console = os.fdopen(os.dup(console_fd), "w", buffering=1)
    log = open(os.path.join(out_dir, "log_coordinator.txt"), "a")
    os.dup2(log.fileno(), 2)  # the service's C++ log lines: in the file, not between the workers' lines
    procs: list[subprocess.Popen] = []
    tails: list[collections.deque] = [collections.deque(maxlen=200) for _ in gpus]
    readers: list[threading.Thread] = []
    killed: list[int] = []

    # the workers have process groups of their own, so a Ctrl-C on the terminal reaches them once,
    # from here (a second SIGINT interrupts a worker at once, without its checkpoint)
    def forward(signum, _frame):
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM if signum == signal.SIGHUP else signum)

    old = {s: signal.signal(s, forward) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    service = None
    try:
        service = distributed.start_service(port, n)
        print(f"{n} GPUs: one process per GPU (jax.distributed on localhost:{port}); process 0 reports "
              f"here, the others log to {os.path.join(out_dir, 'log_process<i>.txt')}", file=console, flush=True)
        for i, gpu in enumerate(gpus):
            env = dict(os.environ, CUDA_VISIBLE_DEVICES=gpu, **{distributed.SERVICE_ENV: distributed.SERVICE_EXTERNAL})
            if i == 0:  # the console itself
                procs.append(subprocess.Popen(_worker_argv(argv, port, n, i), env=env, stderr=console_fd,
                                              process_group=0))
                continue
            p = subprocess.Popen(_worker_argv(argv, port, n, i), env=env, stdout=subprocess.DEVNULL,
                                 stderr=subprocess.PIPE, text=True, errors="replace", process_group=0)
            procs.append(p)
            readers.append(_tail_reader(p.stderr, tails[i]))
        failed = None
        while any([p.poll() is None for p in procs]):  # a list: every process polled
            bad = [i for i, p in enumerate(procs) if p.returncode not in (None, 0)]
            if bad:
                failed = bad[0]
                for i, p in enumerate(procs):  # each waits for the failed one in a collective
                    if p.poll() is None:
                        p.kill()
                        killed.append(i)
                break
            time.sleep(poll_s)
        for p in procs:
            p.wait()
        for t in readers:
            t.join(timeout=5)
        codes = [p.returncode for p in procs]
        if failed is None:
            failed = next((i for i, c in enumerate(codes) if c != 0), None)
        if failed is None:
            return 0
        rc = codes[failed]
        logfile = os.path.join(out_dir, "log.txt" if failed == 0 else f"log_process{failed}.txt")
        stopped = (f"; stopped process{'es' if len(killed) > 1 else ''} {', '.join(map(str, killed))}"
                   if killed else "")
        if failed != 0:
            print(f"bulbjax: error: process {failed} of {n} (GPU {gpus[failed]}) failed: "
                  f"{failure_reason(list(tails[failed]), rc)}{stopped} (its log: {logfile})", file=console, flush=True)
        elif rc != 2:
            print(f"bulbjax: error: process 0 of {n} (GPU {gpus[0]}) failed ({failure_reason([], rc)}; its "
                  f"output is above){stopped} (its log: {logfile})", file=console, flush=True)
        elif killed:  # 2: its own one-line error is on the console already; say only what followed
            print(f"bulbjax: {stopped[2:]} after process 0's error above", file=console, flush=True)
        return rc
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        for s, h in old.items():
            signal.signal(s, h)
        if service is not None:
            service.shutdown()
        os.dup2(console_fd, 2)
        os.close(console_fd)
        console.close()
        log.close()
