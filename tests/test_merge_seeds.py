"""`bulbjax report --merge-seeds`: the seeds of two runs of one configuration (different base
seeds, e.g. one per GPU) pooled into one report; mismatched runs refused."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

from bulbjax.config import preset, read_run_config
from bulbjax.report import merge, records


def _run_dir(path: str, seeds: int, base_seed: int, level: float, epochs: int = 3, **changes) -> str:
    """A run folder as `bulbjax run` leaves it (config.json, metrics.jsonl) with synthetic probed
    epochs: every learner's normalised error is `level` + the seed index / 100."""
    cfg = preset("fig2-invpend").replace(seeds=seeds, **changes)
    os.makedirs(path)
    with open(os.path.join(path, "config.json"), "w") as f:
        json.dump({"experiment": dataclasses.asdict(cfg), "run": {"seed": base_seed, "probe_every": 1}}, f)
    recs = []
    for e in range(epochs):
        for s in range(seeds):
            x = level + s / 100
            stream = {"overall": {"mae_norm": x, "baseline_norm": 1.4},
                      "groups": {"position": {"mae_norm": x, "baseline_norm": 1.5},
                                 "velocity": {"mae_norm": x, "baseline_norm": 1.2}}}
            recs.append({"epoch": e, "seed": s, "rl_return": 100.0 * (e + 1),
                         "probes": {n: {"curr": stream, "rand": stream} for n in cfg.learners}})
    records.write_jsonl(os.path.join(path, "metrics.jsonl"), recs)
    return path


def test_merge_pools_seeds(tmp_path) -> None:
    a = _run_dir(str(tmp_path / "a"), 2, 0, 0.5)
    b = _run_dir(str(tmp_path / "b"), 3, 1, 0.9, epochs=2)  # one epoch behind: left out
    out = str(tmp_path / "m")
    merge.merge_seeds([a, b], out)
    cfg, raw = read_run_config(out)
    assert cfg.seeds == 5 and [s["merged_seeds"] for s in raw["merged_from"]] == [[0, 1], [2, 4]]
    recs = records.read_jsonl(os.path.join(out, "metrics.jsonl"))
    assert sorted({r["seed"] for r in recs}) == [0, 1, 2, 3, 4]
    # seed 3 of the merge is seed 1 of run b
    r = next(r for r in recs if r["seed"] == 3 and r["epoch"] == 0)
    assert r["probes"]["vae"]["curr"]["overall"]["mae_norm"] == pytest.approx(0.91)
    per_seed = records.per_seed_error(recs, "vae", "curr", None, [1])
    np.testing.assert_allclose(per_seed, [0.5, 0.51, 0.9, 0.91, 0.92])
    table = open(os.path.join(out, "table.md")).read()
    assert "5 seeds, 2 epochs" in table and "epoch 0, 1;" in table  # epoch 2 lacks run b's seeds
    assert "| vae | π_curr | 0.748 ± " in table  # the mean of the five seeds' 0.5 .. 0.92
    for name in ("fig2.png", "findings.md"):
        assert os.path.getsize(os.path.join(out, name)) > 0


def test_merge_refuses_mismatch(tmp_path) -> None:
    a = _run_dir(str(tmp_path / "a"), 2, 0, 0.5)
    b = _run_dir(str(tmp_path / "b"), 2, 0, 0.5)
    c = _run_dir(str(tmp_path / "c"), 2, 1, 0.5, num_envs=32)
    with pytest.raises(ValueError, match="share base seed 0"):
        merge.merge_seeds([a, b], str(tmp_path / "m1"))
    with pytest.raises(ValueError, match="num_envs"):
        merge.merge_seeds([a, c], str(tmp_path / "m2"))
    with pytest.raises(ValueError, match="none of the runs"):
        merge.merge_seeds([a, c], a)


def test_runs_that_differ_only_in_how_they_compute_merge(tmp_path) -> None:
    """Seeds of one preset made before and after a speed default changed (the campaign's CartPole
    seed 5 ran with `bias_grad` "auto", seeds 0-4 with "split", and its merge was refused) pool;
    each source keeps its form; a learner field that changes what is computed is still refused."""
    base = preset("fig2-invpend").learner
    a = _run_dir(str(tmp_path / "a"), 1, 0, 0.5, learner=dataclasses.replace(base, bias_grad="split"))
    b = _run_dir(str(tmp_path / "b"), 1, 1, 0.6, overlap="pipeline",
                 learner=dataclasses.replace(base, bias_grad="auto", rnn_unroll=4))
    c = _run_dir(str(tmp_path / "c"), 1, 2, 0.6, learner=dataclasses.replace(base, beta=2.0))
    out = str(tmp_path / "m")
    merge.merge_seeds([a, b], out, figures=False)
    cfg, raw = read_run_config(out)
    assert cfg.seeds == 2 and cfg.learner.bias_grad == "split" and cfg.overlap == "none"
    forms = [s["form"] for s in raw["merged_from"]]
    assert [f["learner.bias_grad"] for f in forms] == ["split", "auto"]
    assert [f["learner.rnn_unroll"] for f in forms] == [1, 4] and forms[1]["overlap"] == "pipeline"
    with pytest.raises(ValueError, match="differs from .* in learner"):
        merge.merge_seeds([a, c], str(tmp_path / "m2"), figures=False)


def test_merging_again_replaces_the_merge(tmp_path) -> None:
    """`bulbjax reproduce` merges a preset's seeds again after every stretch into the same
    folder: the second merge's records are the first's, not twice them (the campaign's sixth
    allocation found each seed's epochs doubled, and the probe-protocol table refusing them)."""
    a = _run_dir(str(tmp_path / "a"), 2, 0, 0.5)
    b = _run_dir(str(tmp_path / "b"), 1, 2, 0.9)
    out = str(tmp_path / "m")
    merge.merge_seeds([a, b], out, figures=False)
    first = records.read_jsonl(os.path.join(out, "metrics.jsonl"))
    merge.merge_seeds([a, b], out, figures=False)
    assert records.read_jsonl(os.path.join(out, "metrics.jsonl")) == first and len(first) == 3 * 3


def test_a_merged_folder_without_its_metrics_pools_its_runs_again(tmp_path) -> None:
    """A plan folder of `bulbjax reproduce` (runs under `runs/<preset>/seedK`, their merge under
    `<figure>/<preset>`), copied to another place without the merge's own metrics (committed
    results keep one copy of the records): its runs are found under the copy, and its records
    are the merge's."""
    plan = tmp_path / "plan"
    runs = [_run_dir(str(plan / "runs" / "p" / f"seed{s}"), 1, s, 0.5 + s / 10) for s in range(3)]
    merged = str(plan / "fig2" / "p")
    merge.merge_seeds(runs, merged, figures=False)
    pooled = records.read_jsonl(os.path.join(merged, "metrics.jsonl"))
    moved = tmp_path / "elsewhere" / "plan_copy"
    os.makedirs(moved.parent)
    os.rename(plan, moved)
    os.remove(moved / "fig2" / "p" / "metrics.jsonl")
    found = merge.merge_sources(str(moved / "fig2" / "p"))
    assert found == [str(moved / "runs" / "p" / f"seed{s}") for s in range(3)]
    assert merge.run_records(str(moved / "fig2" / "p")) == pooled
    os.rename(moved / "runs" / "p" / "seed1", moved / "runs" / "p" / "other")
    with pytest.raises(ValueError, match="base seed 1 .* neither beside it, at that path, nor under a folder above"):
        merge.merge_sources(str(moved / "fig2" / "p"))


def _regions(run_dir: str, epoch: int, seeds: int, level: float, radius: float = 6.4) -> None:
    """A run's `regions_<epoch>.json` as `RunFigures.draw` writes it: every seed's ratio per
    object `level` + the seed index / 10."""
    rows = [[level + s / 10, level + s / 10 + 0.01] for s in range(seeds)]
    with open(os.path.join(run_dir, f"regions_{epoch}.json"), "w") as f:
        json.dump({"epoch": epoch, "objects": ["obj0", "obj1"], "radius_px": radius, "frames": 64,
                   "seeds": seeds, "clear_below": 0.5,
                   "learners": {"spair": {"ratio": rows, "error": rows, "baseline": rows}}}, f)


def test_a_merge_pools_the_runs_region_errors(tmp_path) -> None:
    """Fig. 5's campaign runs a job a seed: the merged folder's findings read the per-object
    reconstruction errors of every seed, so the merge pools the runs' `regions_<epoch>.json` of
    the latest epoch all of them measured, seeds in the records' order (the first merged pages
    said "not tested" beside three runs that had measured it); runs that measured differently
    pool nothing, and a merge again replaces what the one before wrote."""
    from bulbjax.eval import regions

    a = _run_dir(str(tmp_path / "a"), 2, 0, 0.5)
    b = _run_dir(str(tmp_path / "b"), 1, 2, 0.9)
    for epoch in (250, 500):
        _regions(a, epoch, 2, 0.1)
        _regions(b, epoch, 1, 0.7)
    _regions(a, 750, 2, 0.2)  # b has not reached it: not pooled
    out = str(tmp_path / "m")
    merge.merge_seeds([a, b], out, figures=False)
    assert sorted(n for n in os.listdir(out) if n.startswith("regions_")) == ["regions_500.json"]
    got = regions.newest(out)
    assert got["epoch"] == 500 and got["seeds"] == 3 and got["objects"] == ["obj0", "obj1"]
    assert np.allclose(got["learners"]["spair"]["ratio"], [[0.1, 0.11], [0.2, 0.21], [0.7, 0.71]])
    _regions(b, 500, 1, 0.7, radius=3.2)  # measured with other discs: nothing to pool
    merge.merge_seeds([a, b], out, figures=False)
    assert regions.pooled([a, b]) is None and regions.newest(out) is None


def test_a_plan_s_one_seed_merge_keeps_its_region_errors(tmp_path) -> None:
    """A plan preset of one seed is merged by copying its run's reports: its region errors go
    with them, so the merged folder's findings can be drawn again from it."""
    from bulbjax.reproduce import results
    from bulbjax.reproduce.plan import Job

    out = str(tmp_path / "plan")
    run = _run_dir(os.path.join(out, "runs", "p", "seed0"), 1, 0, 0.5)
    _regions(run, 2, 1, 0.3)
    job = Job(id="p/seed0", figure="fig2", kind="run", preset="p", seed=0, epochs=3,
              run_dir="runs/p/seed0", probe_every=1, recon_every=0, flags=(), after=None, seeds=1,
              checkpoint_every=0)
    dest = results.merge(out, "fig2", "p", [job])
    assert dest is not None and "regions_2.json" in os.listdir(dest)
