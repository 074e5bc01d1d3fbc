"""Warm start-ups in `bulbjax reproduce`'s estimate: a job that reached its first epoch notes in
the compile cache that its programs are there (`compile_cache.mark_warm`, per device kind), and a
plan made with that cache (the next stretch, or the next GPU allocation with the cache carried)
estimates that preset's first job warm, and says so. The sixth allocation's estimate took cold
start-ups (271 s) for jobs that started in 38-41 s with the caches carried: 13:34 against 9:33."""

from __future__ import annotations

import json
import os
import time

import pytest

from bulbjax import compile_cache
from bulbjax.reproduce import estimate
from bulbjax.reproduce.main import reproduce
from bulbjax.reproduce.plan import Job, plan_jobs
from bulbjax.reproduce.queue import Queue, Slot

H200 = "NVIDIA H200"


@pytest.fixture
def cache(tmp_path, monkeypatch):
    from bulbjax import local_processes

    monkeypatch.setattr(local_processes, "visible_gpus", lambda: [])
    path = tmp_path / "cache"
    monkeypatch.setenv("BULBJAX_COMPILE_CACHE", str(path))
    return path


def test_a_plan_with_the_programs_cached_estimates_them_warm(tmp_path, cache) -> None:
    job = "fig2-invpend/seed4"
    said: list[str] = []
    plan = dict(dry_run=True, device_kind=H200, log=said.append)
    cold = reproduce("fig2-invpend", "paper", str(tmp_path / "a"), jobs=job, **plan)
    assert "warm start-ups" not in said[-1]
    compile_cache.mark_warm(H200, "fig2-invpend")
    compile_cache.mark_warm(H200, "fig2-invpend")  # once is enough: noted once
    compile_cache.mark_warm("cpu", "fig2-cartpole")
    assert json.loads((cache / compile_cache.WARM_FILE).read_text()) == {H200: ["fig2-invpend"],
                                                                        "cpu": ["fig2-cartpole"]}
    warm = reproduce("fig2-invpend", "paper", str(tmp_path / "a"), jobs=job, **plan)
    t = estimate.load_times(H200)[0]["fig2-invpend"]
    assert cold["estimated_wall_s"] == pytest.approx(t.startup_cold_s + 1000 * t.epoch_s)
    assert warm["estimated_wall_s"] == pytest.approx(t.startup_warm_s + 1000 * t.epoch_s)
    assert f"warm start-ups for fig2-invpend: the compile cache ({cache}) holds" in said[-1]
    # the fp32 job compiles other programs, and with the learners apart every job does
    id32 = "fp32/fig2-invpend/seed1"
    fp32 = reproduce("fig2-invpend,fp32", "paper", str(tmp_path / "b"), jobs=id32, **plan)
    job32 = next(j for j in plan_jobs("fig2-invpend,fp32", "paper") if j.id == id32)
    t32 = estimate.timing_of(job32, estimate.load_times(H200)[0])
    assert fp32["estimated_wall_s"] == pytest.approx(t32.startup_cold_s + 1000 * t32.epoch_s)
    apart = reproduce("fig2-invpend", "paper", str(tmp_path / "c"), gpus=2, jobs=job,
                      learners_apart=True, **plan)
    assert "warm start-ups" not in said[-1]
    assert apart["estimated_wall_s"] == pytest.approx(cold["estimated_wall_s"])


def test_the_queue_notes_a_job_at_its_first_epoch_once(tmp_path, cache) -> None:
    job = Job("fig2-cartpole/seed0", "fig2", "run", "fig2-cartpole", 0, 3,
              "runs/fig2-cartpole/seed0")
    seen: list[str] = []
    q = Queue(str(tmp_path), [job], [job], [Slot("cpu0", None)], estimate.load_times("cpu")[0],
              on_first_epoch=lambda j: seen.append(j.id))
    t = q.tracks[job.id]
    t.started = time.monotonic()
    q._watch([t])
    assert seen == []  # no epoch written yet: still compiling
    run = tmp_path / "runs" / "fig2-cartpole" / "seed0"
    os.makedirs(run)
    (run / "metrics.jsonl").write_text(json.dumps({"epoch": 0, "seed": 0}) + "\n")
    q._watch([t])
    (run / "metrics.jsonl").write_text(json.dumps({"epoch": 1, "seed": 0}) + "\n")
    q._watch([t])
    assert seen == [job.id] and t.startup_s is not None


def test_a_job_s_epoch_time_runs_from_its_first_record_to_its_last(
    tmp_path, cache, monkeypatch
) -> None:
    """An ended job's `epoch_s` is its rate between its records, and what follows its last record
    (the last checkpoint, the exit) is `end_s`: spread over the epochs, those ~9 s made a 30-epoch
    fig3-rearrange-geom job on an H200 read 0.89 s an epoch against 0.55 s by its progress lines."""
    from bulbjax.reproduce import queue as Q

    clock = [0.0]
    monkeypatch.setattr(Q.time, "monotonic", lambda: clock[0])
    job = Job(
        "fig2-cartpole/seed0", "fig2", "run", "fig2-cartpole", 0, 10, "runs/fig2-cartpole/seed0"
    )
    q = Queue(str(tmp_path), [job], [job], [Slot("cpu0", None)], estimate.load_times("cpu")[0])
    t = q.tracks[job.id]
    t.status, t.slot, t.started = "running", q.slots[0], 0.0
    run = tmp_path / "runs" / "fig2-cartpole" / "seed0"
    os.makedirs(run)
    for epoch in range(10):  # the first record at 100 s, then one a second
        clock[0] = 100.0 + epoch
        with open(run / "metrics.jsonl", "a") as f:
            f.write(json.dumps({"epoch": epoch, "seed": 0}) + "\n")
        q._watch([t])

    class Ended:
        def poll(self) -> int:
            return 0

    t.proc = Ended()
    clock[0] = 130.0  # 21 s of last checkpoint and exit after the last record (the poll's)
    q._reap()
    assert t.startup_s == 100.0
    assert t.epoch_s == pytest.approx(1.0) and t.end_s == pytest.approx(21.0)  # not (130 - 100) / 9
    assert q.summary()["jobs"][job.id]["end_s"] == pytest.approx(21.0)


def test_the_queue_s_time_left_is_the_plan_s_with_the_programs_cached(tmp_path, cache) -> None:
    """The progress line's time left takes the warm start-ups the plan took (a newcomer's plan
    said 0:01:16 warm and its progress line 0:02:16 just after, the cold start-up)."""
    job = Job("fig2-cartpole/seed0", "fig2", "run", "fig2-cartpole", 0, 3,
              "runs/fig2-cartpole/seed0")
    times = estimate.load_times("cpu")[0]
    lines: dict[bool, str] = {}
    for warm in (False, True):
        said: list[str] = []
        q = Queue(str(tmp_path), [job], [job], [Slot("cpu0", None)], times, log=said.append,
                  warm=frozenset({"fig2-cartpole"} if warm else ()))
        q.progress()
        lines[warm] = said[-1]
    t = times["fig2-cartpole"]
    assert f"about {estimate.hms(t.startup_cold_s + 3 * t.epoch_s)} left" in lines[False]
    assert f"about {estimate.hms(t.startup_warm_s + 3 * t.epoch_s)} left" in lines[True], lines


def test_a_cache_that_cannot_be_written_warns_and_stops_nothing(tmp_path, monkeypatch) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    monkeypatch.setenv("BULBJAX_COMPILE_CACHE", str(blocked / "cache"))
    with pytest.warns(UserWarning, match="takes no note of 'fig2-cartpole'"):
        compile_cache.mark_warm(H200, "fig2-cartpole")
    assert compile_cache.warm_keys(H200) == frozenset()


def test_an_unreadable_note_is_a_cold_estimate(cache) -> None:
    os.makedirs(cache)
    (cache / compile_cache.WARM_FILE).write_text("{not json")
    assert compile_cache.warm_keys(H200) == frozenset()
    compile_cache.mark_warm(H200, "fig2-cartpole")
    assert compile_cache.warm_keys(H200) == {"fig2-cartpole"}
