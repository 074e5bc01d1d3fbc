"""Several processes (`jax.distributed`, `bulbjax.distributed`) and seed groups
(`bulbjax.epoch.groups`) on the CPU.

Two `bulbjax run` processes on localhost (a local coordinator, one CPU device each, Gloo for the
collectives) run a 2-seed CartPole experiment as two seed groups; process 0 writes metrics.jsonl;
both resume from their own checkpoints.
Its records must equal those of one process running both seeds on one device, within the float
tolerance of tests/test_sharding.py: every draw of a group is its seeds' share of the whole run's
(`seeds.SeedGroup.seed_keys`), and the reference spread is pooled over the processes, but XLA compiles
the updates for one seed instead of two, so sums run in another order.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from bulbjax.distributed import DistributedConfig
from bulbjax.epoch.groups import group_count

# --small with one short PPO update per epoch (16 steps): the equality below does not depend on
# how long PPO trains, and each of the test's ten process-epochs then takes ~6.5 s instead of ~14.5
# on this 2-core machine (`bulbjax run ... --small` measured alone)
BASE = ["run", "--env", "CartPole", "--learners", "vae_rpl", "--seeds", "2", "--small", "--ppo-updates", "1",
        "--ppo-option", "num_steps=16"]
RUN = [*BASE, "--epochs", "2"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cli(args: list[str], env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bulbjax.cli", *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _records(run_dir) -> list[dict]:
    with open(os.path.join(run_dir, "metrics.jsonl")) as f:
        return [json.loads(line) for line in f if line.strip()]


def test_group_count():
    assert group_count(6, 2) == 2 and group_count(12, 2) == 2 and group_count(6, 4) == 3
    assert group_count(6, 8) == 6 and group_count(1, 8) == 1 and group_count(5, 2) == 1
    assert group_count(6, 4, processes=2) == 2  # 3 groups would leave the processes uneven
    with pytest.raises(ValueError, match="multiple of 2"):
        group_count(3, 4, processes=2)


def test_process_checkpoint_round_trip(tmp_path):
    """A process's own checkpoint folder (multi-process runs) saves host copies and restores them
    onto the devices of the state it is restored into."""
    import jax
    import jax.numpy as jnp

    from bulbjax.run.checkpoint import Checkpointer

    state = {"a": jnp.arange(6.0).reshape(2, 3), "b": jnp.zeros((0,)), "k": jax.random.PRNGKey(3)}
    ck = Checkpointer(str(tmp_path), process=0)
    ck.save(4, state, {"epoch": 4})
    ck.close()
    assert os.listdir(tmp_path / "checkpoints") == ["process_0"]
    got, host, epoch = Checkpointer(str(tmp_path), process=0).restore(state)
    assert epoch == 4 and host == {"epoch": 4}
    for k in state:
        np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(state[k]))
        assert isinstance(got[k], jax.Array)


def test_distributed_settings():
    assert not DistributedConfig().wanted
    with pytest.raises(ValueError, match="--num-processes"):
        DistributedConfig(coordinator="h:1").check()
    with pytest.raises(ValueError, match="HOST:PORT"):
        DistributedConfig(coordinator="h", num_processes=2, process_id=0).check()
    with pytest.raises(ValueError, match=r"\[0, --num-processes 2\)"):
        DistributedConfig(coordinator="h:1", num_processes=2, process_id=2).check()
    DistributedConfig(coordinator="h:1", num_processes=2, process_id=1).check()


def _assert_close(one: list[dict], two: list[dict]) -> None:
    """Records of one process and of two, within tests/test_sharding.py's float tolerance."""
    assert len(one) == len(two)
    for a, b in zip(one, two):
        np.testing.assert_allclose(a["rl_return"], b["rl_return"], rtol=1e-4)
        np.testing.assert_allclose(a["learners"]["vae_rpl"]["loss"], b["learners"]["vae_rpl"]["loss"], rtol=1e-4)
        np.testing.assert_allclose(a["ref_spread"], b["ref_spread"], rtol=1e-5)
        for stream in ("curr", "rand"):
            pa, pb = a["probes"]["vae_rpl"][stream], b["probes"]["vae_rpl"][stream]
            np.testing.assert_allclose(pa["overall"]["mae_norm"], pb["overall"]["mae_norm"], rtol=0.05, atol=1e-3)


@pytest.mark.slow  # the slow tier: `make test-all` runs it, `make test` does not (tests/conftest.py)
def test_two_processes_equal_one(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "BULBJAX_COMPILE_CACHE": "off", "PYTHONUNBUFFERED": "1"}
    env.pop("XLA_FLAGS", None)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # off means off: not the test session's cache (conftest.py) either
    one_dir, two_dir = tmp_path / "one", tmp_path / "two"
    one = _cli([*RUN, "--out", str(one_dir)], env)
    port = _free_port()
    # the two processes run one epoch more, checkpointing every epoch, and share a compile cache
    # of the test's own: their resume below loads the programs this stretch compiled
    env_two = {**env, "BULBJAX_COMPILE_CACHE": str(tmp_path / "xla")}
    two = [_cli([*BASE, "--epochs", "3", "--checkpoint-every", "1", "--out", str(two_dir),
                 "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)], env_two)
           for i in range(2)]
    logs = [p.communicate(timeout=1500)[0] for p in (one, *two)]
    for p, log in zip((one, *two), logs):
        assert p.returncode == 0, log[-3000:]
    assert "2 seed groups of 1 seeds" in logs[1] and "over 2 processes" in logs[1]
    r1, r2 = _records(one_dir), _records(two_dir)
    assert [(r["epoch"], r["seed"]) for r in r2] == [(e, s) for e in range(3) for s in range(2)]
    assert [(r["epoch"], r["seed"]) for r in r1] == [(r["epoch"], r["seed"]) for r in r2[:4]]
    # process 1 wrote nothing of its own beside its checkpoints
    assert sorted(os.listdir(two_dir / "checkpoints")) == ["process_0", "process_1"]
    cfg2 = json.loads((two_dir / "config.json").read_text())
    assert cfg2["provenance"]["processes"] == 2 and cfg2["provenance"]["seed_groups"] == 2
    # 2 epochs: within the sharding tolerance (later, a PPO episode that ends one step apart moves
    # a return by percents: CartPole seed 0's third epoch gave 92.0 in one process, 88.4 in two)
    _assert_close(r1, r2[:4])
    # a kill after epoch 2's checkpoint: the last one goes, both processes resume from their own
    # and recompute epoch 3 exactly as the uninterrupted stretch did
    for i in range(2):
        assert sorted(os.listdir(two_dir / "checkpoints" / f"process_{i}")) == ["2", "3"]
        shutil.rmtree(two_dir / "checkpoints" / f"process_{i}" / "3")
    port = _free_port()
    more = [_cli(["run", "--resume", str(two_dir), "--coordinator", f"127.0.0.1:{port}",
                  "--num-processes", "2", "--process-id", str(i)], env_two) for i in range(2)]
    logs = [p.communicate(timeout=1500)[0] for p in more]
    for p, log in zip(more, logs):
        assert p.returncode == 0, log[-3000:]
    assert f"resuming {two_dir} at epoch 2" in logs[0], logs[0][-3000:]
    assert _records(two_dir) == r2  # bit for bit, none lost or doubled
    cfg3 = json.loads((two_dir / "config.json").read_text())
    assert cfg3["resumes"][-1]["processes"] == 2 and cfg3["resumes"][-1]["from_epoch"] == 2
    # a resume with another process count is refused in one clear line
    r = subprocess.run([sys.executable, "-m", "bulbjax.cli", "run", "--resume", str(two_dir), "--epochs", "3"],
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 2 and "made by 2 process(es)" in r.stderr, r.stderr[-2000:]


# ---------------------------------------------------------------------------- the one-process-per-GPU launcher
# absl's error and fatal lines (E1128 12:00:00.000 ...), tracebacks, and the gRPC wall a coordination
# service that went first leaves behind (issue 56)
_ERROR_LINE = re.compile(r"^[EF]\d{4} |Traceback|WatchTasks|UNAVAILABLE|CANCELLED|[Cc]onnection refused|"
                         r"^bulbjax: error|Error: ")


def _launch(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    """`bulbjax run ...` as a user starts it on a host with two GPUs: CUDA_VISIBLE_DEVICES names two
    (the launcher starts one process per GPU), and JAX runs each worker on one CPU device."""
    return subprocess.run([sys.executable, "-m", "bulbjax", *args], env={**env, "CUDA_VISIBLE_DEVICES": "0,1"},
                          capture_output=True, text=True, timeout=1500)


def _lines(text: str) -> list[str]:
    """Console lines without the progress bar's redraws."""
    return [x for x in text.replace("\r", "\n").splitlines() if x.strip() and " seeds: " not in x]


def _launch_env(tmp_path) -> dict[str, str]:
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONUNBUFFERED": "1", "BULBJAX_COMPILE_CACHE": str(tmp_path / "xla")}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # the test's own cache: it counts the entries below
    return env


@pytest.mark.slow  # the slow tier: two processes compile a run (~3-4 min on a busy 2-core CPU)
def test_launcher_run_ends_without_error_lines_and_a_refused_folder_is_one_line(tmp_path):
    """A run through the launcher that ends well leaves no error line on the console (stderr) or in
    any process's log (the coordination service runs in the launcher and outlives the workers);
    every process wrote its own programs to the compile cache; the same command again is refused
    for its folder in one line, before any worker starts."""
    env, out = _launch_env(tmp_path), str(tmp_path / "run")
    r = _launch([*BASE, "--epochs", "1", "--out", out], env)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "2 GPUs: one process per GPU" in r.stderr and "over 2 processes" in r.stdout, r.stdout[-2000:]
    bad = [x for x in _lines(r.stderr) if _ERROR_LINE.search(x)]
    assert not bad, bad
    for name in ("log.txt", "log_process1.txt", "log_coordinator.txt"):
        text = open(os.path.join(out, name)).read()
        assert not [x for x in _lines(text) if _ERROR_LINE.search(x)], (name, text[-3000:])
    cached = os.listdir(tmp_path / "xla")
    assert sum(n.startswith("jit__epoch-") for n in cached) == 2, cached  # process 0's and process 1's
    assert sum(n.startswith("jit__init-") for n in cached) == 2, cached
    again = _launch([*BASE, "--epochs", "1", "--out", out], env)
    assert again.returncode == 2
    assert _lines(again.stderr) == [next(x for x in _lines(again.stderr) if x.startswith("bulbjax: error: "))]
    assert "holds a run" in again.stderr and "one process per GPU" not in again.stderr + again.stdout


def test_launcher_names_the_failed_process_and_stops_the_others(tmp_path):
    """One worker fails (process 1 cannot open its log: a folder is in the way): the launcher stops
    process 0 at once and says in one line which process failed and why."""
    env, out = _launch_env(tmp_path), tmp_path / "run"
    os.makedirs(out / "log_process1.txt")
    t = time.time()
    r = _launch([*BASE, "--epochs", "1", "--out", str(out)], env)
    assert r.returncode == 1
    lines = [x for x in _lines(r.stderr) if not x.startswith(("[", "2 GPUs: "))]
    assert len(lines) == 1, r.stderr[-3000:]
    assert lines[0].startswith("bulbjax: error: process 1 of 2 (GPU 1) failed: IsADirectoryError: ")
    assert "stopped process 0" in lines[0]
    assert time.time() - t < 300  # not JAX's shutdown barrier (5 minutes) nor its heartbeat timeout
