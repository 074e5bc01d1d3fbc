"""benchmarks/lease/: the scripts that run a campaign allocation on a lent GPU machine, run here
end to end with a dry run in place of the stretch (LEASE_ROOT a temporary folder, this checkout's
Python in place of the installed wheel): launch copies the tree and starts the job detached,
poll waits for it, collect packs the plan folder without checkpoints and the caches into $OUT."""

from __future__ import annotations

import os
import shutil
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


def _stage(lease) -> None:
    """The kit's scripts where the last part puts them (no wheel parts: nothing to install)."""
    (lease / "stage").mkdir(parents=True)
    for name in ("install.sh", "launch.sh", "jobs.sh", "poll.sh", "collect.sh"):
        with open(os.path.join(KIT, name)) as f, open(lease / "stage" / name, "w") as g:
            g.write(f.read())


def test_the_kit_runs_a_stretch_and_brings_it_back(tmp_path) -> None:
    lease, out, home = tmp_path / "lease", tmp_path / "out", tmp_path / "home"
    _stage(lease)
    out.mkdir()
    env = {**os.environ, "LEASE_ROOT": str(lease), "LEASE_PYTHON": sys.executable, "HOME": str(home),
           "OUT": str(out)}
    # this machine's caches, as its compiles and Warp's builds leave them
    (lease / "bjcache" / "jax").mkdir(parents=True)
    (lease / "bjcache" / "jax" / "entry").write_text("program")
    (home / ".cache" / "warp").mkdir(parents=True)
    (home / ".cache" / "warp" / "kernel").write_text("kernel")
    said = _sh("launch.sh", "--jobs fig2-ant/seed1 --learners-apart --dry-run --device-kind 'NVIDIA H200' "
               "--gpus 2", env=env)
    assert "install: no parts" in said and "launched" in said
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

    # a later machine: the caches collect.sh brought back, carried beside the scripts
    later, home2 = tmp_path / "later", tmp_path / "home2"
    _stage(later)
    for piece in os.listdir(out / "caches"):
        shutil.copy(out / "caches" / piece, later / "stage" / piece)
    env2 = {**env, "LEASE_ROOT": str(later), "HOME": str(home2)}
    # ... and a finished run dropped to run again (CartPole's seed 0, for its Fig. 4)
    env2["DROP"] = "runs/fig2-cartpole/seed0"
    said = _sh("launch.sh", "--jobs fig2-cartpole/seed0 --dry-run --device-kind 'NVIDIA H200'", env=env2)
    assert "caches unpacked" in said
    assert (later / "bjcache" / "jax" / "entry").read_text() == "program"
    assert (home2 / ".cache" / "warp" / "kernel").read_text() == "kernel"
    assert "rc: 0" in _sh("poll.sh", "240", env=env2)
    with open(later / "res" / "jobs.out") as f:
        assert "dropped runs/fig2-cartpole/seed0: it runs again" in f.read()
    with open(later / "res" / "reproduce.log") as f:
        log = f.read()
    assert "fig2-cartpole/seed0" in log and "fig4/fig2-cartpole" in log and "left out" not in log, log
