"""`bulbjax reproduce`'s fp32 entry (the issue's "fp32 column: at least InvertedPendulum 6 x 1,000
in fp32 beside its bf16 run"): its jobs beside Fig. 2's without colliding, its estimate, a campaign
folder planned before it continuing with it, and the results page's comparison of each claim's
verdict in bf16 and in fp32, from the two merged runs' findings. Plans only and synthetic run
folders: nothing here runs `bulbjax run`."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil

import pytest

from bulbjax.config import ExperimentConfig
from bulbjax.report import records
from bulbjax.reproduce import claims, estimate, plan, results
from bulbjax.reproduce.main import reproduce
from bulbjax.reproduce.plan import Job, plan_jobs

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CAMPAIGN = os.path.join(ROOT, "docs", "results", "paper_h200", "plan.json")  # read, never written
REPLAY = "replay fixes VAE_v0 on π_rand (vae_rpl's error below vae's)"


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
    """The committed campaign's plan.json is today's "all" (it grew when its first fp32 job was
    gathered); as it was before the fp32 entry (its 34 jobs), it holds the first jobs of today's
    "all", each the same, and a folder holding it continues as "all" with the 6 fp32 jobs added
    (new), each host's shard of its jobs unchanged; a saved plan of a former "all" whose jobs differ,
    or of other figures, is still refused."""
    from bulbjax.assets.ycb import OBJ_FILE, YCB_DIR_ENV, YCB_INFO

    with open(CAMPAIGN) as f:
        committed = json.load(f)
    new = plan_jobs("all", "paper")
    record = plan.plan_record(plan.parse_figures("all"), "paper", [], new)
    assert plan.plan_differences(committed, record) == [] and plan.grown_from(committed, record) == []
    saved = dict(committed, figures=[f for f in committed["figures"] if f != "fp32"],
                 jobs=[d for d in committed["jobs"] if d["figure"] != "fp32"])
    old = [plan.job_of(d) for d in saved["jobs"]]
    assert len(old) == 34 and new[:len(old)] == old and {j.figure for j in new[len(old):]} == {"fp32"}
    assert plan.plan_differences(saved, record) == []
    assert plan.grown_from(saved, record) == [f"fp32/fig2-invpend/seed{k}" for k in range(6)]
    times, _ = estimate.load_times("NVIDIA H200")
    cost = {j.id: estimate.job_cost(j, times) for j in new}
    for n in (2, 3, 6):
        before, after = plan.shard_of(old, cost, n), plan.shard_of(new, cost, n)
        assert {i: after[i] for i in before} == before

    out = tmp_path / "campaign"
    out.mkdir()
    (out / plan.PLAN_FILE).write_text(json.dumps(saved))
    for name in YCB_INFO:  # the models' files where the dry run looks for them
        os.makedirs(os.path.dirname(os.path.join(tmp_path, "ycb", name, OBJ_FILE)))
        open(os.path.join(tmp_path, "ycb", name, OBJ_FILE), "w").close()
    monkeypatch.setenv(YCB_DIR_ENV, str(tmp_path / "ycb"))
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
    times, _ = estimate.load_times("NVIDIA H100 80GB HBM3")  # a device with no fp32 row
    h200, _ = estimate.load_times("NVIDIA H200")
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
    assert estimate.derived_fp32([fp32], h200) == [] and not estimate.timing_of(fp32, h200).derived  # measured
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


def _synthetic_job_run(out: str, job: Job, vae_rpl: float, dtype: str, env: str = "InvertedPendulum") -> None:
    """`job`'s run folder as `bulbjax run` leaves it (config.json, metrics.jsonl) with synthetic
    probed epochs: vae's normalised error 0.5 on every stream and group, vae_rpl's `vae_rpl` (+ the
    seed / 100), its learners in `dtype`."""
    cfg = ExperimentConfig(env=env, learners=("vae", "vae_rpl"), seeds=job.seeds, epochs=job.epochs)
    cfg = cfg.replace(learner=dataclasses.replace(cfg.learner, compute_dtype=dtype))
    path = os.path.join(out, job.run_dir)
    os.makedirs(path)
    with open(os.path.join(path, "config.json"), "w") as f:
        json.dump({"experiment": dataclasses.asdict(cfg), "run": {"seed": job.seed, "probe_every": 1}}, f)

    def stream(x: float) -> dict:
        return {"overall": {"mae_norm": x, "baseline_norm": 1.4},
                "groups": {"position": {"mae_norm": x, "baseline_norm": 1.5},
                           "velocity": {"mae_norm": x, "baseline_norm": 1.2}}}

    x = vae_rpl + job.seed / 100
    records.write_jsonl(os.path.join(path, "metrics.jsonl"), [
        {"epoch": e, "seed": 0, "rl_return": 10.0 * (e + 1),
         "probes": {"vae": {"curr": stream(0.5), "rand": stream(0.5)},
                    "vae_rpl": {"curr": stream(x), "rand": stream(x)}}}
        for e in range(job.epochs)])


def test_the_results_page_compares_the_verdicts_of_the_two_merged_runs(tmp_path) -> None:
    """A tiny plan of Fig. 2's InvertedPendulum and the fp32 entry, its runs synthetic: in bf16
    vae_rpl's error is below vae's (replay fixes VAE_v0 holds), in fp32 above (does not hold). The
    page has the fp32 runs' merged section and a comparison whose rows are the two merged
    findings.md's verdicts; with an fp32 seed unfinished, one line says so."""
    out = str(tmp_path / "plan")
    jobs = plan_jobs("fig2-invpend,fp32", "tiny")
    assert [j.id for j in jobs] == ["fig2-invpend/seed0", "fig2-invpend/seed1",
                                    "fp32/fig2-invpend/seed0", "fp32/fig2-invpend/seed1"]
    for j in jobs:
        bf16 = j.figure == "fig2"
        _synthetic_job_run(out, j, 0.3 if bf16 else 0.7, "bfloat16" if bf16 else "float32")
    with open(os.path.join(out, plan.PLAN_FILE), "w") as f:
        json.dump(plan.plan_record(["fig2-invpend", "fp32"], "tiny", [], jobs), f)

    page = open(results.write(out)).read()
    fp32_part = page[page.index(f"## {plan.TITLES['fp32']}"):]
    assert "### fp32/fig2-invpend: 2 seeds x 2 epochs" in fp32_part and "(fp32/fig2-invpend/fig2.png)" in fp32_part
    rows = {f: claims.findings_rows(os.path.join(out, f, "fig2-invpend")) for f in ("fig2", "fp32")}
    assert rows["fig2"][REPLAY][0] == "holds" and rows["fp32"][REPLAY][0] == "does not hold"
    compared = fp32_part[fp32_part.index("### fig2-invpend: the claims in bf16 and in fp32"):]
    table = [ln for ln in compared.splitlines() if ln.startswith("| ")]
    assert table[0] == ("| claim (paper, Fig. 2) | Fig. 2 runs (bfloat16 learners) | fp32 runs (float32 learners) "
                        "| same verdict |")
    body = {ln.split(" | ")[0][2:]: ln for ln in table[1:]}
    assert body[REPLAY] == (f"| {REPLAY} | {claims.cell(*rows['fig2'][REPLAY])} | "
                            f"{claims.cell(*rows['fp32'][REPLAY])} | **no** |")
    # every row a claim of the paper this domain tests, as both findings give it
    shown = {c for r in rows.values() for c, (v, _) in r.items()} - {
        c for c in rows["fig2"] if "beyond the paper" in c
        or all(r.get(c, ("not tested",))[0].startswith("not tested") for r in rows.values())}
    assert set(body) == shown and REPLAY in shown
    for c in shown:
        cells = [claims.cell(*r[c]) if c in r else "-" for r in rows.values()]
        assert body[c].startswith(f"| {c} | {cells[0]} | {cells[1]} | ")

    os.remove(os.path.join(out, "runs", "fp32", "fig2-invpend", "seed1", "metrics.jsonl"))
    page = open(results.write(out)).read()
    assert ("Not compared yet: the fp32 entry's runs (1 of 2 jobs finished) unfinished; compared once "
            "both sides are merged.") in page
    assert "| claim (paper, Fig. 2) | Fig. 2 runs" not in page


def test_the_probe_protocol_table_takes_the_fp32_run_of_its_domain(tmp_path) -> None:
    """The Fig. 2 protocol table (over the merged runs with the probe variants) gets the fp32
    entry's merged run of the same domain as its "fp32 run" column, `bulbjax report
    --probe-protocol --fp32`'s own table; an fp32 run of a domain without such a run is left out,
    not an error. (A campaign InvertedPendulum seed stands in for both sides.)"""
    from bulbjax.report.protocol import probe_protocol_table

    run = os.path.join(ROOT, "docs", "results", "paper_h200", "runs", "fig2-invpend", "seed0")
    merged, fp32 = tmp_path / "out" / "fig2" / "fig2-invpend", tmp_path / "out" / "fp32" / "fig2-invpend"
    shutil.copytree(run, merged)
    shutil.copytree(run, fp32)
    other = tmp_path / "out" / "fp32" / "fig2-cartpole"
    _synthetic_job_run(str(other), Job("c/seed0", "fp32", "run", "fig2-cartpole", 0, 2, "."), 0.3, "float32",
                       env="CartPole")
    results._protocol_section(str(tmp_path / "out"), [str(merged)], [str(fp32), str(other)])
    table = (tmp_path / "out" / results.PROTOCOL_DIR / "table.md").read_text()
    assert table == probe_protocol_table([str(merged)], [str(fp32)])
    head = next(ln for ln in table.splitlines() if ln.startswith("| claim"))
    assert head.endswith("| raw MAE | fp32 run |") and "CartPole" not in table
