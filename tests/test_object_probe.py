"""The object-level probe in the experiment (issue 11): SPAIR's present boxes against the true
objects' image positions on the held-out streams of a Rearrange run, in the epoch's metrics,
the metrics.jsonl records and table.md next to the MLP probe's object-position errors; nothing
of it for domains without objects (CartPole). The jittable reduction agrees with `summarise`,
boxes placed on the projected objects score 0 px and all found, boxes far away none found."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.epoch import Experiment, ExperimentConfig
from bulbjax.eval.objects import (
    comparison_table,
    object_names,
    object_scores,
    reduce_scores,
    summarise,
    summary_of,
)
from bulbjax.eval.probe import ProbeConfig
from bulbjax.learners import LearnerConfig, make_learner
from bulbjax.report import records, report
from bulbjax.rl.ppo import PPOConfig

SEEDS = 2


def tiny(env: str, learners: tuple[str, ...]) -> ExperimentConfig:
    """One epoch of 4 worlds per seed at 32 px; SPAIR on a 2x2 grid with 8 px glimpses."""
    return ExperimentConfig(
        env=env, learners=learners, seeds=SEEDS, epochs=1, num_envs=4, resolution=32,
        ppo=PPOConfig(num_envs=4, num_steps=4, num_minibatches=1, update_epochs=1),
        ppo_updates_per_epoch=1, frames_per_epoch=8, replay_capacity=16,
        learner=LearnerConfig(batch_size=4, conv_features=(8, 8, 8, 8), hidden=16, lr=1e-3,
                              spair_grid=2, spair_glimpse=8, spair_what_dim=4),
        learner_batches=1, eval_frames=8, probe_train_frames=8,
        probe=ProbeConfig(hidden=(8,), steps=2, batch_size=8), reference_steps=4)


@pytest.fixture(scope="module")
def rearrange():
    """One epoch of SPAIR and VAE_rpl. An untrained SPAIR's presences are near 0.5, on either side
    depending on the seed: its presence head is set to present everywhere in seed 0 and nowhere
    in seed 1 (log-odds +-10; training wheels keep the head fixed during the epoch's update)."""
    exp = Experiment(tiny("ReacherRearrangeGeom", ("spair", "vae_rpl")))
    rs = exp.init(jax.random.PRNGKey(0))
    ls = rs.learners["spair"]
    params = {**ls.params, "pres": {**ls.params["pres"], "out": {
        "kernel": jnp.zeros_like(ls.params["pres"]["out"]["kernel"]),
        "bias": jnp.array([[10.0], [-10.0]], jnp.float32)}}}
    rs = rs.replace(learners={**rs.learners, "spair": ls.replace(params=params)})
    _, m = exp.epoch(rs, jax.random.PRNGKey(1))
    return exp, jax.device_get(m)


def test_rearrange_run_has_the_object_probe(rearrange, tmp_path) -> None:
    exp, m = rearrange
    names, _ = exp.probing.objects
    assert names == ["obj0", "obj1", "obj2", "obj3"] and exp.probing.object_radius == pytest.approx(3.2)
    mcount = len(names)
    for stream in ("curr", "rand"):
        o = m["probes"]["spair"][stream]["objects"]
        assert o["error"].shape == o["found"].shape == (SEEDS, mcount)
        assert o["error_mean"].shape == o["found_share"].shape == (SEEDS,)
        # seed 0: all 2 x 2 boxes present, finite errors within the 32 px frame's diagonal
        np.testing.assert_array_equal(o["present_per_frame"], [4, 0])
        assert np.all(np.isfinite(o["error"][0])) and np.all((o["error"][0] >= 0) & (o["error"][0] < 46))
        assert np.isfinite(o["error_mean"][0]) and o["missing"][0] == 0 and o["spurious_per_frame"][0] <= 4
        assert np.all((o["found"] >= 0) & (o["found"] <= 1))
        assert np.all((o["found_share"] >= 0) & (o["found_share"] <= 1))
        # seed 1: no present box, every object missing: infinite error, none found
        assert np.all(np.isinf(o["error"][1])) and np.all(o["found"][1] == 0) and o["missing"][1] == 1
        np.testing.assert_allclose(o["radius"], 3.2)
        assert "objects" not in m["probes"]["vae_rpl"][stream]  # no boxes: the MLP probe only
    recs = records.epoch_records(0, m, exp.spec)
    assert len(recs) == SEEDS
    for s, r in enumerate(recs):
        assert set(r["objects"]) == {"spair"} and set(r["objects"]["spair"]) == {"curr", "rand"}
        rr = r["objects"]["spair"]["rand"]
        assert list(rr["per_object"]) == names and rr["radius"] == pytest.approx(3.2)
        assert rr["error_mean"] == pytest.approx(float(m["probes"]["spair"]["rand"]["objects"]["error_mean"][s]))
        assert rr["per_object"]["obj2"]["found"] == pytest.approx(
            float(m["probes"]["spair"]["rand"]["objects"]["found"][s, 2]))
    assert np.isinf(recs[1]["objects"]["spair"]["curr"]["error_mean"])
    path = tmp_path / "metrics.jsonl"
    records.write_jsonl(str(path), recs)
    assert records.read_jsonl(str(path))[0]["objects"] == recs[0]["objects"]
    tab = report.write_reports(str(tmp_path), recs, exp.config, exp.spec)
    text = (tmp_path / "table.md").read_text()
    assert "## Objects" in tab and "## Objects" in text
    assert (tmp_path / "objects.png").stat().st_size > 10_000  # the object-probe curves
    # the object section: spair with boxes and MLP, vae_rpl with its MLP probe only
    section = text.split("## Objects")[1].splitlines()
    spair_row = [ln for ln in section if ln.startswith("| spair | π_rand |")]
    rpl_row = [ln for ln in section if ln.startswith("| vae_rpl | π_rand |")]
    assert len(spair_row) == len(rpl_row) == 1
    cells = [c.strip() for c in spair_row[0].split("|")[1:-1]]
    assert len(cells) == 6 + mcount and all("–" not in c for c in cells[:6])
    # the mean over seeds of finite values: the box error is seed 0's, the share both seeds'
    o = recs[0]["objects"]["spair"]["rand"]
    assert float(cells[3]) == pytest.approx(o["error_mean"], abs=0.006)
    assert float(cells[4]) == pytest.approx(o["found_share"] / 2, abs=0.006)
    assert float(cells[6].split("/")[1]) == pytest.approx(o["per_object"]["obj0"]["error"], abs=0.006)
    rcells = [c.strip() for c in rpl_row[0].split("|")[1:-1]]
    assert rcells[2] != "–" and rcells[3] == rcells[4] == "–" and rcells[6].endswith("/ –")


def test_figures_of_a_rearrange_run_write_region_errors(rearrange, tmp_path) -> None:
    """`RunFigures.draw` in a domain with objects also writes every seed's per-object
    reconstruction error (`regions_<epoch>.json`), which the YCB claim reads."""
    from bulbjax.eval import regions
    from bulbjax.run.recon import REGION_FRAMES, RunFigures

    exp, _ = rearrange
    rs = exp.init(jax.random.PRNGKey(0))
    paths = RunFigures(exp).draw(rs, str(tmp_path), 3)
    assert sorted(os.path.basename(p) for p in paths) == ["boxes_3.png", "recon_3.png", "regions_3.json"]
    got = regions.newest(str(tmp_path))
    assert got["epoch"] == 3 and got["objects"] == ["obj0", "obj1", "obj2", "obj3"] and got["seeds"] == SEEDS
    assert got["radius_px"] == pytest.approx(3.2) and 0 < got["frames"] <= REGION_FRAMES
    for name in ("spair", "vae_rpl"):
        r = np.asarray(got["learners"][name]["ratio"], np.float64)
        assert r.shape == (SEEDS, 4) and np.isfinite(r).any()
        assert np.all(r[np.isfinite(r)] > 0)  # untrained learners reconstruct nothing exactly


def test_rearrange_run_probes_major_axis_angles(rearrange, tmp_path) -> None:
    """Issue 37: the probes regress the state and the objects' major-axis angles (derived targets,
    the env's state unchanged); the reference spread covers them; the spheres' angle entries
    (always (0, 0)) and the objects' static properties (one version) are excluded; records carry
    per-object angle errors (rad), NaN for the spheres; table.md says "excluded", never nan."""
    exp, m = rearrange
    d = len(exp.env.state_spec)
    assert d == 100 and len(exp.spec) == d + 8 and exp.spec[:d] == exp.env.state_spec
    assert [e.group for e in exp.spec[d:]] == ["object_angle"] * 8
    assert m["ref_spread"].shape == (SEEDS, d + 8)
    for stream in ("curr", "rand"):
        assert m["probes"]["vae_rpl"][stream]["mae"].shape == (SEEDS, d + 8)
        a = m["probes"]["vae_rpl"][stream]["angle"]
        assert a["mae"].shape == a["baseline"].shape == (SEEDS, 4)
        assert np.isnan(a["mae"][:, 2:]).all()  # the spheres: no axis
    recs = records.epoch_records(0, m, exp.spec)
    r = recs[0]
    assert set(r["angles"]["vae_rpl"]["rand"]) == {"obj0", "obj1", "obj2", "obj3"}
    assert np.isnan(r["angles"]["vae_rpl"]["rand"]["obj2"]["mae"])
    excl = set(r["probes"]["vae_rpl"]["rand"]["excluded"])
    assert {"obj2_axis_cos2", "obj2_axis_sin2", "obj3_axis_cos2", "obj3_axis_sin2"} <= excl
    assert records.excluded_groups(recs) >= {"object_static"}
    report.write_reports(str(tmp_path), recs, exp.config, exp.spec)
    text = (tmp_path / "table.md").read_text()
    assert "object_angle" in text and "excluded" in text and "nan" not in text.split("## Objects")[0].lower()


def test_spair_boxes_of_latents_match_boxes() -> None:
    learner = make_learner("spair", 8, {"spair_grid": 2, "spair_glimpse": 8, "spair_what_dim": 4,
                                         "conv_features": (8, 8, 8, 8), "hidden": 16})
    params = learner.init(jax.random.PRNGKey(0), (32, 32, 3)).params
    frames = jax.random.randint(jax.random.PRNGKey(1), (3, 32, 32, 3), 0, 256).astype(jnp.uint8)
    centres, _, pres = learner.boxes(params, frames)
    c2, p2 = learner.boxes_of_latents(learner.encode(params, frames)[:, None], 32)
    np.testing.assert_allclose(c2[:, 0], centres, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(p2[:, 0], pres, rtol=1e-6)


def test_reduction_agrees_with_summarise_and_known_answers() -> None:
    """Boxes exactly on the objects: 0 px, all found, no spurious box; the same boxes 100 px
    away: nothing found within 3.2 px; in-jit reduction == host `summarise` with a valid mask."""
    rng = np.random.default_rng(0)
    pos = rng.uniform(4, 28, (6, 3, 2)).astype(np.float32)  # 6 frames, 3 objects
    on = np.concatenate([pos, rng.uniform(0, 32, (6, 2, 2)).astype(np.float32)], 1)  # + 2 absent boxes
    pres = np.array([[0.9, 0.8, 0.7, 0.1, 0.2]] * 6, np.float32)
    reduce = jax.jit(lambda c, p, o, v: reduce_scores(object_scores(c, p, o, 3.2), v))
    valid = np.array([True, True, False, True, True, True])
    hit = summary_of(jax.device_get(reduce(on, pres, pos, valid)), ["a", "b", "c"])
    assert hit["error_mean"] == pytest.approx(0.0, abs=1e-5) and hit["found_share"] == 1.0
    assert all(v["error"] == pytest.approx(0.0, abs=1e-5) and v["found"] == 1.0 for v in hit["per_object"].values())
    assert hit["missing"] == 0.0 and hit["spurious_per_frame"] == 0.0 and hit["present_per_frame"] == 3.0
    far = on.copy()
    far[:, :3] += 100.0  # off the frame
    miss = summary_of(jax.device_get(reduce(far, pres, pos, valid)), ["a", "b", "c"])
    assert miss["found_share"] == 0.0 and miss["error_mean"] > 10.0
    # mixed case with frames without any present box, against the host summary
    pres2 = pres.copy()
    pres2[1] = 0.0  # no box in frame 1: its objects are missing
    cen = on + rng.normal(0, 3, on.shape).astype(np.float32)
    got = summary_of(jax.device_get(reduce(cen, pres2, pos, valid)), ["a", "b", "c"])
    want = summarise(object_scores(cen, pres2, pos, 3.2), ["a", "b", "c"], valid=valid)
    assert got["per_object"].keys() == want["per_object"].keys()
    for k in ("error_mean", "found_share", "missing", "spurious_per_frame", "present_per_frame"):
        assert got[k] == pytest.approx(want[k], rel=1e-5, abs=1e-6), k
    for n in "abc":
        for k in ("error", "found"):
            assert got["per_object"][n][k] == pytest.approx(want["per_object"][n][k], rel=1e-5, abs=1e-6)
    assert 0 < got["missing"] < 1
    # no present box at all: infinite error, nothing found (as `summarise`)
    none = summary_of(jax.device_get(reduce(on, np.zeros_like(pres), pos, valid)))
    assert np.isinf(none["error_mean"]) and none["found_share"] == 0.0 and none["missing"] == 1.0
    assert list(none["per_object"]) == ["object0", "object1", "object2"]


def test_comparison_table_side_by_side() -> None:
    from bulbjax.eval.spec import StateEntry

    spec = [StateEntry(f"obj{i}_{a}", "1", "object_position") for i in range(2) for a in "xyz"]
    spec.append(StateEntry("j0_sin", "1", "robot"))

    def probes(v: float) -> dict:
        ent = {e.name: {"mae_norm": v} for e in spec}
        return {"rand": {"groups": {"object_position": {"mae_norm": v}}, "entries": ent}}

    box = {"per_object": {"obj0": {"error": 2.0, "found": 1.0}, "obj1": {"error": 4.0, "found": 0.0}},
           "error_mean": 3.0, "found_share": 0.5, "spurious_per_frame": 1.0, "radius": 3.2}
    recs = [{"epoch": 0, "seed": s, "probes": {"spair": probes(0.5), "vae_rpl": probes(0.25)},
             "objects": {"spair": {"rand": box}}} for s in range(2)]
    tab = comparison_table(recs, spec)
    assert "| spair | π_rand | 0.500 | 3.00 | 0.50 | 1.00 | 0.500 / 2.00 | 0.500 / 4.00 |" in tab
    assert "| vae_rpl | π_rand | 0.250 | – | – | – | 0.250 / – | 0.250 / – |" in tab
    assert "3.2 px" in tab and object_names(spec) == ["obj0", "obj1"]
    assert comparison_table(recs, [StateEntry("x", "m", "position")]) == ""
