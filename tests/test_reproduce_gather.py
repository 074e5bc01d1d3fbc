"""`bulbjax reproduce --gather`: plan folders brought back from several hosts gathered into one.
Tested on the campaign's own folder (docs/results/paper_h200): taken apart as its allocations
brought it back and gathered again, it gives the committed page."""

from __future__ import annotations

import glob
import json
import os
import shutil
import subprocess
import sys

import pytest

from bulbjax.report.merge import is_merged
from bulbjax.reproduce.gather import gather

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CAMPAIGN = os.path.join(ROOT, "docs", "results", "paper_h200")
# what the allocations after the first finished: the second (CartPole seed 4, InvertedPendulum seed 0
# and its Fig. 4), the third (the first fp32 job, whose gathering grew the plan by the fp32 entry),
# the fourth (InvertedPendulum seed 1), the fifth (InvertedPendulum seeds 2 and 3 under MPS), the
# sixth (InvertedPendulum seeds 4 and 5 under MPS, whose gathering merged the preset's six seeds
# into fig2/ and the probe-protocol table; fp32 seed 1), the seventh (HalfCheetah seed 0 with the
# learners on a second GPU, and its Fig. 4), the eighth (Ant seed 0 the same way, and its Fig. 4), the
# ninth (HalfCheetah seed 1 the same way), the eleventh (CartPole seed 5, whose gathering merged the
# preset's six seeds, made before and after bias_grad's default changed), the fourteenth (Ant seed 1
# with pred on the environment's GPU), the fifteenth (HalfCheetah seed 2 the same way), the
# sixteenth (Ant seed 2 the same way), the seventeenth (Fig. 5's seed 0; CartPole seed 0 again,
# with its Fig. 4), the eighteenth (Fig. 5's seeds 1 and 2), the twenty-second (fp32 seeds 2 and 3
# under MPS), the twenty-third (fp32 seeds 4 and 5, whose gathering merged the fp32 entry's six)
LATER = ("runs/fig2-cartpole/seed0", "runs/fig2-cartpole/seed4", "runs/fig2-cartpole/seed5", "runs/fig2-invpend",
         "fig4", "runs/fp32", "fig2", "probe_protocol", "runs/fig2-halfcheetah", "runs/fig2-ant",
         "runs/fig5-rearrange-ycb", "fig5", "fp32")
LATER_JOBS = ["fig2-ant/seed0", "fig2-ant/seed1", "fig2-ant/seed2", "fig2-cartpole/seed0", "fig2-cartpole/seed4",
              "fig2-cartpole/seed5", "fig2-halfcheetah/seed0", "fig2-halfcheetah/seed1", "fig2-halfcheetah/seed2",
              "fig2-invpend/seed0", "fig2-invpend/seed1", "fig2-invpend/seed2",
              "fig2-invpend/seed3", "fig2-invpend/seed4", "fig2-invpend/seed5", "fig4/fig2-ant",
              "fig4/fig2-cartpole", "fig4/fig2-halfcheetah", "fig4/fig2-invpend", "fig5-rearrange-ycb/seed0",
              "fig5-rearrange-ycb/seed1", "fig5-rearrange-ycb/seed2", "fp32/fig2-invpend/seed0",
              "fp32/fig2-invpend/seed1", "fp32/fig2-invpend/seed2", "fp32/fig2-invpend/seed3",
              "fp32/fig2-invpend/seed4", "fp32/fig2-invpend/seed5"]
LATER_SUMMARIES = ("summary_20261129", "summary_20261130", "summary_20261201")

def _before_second(dest: str) -> str:
    """The campaign folder as it was before its second allocation: without what that one and the
    later ones ran (and without CartPole's seed 0, which the seventeenth ran again), its plan the
    34 jobs of before the fp32 entry."""
    shutil.copytree(CAMPAIGN, dest, ignore=shutil.ignore_patterns("results.md"))
    for rel in LATER:
        shutil.rmtree(os.path.join(dest, rel))
    for name in os.listdir(dest):
        if name.startswith(LATER_SUMMARIES):
            os.remove(os.path.join(dest, name))
    with open(os.path.join(dest, "plan.json")) as f:
        plan = json.load(f)
    with open(os.path.join(dest, "plan.json"), "w") as f:
        json.dump(dict(plan, figures=[x for x in plan["figures"] if x != "fp32"],
                       jobs=[j for j in plan["jobs"] if j["figure"] != "fp32"]), f, indent=1)
    return dest


def test_gathering_the_allocations_gives_the_committed_page(tmp_path) -> None:
    """What the later allocations brought back, gathered into the folder from before them: their
    jobs taken (the run folders, Fig. 4's figure), the ones finished in both kept, the plan grown
    by the fp32 entry, their stretch summaries added under their finished time; the page is the
    committed one. Gathering again adds nothing."""
    from bulbjax.reproduce import results

    out = _before_second(str(tmp_path / "out"))
    host = str(tmp_path / "host")
    shutil.copytree(CAMPAIGN, host)
    said: list[str] = []
    found = gather(out, [host], log=said.append)
    assert sorted(found["taken"]) == LATER_JOBS
    assert "fig2-cartpole/seed3" in found["kept"] and found["unfinished"] == []
    assert sorted(n for n in os.listdir(out) if n.startswith(LATER_SUMMARIES)) == sorted(
        n for n in os.listdir(CAMPAIGN) if n.startswith(LATER_SUMMARIES))
    results.write(out, results.read_summary(out), out_name="docs/results/paper_h200")
    with open(os.path.join(CAMPAIGN, "results.md")) as f, open(os.path.join(out, "results.md")) as g:
        assert f.read() == g.read()
    before = sorted(os.listdir(out))
    again = gather(out, [host], log=said.append)
    assert again["taken"] == [] and sorted(os.listdir(out)) == before


def test_a_host_summary_is_named_by_its_end_and_unfinished_jobs_stay(tmp_path) -> None:
    """A host's `summary_<start>.json` arrives as `summary_<finished UTC>.json` (two hosts that
    started at once do not collide); a job the host left unfinished is named and not taken."""
    out = _before_second(str(tmp_path / "out"))
    host = str(tmp_path / "host")
    shutil.copytree(out, host)
    (tmp_path / "host" / "summary_20261129T034128Z.json").write_text(
        json.dumps({"finished_utc": "2026-11-29T05:06:07+00:00", "jobs": {}, "busy_s": 1.0}))
    part = tmp_path / "host" / "runs" / "fig2-cartpole" / "seed5"
    part.mkdir(parents=True)
    (part / "metrics.jsonl").write_text("".join(json.dumps({"epoch": e}) + "\n" for e in range(5)))
    found = gather(out, [host], log=lambda _: None)
    assert found["taken"] == [] and found["unfinished"] == ["fig2-cartpole/seed5"]
    assert os.path.exists(os.path.join(out, "summary_20261129T050607Z.json"))
    assert not os.path.exists(os.path.join(out, "runs", "fig2-cartpole", "seed5"))


def test_folders_of_another_plan_are_refused_in_one_line(tmp_path) -> None:
    out = _before_second(str(tmp_path / "out"))
    other = tmp_path / "other"
    other.mkdir()
    with pytest.raises(ValueError, match="no reproduce plan there"):
        gather(out, [str(other)])
    plan = json.loads((tmp_path / "out" / "plan.json").read_text())
    (other / "plan.json").write_text(json.dumps(dict(plan, scale="quick")))
    with pytest.raises(ValueError, match="its plan differs from .*scale 'quick' there, 'paper' in "):
        gather(out, [str(other)])
    r = subprocess.run([sys.executable, "-m", "bulbjax", "reproduce", "--out", out, "--gather", str(other)],
                       capture_output=True, text=True, timeout=120, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "its plan differs" in r.stderr


def test_a_dry_gather_copies_nothing_and_changes_are_said(tmp_path) -> None:
    """`--dry-run` says what a gather would take and writes nothing; a gather that grows OUT's plan
    (a folder of today's "all" into one of the former) or replaces an unfinished copy of a job
    says so; a missing folder, an empty list and an OUT that holds no plan are refused; the CLI
    refuses the flags that shape or run a plan beside --gather, in one line."""
    from bulbjax.reproduce.gather import gather_and_report

    out = _before_second(str(tmp_path / "out"))
    partial = tmp_path / "out" / "runs" / "fig2-cartpole" / "seed4"
    partial.mkdir(parents=True)
    (partial / "metrics.jsonl").write_text("".join(json.dumps({"epoch": e}) + "\n" for e in range(3)))
    host = str(tmp_path / "host")
    shutil.copytree(CAMPAIGN, host)
    from bulbjax.reproduce.plan import ENTRIES, plan_jobs

    plan = json.loads((tmp_path / "host" / "plan.json").read_text())  # the host's: today's "all", fp32 in it
    grown = plan_jobs(ENTRIES, "paper")
    (tmp_path / "host" / "plan.json").write_text(json.dumps(dict(plan, figures=list(ENTRIES),
                                                                 jobs=[j.as_dict() for j in grown])))
    before = {p: os.path.getmtime(os.path.join(dp, p)) for dp, _, fs in os.walk(out) for p in fs}
    said: list[str] = []
    assert gather_and_report(out, [host], log=said.append, dry_run=True) is None
    assert {p: os.path.getmtime(os.path.join(dp, p)) for dp, _, fs in os.walk(out) for p in fs} == before
    text = "\n".join(said)
    assert "would gather" in text and "plan grows" in text and "6 job(s) added" in text
    assert "fig2-cartpole/seed4: " in text and "held it unfinished (epoch 0 of 1000)" in text
    with pytest.raises(ValueError, match="no such folder"):
        gather(out, [str(tmp_path / "nowhere")])
    with pytest.raises(ValueError, match="needs the plan folders"):
        gather_and_report(out, [])
    stray = tmp_path / "stray"
    stray.mkdir()
    (stray / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match="holds no reproduce plan"):
        gather(str(stray), [host])
    r = subprocess.run([sys.executable, "-m", "bulbjax", "reproduce", "--out", out, "--gather", host,
                        "--jobs-per-gpu", "3"], capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "not --jobs-per-gpu" in r.stderr


def test_a_plan_of_fewer_figures_gathers_into_the_whole_and_the_whole_into_it(tmp_path) -> None:
    """A host that ran `--figures fig2-cartpole` ran jobs of the plan of every figure: its folder
    gathers into that plan's (its finished job taken, the plan kept), and the plan of every figure
    gathers into its folder (whose plan becomes the larger one, the jobs added named); a part with
    a job that differs is refused."""
    from bulbjax.reproduce.plan import parse_figures, plan_jobs, plan_record

    part = plan_record(parse_figures("fig2-cartpole"), "paper", [], plan_jobs("fig2-cartpole", "paper"))
    host = tmp_path / "host"
    shutil.copytree(os.path.join(CAMPAIGN, "runs", "fig2-cartpole", "seed4"), host / "runs" / "fig2-cartpole" / "seed4")
    (host / "plan.json").write_text(json.dumps(part))
    out = _before_second(str(tmp_path / "out"))
    whole = json.loads((tmp_path / "out" / "plan.json").read_text())
    said: list[str] = []
    found = gather(out, [str(host)], log=said.append)
    assert found["taken"] == ["fig2-cartpole/seed4"] and "grows" not in "\n".join(said)
    # the plan's jobs that no folder began are named (a shard never run shows)
    ids = [j["id"] for j in json.loads((tmp_path / "out" / "plan.json").read_text())["jobs"]]
    never = [i for i in ids if not os.path.isdir(os.path.join(out, "runs", i))]
    assert never and found["not_begun"] == never
    assert f"{len(never)} job(s) of the plan begun nowhere: {never[0]}, " in said[-1]
    assert json.loads((tmp_path / "out" / "plan.json").read_text()) == whole

    small = tmp_path / "small"
    shutil.copytree(host, small)
    said.clear()
    found = gather(str(small), [out], log=said.append)
    assert json.loads((small / "plan.json").read_text()) == whole
    assert f"{len(whole['jobs']) - 6} job(s) added" in said[0] and "fig2-cartpole/seed1" in found["taken"]

    changed = dict(part, jobs=[dict(part["jobs"][0], epochs=10), *part["jobs"][1:]])
    (host / "plan.json").write_text(json.dumps(changed))
    with pytest.raises(ValueError, match="its plan differs from"):
        gather(str(tmp_path / "out"), [str(host)], log=lambda _: None)


def _campaign_gather():
    import importlib.util

    path = os.path.join(ROOT, "benchmarks", "campaign_gather.py")
    spec = importlib.util.spec_from_file_location("campaign_gather", path)
    cg = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cg)
    return cg


def test_a_run_keeps_its_last_epoch_s_pictures(tmp_path) -> None:
    """A Fig. 5 run draws its reconstructions and SPAIR's boxes every 250 epochs: the campaign
    keeps the last epoch's (by number: recon_1000 sorts before recon_250 by name) and
    objects.png, and the page's "last drawn" is that epoch's."""
    from PIL import Image

    from bulbjax.reproduce.results import drawn_pictures, last_drawn

    names = ["recon_250.png", "recon_1000.png", "boxes_250_spair.png", "boxes_1000_spair.png",
             "boxes_1000_spair6.png", "objects.png", "fig2.png"]
    for name in names:
        Image.new("RGB", (8, 8), (200, 30, 30)).save(tmp_path / name)
    assert sorted(drawn_pictures(str(tmp_path), "recon")) == [250, 1000]
    assert last_drawn(str(tmp_path.parent), str(tmp_path)) == [
        f"Seed 0's reconstructions, last drawn (epoch 1000): ![reconstructions]({tmp_path.name}/recon_1000.png)", "",
        f"Seed 0's SPAIR's boxes, last drawn (epoch 1000): ![spair's boxes]({tmp_path.name}/boxes_1000_spair.png) "
        f"![spair6's boxes]({tmp_path.name}/boxes_1000_spair6.png)", ""]
    kept = _campaign_gather().last_pictures_only(str(tmp_path))
    assert [os.path.basename(p) for p in kept] == ["recon_1000.png", "boxes_1000_spair.png",
                                                   "boxes_1000_spair6.png", "objects.png"]
    assert sorted(os.listdir(tmp_path)) == sorted([os.path.basename(p) for p in kept] + ["fig2.png"])
    assert {k: [os.path.basename(p) for p in v] for k, v in drawn_pictures(str(tmp_path), "boxes").items()} \
        == {1000: ["boxes_1000_spair.png", "boxes_1000_spair6.png"]}


def test_campaign_gather_commits_an_allocation_as_the_readme_says(tmp_path) -> None:
    """benchmarks/campaign_gather.py over a folder brought back as an allocation leaves it (a run's
    metrics plain and in full, its own fig2.png, the consoles): the runs it finished arrive
    reduced and gzipped, without their fig2.png; Fig. 4's grids as palette PNGs; no logs; the
    page is the committed one; a second pass takes nothing and changes nothing."""
    import gzip

    from PIL import Image

    cg = _campaign_gather()
    out = _before_second(str(tmp_path / "out"))
    host = str(tmp_path / "host")
    shutil.copytree(CAMPAIGN, host)
    run = os.path.join(host, "runs", "fig2-invpend", "seed4")
    with gzip.open(os.path.join(run, "metrics.jsonl.gz"), "rb") as f:
        committed = f.read()
    with open(os.path.join(run, "metrics.jsonl"), "wb") as f:  # as the run wrote it (here: reduced)
        f.write(committed)
    os.remove(os.path.join(run, "metrics.jsonl.gz"))
    shutil.copy(os.path.join(CAMPAIGN, "fig2", "fig2-invpend", "fig2.png"), os.path.join(run, "fig2.png"))
    os.makedirs(os.path.join(host, "logs"), exist_ok=True)
    recon = os.path.join("fig4", "fig2-halfcheetah", "recon_1000.png")
    with Image.open(os.path.join(CAMPAIGN, recon)) as im:  # as the job drew it: RGBA
        im.convert("RGBA").save(os.path.join(host, recon))
    said: list[str] = []
    taken = cg.campaign_gather(out, [host], log=said.append)
    assert sorted(taken) == LATER_JOBS
    mine = os.path.join(out, "runs", "fig2-invpend", "seed4")
    assert sorted(os.listdir(mine)) == sorted(os.listdir(os.path.join(CAMPAIGN, "runs", "fig2-invpend", "seed4")))
    with gzip.open(os.path.join(mine, "metrics.jsonl.gz"), "rb") as f:
        assert f.read() == committed
    assert not os.path.exists(os.path.join(out, "logs"))
    with Image.open(os.path.join(out, recon)) as im:
        assert im.mode == "P"
    with open(os.path.join(CAMPAIGN, "results.md")) as f, open(os.path.join(out, "results.md")) as g:
        assert f.read() == g.read().replace(out, "docs/results/paper_h200")
    before = {n: os.path.getsize(os.path.join(d, n)) for d, _, ns in os.walk(out) for n in ns}
    assert cg.campaign_gather(out, [host], log=said.append) == []
    assert {n: os.path.getsize(os.path.join(d, n)) for d, _, ns in os.walk(out) for n in ns} == before
    assert "job(s) taken" in said[-1] and "MB as committed" in said[-1]


def test_the_page_says_where_each_job_ran(tmp_path) -> None:
    """A gathered page's job table says, per job, the day, slot and shard of the stretch that ran
    it last, and its stretch line names the last stretch's shard and end (a newcomer's gathered
    page said "This stretch" of one host's run, and no host or shard per job)."""
    from bulbjax.reproduce import results

    out = str(tmp_path / "out")
    os.makedirs(out)
    for k, (job, slot) in enumerate([("a", "cpu0"), ("b", "cpu0")], start=1):
        rec = {"device_kind": "cpu", "shard": [k, 2], "finished_utc": f"2026-11-3{k - 1}T0{k}:05:00+00:00",
               "busy_s": 60.0, "jobs": {job: {"attempts": 1, "busy_s": 60.0, "slot": slot}}}
        with open(os.path.join(out, f"summary_{k}.json"), "w") as f:
            json.dump(rec, f)
    ran = results.job_times(out)
    assert ran["a"]["ran"] == "2026-11-30, cpu0, shard 1/2" and ran["b"]["ran"] == "2026-11-31, cpu0, shard 2/2"
    line = results._summary_line({**rec, "gpus": 1, "measured_wall_s": 60.0})
    assert line.startswith("The last stretch (shard 2/2, ended 2026-11-31 02:05 UTC): 1 cpu slot(s)"), line


def test_a_folder_started_from_a_host_s_copy_takes_its_summaries_once(tmp_path) -> None:
    """The first round of docs/reproduce.md's SLURM rounds: OUT starts as a copy of host 0's folder
    and then gathers host 0 and host 1; host 0's stretch summary, which OUT holds under its own
    name, is not copied again (it was, and the page counted its GPU time twice)."""
    out = _before_second(str(tmp_path / "out"))
    host = tmp_path / "host"
    shutil.copytree(out, host)
    rec = {"finished_utc": "2026-12-01T05:06:07+00:00", "jobs": {}, "busy_s": 1.0}
    (host / "summary_shard1of2.json").write_text(json.dumps(rec))
    shutil.copy(host / "summary_shard1of2.json", os.path.join(out, "summary_shard1of2.json"))
    before = sorted(os.listdir(out))
    gather(out, [str(host)], log=lambda _: None)
    assert sorted(os.listdir(out)) == before


def test_merged_presets_keep_their_pooled_metrics_out_of_git() -> None:
    """A plan folder's merged preset (`<figure>/<preset>`, fp32 included) is read again from its
    runs, so its pooled `metrics.jsonl` (3.6 MB for six pendulum seeds) stays untracked: every such
    path of the campaign's folder is one .gitignore ignores."""
    if not os.path.isdir(os.path.join(ROOT, ".git")):
        pytest.skip("not a git checkout")
    merged = sorted(os.path.join(d, "metrics.jsonl") for d in glob.glob(os.path.join(CAMPAIGN, "**"), recursive=True)
                    if is_merged(d))
    assert any(os.sep + "fp32" + os.sep in m for m in merged) and len(merged) >= 4
    ignored = subprocess.run(["git", "check-ignore", "--no-index", *merged], cwd=ROOT, capture_output=True,
                             text=True).stdout.split()
    assert sorted(ignored) == merged
