"""One process per GPU (`bulbjax.local_processes`): which GPUs, how many processes, the workers'
command lines, exit codes passed on. The GPUs themselves are not needed: the workers' own
multi-process run is tested in test_distributed.py."""

from __future__ import annotations

import sys

import pytest

from bulbjax import cli, local_processes as lp


def test_visible_gpus_follow_cuda_visible_devices(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2, 5")
    assert lp.visible_gpus() == ["2", "5"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "-1")
    assert lp.visible_gpus() == []
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    assert lp.visible_gpus() == []


def test_process_count_splits_the_seeds_evenly() -> None:
    assert lp.process_count(6, 2) == 2
    assert lp.process_count(6, 4) == 3  # not 4: every process runs as many seeds
    assert lp.process_count(12, 8) == 6
    assert lp.process_count(5, 2) == 1  # a prime seed count stays in one process
    assert lp.process_count(1, 8) == 1


def test_worker_argv_replaces_this_launchs_flags() -> None:
    argv = ["run", "--preset", "fig2-invpend", "--layout", "auto", "--devices=2", "--bf16"]
    w = lp._worker_argv(argv, 1234, 2, 1)
    assert w[:3] == [sys.executable, "-m", "bulbjax"]
    assert w[3:] == ["run", "--preset", "fig2-invpend", "--bf16", "--layout", "groups",
                     "--coordinator", "localhost:1234", "--num-processes", "2", "--process-id", "1"]


def test_a_failing_worker_fails_the_launch(tmp_path, capfd: pytest.CaptureFixture) -> None:
    """Real worker processes that exit at once (an unknown environment): the launch returns their
    non-zero code, and the console has that one-line error once (process 0's own, or the
    launcher's naming the process), not a line per process."""
    rc = lp.run_per_gpu(["run", "--env", "NoSuchEnv", "--out", str(tmp_path / "r")], ["0", "1"], str(tmp_path / "r"))
    assert rc == 2
    err = [x for x in capfd.readouterr().err.splitlines() if x.startswith("bulbjax: error: ")]
    assert len(err) == 1 and "unknown environment 'NoSuchEnv'" in err[0], err


def test_failure_reason_reads_the_workers_last_words() -> None:
    assert lp.failure_reason(["x", "bulbjax: error: bad flag", "later"], 2) == "bad flag"
    tb = ["Traceback (most recent call last):", '  File "x.py", line 1', "OSError: [Errno 28] No space left"]
    assert lp.failure_reason(tb, 1) == "OSError: [Errno 28] No space left"
    assert lp.failure_reason([], -9) == "killed by SIGKILL"
    assert lp.failure_reason(["nothing useful"], 3) == "exit code 3"


def test_layout_processes_without_gpus_is_one_clear_line(monkeypatch: pytest.MonkeyPatch, tmp_path,
                                                          capsys: pytest.CaptureFixture) -> None:
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert cli.main(["run", "--env", "CartPole", "--layout", "processes", "--out", str(tmp_path / "r")]) != 0
    assert "one process per GPU and this host has 0" in capsys.readouterr().err
