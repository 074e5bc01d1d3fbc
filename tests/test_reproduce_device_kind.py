"""`bulbjax reproduce --dry-run --device-kind KIND`: a plan's estimate for hosts of another kind,
from a node without their GPUs (a login node, this CPU machine): the table's rows of that kind on
`--gpus` of them, shared or not; an unknown kind, a run (not a dry run) and a gather are refused
in one line, and nothing is written."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bulbjax.reproduce import estimate
from bulbjax.reproduce.main import reproduce
from bulbjax.reproduce.plan import plan_jobs

H200 = "NVIDIA H200"


@pytest.fixture
def no_gpus(monkeypatch):
    from bulbjax import local_processes

    monkeypatch.setattr(local_processes, "visible_gpus", lambda: [])


def test_a_dry_run_costs_the_plan_on_gpus_of_another_kind(tmp_path, no_gpus) -> None:
    out = str(tmp_path / "plan")
    said: list[str] = []
    s = reproduce("fig2-cartpole", "paper", out, gpus=2, dry_run=True, device_kind=H200,
                  log=said.append)
    times, used = estimate.load_times(H200)
    assert used == H200 and s["device_kind"] == H200 and s["times_of"] == H200 and s["gpus"] == 2
    planned = estimate.simulate(plan_jobs("fig2-cartpole", "paper"), times, 2)
    assert s["estimated_wall_s"] == pytest.approx(planned.wall_s)
    assert "on 2 NVIDIA H200 slot(s)" in said[-1] and "GPU-hours" in said[-1]
    # three slots on the one GPU, which this host does not have
    shared = reproduce("fig2-cartpole", "paper", out, dry_run=True, device_kind=H200,
                       jobs_per_gpu=3, log=said.append)
    assert shared["gpus"] == 1 and shared["jobs_per_gpu"] == 3
    alone = reproduce("fig2-cartpole", "paper", out, dry_run=True, device_kind=H200,
                      log=said.append)
    assert shared["estimated_gpu_s"] < alone["estimated_gpu_s"]
    assert not os.path.exists(out)


def test_unknown_kinds_runs_and_gathers_are_refused(tmp_path, no_gpus) -> None:
    out = str(tmp_path / "plan")
    with pytest.raises(ValueError, match=r"--device-kind 'H200': the table times .*'NVIDIA H200'"):
        reproduce("fig2-cartpole", "paper", out, dry_run=True, device_kind="H200",
                  log=lambda _: None)
    with pytest.raises(ValueError, match="add --dry-run"):
        reproduce("fig2-cartpole", "paper", out, device_kind=H200, log=lambda _: None)
    assert not os.path.exists(out)
    r = subprocess.run([sys.executable, "-m", "bulbjax", "reproduce", "--out", out,
                        "--gather", str(tmp_path), "--device-kind", H200],
                       capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "--device-kind" in r.stderr


def test_a_cpu_estimate_of_full_size_jobs_says_it_is_a_lower_bound(tmp_path, no_gpus) -> None:
    """The CPU rows time the tiny scale's `--small` runs: a plan of full-size jobs timed by them
    on a CPU says its estimate is a lower bound (a newcomer read 94 CPU-hours as the paper's
    cost here); the tiny scale's plan, which those rows measure, does not; nor an H200's."""
    said: list[str] = []
    reproduce("fig2-cartpole", "paper", str(tmp_path / "p"), dry_run=True, log=said.append)
    assert "the estimate is a lower bound" in said[-1] and "CPU-hours" in said[-1]
    reproduce("fig2-cartpole", "tiny", str(tmp_path / "t"), dry_run=True, log=said.append)
    assert "lower bound" not in said[-1]
    reproduce("fig2-cartpole", "paper", str(tmp_path / "h"), dry_run=True, device_kind=H200,
              log=said.append)
    assert "lower bound" not in said[-1]
