"""`bulbjax reproduce --learners-apart`: a job's learners on a second GPU (`bulbjax run --overlap
apart`). Slots of two GPUs each, jobs timed by their preset's `<preset> apart` row and counted as
two GPUs' hours in the estimate and on the page, and `benchmarks/epoch_times.py` measuring that
row from such a stretch."""

from __future__ import annotations

import json
import os

import pytest

from bulbjax.reproduce.main import reproduce
from bulbjax.reproduce.plan import plan_jobs


def test_learners_apart_gives_each_job_a_pair_of_devices(tmp_path, monkeypatch) -> None:
    """`--learners-apart`: a slot per two GPUs (an odd one left over unused), two CPU devices per
    CPU worker, one line on a host of one GPU; every job's command asks for `--overlap apart`."""
    from bulbjax import local_processes
    from bulbjax.reproduce import main

    monkeypatch.setattr(main, "host_kind", lambda gpus: "NVIDIA H200")
    monkeypatch.setattr(local_processes, "visible_gpus", lambda: ["0", "1", "2", "3", "4"])
    slots, kind = main.slots_of(None, 2)
    assert [s.gpu for s in slots] == ["0,1", "2,3"] and kind == "NVIDIA H200"
    assert slots[0].env()["CUDA_VISIBLE_DEVICES"] == "0,1"
    assert [s.gpu for s in main.slots_of(None)[0]] == ["0", "1", "2", "3", "4"]
    monkeypatch.setattr(local_processes, "visible_gpus", lambda: ["0"])
    with pytest.raises(ValueError, match="--learners-apart runs each job on 2 GPUs and this host has 1"):
        main.slots_of(None, 2)
    monkeypatch.setattr(local_processes, "visible_gpus", lambda: [])
    (cpu,), _ = main.slots_of(None, 2)
    assert "--xla_force_host_platform_device_count=2" in cpu.env()["XLA_FLAGS"]
    summary = reproduce("fig2-cartpole", "tiny", str(tmp_path / "o"), dry_run=True, learners_apart=True,
                        log=lambda _: None)
    assert summary["learners_apart"] and summary["gpus"] == 1 and summary["apart_env_learners"] == "auto"
    from bulbjax.reproduce import jobs as J

    job = plan_jobs("fig2-cartpole", "tiny")[0]
    apart = J.command(str(tmp_path / "o"), job, 1.0, run_flags=("--overlap", "apart"))
    assert " ".join(apart[apart.index("--overlap"):][:2]) == "--overlap apart"
    assert "--overlap" not in J.command(str(tmp_path / "o"), job, 1.0)
    # the flags a stretch gives its jobs: --apart-env-learners only beside --learners-apart, auto
    # unless given (pred on the first GPU: 0.997 s a fig2-ant epoch against 1.08-1.13 s without)
    from bulbjax.reproduce.main import apart_flags

    assert apart_flags(True, None) == ("--overlap", "apart", "--apart-env-learners", "auto")
    assert apart_flags(False, None) == ()
    assert apart_flags(True, "none") == ("--overlap", "apart", "--apart-env-learners", "none")
    with pytest.raises(ValueError, match="give --learners-apart too"):
        apart_flags(False, "pred")
    with pytest.raises(ValueError, match="no learner prd; give auto, none"):
        apart_flags(True, "prd")


def test_learners_apart_are_timed_by_their_rows_and_count_two_gpus(tmp_path, monkeypatch) -> None:
    """With `--learners-apart` a job is timed by its preset's `<preset> apart` row (fig2-halfcheetah
    on an H200: 1.133 s an epoch against 1.75 s on one GPU), a preset without one by its one-GPU
    row, said in the plan; a job's GPU-hours count both its GPUs, in the estimate and the page."""
    from bulbjax import local_processes
    from bulbjax.reproduce import estimate, main, results

    times, _ = estimate.load_times("NVIDIA H200")
    apart = estimate.apart_times(times)
    assert apart["fig2-halfcheetah"] == times["fig2-halfcheetah apart"]
    assert apart["fig2-halfcheetah"].epoch_s < 0.7 * times["fig2-halfcheetah"].epoch_s
    assert apart["fig2-cartpole"].epoch_s == times["fig2-cartpole"].epoch_s
    assert "no apart row" in apart["fig2-cartpole"].derived
    assert not [k for k in [*apart, *estimate.without_apart_rows(times)] if k.endswith(" apart")]
    monkeypatch.setattr(main, "host_kind", lambda gpus: "NVIDIA H200")
    monkeypatch.setattr(local_processes, "visible_gpus", lambda: ["0", "1"])
    said: list[str] = []
    two = reproduce("fig2-halfcheetah", "paper", str(tmp_path / "a"), dry_run=True, learners_apart=True,
                    jobs="fig2-halfcheetah/seed0", log=said.append)
    row = times["fig2-halfcheetah apart"]
    chain = row.startup_cold_s + 1000 * row.epoch_s
    assert two["gpus"] == 2 and two["estimated_wall_s"] == pytest.approx(chain)
    assert two["estimated_gpu_s"] == pytest.approx(2 * chain)
    assert "slot(s) of two GPUs each" in said[-1] and ": estimated" not in said[-1]
    reproduce("fig2-cartpole", "paper", str(tmp_path / "c"), dry_run=True, learners_apart=True,
              jobs="fig2-cartpole/seed0", log=said.append)
    assert "fig2-cartpole: estimated, " in said[-1] and "no apart row" in said[-1]
    one = reproduce("fig2-halfcheetah", "paper", str(tmp_path / "b"), dry_run=True,
                    jobs="fig2-halfcheetah/seed0", log=lambda _: None)
    assert one["estimated_wall_s"] > two["estimated_wall_s"] + 500  # the point of taking two GPUs
    out = tmp_path / "page"
    out.mkdir()
    rec = {"learners_apart": True, "device_kind": "NVIDIA H200", "busy_s": 600.0, "finished_utc": "x",
           "jobs": {"j": {"attempts": 1, "busy_s": 600.0}}}
    (out / "summary_x.json").write_text(json.dumps(rec))
    assert results.job_times(str(out))["j"]["busy_s"] == pytest.approx(1200.0)
    (out / "summary_x.json").write_text(json.dumps({**rec, "device_kind": "cpu"}))  # a CPU worker: one
    assert results.job_times(str(out))["j"]["busy_s"] == pytest.approx(600.0)
    # the page's stretch line counts the GPUs and the slots they make
    line = results._summary_line({**rec, "gpus": 2, "measured_wall_s": 600.0})
    assert line.startswith("The last stretch (ended x UTC): 2 NVIDIA H200 GPUs, 1 slot(s) of two"), line


def test_epoch_times_reads_an_apart_stretch_into_its_apart_row(tmp_path) -> None:
    """`benchmarks/epoch_times.py --from-summary` of a stretch with the learners apart measures
    the `<preset> apart` row (two GPUs a job), never the preset's one-GPU row."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "epoch_times", os.path.join(os.path.dirname(os.path.dirname(__file__)), "benchmarks", "epoch_times.py"))
    et = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(et)
    rec = {"device_kind": "NVIDIA H200", "jobs": {"fig2-halfcheetah/seed0": {"epoch_s": 1.1, "startup_s": 190.0}}}
    for apart, row in ((True, "fig2-halfcheetah apart"), (False, "fig2-halfcheetah")):
        path = tmp_path / f"summary_{apart}.json"
        path.write_text(json.dumps({**rec, "learners_apart": apart}))
        kind, found = et.from_summary(str(path))
        assert kind == "NVIDIA H200" and found == {row: {"epoch_s": 1.1, "startup_cold_s": 190}}
