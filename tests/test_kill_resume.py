"""Crashes at the worst moments, CI-sized (`benchmarks/kill_resume.py --size tiny`): a run of 3
epochs is killed with SIGKILL once with checkpoint 2 written but not committed and once with
half an epoch's records in metrics.jsonl; each stretch resumes from the newest complete
checkpoint, and the finished metrics.jsonl equals an uninterrupted run's byte for byte. The CLI
output of the stretches names the start-up stages in order. ~4 minutes on a busy 2-core CPU
(three stretches and the reference, each ~50 s of start-up)."""

from __future__ import annotations

import importlib.util
import os
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))


def _script():
    path = os.path.join(os.path.dirname(HERE), "benchmarks", "kill_resume.py")
    spec = importlib.util.spec_from_file_location("kill_resume", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _stages(console: str) -> list[str]:
    out = []
    for piece in open(console, errors="replace").read().replace("\r", "\n").split("\n"):
        if "[" in piece and " s] " in piece:
            out.append(piece[piece.index(" s] ") + 4:].strip())
    return out


def _in_order(lines: list[str], starts: list[str]) -> bool:
    idx = [next((i for i, x in enumerate(lines) if x.startswith(s)), -1) for s in starts]
    return -1 not in idx and idx == sorted(idx)


@pytest.mark.slow  # the slow tier: `make test-all` runs it, `make test` does not (tests/conftest.py)
def test_kills_at_the_worst_moments_resume_exactly(tmp_path):
    work = tmp_path / "work"
    res = _script().main(["--size", "tiny", "--epochs", "3", "--kills", "2", "--plan", "commit:2,append:1",
                          "--pause-append", "0.4", "--pause-commit", "0.6", "--work", str(work),
                          "--json", str(tmp_path / "kill_resume.json")])
    s = res["summary"]
    assert s["failures"] == [], s["failures"]
    commit, append = res["kills"]
    # killed with checkpoint 2 written but not renamed: checkpoint 1 is the newest complete one (the
    # checkpoint is written in the background, so the loop may have started the next epoch and even
    # appended its records meanwhile: metrics run ahead, never behind)
    assert commit["kind"] == "commit" and "ckpt-commit 2" in commit["last_events"]
    assert commit["state_after_kill"]["complete_checkpoints"] == [1]
    assert commit["state_after_kill"]["partial_checkpoints"] == 1
    assert commit["state_after_kill"]["metrics_epochs"] in (2, 3)
    assert (commit["resumed_from"], commit["resume_ok"]) == (1, True)
    # killed mid-append: half a record on disk, cut by the resume
    assert append["kind"] == "append" and append["state_after_kill"]["half_line"]
    assert (append["resumed_from"], append["resume_ok"]) == (1, True)
    run = res["runs"][0]
    assert run["exit"] == 0 and run["final_equal"] and run["unfinished_checkpoints_left"] == 0
    assert s["runs_equal_to_reference"] == 1 and os.path.getsize(tmp_path / "kill_resume.json") > 1000
    # the start-up stages, in order, on the console of the fresh stretch and of a resumed one
    fresh = _stages(str(work / "run0_s0.console"))
    assert _in_order(fresh, ["building the environment and learners ...", "tracing and lowering init and the epoch ...",
                             "compiling init ...", "running init ...", "compiling the epoch ...", "first epoch (0) ...",
                             "first epoch (0): "]), fresh
    resumed = _stages(str(work / "run0_s2.console"))
    assert _in_order(resumed, ["building the environment and learners ...", "tracing and lowering the epoch ...",
                               "restoring the checkpoint of epoch 1 ...", "compiling the epoch ...",
                               "first epoch (1) ..."]), resumed
    log = open(work / "run0" / "log.txt").read()
    assert log.count("==== ") == 3 and "restoring the checkpoint of epoch 1 ..." in log  # 3 stretches, one log
