"""`bulbjax reproduce --mps`: the stretch's jobs under a CUDA MPS control daemon of its own
(`bulbjax/reproduce/mps.py`). Checked with a stand-in for `nvidia-cuda-mps-control` (this machine
has no GPU): the daemon is started before the jobs with pipe and log folders of its own, the jobs'
processes inherit them, it is told to quit after, and this process's environment is as before;
a host without the control program, a daemon that does not start and a host of CPU workers are
refused in one line before anything runs."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import time

import pytest

from bulbjax.reproduce import main as rmain
from bulbjax.reproduce import results
from bulbjax.reproduce.mps import MpsDaemon

H200 = "NVIDIA H200"
PIPE = "CUDA_MPS_PIPE_DIRECTORY"


def _control(tmp_path, rc: int = 0) -> tuple[str, str]:
    """A stand-in control program that logs how it was called (and the pipe folder it was given)
    and exits `rc`; its path and its log's."""
    log = str(tmp_path / "control.log")
    path = tmp_path / "nvidia-cuda-mps-control"
    path.write_text(f"#!/bin/sh\nif [ \"$1\" = -d ]; then echo \"start ${PIPE}\" >> {log}; "
                    f"else echo \"stdin $(cat)\" >> {log}; fi\n"
                    + (f"echo 'An instance of this daemon is already running' >&2\nexit {rc}\n"
                       if rc else ""))
    path.chmod(path.stat().st_mode | stat.S_IEXEC)
    return str(path), log


def test_the_daemon_runs_with_folders_of_its_own_and_is_quit(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv(PIPE, raising=False)
    control, log = _control(tmp_path)
    with MpsDaemon(control) as d:
        pipe = os.environ[PIPE]
        assert pipe.startswith(d.folder) and os.path.isdir(pipe)
        child = subprocess.run(["sh", "-c", f"echo ${PIPE}"], capture_output=True,
                               text=True).stdout.strip()
        assert child == pipe  # what the jobs' processes see
    assert PIPE not in os.environ and not os.path.exists(d.folder)
    with open(log) as f:
        assert f.read().splitlines() == [f"start {pipe}", "stdin quit"]


def test_leaving_waits_until_the_daemon_and_its_server_have_exited(tmp_path,
                                                                   monkeypatch) -> None:
    """A stand-in whose `-d` leaves a process of the daemon's name behind that exits a second
    after `quit`: leaving returns only once it is gone (the next daemon's clients would wait)."""
    monkeypatch.delenv(PIPE, raising=False)
    log, flag = tmp_path / "control.log", tmp_path / "quit"
    path = tmp_path / "nvidia-cuda-mps-control"
    path.write_text(
        "#!/bin/sh\n"
        f"if [ \"$1\" = -d ]; then \"$0\" serve </dev/null >/dev/null 2>&1 &\n"
        f"elif [ \"$1\" = serve ]; then until [ -f {flag} ]; do sleep 0.1; done; sleep 1; "
        f"echo 'server gone' >> {log}\n"
        f"else cat > /dev/null; touch {flag}; echo quit >> {log}; fi\n")
    path.chmod(path.stat().st_mode | stat.S_IEXEC)
    with MpsDaemon(str(path)):
        time.sleep(0.3)
    assert log.read_text().splitlines() == ["quit", "server gone"]


def test_no_control_program_and_a_daemon_that_does_not_start_are_refused(tmp_path,
                                                                          monkeypatch) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))  # no nvidia-cuda-mps-control on it
    with pytest.raises(ValueError, match="--mps needs nvidia-cuda-mps-control on the PATH"):
        MpsDaemon()
    monkeypatch.setenv(PIPE, "/somewhere/else")
    control, _ = _control(tmp_path, rc=1)
    refused = "did not start .*exited 1: An instance of this daemon is already running"
    with pytest.raises(ValueError, match=refused):
        with MpsDaemon(control):
            pass
    assert os.environ[PIPE] == "/somewhere/else"


def test_a_stretch_runs_its_jobs_under_the_daemon(tmp_path, monkeypatch) -> None:
    """The queue runs inside the daemon's span (it sees the pipe folder), the summary says so."""
    from bulbjax import local_processes

    monkeypatch.setattr(local_processes, "visible_gpus", lambda: ["0"])
    monkeypatch.setattr(rmain, "host_kind", lambda _: H200)
    control, log = _control(tmp_path)
    monkeypatch.setenv("PATH", f"{os.path.dirname(control)}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.delenv(PIPE, raising=False)
    seen: list[str | None] = []

    class Queue:  # the jobs' processes: what their environment would hold
        def __init__(self, *args, **kwargs) -> None:
            pass

        def run(self) -> dict:
            seen.append(os.environ.get(PIPE))
            return {"wall_s": 1.0, "utilisation": 1.0, "busy_s": 1.0, "failed": [],
                    "unfinished": [], "jobs": {}}

    monkeypatch.setattr(rmain, "Queue", Queue)
    said: list[str] = []
    s = rmain.reproduce("fig2-cartpole", "paper", str(tmp_path / "plan"),
                        jobs="fig2-cartpole/seed0", jobs_per_gpu=2, mps=True, log=said.append)
    assert s["mps"] is True and seen[0] and seen[0].startswith("/") and PIPE not in os.environ
    with open(log) as f:
        assert f.read().splitlines() == [f"start {seen[0]}", "stdin quit"]
    assert any("x 1.51 at 2 jobs per H200 under MPS" in line for line in said)  # MPS's gain
    ran = dict(s, measured_wall_s=1.0, gpu_hours=0.1)
    assert "under an MPS daemon" in results._summary_line(ran)
    assert "MPS" not in results._summary_line(dict(ran, mps=False))


def test_cpu_workers_and_gathers_refuse_it(tmp_path, monkeypatch) -> None:
    from bulbjax import local_processes

    monkeypatch.setattr(local_processes, "visible_gpus", lambda: [])
    out = str(tmp_path / "plan")
    with pytest.raises(ValueError,
                       match="--mps shares GPUs between processes and this host runs CPU workers"):
        rmain.reproduce("fig2-cartpole", "tiny", out, mps=True, log=lambda _: None)
    assert not os.path.exists(out)
    r = subprocess.run([sys.executable, "-m", "bulbjax", "reproduce", "--out", out,
                        "--gather", str(tmp_path), "--mps"], capture_output=True, text=True,
                       timeout=120,
                       env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "--mps" in r.stderr
