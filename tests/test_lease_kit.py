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
    # what was on this machine before the launch (as a set carried here): not brought back again
    (lease / "bjcache" / "jax").mkdir(parents=True)
    (lease / "bjcache" / "jax" / "carried").write_text("old program")
    (home / ".cache" / "warp").mkdir(parents=True)
    (home / ".cache" / "warp" / "carried_kernel").write_text("old kernel")
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
    # this machine's additions, as its compiles and Warp's builds leave them after the launch
    t0 = os.path.getmtime(lease / "res" / "t0")
    for path, text in ((lease / "bjcache" / "jax" / "entry", "program"),
                       (home / ".cache" / "warp" / "kernel", "kernel")):
        path.write_text(text)
        os.utime(path, (t0 + 5, t0 + 5))
    _sh("collect.sh", env=env)
    assert sorted(n for n in os.listdir(out) if n.startswith("paper")) == ["paper.tgz.aa"]  # 15 MB pieces
    with tarfile.open(out / "paper.tgz.aa") as t:
        names = t.getnames()
    assert "paper/plan.json" in names and "reproduce.log" in names and "rc" in names
    assert not any("checkpoints" in n for n in names)
    pieces = sorted(os.listdir(out / "caches"))
    name = f"caches-{(lease / 'res' / 't0').read_text().strip()}.tgz"
    assert pieces == [f"{name}.aa"], pieces
    with tarfile.open(out / "caches" / pieces[0]) as t:
        assert sorted(n for n in t.getnames() if t.getmember(n).isfile()) == ["./jax/entry", "./warp/kernel"]

    # a later machine: that set and an earlier one carried beside the scripts, merged
    later, home2 = tmp_path / "later", tmp_path / "home2"
    _stage(later)
    for piece in pieces:
        shutil.copy(out / "caches" / piece, later / "stage" / piece)
    earlier = tmp_path / "earlier"
    (earlier / "jax").mkdir(parents=True)
    (earlier / "jax" / "carried").write_text("old program")
    (earlier / "warp").mkdir()
    (earlier / "warp" / "carried_kernel").write_text("old kernel")
    with tarfile.open(later / "stage" / "caches-1.tgz.aa", "w:gz") as t:
        t.add(earlier, arcname=".")
    env2 = {**env, "LEASE_ROOT": str(later), "HOME": str(home2)}
    # ... and a finished run dropped to run again (CartPole's seed 0, for its Fig. 4)
    env2["DROP"] = "runs/fig2-cartpole/seed0"
    said = _sh("launch.sh", "--jobs fig2-cartpole/seed0 --dry-run --device-kind 'NVIDIA H200'", env=env2)
    assert "caches unpacked (2 set(s))" in said
    assert (later / "bjcache" / "jax" / "entry").read_text() == "program"
    assert (later / "bjcache" / "jax" / "carried").read_text() == "old program"
    assert (home2 / ".cache" / "warp" / "kernel").read_text() == "kernel"
    assert (home2 / ".cache" / "warp" / "carried_kernel").read_text() == "old kernel"
    assert "rc: 0" in _sh("poll.sh", "240", env=env2)
    with open(later / "res" / "jobs.out") as f:
        assert "dropped runs/fig2-cartpole/seed0: it runs again" in f.read()
    with open(later / "res" / "reproduce.log") as f:
        log = f.read()
    assert "fig2-cartpole/seed0" in log and "fig4/fig2-cartpole" in log and "left out" not in log, log
