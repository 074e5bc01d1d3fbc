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
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from typing import Any

CONTROL = "nvidia-cuda-mps-control"


class MpsDaemon:
    """`with MpsDaemon(): ...`: an MPS control daemon for the processes started inside, quit on
    leaving (its folders removed, this process's environment restored). `control`: the control
    program (default: `nvidia-cuda-mps-control` on the PATH). No control program, or a daemon
    that does not start: ValueError, which the CLI says in one line."""

    def __init__(self, control: str | None = None) -> None:
        self.control = control or shutil.which(CONTROL)
        if not self.control:
            raise ValueError(f"--mps needs {CONTROL} on the PATH (it comes with the CUDA driver): "
                             "run without --mps, or on a host that has it")
        self.folder = ""
        self._saved: dict[str, str | None] = {}

    def __enter__(self) -> "MpsDaemon":
        self.folder = tempfile.mkdtemp(prefix="bulbjax_mps_")
        env = {"CUDA_MPS_PIPE_DIRECTORY": os.path.join(self.folder, "pipe"),
               "CUDA_MPS_LOG_DIRECTORY": os.path.join(self.folder, "log")}
        for d in env.values():
            os.makedirs(d)
        self._saved = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
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
        finally:
            self._restore()

    def _restore(self) -> None:
        for k, v in self._saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        shutil.rmtree(self.folder, ignore_errors=True)
