"""A CUDA MPS control daemon for the processes a command starts (`bulbjax reproduce --mps`,
`benchmarks/bench_split.py --mps`).

Why: processes that share one GPU without MPS take turns on it (time-slicing), each context whole
while it runs; under MPS their kernels run at once on the GPU's SMs. On one H200 the two halves of
a locomotion epoch in two processes did 1.03x the work of their pace alone side by side
time-sliced and 1.38x under MPS (docs/performance.md, "The locomotion epoch"), so jobs side by
side on a GPU (`--jobs-per-gpu`) may gain more under MPS than the 1.14x measured time-sliced.

The daemon gets pipe and log folders of its own (`CUDA_MPS_PIPE_DIRECTORY`,
`CUDA_MPS_LOG_DIRECTORY`, set in this process's environment while it runs, so the processes it
starts inherit them and no daemon of another user or command is touched) and is quit on leaving.
It needs `nvidia-cuda-mps-control` (a CUDA driver install) and GPUs in the Default compute mode.
Leaving waits (up to `exit_wait_s`) until the daemon and the server it started have exited: a
daemon started while the last one's server still held the GPU left a benchmark's processes
waiting for 330 s with no output (the fourth allocation of 2026-11-29).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any

CONTROL = "nvidia-cuda-mps-control"
COMM = CONTROL[:15]  # /proc/<pid>/comm keeps 15 characters: the daemon's and its server's


def mps_pids() -> set[int]:
    """The processes named like MPS's daemon or server (`nvidia-cuda-mps-control`,
    `nvidia-cuda-mps-server`); empty where there is no /proc."""
    out = set()
    for d in os.listdir("/proc") if os.path.isdir("/proc") else []:
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/comm") as f:
                if f.read().strip() == COMM:
                    out.add(int(d))
        except OSError:
            continue
    return out


class MpsDaemon:
    """`with MpsDaemon(): ...`: an MPS control daemon for the processes started inside, quit on
    leaving (its folders removed, this process's environment restored). `control`: the control
    program (default: `nvidia-cuda-mps-control` on the PATH). No control program, or a daemon
    that does not start: ValueError, which the CLI says in one line."""

    def __init__(self, control: str | None = None, exit_wait_s: float = 60.0) -> None:
        self.control = control or shutil.which(CONTROL)
        if not self.control:
            raise ValueError(f"--mps needs {CONTROL} on the PATH (it comes with the CUDA driver): "
                             "run without --mps, or on a host that has it")
        self.folder = ""
        self.exit_wait_s = exit_wait_s
        self._before: set[int] = set()
        self._saved: dict[str, str | None] = {}

    def __enter__(self) -> "MpsDaemon":
        self.folder = tempfile.mkdtemp(prefix="bulbjax_mps_")
        env = {"CUDA_MPS_PIPE_DIRECTORY": os.path.join(self.folder, "pipe"),
               "CUDA_MPS_LOG_DIRECTORY": os.path.join(self.folder, "log")}
        for d in env.values():
            os.makedirs(d)
        self._saved = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        self._before = mps_pids()
        started = subprocess.run([self.control, "-d"], capture_output=True, text=True)
        if started.returncode:
            self._restore()
            said = (started.stderr or started.stdout).strip()[-300:]
            raise ValueError(f"the MPS control daemon did not start ({self.control} -d exited "
                             f"{started.returncode}{': ' + said if said else ''}): "
                             "run without --mps")
        return self

    def __exit__(self, *exc: Any) -> None:
        try:
            subprocess.run([self.control], input="quit\n", capture_output=True, text=True,
                           timeout=60)
            self._wait_gone()
        finally:
            self._restore()

    def _wait_gone(self) -> None:
        """Wait until the daemon and any server started since `__enter__` have exited (a
        server that is still closing holds the GPU from the next daemon's clients)."""
        end = time.monotonic() + self.exit_wait_s
        while (left := mps_pids() - self._before) and time.monotonic() < end:
            time.sleep(0.2)
        if left:
            print(f"bulbjax: the MPS daemon's processes {sorted(left)} were still running "
                  f"{self.exit_wait_s:.0f} s after it was told to quit", file=sys.stderr)

    def _restore(self) -> None:
        for k, v in self._saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        shutil.rmtree(self.folder, ignore_errors=True)
