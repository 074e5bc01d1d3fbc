"""`bulbjax reproduce`'s fp32 entry (the issue's "fp32 column: at least InvertedPendulum 6 x 1,000
in fp32 beside its bf16 run"): its jobs beside Fig. 2's without colliding, its estimate, and a
campaign folder planned before it continuing with it. Plans only: nothing here runs `bulbjax run`."""

from __future__ import annotations

import json
import os
import re
import shutil

import pytest

from bulbjax.reproduce import estimate, plan
from bulbjax.reproduce.main import reproduce
from bulbjax.reproduce.plan import plan_jobs

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CAMPAIGN = os.path.join(ROOT, "docs", "results", "paper_h200", "plan.json")  # read, never written


@pytest.mark.parametrize("scale", plan.SCALES)
def test_the_fp32_entry_is_fig2s_invpend_without_bf16(scale: str) -> None:
    """At each scale: the fp32 jobs are Fig. 2's InvertedPendulum jobs (seeds, epochs, probes,
    seeds per job, the other flags) without `--bf16`, with ids and folders of their own, last in
    "all"; `--figures fp32` plans exactly them."""
    every = plan_jobs("all", scale)
    assert len({j.id for j in every}) == len(every) and len({j.run_dir for j in every}) == len(every)
    fp32 = [j for j in every if j.figure == "fp32"]
    fig2 = [j for j in every if j.figure == "fig2" and j.preset == "fig2-invpend"]
    assert fp32 and every[-len(fp32):] == fp32  # after every job of the paper's figures
    assert plan_jobs("fp32", scale) == fp32
    assert [(j.seed, j.seeds, j.epochs, j.probe_every, j.recon_every, j.preset) for j in fp32] == \
           [(j.seed, j.seeds, j.epochs, j.probe_every, j.recon_every, j.preset) for j in fig2]
    for a, b in zip(fp32, fig2):
        assert "--bf16" not in a.flags and a.flags == tuple(f for f in b.flags if f != "--bf16")
        assert a.id == f"fp32/{b.id}" and a.run_dir == f"runs/fp32/{b.id}"
    assert not any(x.run_dir.startswith(y.run_dir + "/") or y.run_dir.startswith(x.run_dir + "/")
                   for x in fp32 for y in every if y is not x)  # no run folder inside another
    if scale == "paper":
        assert [j.seed for j in fp32] == list(range(6)) and {j.epochs for j in fp32} == {1000}
        assert {j.probe_every for j in fp32} == {10} and all("--probe-variants" in j.flags for j in fp32)
    if scale == "quick":
        assert [(j.id, j.seeds, j.epochs) for j in fp32] == [("fp32/fig2-invpend/seeds0-1", 2, 60)]


def test_the_campaigns_jobs_are_unchanged_and_its_folder_continues(tmp_path, monkeypatch) -> None:
    """The committed campaign's plan.json (made before the fp32 entry) holds the first jobs of
    today's "all", each the same; a folder holding it continues as "all" with the 6 fp32 jobs added
    (new), each host's shard of its jobs unchanged; a saved plan of a former "all" whose jobs differ,
    or of other figures, is still refused."""
    from bulbjax.assets.ycb import YCB_DIR_ENV

    with open(CAMPAIGN) as f:
        saved = json.load(f)
    old = [plan.job_of(d) for d in saved["jobs"]]
    new = plan_jobs("all", "paper")
    assert new[:len(old)] == old and {j.figure for j in new[len(old):]} == {"fp32"}
    record = plan.plan_record(plan.parse_figures("all"), "paper", [], new)
    assert plan.plan_differences(saved, record) == []
    assert plan.grown_from(saved, record) == [f"fp32/fig2-invpend/seed{k}" for k in range(6)]
    times, _ = estimate.load_times("NVIDIA H200")
    cost = {j.id: estimate.job_cost(j, times) for j in new}
    for n in (2, 3, 6):
        before, after = plan.shard_of(old, cost, n), plan.shard_of(new, cost, n)
        assert {i: after[i] for i in before} == before

    out = tmp_path / "campaign"
    out.mkdir()
    shutil.copy(CAMPAIGN, out / plan.PLAN_FILE)
    monkeypatch.setenv(YCB_DIR_ENV, str(tmp_path))
    said: list[str] = []
    s = reproduce("all", "paper", str(out), dry_run=True, log=said.append)
    assert s["jobs_planned"] == len(old) + 6
    assert "before fp32 joined --figures all: its 34 jobs continue, 6 added" in said[0]
    assert re.search(r"\nfp32/fig2-invpend/seed5 +0/1000 +[0-9:]+  new\n", said[1]), said[1]

    changed = dict(saved, jobs=[dict(saved["jobs"][0], flags=["--bf16"]), *saved["jobs"][1:]])
    assert plan.grown_from(changed, record) == [] and plan.plan_differences(changed, record)
    fig2 = dict(saved, figures=["fig2"], jobs=[d for d in saved["jobs"] if d["figure"] == "fig2"])
    assert plan.grown_from(fig2, record) == [] and plan.plan_differences(fig2, record)
    (out / plan.PLAN_FILE).write_text(json.dumps(changed))
    with pytest.raises(ValueError, match="other settings"):
        reproduce("all", "paper", str(out), dry_run=True, log=said.append)


def test_fp32_jobs_are_estimated_slower_and_say_how(tmp_path) -> None:
    """Without an fp32 row an fp32 job costs its preset's bf16 epochs x FP32_EPOCH_FACTOR (start-up
    as is, its own compile: not warm after a bf16 job), and the dry run says the row is derived; a
    measured `fig2-invpend fp32` row is used as it is. `--jobs` picks one fp32 job."""
    times, _ = estimate.load_times("NVIDIA H200")
    bf16, fp32 = plan_jobs("fig2-invpend", "paper")[0], plan_jobs("fp32", "paper")[0]
    t = times["fig2-invpend"]
    assert estimate.job_cost(fp32, times) == pytest.approx(
        t.startup_cold_s + 1000 * t.epoch_s * estimate.FP32_EPOCH_FACTOR)
    assert estimate.job_cost(fp32, times) > estimate.job_cost(bf16, times)
    assert "FP32_EPOCH_FACTOR" in estimate.timing_of(fp32, times).derived
    assert estimate.timing_key(bf16) == "fig2-invpend" and estimate.timing_key(fp32) == "fig2-invpend fp32"
    assert estimate.timing_key(plan_jobs("fp32", "tiny")[0]) == "fig2-invpend"  # the CPU rows' --small runs
    # on one slot the fp32 job after the bf16 one still starts cold: other programs
    assert estimate.simulate([bf16, fp32], times, 1).wall_s == pytest.approx(
        estimate.job_cost(bf16, times) + estimate.job_cost(fp32, times))
    measured = dict(times, **{"fig2-invpend fp32": estimate.Timing(0.9, 200.0, 50.0)})
    assert estimate.job_cost(fp32, measured) == 200.0 + 900.0 and estimate.derived_fp32([fp32], measured) == []

    said: list[str] = []
    s = reproduce("fp32", "paper", str(tmp_path / "o"), dry_run=True, jobs="fp32/fig2-invpend/seed0",
                  log=said.append)
    assert s["jobs_planned"] == 1 and "plan: 1 job(s) of 6, 1 picked by --jobs" in said[0]
    assert "fp32/fig2-invpend/seed0" in said[0] and "fp32/fig2-invpend/seed1" not in said[0]
    assert "fig2-invpend fp32: estimated, no 'fig2-invpend fp32' row" in said[0]
    with pytest.raises(ValueError, match="--jobs: fig2-invpend/seed0 not in this plan"):
        plan.parse_jobs("fig2-invpend/seed0", plan_jobs("fp32", "paper"))

