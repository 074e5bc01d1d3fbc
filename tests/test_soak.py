"""The GPU soak script at CPU size (`benchmarks/soak.py --small`, one environment): it steps every
world for the steps asked, counts episodes and non-finite resets, leaks nothing non-finite, and
writes its JSON; bad flags and unknown names are refused."""

from __future__ import annotations

import importlib.util
import json
import os
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))


def _script():
    path = os.path.join(os.path.dirname(HERE), "benchmarks", "soak.py")
    spec = importlib.util.spec_from_file_location("soak", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_small_soak_counts_and_writes_json(tmp_path, capsys):
    soak = _script()
    # 8 worlds x 50 steps in 2 chunks; CartPole's random episodes end in ~20 steps: episodes are counted
    assert soak.main(["--small", "--envs", "CartPole", "--out-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    files = [f for f in os.listdir(tmp_path) if f.startswith("soak_") and f.endswith(".json")]
    assert len(files) == 1
    res = json.load(open(tmp_path / files[0]))
    (rec,) = res["envs"]
    assert rec["env"] == "CartPole" and rec["worlds"] == 8
    assert rec["steps"] == rec["target_steps"] == 400 and rec["steps_per_world"] == 50 and rec["chunk"] == 25
    assert rec["episodes"] > 8 and rec["episodes"] == rec["terminated"] + rec["truncated"]
    assert rec["nonfinite_resets"] == 0 and rec["leaked_nonfinite"] == rec["reset_nonfinite"] == 0
    assert rec["actions_fixed"] == 0
    assert rec["steps_per_s"] > 0 and rec["run_s"] > 0
    assert res["summary"]["steps"] == rec["steps"] and res["summary"]["with_nonfinite"] == []
    # the environment ran in a child process of its own, its record handed back, nothing failed
    assert res["isolated"] is True and res["summary"]["failed"] == [] and res["device"]["platform"] == "cpu"
    assert not [f for f in os.listdir(tmp_path) if f.endswith(".child.json")]
    assert "CartPole" in out and "non-finite resets" in out  # one line per environment


def test_soak_flags():
    soak = _script()
    a = soak.parse_args(["--small"])
    assert (a.worlds, a.envs) == (8, "CartPole,InvertedPendulum")
    full = soak.parse_args([])
    assert (full.worlds, full.steps, full.long_steps) == (4096, 1_000_000, 10_000_000)
    assert soak.steps_for("HalfCheetahMulticolour", full) == 10_000_000 and soak.steps_for("GeomOnIncline", full) == 1_000_000
    with pytest.raises(SystemExit):
        soak.parse_args(["--worlds", "0"])
    assert soak.main(["--small", "--envs", "Pendulum", "--list"]) == 2
