"""Several processes (`jax.distributed`, `bulbjax.distributed`) and seed groups
(`bulbjax.experiment.groups`) on the CPU.

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
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest

from bulbjax.distributed import DistributedConfig
from bulbjax.experiment.groups import group_count

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

    from bulbjax.experiment.checkpoint import Checkpointer

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
