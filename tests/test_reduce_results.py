"""benchmarks/reduce_results.py: committed metrics reduced in place (probed epochs whole, rounded;
the epochs in between as scalars) give the same reports; plots become palette PNGs, images with
smooth shading stay lossless."""

from __future__ import annotations

import dataclasses
import gzip
import importlib.util
import json
import os
import shutil

import numpy as np
import pytest

from bulbjax.config import preset
from bulbjax.envs.registry import env_class
from bulbjax.report import merge, records, report

HERE = os.path.dirname(os.path.abspath(__file__))
EPOCHS, SEEDS, PROBED = 12, 3, (0, 4, 8, 11)


def _module():
    path = os.path.join(os.path.dirname(HERE), "benchmarks", "reduce_results.py")
    spec = importlib.util.spec_from_file_location("reduce_results", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _fake_run(path: str, epochs: int = EPOCHS, probed=PROBED, base_seed: int = 0) -> str:
    """A run folder as `bulbjax run --probe-every 4` leaves it (config.json, metrics.jsonl.gz as
    committed), records made by `records.epoch_records` from float32 metrics as on a GPU."""
    cfg = preset("fig2-invpend").replace(seeds=SEEDS, epochs=epochs)
    spec = env_class(cfg.env).state_spec
    d = len(spec)
    os.makedirs(path)
    with open(os.path.join(path, "config.json"), "w") as f:
        json.dump({"experiment": dataclasses.asdict(cfg), "run": {"seed": base_seed, "probe_every": 4}}, f)
    rng = np.random.default_rng(base_seed)
    f32 = lambda *shape: rng.uniform(0.05, 2.0, shape).astype(np.float32)  # noqa: E731
    ref = f32(SEEDS, d)
    recs = []
    for e in range(epochs):
        m = {"rl_return": f32(SEEDS) * 500, "rl_episodes": np.full(SEEDS, 64.0, np.float32),
             "ppo": {k: f32(SEEDS) for k in ("approx_kl", "entropy", "total_loss")},
             "learners": {n: {"loss": f32(SEEDS) * 8000, "kl": f32(SEEDS), "recon": f32(SEEDS) * 8000}
                          for n in cfg.learners},
             "replay_dropped": {"retain_0": np.zeros(SEEDS, np.int32)}, "ref_spread": ref}
        m["rl_return"][1] = np.nan if e % 5 == 2 else m["rl_return"][1]  # no episode ended
        if e in probed:
            m["probes"] = {n: {s: {"mae": f32(SEEDS, d) * ref, "baseline": f32(SEEDS, d) * ref,
                                   "spread": f32(SEEDS, d)} for s in ("curr", "rand")}
                           for n in cfg.learners}
        recs += records.epoch_records(e, m, spec)
    with gzip.open(os.path.join(path, "metrics.jsonl.gz"), "wt") as f:
        for r in recs:
            f.write(json.dumps(r, allow_nan=True) + "\n")
    return path


def _same_shape(a, b) -> bool:
    """Same nested keys (and list lengths) in `a` and `b`."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same_shape(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(_same_shape(x, y) for x, y in zip(a, b))
    return type(a) is type(b) or {type(a), type(b)} <= {int, float}


def test_reduced_metrics_keep_probed_epochs_and_reports(tmp_path) -> None:
    rr = _module()
    full = _fake_run(str(tmp_path / "full"))
    small = str(tmp_path / "small")
    shutil.copytree(full, small)
    path = os.path.join(small, "metrics.jsonl.gz")
    assert rr.main([small, "--no-png"]) == 0
    before, after = records.read_jsonl(os.path.join(full, "metrics.jsonl.gz")), records.read_jsonl(path)
    assert os.path.getsize(path) < 0.6 * os.path.getsize(os.path.join(full, "metrics.jsonl.gz"))
    assert [(r["epoch"], r["seed"]) for r in after] == [(r["epoch"], r["seed"]) for r in before]
    for b, a in zip(before, after):
        assert a["rl_return"] == pytest.approx(b["rl_return"], rel=1e-6, nan_ok=True)
        if b["epoch"] in PROBED:  # whole, rounded
            assert _same_shape(b, a)
            x = a["probes"]["pred"]["rand"]
            y = b["probes"]["pred"]["rand"]
            assert x["entries"]["theta_vel"]["mae"] == pytest.approx(y["entries"]["theta_vel"]["mae"], rel=1e-4)
            assert x["entries"]["theta_vel"]["mae"] != y["entries"]["theta_vel"]["mae"]  # rounded
            assert x["overall"]["mae_norm"] == pytest.approx(y["overall"]["mae_norm"], rel=1e-6)
            assert a["ref_spread"] == pytest.approx(b["ref_spread"], rel=1e-4)
        else:  # scalars only
            assert set(a) == {"epoch", "seed", "rl_return", "rl_episodes", "ppo", "learners",
                              "replay_dropped", "probes"} and a["probes"] == {}
            assert all(set(v) == {"loss"} for v in a["learners"].values())
            assert a["learners"]["vae"]["loss"] == pytest.approx(b["learners"]["vae"]["loss"], rel=1e-4)
            assert a["ppo"]["entropy"] == pytest.approx(b["ppo"]["entropy"], rel=1e-4)
    # the reports read from the reduced file are those of the full one, to the byte
    for d in (full, small):
        report.redraw(d)
    for name in ("table.md", "findings.md"):
        assert open(os.path.join(small, name)).read() == open(os.path.join(full, name)).read()
    assert f"{SEEDS} seeds, {EPOCHS} epochs" in open(os.path.join(small, "table.md")).read()
    # a second pass changes nothing
    data = open(path, "rb").read()
    assert rr.main([small, "--no-png"]) == 0 and open(path, "rb").read() == data
    # minimal: epoch, seed, return and episodes between the probes; the reports still the same
    assert rr.main([full, "--no-png", "--unprobed", "minimal"]) == 0
    mini = records.read_jsonl(os.path.join(full, "metrics.jsonl.gz"))
    assert {k for r in mini if not r["probes"] for k in r} == {"epoch", "seed", "rl_return", "rl_episodes", "probes"}
    report.redraw(full)
    assert open(os.path.join(small, "table.md")).read() == open(os.path.join(full, "table.md")).read()


def test_pngs_palette_for_plots_lossless_for_shading(tmp_path) -> None:
    from PIL import Image

    rr = _module()
    run = _fake_run(str(tmp_path / "run"))
    report.redraw(run)
    plot = os.path.join(run, "fig2.png")
    ref = np.asarray(Image.open(plot).convert("RGB"), np.int16)
    size = os.path.getsize(plot)
    # smooth shading (a reconstruction's blur): 256 colours would band it
    yy, xx = np.mgrid[0:256, 0:256]
    shade = np.stack([xx, yy, (xx + yy) // 2], -1).astype(np.uint8)
    shaded = os.path.join(run, "recon.png")
    Image.fromarray(shade).save(shaded, compress_level=1)
    assert rr.main([run, "--no-metrics"]) == 0
    with Image.open(plot) as im:
        assert im.mode == "P"
        got = np.asarray(im.convert("RGB"), np.int16)
    assert os.path.getsize(plot) < 0.6 * size
    assert np.abs(got - ref).mean() < 2.0 and (np.abs(got - ref).max(-1) > 16).mean() < 0.01
    assert (got[5, 5] == 255).all()  # the white background stays white
    with Image.open(shaded) as im:
        assert im.mode == "RGB" and (np.asarray(im) == shade).all()  # lossless, only recompressed
    again = open(plot, "rb").read()
    assert rr.main([run, "--no-metrics"]) == 0 and open(plot, "rb").read() == again


def test_probed_every_keeps_what_the_reports_read(tmp_path) -> None:
    """`--probed-every N` (runs probed every epoch): whole records at multiples of N, the last 3
    probed epochs (tables, findings) and the 3 at or before the object findings' early epoch
    (min(300, last // 2)); the other probed records keep only the scalars, every (epoch, seed)."""
    rr = _module()
    assert rr.kept_probed_epochs(range(500), 50) == set(range(0, 500, 50)) | {247, 248, 249, 497, 498, 499}
    assert rr.kept_probed_epochs(range(0, 1000, 5), 100) == set(range(0, 1000, 100)) | {290, 295, 300, 985, 990, 995}
    path = str(tmp_path / "metrics.jsonl.gz")
    recs = [{"epoch": e, "seed": s, "rl_return": 1.5 * e, "rl_episodes": 3.0,
             "probes": {"vae": {"curr": {"overall": {"mae_norm": 0.5 + e}}}}, "objects": {"o": e}}
            for e in range(20) for s in range(2)]
    with gzip.open(path, "wt") as f:
        f.write("".join(json.dumps(r) + "\n" for r in recs))
    rr.reduce_metrics(path, unprobed="minimal", probed_every=8)
    out = records.read_jsonl(path)
    assert [(r["epoch"], r["seed"]) for r in out] == [(r["epoch"], r["seed"]) for r in recs]
    whole = {r["epoch"] for r in out if r["probes"]}
    assert whole == {0, 8, 16, 17, 18, 19, 7, 8, 9}  # early: min(300, 19 // 2) = 9 -> 7, 8, 9
    for r in out:
        if r["epoch"] in whole:
            assert r["objects"] == {"o": r["epoch"]} and r["probes"]["vae"]["curr"]["overall"]["mae_norm"] == 0.5 + r["epoch"]
        else:
            assert set(r) == {"epoch", "seed", "rl_return", "rl_episodes", "probes"} and r["rl_return"] == 1.5 * r["epoch"]


def test_probed_every_keeps_what_a_merge_beside_reads(tmp_path) -> None:
    """A merged folder beside two halves of different lengths reads the last epochs both have,
    which are not the longer half's own last ones (fig2_invpend_h100_6seeds: seed0's metrics end
    at 943, the merge reads 920-940, seed1's own rule kept 980-999 and dropped them, and the
    merged reports fell back to seed0's three seeds at those epochs). `--probed-every` keeps
    them: the merged reports come out the same from the reduced halves."""
    rr = _module()
    a = _fake_run(str(tmp_path / "seed0"), epochs=12, probed=range(12), base_seed=0)
    b = _fake_run(str(tmp_path / "seed1"), epochs=20, probed=range(20), base_seed=1)
    merged = str(tmp_path / "merged")
    merge.merge_seeds([a, b], merged, figures=False)
    before = {n: open(os.path.join(merged, n)).read() for n in ("table.md", "findings.md")}
    assert "epoch 9, 10, 11;" in before["table.md"]
    assert not {10, 11} <= rr.kept_probed_epochs(range(20), 8)  # seed1's own rule lacks them
    assert rr.merged_read_epochs(b, 8) >= {9, 10, 11} and rr.merged_read_epochs(a, 8) >= {9, 10, 11}
    for d in (a, b):
        rr.reduce_metrics(os.path.join(d, "metrics.jsonl.gz"), unprobed="minimal", probed_every=8)
    kept = {r["epoch"] for r in records.read_jsonl(os.path.join(b, "metrics.jsonl.gz")) if r["probes"]}
    assert {9, 10, 11} <= kept and 12 not in kept and 15 not in kept
    again = str(tmp_path / "again")
    merge.merge_seeds(merge.merge_sources(merged), again, figures=False)
    for name, text in before.items():
        assert open(os.path.join(again, name)).read() == text, name


def test_entries_read_keeps_per_entry_errors_where_the_reports_read_them(tmp_path) -> None:
    """`--entries read`: per-entry errors only in the first and last 3 probed records (no objects
    here, so no early ones); every probed record keeps its groups and overall (the curves); the
    tables, findings and excluded groups come out as from the full file."""
    rr = _module()
    probed = (0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 19)
    full = _fake_run(str(tmp_path / "full"), epochs=20, probed=probed)
    small = str(tmp_path / "small")
    shutil.copytree(full, small)
    path = os.path.join(small, "metrics.jsonl.gz")
    assert rr.main([small, "--no-png", "--entries", "read"]) == 0
    before, after = records.read_jsonl(os.path.join(full, "metrics.jsonl.gz")), records.read_jsonl(path)
    assert os.path.getsize(path) < 0.7 * rr.reduce_metrics(os.path.join(full, "metrics.jsonl.gz"), dry_run=True)[1]
    with_entries = {r["epoch"] for r in after if r["probes"] and "entries" in r["probes"]["vae"]["curr"]}
    assert with_entries == {0, 16, 18, 19}
    for b, a in zip(before, after):
        if b["epoch"] in probed:
            for name, streams in b["probes"].items():
                for s, x in streams.items():
                    y = a["probes"][name][s]
                    assert y["overall"]["mae_norm"] == pytest.approx(x["overall"]["mae_norm"], rel=1e-6)
                    assert y["groups"].keys() == x["groups"].keys()
    assert records.excluded_groups(after) == records.excluded_groups(before)
    for d in (full, small):
        report.redraw(d, figures=False)
    for name in ("table.md", "findings.md"):
        assert open(os.path.join(small, name)).read() == open(os.path.join(full, name)).read(), name
    with pytest.raises(ValueError, match="entries must be one of"):
        rr.reduce_metrics(path, entries="some")
