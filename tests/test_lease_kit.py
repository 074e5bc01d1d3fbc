"""benchmarks/lease/: the scripts that run a campaign allocation on a lent GPU machine, run here
end to end with a dry run in place of the stretch (LEASE_ROOT a temporary folder, this checkout's
Python in place of the installed wheel): launch copies the tree and starts the job detached,
poll waits for it, collect packs the plan folder without checkpoints and the caches into $OUT."""

from __future__ import annotations

import os
import subprocess
import sys
import tarfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
KIT = os.path.join(ROOT, "benchmarks", "lease")


def _sh(script: str, *args: str, env: dict, cwd: str = ROOT) -> str:
    done = subprocess.run(["bash", os.path.join(env["LEASE_ROOT"], "stage", script), *args], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_the_kit_runs_a_stretch_and_brings_it_back(tmp_path) -> None:
    lease, out = tmp_path / "lease", tmp_path / "out"
    (lease / "stage").mkdir(parents=True)
    out.mkdir()
    for name in ("install.sh", "launch.sh", "jobs.sh", "poll.sh", "collect.sh"):
        with open(os.path.join(KIT, name)) as f, open(lease / "stage" / name, "w") as g:
            g.write(f.read())
    env = {**os.environ, "LEASE_ROOT": str(lease), "LEASE_PYTHON": sys.executable, "HOME": str(tmp_path),
           "OUT": str(out)}
    # caches brought from an earlier machine, packed as collect.sh packs them
    earlier = tmp_path / "earlier"
    (earlier / "bjcache" / "jax").mkdir(parents=True)
    (earlier / "bjcache" / "jax" / "entry").write_text("program")
    (earlier / ".cache" / "warp").mkdir(parents=True)
    (earlier / ".cache" / "warp" / "kernel").write_text("kernel")
    subprocess.run(["tar", "czf", str(lease / "stage" / "caches.tgz.aa"), "-C", str(earlier / "bjcache"), ".",
                    "-C", str(earlier / ".cache"), "warp"], check=True)
    said = _sh("launch.sh", "--jobs fig2-ant/seed1 --learners-apart --dry-run --device-kind 'NVIDIA H200' "
               "--gpus 2", env=env)
    assert "install: no parts" in said and "caches unpacked" in said and "launched" in said
    assert (lease / "bjcache" / "jax" / "entry").read_text() == "program"
    assert (tmp_path / ".cache" / "warp" / "kernel").read_text() == "kernel"
    assert not os.path.exists(lease / "bj" / ".venv") and os.path.exists(lease / "bj" / "pyproject.toml")
    said = _sh("poll.sh", "240", env=env)
    assert "rc: 0" in said, said
    with open(lease / "res" / "reproduce.log") as f:
        log = f.read()
    # the quoted device kind reached reproduce as one argument: the plan is estimated on its rows
    assert "fig2-ant/seed1" in log and "on 1 NVIDIA H200 slot(s) of two GPUs" in log, log
    ckpt = lease / "res" / "paper" / "runs" / "fig2-ant" / "seed0" / "checkpoints"
    ckpt.mkdir()
    (ckpt / "state.bin").write_bytes(b"x")
    _sh("collect.sh", env=env)
    with tarfile.open(out / "paper.tgz") as t:
        names = t.getnames()
    assert "paper/plan.json" in names and "reproduce.log" in names and "rc" in names
    assert not any("checkpoints" in n for n in names)
    assert os.listdir(out / "caches")
