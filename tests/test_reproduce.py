"""`bulbjax reproduce` (issue 57): the plan as data, its shards, its estimate, bad input, and one
real run on two CPU slots (the queue, a killed job continued from its checkpoint, a failing job
reported and retried once without holding up the rest, the results page)."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest

from bulbjax.config import ExperimentConfig
from bulbjax.reproduce import estimate, plan
from bulbjax.reproduce.estimate import Timing, simulate
from bulbjax.reproduce.main import reproduce
from bulbjax.reproduce.plan import Job, plan_jobs, shard_of
from bulbjax.reproduce.queue import Queue, Slot

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_the_paper_plan() -> None:
    jobs = plan_jobs("all", "paper")
    assert len({j.id for j in jobs}) == len(jobs) == 4 * 6 + 3 + 3 + 4 + 6  # + the fp32 entry's 6 (last)
    jobs = [j for j in jobs if j.figure != "fp32"]  # tests/test_reproduce_fp32.py checks those
    runs = [j for j in jobs if j.kind == "run"]
    for preset in ("fig2-cartpole", "fig2-invpend", "fig2-halfcheetah", "fig2-ant"):
        mine = [j for j in runs if j.preset == preset]
        assert [j.seed for j in mine] == list(range(6)) and {j.epochs for j in mine} == {1000}
    assert sorted(j.seed for j in runs if j.preset == "fig5-rearrange-ycb") == [0, 1, 2]
    assert all("--bf16" in j.flags and j.seeds == 1 for j in runs)
    recon = [j for j in jobs if j.kind == "recon"]
    assert {j.after for j in recon} == {f"{p}/seed0" for p in plan.figure_specs("paper")["fig2"].presets}


def test_quick_tiny_and_figure_selection() -> None:
    quick = plan_jobs("fig2,fig3", "quick")
    assert [(j.id, j.seeds) for j in quick][:2] == [("fig2-cartpole/seeds0-1", 2), ("fig2-invpend/seeds0-1", 2)]
    assert {j.epochs for j in quick if "halfcheetah" in j.id} == {20}
    alone = plan_jobs("fig4", "paper")  # Fig. 4 plans the seed-0 runs it draws
    assert sorted(j.id for j in alone if j.kind == "run") == sorted(f"{p}/seed0" for p in
                                                                    plan.figure_specs("paper")["fig2"].presets)
    one = plan_jobs("fig2-ant,fig4", "tiny")
    assert [j.id for j in one] == ["fig2-ant/seed0", "fig2-ant/seed1", "fig4/fig2-ant"]
    added = plan_jobs("fig2-invpend", "paper", ["mymod:Mine"])[0].flags
    assert added[-2:] == ("--learners", "vae,vae_rpl,beta_vae,svae,pred,dsa,mymod:Mine")


def test_shards_split_the_plan_the_same_way_everywhere() -> None:
    jobs = plan_jobs("all", "paper")
    times, _ = estimate.load_times("NVIDIA H100 80GB HBM3")
    cost = {j.id: estimate.job_cost(j, times) for j in jobs}
    for n in (1, 2, 3, 4):
        where = shard_of(jobs, cost, n)
        assert where == shard_of(list(jobs), dict(cost), n)  # the same split from the plan alone
        assert set(where.values()) == set(range(n)) and set(where) == {j.id for j in jobs}
        assert all(where[j.id] == where[j.after] for j in jobs if j.after)
        loads = [sum(cost[i] for i, k in where.items() if k == s) for s in range(n)]
        assert max(loads) - min(loads) <= max(cost.values())  # balanced to within one job


def test_the_estimate_is_the_queue_simulated() -> None:
    t = {"a": Timing(10.0, 100.0, 20.0), "recon": Timing(0.0, 30.0, 30.0)}
    run = [Job(f"a/seed{i}", "fig2", "run", "a", i, 10, f"runs/a/seed{i}") for i in range(2)]
    # two jobs on two slots: side by side, both cold (neither has compiled when the other starts)
    assert simulate(run, t, 2).wall_s == 200.0
    # on one slot the second starts warm: 200 + 20 + 100
    est = simulate(run, t, 1)
    assert est.wall_s == 320.0 and est.utilisation == 1.0
    recon = Job("fig4/a", "fig4", "recon", "a", 0, 10, "fig4/a", after="a/seed0")
    est = simulate([*run, recon], t, 2)
    assert est.spans["fig4/a"][0] == est.spans["a/seed0"][1]  # drawn once its run has ended
    assert simulate([recon], t, 1).wall_s == 30.0  # its run finished before: ready at once
    # a preset's own recon row where the table has one (locomotion's grids take longer)
    assert simulate([recon], {**t, "recon a": Timing(0.0, 50.0, 50.0)}, 1).wall_s == 50.0
    assert simulate([recon], {**t, "recon b": Timing(0.0, 50.0, 50.0)}, 1).wall_s == 30.0
    assert simulate(run, t, 1, epochs_done={"a/seed0": 10, "a/seed1": 5}).wall_s == 100 + 20 + 50


def test_the_docs_table_is_the_times_file() -> None:
    with open(os.path.join(ROOT, "docs", "reproduce.md"), encoding="utf-8") as f:
        text = f.read()
    table = re.search(r"<!-- epoch-times.*?-->\n(.*?)\n<!-- /epoch-times -->", text, re.S).group(1)
    assert table == estimate.times_markdown()


def test_the_docs_paper_estimate_is_the_table_s() -> None:
    """docs/reproduce.md's paper plan on four H200s (jobs, GPU-hours, wall) is what the estimate
    makes of today's epoch_times.json (a figure there once outlived a change of the table)."""
    with open(os.path.join(ROOT, "docs", "reproduce.md"), encoding="utf-8") as f:
        m = re.search(r"the paper's (\d+) jobs: ([\d.]+) GPU-hours, (\d+):(\d\d) on four H200s", f.read())
    jobs = plan_jobs(["all"], "paper")
    est = simulate(jobs, estimate.load_times("NVIDIA H200")[0], 4)
    assert int(m.group(1)) == len(jobs) and m.group(2) == f"{est.gpu_s / 3600:.2f}"
    assert int(m.group(3)) * 60 + int(m.group(4)) == round(est.wall_s / 60)


@pytest.mark.parametrize("kw, says", [
    (dict(figures="fig9"), "unknown figure"),
    (dict(shard="3/2"), "--shard '3/2' must be K/N"),
    (dict(shard="0/2"), "must be K/N"),
    (dict(gpus=0), "--gpus 0"),
    (dict(scale="huge"), "unknown --scale"),
    (dict(add_learners=["no_such_learner"]), "not a registered learner"),
    (dict(add_learners=["vae_rpl"]), "already in the paper's runs"),
    (dict(max_minutes=-1), "--max-minutes"),
    (dict(shard="1/2", overwrite=True), "every shard shares"),
])
def test_bad_input_is_one_clear_error_and_changes_nothing(tmp_path, kw, says) -> None:
    out = tmp_path / "plan"
    with pytest.raises(ValueError, match=re.escape(says)):
        reproduce(**{"out": str(out), "dry_run": True, **kw}, log=lambda s: None)
    assert not out.exists()


def test_an_out_folder_of_another_plan_or_of_something_else_is_refused(tmp_path) -> None:
    out = tmp_path / "plan"
    said: list[str] = []
    reproduce("fig2-cartpole", "tiny", str(out), dry_run=True, log=said.append)
    assert "fig2-cartpole/seed1" in said[0] and "estimated:" in said[0] and not out.exists()
    out.mkdir()
    (out / plan.PLAN_FILE).write_text(json.dumps(plan.plan_record(["fig2-cartpole"], "tiny", [], [])))
    with pytest.raises(ValueError, match=r"other settings \(scale: saved 'tiny', given 'quick'\).*--overwrite"):
        reproduce("fig2-cartpole", "quick", str(out), dry_run=True, log=said.append)
    reproduce("fig2-cartpole", "tiny", str(out), dry_run=True, log=said.append)  # the same plan: continues
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="holds no reproduce plan"):
        reproduce("fig2-cartpole", "tiny", str(other), dry_run=True, overwrite=True, log=said.append)
    assert (other / "notes.txt").exists()


def test_a_dry_run_checks_the_ycb_models_as_the_run_does(tmp_path, monkeypatch) -> None:
    """`--dry-run` of Fig. 5 without $BULBJAX_YCB_DIR is the real run's one-line error (it planned
    Fig. 5's hours with no models), before anything is written; with the folder it plans."""
    from bulbjax.assets.ycb import YCB_DIR_ENV, YCB_INFO

    monkeypatch.delenv(YCB_DIR_ENV, raising=False)
    out = tmp_path / "plan"
    with pytest.raises(ValueError) as caught:
        reproduce("fig5", "tiny", str(out), dry_run=True, log=lambda s: None)
    assert str(caught.value) == (f"Fig. 5 (fig5-rearrange-ycb) reads the YCB models from ${YCB_DIR_ENV}, "
                                 "which is not set: set it to the YCB google_16k folder, or leave Fig. 5 "
                                 "out (--figures fig2,fig3,fig4,fp32 for a new plan; --jobs or "
                                 "--fit-minutes picks a share of one that holds Fig. 5)")
    assert not out.exists()
    models = tmp_path / "ycb"
    models.mkdir()
    monkeypatch.setenv(YCB_DIR_ENV, str(models))  # a folder without the models: refused too
    with pytest.raises(ValueError, match=r"lacks 13 of its 13 models \(first: 002_master_chef_can/google_16k"):
        reproduce("fig5", "tiny", str(out), dry_run=True, log=lambda s: None)
    for name in YCB_INFO:
        (models / name / "google_16k").mkdir(parents=True)
        (models / name / "google_16k" / "textured.obj").write_text("v 0 0 0\n")
    said: list[str] = []
    reproduce("fig5", "tiny", str(out), dry_run=True, log=said.append)
    assert "fig5-rearrange-ycb/seed0" in said[0] and not out.exists()


def test_a_dry_run_names_the_hours_of_its_slots(tmp_path, monkeypatch) -> None:
    """The estimate's busy hours are CPU-hours on a host without a GPU (its slots are CPU worker
    processes; it said GPU-hours), GPU-hours on GPUs."""
    from bulbjax import local_processes
    from bulbjax.reproduce import main

    monkeypatch.setattr(local_processes, "visible_gpus", lambda: [])
    said: list[str] = []
    reproduce("fig2-cartpole", "tiny", str(tmp_path / "cpu"), dry_run=True, log=said.append)
    assert re.search(r"\nestimated: [0-9.]+ CPU-hours, ", said[0]) and "GPU-hours" not in said[0], said[0]
    monkeypatch.setattr(local_processes, "visible_gpus", lambda: ["0", "1"])
    monkeypatch.setattr(main, "host_kind", lambda gpus: "NVIDIA H100 80GB HBM3")
    said.clear()
    reproduce("fig2-cartpole", "tiny", str(tmp_path / "gpu"), dry_run=True, log=said.append)
    assert re.search(r"\nestimated: [0-9.]+ GPU-hours, .* on 2 slot\(s\)", said[0]), said[0]


def test_the_cli_says_a_bad_shard_in_one_line(tmp_path) -> None:
    r = subprocess.run([sys.executable, "-m", "bulbjax", "reproduce", "--shard", "3/2", "--out", str(tmp_path / "o")],
                       capture_output=True, text=True, timeout=120, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "--shard '3/2' must be K/N" in r.stderr


def test_a_failing_job_is_retried_once_and_holds_up_nothing(tmp_path) -> None:
    """A job whose run cannot start (an unknown learner) fails, is reported with what it said,
    started once more, and left failed; a job queued behind it on the one slot still runs (here
    a recon of a run that does not exist, which fails too: both are tried, neither blocks)."""
    bad = Job("fig2-cartpole/seed0", "fig2", "run", "fig2-cartpole", 0, 1, "runs/fig2-cartpole/seed0",
              flags=("--small", "--learners", "no_such_learner"))
    after = Job("fig2-invpend/seed0", "fig2", "run", "fig2-invpend", 0, 1, "runs/fig2-invpend/seed0",
                flags=("--small", "--learners", "also_not_one"))
    said: list[str] = []
    times, _ = estimate.load_times("cpu")
    q = Queue(str(tmp_path), [bad, after], [bad, after], [Slot("cpu0", None)], times, progress_every=1e9,
              log=said.append, poll_s=0.2)
    summary = q.run()
    assert summary["failed"] == [bad.id, after.id]
    for job in (bad, after):
        rec = summary["jobs"][job.id]
        assert rec["attempts"] == 2 and len(rec["errors"]) == 2
        assert "unknown learners" in rec["errors"][0]
    text = "\n".join(said)
    assert "FAILED fig2-cartpole/seed0" in text and "trying it once more" in text and "giving up on it" in text


def _kill_when(pattern: str, ready, timeout: float = 900.0) -> bool:
    """SIGKILL the process whose command line matches `pattern` once `ready()`; False on timeout."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if ready():
            pids = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True).stdout.split()
            for pid in pids:
                os.kill(int(pid), signal.SIGKILL)
            return bool(pids)
        time.sleep(0.2)
    return False


def test_a_tiny_plan_on_two_slots(tmp_path) -> None:
    """The command itself on two CPU slots: two seeds side by side; seed 0 killed after its
    first checkpoint is reported, continued from that checkpoint and finished; the results page
    pools both seeds; a rerun finds everything done and starts nothing."""
    from bulbjax.run import rundir

    out = tmp_path / "paper"
    cmd = [sys.executable, "-m", "bulbjax", "reproduce", "--scale", "tiny", "--figures", "fig2-cartpole",
           "--gpus", "2", "--out", str(out), "--progress-every", "5"]
    log = open(tmp_path / "console.txt", "w")
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    seed0 = out / "runs" / "fig2-cartpole" / "seed0"
    killed = _kill_when(f"bulbjax run --preset fig2-cartpole --seeds 1 --seed 0 .*{seed0}",
                        lambda: rundir.checkpoint_steps(str(seed0)) == [1])
    rc = proc.wait(timeout=1200)
    log.close()
    console = (tmp_path / "console.txt").read_text()
    assert rc == 0, console
    assert killed, console
    assert "FAILED fig2-cartpole/seed0 (exit -9" in console and "start fig2-cartpole/seed0 on " in console
    assert re.search(r"start fig2-cartpole/seed0 on cpu\d \(attempt 2, from epoch 1\)", console), console
    assert "done fig2-cartpole/seed1" in console and "done fig2-cartpole/seed0" in console
    relaunch = (out / "logs" / "fig2-cartpole_seed0.txt").read_text()
    assert f"run --resume {seed0}" in relaunch  # continued, not started over
    records = [json.loads(x) for x in (seed0 / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in records] == [0, 1]  # epoch 0 not repeated, epoch 1 written once
    page = (out / "results.md").read_text()
    assert "### fig2-cartpole: 2 seeds x 2 epochs" in page and "replay fixes VAE_v0" in page
    assert (out / "fig2" / "fig2-cartpole" / "fig2.png").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["gpus"] == 2 and summary["failed"] == [] and 0 < summary["utilisation"] <= 1
    # each job's estimate kept beside what it took, and the page shows both with the error
    assert all(r["estimated_s"] > 0 for r in summary["jobs"].values()), summary["jobs"]
    assert re.search(r"\| fig2-cartpole/seed1 \|.* \| \d:\d\d:\d\d / \d:\d\d:\d\d \([+-]\d+%\) \|", page), page
    # CPU worker processes: the page's time is CPU time, not GPU time
    assert "| CPU time |" in page and "\nCPU time of the stretches" in page and "GPU time" not in page, page
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    assert again.returncode == 0 and "start " not in again.stdout and "2 done, 0 running" in again.stdout


def test_the_results_page_holds_the_generated_claims_tables() -> None:
    """docs/results.md's claims tables are what `bulbjax report docs/results` writes from the
    committed folders' findings.md (themselves regenerated from the metrics by
    tests/test_results_regenerate.py): the page cannot drift from the numbers."""
    from bulbjax.reproduce import claims

    results = os.path.join(ROOT, "docs", "results")
    with open(os.path.join(ROOT, "docs", "results.md"), encoding="utf-8") as f:
        page = f.read()
    assert page.count("<!-- claims:") == len(claims.read_spec(results)["tables"]) >= 3
    assert claims.render(page, results) == page, "run `bulbjax report docs/results` to regenerate docs/results.md"
    # and a changed number would show: the generated table depends on the findings
    assert "**holds**, π_rand +0.345 ± 0.033" in page
    assert claims.bands("overall, π_rand: a 0.1, b 0.5; b - a = +0.400 ± 0.050; overall, π_curr: a 0.2, b 0.2; "
                        "b - a = +0.000 ± 0.010") == "π_rand +0.400 ± 0.050; π_curr +0.000 ± 0.010"
    with pytest.raises(ValueError, match="does not define"):
        claims.render("<!-- claims:nope -->\n<!-- /claims:nope -->", results)


def test_an_added_learner_joins_every_run_job(tmp_path, monkeypatch) -> None:
    """`--add-learner MODULE:NAME` loads the learner (a module outside the package), and every
    run job of the plan runs it beside the preset's learners; the recon job draws it too."""
    (tmp_path / "my_plugin_mod.py").write_text(
        "from bulbjax.learners import make_learner\n"
        "def Mine(latent_dim, config, action_dim):\n"
        "    return make_learner('vae', latent_dim, config, action_dim)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    said: list[str] = []
    s = reproduce("fig2-invpend,fig4", "paper", str(tmp_path / "out"), dry_run=True,
                  add_learners=["my_plugin_mod:Mine"], log=said.append)
    assert s["jobs_planned"] == 7 and "fig4/fig2-invpend" in said[0]
    jobs = plan_jobs("fig2-invpend", "paper", ["my_plugin_mod:Mine"])
    assert all(j.flags[-1].endswith(",my_plugin_mod:Mine") for j in jobs)
    from bulbjax.reproduce.main import _learners_of

    assert _learners_of(["Mine"])(jobs[0])[-1] == "Mine"
    assert plan.fig4_learners(_learners_of(["Mine"])(jobs[0])) == ["vae_rpl", "svae", "pred", "dsa", "Mine"]
    assert plan.fig4_learners(["vae_rpl", "stdim", "dsa"]) == ["vae_rpl", "dsa"]  # no reconstruct: no row
    with pytest.raises(ValueError, match="cannot import|No module"):
        reproduce("fig2-invpend", "paper", str(tmp_path / "o2"), dry_run=True, add_learners=["no_mod_xyz:Mine"],
                  log=said.append)


def test_the_docs_give_the_python_signature() -> None:
    """docs/reproduce.md's `reproduce(...)` line is the function's signature (names and defaults)."""
    import inspect

    with open(os.path.join(ROOT, "docs", "reproduce.md"), encoding="utf-8") as f:
        text = f.read()
    doc = re.search(r"```python\nreproduce\((.*?)\)\n```", text, re.S).group(1)
    documented = [p.strip() for p in doc.replace("\n", " ").split(",") if p.strip()]
    actual = [f"{n}={p.default!r}" if not callable(p.default) else f"{n}={p.default.__name__}"
              for n, p in inspect.signature(reproduce).parameters.items()]
    actual = [a.replace("'", '"') for a in actual]
    assert documented == actual


def test_fig2_runs_carry_the_probe_variants_and_the_page_their_table(tmp_path):
    """Paper and quick Fig. 2 jobs run with the probe protocol's variants (issue 59's question
    answered by the reproduction's own runs); the results page writes their table across domains
    from the merged runs that carry them (here a campaign InvertedPendulum seed), and nothing
    for runs without them."""
    from run_folders import write_synthetic_run

    from bulbjax.report.protocol import probe_protocol_table
    from bulbjax.reproduce import results

    for scale in ("paper", "quick"):
        fig2 = [j for j in plan_jobs("fig2", scale) if j.kind == "run"]
        assert fig2 and all("--probe-variants" in j.flags for j in fig2)
    assert not any("--probe-variants" in j.flags for j in plan_jobs("fig3,fig5", "paper") if j.kind == "run")
    run = os.path.join(ROOT, "docs", "results", "paper_h200", "runs", "fig2-invpend", "seed0")
    merged = tmp_path / "out" / "fig2" / "fig2-invpend"
    shutil.copytree(run, merged)
    lines = results._protocol_section(str(tmp_path / "out"), [str(merged), str(tmp_path / "out" / "fig2" / "unfinished")])
    table = tmp_path / "out" / results.PROTOCOL_DIR / "table.md"
    assert "probe_protocol/table.md" in "\n".join(lines) and table.exists()
    assert table.read_text() == probe_protocol_table([str(merged)])
    assert "| replay fixes VAE_v0 on π_rand" in table.read_text()
    other = tmp_path / "plain"
    write_synthetic_run(str(other), ExperimentConfig(env="CartPole", learners=("vae", "vae_rpl"), seeds=2, epochs=3))
    assert results._protocol_section(str(tmp_path / "out2"), [str(other)]) == []


def test_epochs_written_reads_a_last_line_longer_than_its_first_window(tmp_path):
    """A finished Fig. 2 job's last record (probed, with the probe variants: ~80 KB a line on an
    H200) is longer than the 64 KB first read from the file's end: the count still comes from the
    last whole line, not 0 (which left every finished job's measured epoch time unset)."""
    from bulbjax.reproduce import jobs as J

    job = Job(id="p/seed0", figure="fig2", kind="run", preset="p", seed=0, epochs=3, run_dir="runs/p/seed0")
    d = tmp_path / job.run_dir
    d.mkdir(parents=True)
    small = [json.dumps({"epoch": e, "seed": 0, "probes": {}}) for e in range(2)]
    big = json.dumps({"epoch": 2, "seed": 0, "probes": {"x": "y" * 200_000}})
    (d / "metrics.jsonl").write_text("\n".join([*small, big]) + "\n")
    assert J.epochs_written(str(tmp_path), job) == 3
    (d / "metrics.jsonl").write_text("\n".join(small) + "\n" + big[:1000])  # a last line being written
    assert J.epochs_written(str(tmp_path), job) == 2
    assert J.epochs_written(str(tmp_path / "none"), job) == 0


def test_a_job_brought_back_without_its_checkpoints_counts_as_done(tmp_path) -> None:
    """A shard run on a host whose disk went with it comes back as reduced metrics
    (`metrics.jsonl.gz`) and reports, no checkpoint: the plan counts it done by its metrics, so the
    next host skips it; a part of a job without a checkpoint counts nothing."""
    import gzip

    from bulbjax.reproduce import jobs as J

    job = Job("p/seed0", "fig2", "run", "p", 0, 3, "runs/p/seed0")
    d = tmp_path / job.run_dir
    d.mkdir(parents=True)
    with gzip.open(d / "metrics.jsonl.gz", "wt") as f:
        f.write("\n".join(json.dumps({"epoch": e, "seed": 0}) for e in range(3)) + "\n")
    assert J.epochs_done(str(tmp_path), job) == 3 and J.is_done(str(tmp_path), job)
    with gzip.open(d / "metrics.jsonl.gz", "wt") as f:
        f.write("\n".join(json.dumps({"epoch": e, "seed": 0}) for e in range(2)) + "\n")
    assert J.epochs_done(str(tmp_path), job) == 0 and not J.is_done(str(tmp_path), job)


def test_jobs_per_gpu_shares_each_gpu_and_counts_it_once(tmp_path, monkeypatch) -> None:
    """`--jobs-per-gpu 3`: three slots per GPU on its CUDA device, each with a third of JAX's
    memory (a user's XLA_PYTHON_CLIENT_MEM_FRACTION wins); each job's epochs estimated slower by
    the measured gain, the plan's GPU-hours counted per GPU; refused beside --learners-apart and
    on a host without GPUs; the page's GPU time divides a shared stretch's slot time by 3."""
    from bulbjax import local_processes
    from bulbjax.reproduce import estimate, main, results

    monkeypatch.setattr(main, "host_kind", lambda gpus: "NVIDIA H200")
    monkeypatch.setattr(local_processes, "visible_gpus", lambda: ["0", "1"])
    monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION", raising=False)
    slots, _ = main.slots_of(None, 1, 3)
    assert [s.gpu for s in slots] == ["0"] * 3 + ["1"] * 3 and len({s.name for s in slots}) == 6
    assert slots[0].env()["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.250"
    monkeypatch.setenv("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.2")
    assert slots[0].env()["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.2"
    assert main.slots_of(None)[0][0].mem_fraction is None  # one job per GPU: JAX's own default
    with pytest.raises(ValueError, match="use one of them"):
        main.slots_of(None, 2, 3)
    times, _ = estimate.load_times("NVIDIA H200")
    shared = estimate.shared_times(times, 3)
    assert shared["fig2-cartpole"].epoch_s == pytest.approx(times["fig2-cartpole"].epoch_s * 3 / estimate.SHARED_GAIN)
    assert estimate.shared_times(times, 1) is times
    mps = estimate.shared_times(times, 2, mps=True)  # measured at 2 jobs per H200 under MPS: 1.51x
    assert mps["fig2-invpend"].epoch_s == pytest.approx(times["fig2-invpend"].epoch_s * 2 / estimate.MPS_GAIN)
    assert mps["fig2-invpend"].startup_warm_s == times["fig2-invpend"].startup_warm_s
    # the measured fp32 row gains less under MPS (1.27-1.29x); time-sliced, every row the same gain
    fp32 = "fig2-invpend fp32"
    assert mps[fp32].epoch_s == pytest.approx(times[fp32].epoch_s * 2 / estimate.MPS_GAIN_FP32)
    assert shared[fp32].epoch_s == pytest.approx(times[fp32].epoch_s * 3 / estimate.SHARED_GAIN)
    assert estimate.SHARED_GAIN < estimate.MPS_GAIN_FP32 < estimate.MPS_GAIN
    one = reproduce("fig2-cartpole", "paper", str(tmp_path / "a"), dry_run=True, log=lambda _: None)
    three = reproduce("fig2-cartpole", "paper", str(tmp_path / "b"), dry_run=True, jobs_per_gpu=3,
                      log=lambda _: None)
    assert three["gpus"] == 2 and three["jobs_per_gpu"] == 3
    # the same seed-epochs on the same two GPUs: fewer GPU-hours by the gain (start-ups aside)
    assert three["estimated_gpu_s"] < one["estimated_gpu_s"]
    monkeypatch.setattr(local_processes, "visible_gpus", lambda: [])
    with pytest.raises(ValueError, match="this host has none: leave it out"):
        main.slots_of(None, 1, 3)
    out = tmp_path / "page"
    out.mkdir()
    for name, per in (("summary_a.json", 3), ("summary_b.json", 1)):
        rec = {"jobs_per_gpu": per, "busy_s": 3000.0 if per == 3 else 600.0, "finished_utc": name,
               "jobs": {f"j{name}": {"attempts": 1, "busy_s": 900.0}}}
        (out / name).write_text(json.dumps(rec))
    ran = results.job_times(str(out))
    assert ran["jsummary_a.json"]["busy_s"] == pytest.approx(300.0)
    assert ran["jsummary_b.json"]["busy_s"] == pytest.approx(900.0)


def test_the_plan_table_rows_are_the_schedule_and_lost_figures_are_said(tmp_path, monkeypatch) -> None:
    """Each row's estimate is the schedule's (a preset's second job on one slot starts warm, so
    it is shorter than the first, and the rows add up to the total); a Fig. 4 job picked with
    --jobs whose run finished elsewhere, without its checkpoint, is left out with a line saying
    why; a shard's header names the plan's size once."""
    said: list[str] = []
    reproduce("fig2-cartpole", "paper", str(tmp_path / "a"), dry_run=True, log=said.append)
    rows = {line.split()[0]: line.split()[2] for line in said[0].splitlines() if line.startswith("fig2-cartpole/")}
    secs = {k: sum(int(x) * m for x, m in zip(v.split(":"), (3600, 60, 1))) for k, v in rows.items()}
    assert secs["fig2-cartpole/seed1"] < secs["fig2-cartpole/seed0"]
    total = re.search(r"estimated: ([0-9.]+) CPU-hours", said[0]).group(1)
    assert abs(sum(secs.values()) / 3600 - float(total)) < 0.01
    out = tmp_path / "b"
    campaign = os.path.join(ROOT, "docs", "results", "paper_h200")
    shutil.copytree(campaign, out)
    shutil.rmtree(out / "fig4" / "fig2-cartpole")  # as before the seventeenth allocation drew it
    said.clear()
    reproduce("all", "paper", str(out), dry_run=True, jobs="fig4/fig2-cartpole,fig2-invpend/seed1",
              log=said.append)
    text = "\n".join(said)
    assert "fig4/fig2-cartpole left out: its run fig2-cartpole/seed0 finished on another host" in text
    assert not re.search(r"^fig4/fig2-cartpole +recon", text, re.M)
    assert re.search(r"^fig2-invpend/seed1 +1000/1000 .* done$", text, re.M), text
    # a job named that is done here says so (the seventeenth allocation's launch ran none of it)
    assert (f"fig2-invpend/seed1 is done here already and does not run again: delete "
            f"{out / 'runs' / 'fig2-invpend' / 'seed1'} to run it again") in text
    said.clear()
    reproduce("fig2", "paper", str(tmp_path / "c"), dry_run=True, shard="2/2", log=said.append)
    assert re.match(r"plan: \d+ job\(s\), shard 2/2 of 24, scale paper", said[0]), said[0]
