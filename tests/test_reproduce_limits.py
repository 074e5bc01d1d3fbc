"""`bulbjax reproduce` on a host held for a limited time, or one share of several: what
`--fit-minutes` picks, a job that cannot start in the time `--max-minutes` leaves, a shard with
no jobs."""

from __future__ import annotations

import time

import pytest

from bulbjax.reproduce import estimate, plan
from bulbjax.reproduce.estimate import Timing
from bulbjax.reproduce.main import reproduce
from bulbjax.reproduce.plan import Job
from bulbjax.reproduce.queue import Queue, Slot


def test_a_host_held_for_minutes_picks_what_it_can_finish() -> None:
    """`--fit-minutes`: longest first, a job kept while the simulated schedule still ends in time;
    a Fig. 4 job only with the run it reads. `--jobs`: the named jobs with their Fig. 4 partner."""
    t = {"a": Timing(1.0, 100.0, 20.0), "b": Timing(1.0, 100.0, 20.0), "recon": Timing(0.0, 30.0, 30.0)}
    runs = [Job("a/seed0", "fig2", "run", "a", 0, 500, "runs/a/seed0"),   # 600 s cold
            Job("a/seed1", "fig2", "run", "a", 1, 500, "runs/a/seed1"),   # 520 s warm after it
            Job("b/seed0", "fig2", "run", "b", 0, 200, "runs/b/seed0")]   # 300 s cold
    recon = Job("fig4/a", "fig4", "recon", "a", 0, 500, "fig4/a", after="a/seed0")
    jobs = [*runs, recon]
    # 11 minutes on one GPU: a/seed0 with its Fig. 4 (630 s); nothing else fits beside them
    assert [j.id for j in estimate.fit_jobs(jobs, t, 1, 11)] == ["a/seed0", "fig4/a"]
    # 12 minutes on two GPUs: a/seed0 + fig4 on one, a/seed1 (600 s cold beside it) on the other
    assert [j.id for j in estimate.fit_jobs(jobs, t, 2, 12)] == ["a/seed0", "a/seed1", "fig4/a"]
    # a run half done (a checkpoint at epoch 250) costs its start-up and the epochs left
    assert [j.id for j in estimate.fit_jobs(runs[1:], t, 1, 6, {"a/seed1": 250})] == ["a/seed1"]
    assert estimate.fit_jobs(jobs, t, 1, 4) == []
    with pytest.raises(ValueError, match="--fit-minutes must be > 0"):
        estimate.fit_jobs(jobs, t, 1, 0)
    assert [j.id for j in plan.parse_jobs("fig4/a", jobs)] == ["a/seed0", "fig4/a"]
    assert [j.id for j in plan.parse_jobs("b/seed0,a/seed0", jobs)] == ["a/seed0", "b/seed0", "fig4/a"]
    assert plan.parse_jobs(None, jobs) is None
    with pytest.raises(ValueError, match=r"--jobs: c/seed0 not in this plan \(a job of a figure the plan leaves "
                                         r"out\? add it to --figures\); its jobs, as --dry-run lists them: a/\.\.\., "):
        plan.parse_jobs("c/seed0", jobs)
    with pytest.raises(ValueError, match=r"--jobs: a/seed7 not in this plan; its jobs"):  # a seed the plan lacks
        plan.parse_jobs("a/seed7", jobs)


def test_a_job_that_cannot_start_in_the_time_left_is_said_and_the_command_ends(tmp_path) -> None:
    """--max-minutes shorter than a job's start-up and a minute: the job is not started, the log
    says why, and the command ends at once (it sat idle to the deadline, saying nothing)."""
    job = Job("fig2-cartpole/seed0", "fig2", "run", "fig2-cartpole", 0, 1, "runs/fig2-cartpole/seed0",
              flags=("--small",))
    said: list[str] = []
    times, _ = estimate.load_times("cpu")
    t0 = time.monotonic()
    q = Queue(str(tmp_path), [job], [job], [Slot("cpu0", None)], times, deadline=t0 + 30, progress_every=1e9,
              log=said.append, poll_s=0.2)
    summary = q.run()
    assert time.monotonic() - t0 < 10 and summary["unfinished"] == [job.id]
    assert summary["jobs"][job.id]["attempts"] == 0
    assert any(x.startswith("fig2-cartpole/seed0 not started: ") and "--max-minutes" in x for x in said), said
    assert len([x for x in said if x.startswith("[0:")]) == 1, said  # the last progress line once, not twice


def test_a_shard_with_no_jobs_says_so(tmp_path) -> None:
    said: list[str] = []
    reproduce("fig2-cartpole", "tiny", str(tmp_path / "p"), shard="3/3", dry_run=True, log=said.append)
    assert any(x.startswith("shard 3/3 has no jobs: the plan's 2 job(s) make fewer than 3 shares") for x in said), said
