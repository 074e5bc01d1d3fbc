"""SyntheticMovers: a check only sequence learners can pass. A square moves at a constant
velocity; a single frame shows its position only. After a few hundred offline updates every
sequential learner's latents must hold the velocity (normalised error clearly below the constant
predictor), the frame VAE's must not, positions must be decodable for all, and the check must
fail for a deliberately broken latent (per-step latents shuffled across time steps)."""

from __future__ import annotations

import json
import os

import jax
import numpy as np
import pytest

from bulbjax.data import sequence, synthetic
from bulbjax.eval.probe import ProbeConfig, summarise
from bulbjax.config import ExperimentConfig
from bulbjax.offline_config import OfflineConfig
from bulbjax.epoch.offline import OfflineFit, reference_spread
from bulbjax.run.offline import load_or_collect
from bulbjax.learners import LearnerConfig

UPDATES = 400
SEQUENTIAL = ("svae", "pred", "dsa")


def movers_config(learners=("vae",) + SEQUENTIAL, updates=UPDATES) -> OfflineConfig:
    """16x16 frames of one square, small nets, lr 1e-3, 256-frame batches (32 windows of 8)."""
    base = ExperimentConfig(
        env=synthetic.NAME, learners=learners, seeds=1, resolution=16, sequence_length=8,
        learner=LearnerConfig(lr=1e-3, batch_size=256, conv_features=(16, 32), hidden=64,
                              pred_horizon=4, dsa_encoder="lstm"),
        probe_train_frames=2048, probe=ProbeConfig(hidden=(128, 128), steps=400))
    return OfflineConfig(
        base=base, updates=updates, probe_every=updates, data_worlds=64, data_steps=256,
        heldout_steps=48, updates_per_call=1,
        movers=synthetic.MoversConfig(resolution=16, num_objects=1, size=5.0, max_speed=1.0))


def test_movers_data() -> None:
    c = synthetic.MoversConfig(resolution=16, num_objects=2, size=4.0, max_speed=1.0, episode_length=8)
    t = synthetic.generate(jax.random.PRNGKey(0), c, 40, 3)
    assert t.frames.shape == (40, 3, 16, 16, 3) and t.frames.dtype == np.uint8
    assert t.states.shape == (40, 3, 8) and [e.group for e in c.state_spec].count("velocity") == 4
    s, d = np.asarray(t.states), np.asarray(t.dones) > 0
    assert np.all(s[..., :4] >= 0) and np.all(s[..., :4] <= 12)
    # velocities are constant within an episode up to sign flips at the walls
    same = ~d[1:]
    assert np.allclose(np.abs(s[1:, :, 4:])[same], np.abs(s[:-1, :, 4:])[same])
    assert np.all(d.sum(0) >= 4)  # episodes of 8 steps in 40 steps
    with pytest.raises(ValueError, match="num_objects"):
        synthetic.MoversConfig(num_objects=9)


@pytest.fixture(scope="module")
def fitted():
    """Four learners, UPDATES updates each on one cached-free dataset, probed once."""
    cfg = movers_config()
    fit = OfflineFit(cfg)
    data, held_traj, _ = load_or_collect(cfg, fit.source, None)
    held = sequence.consecutive_windows(held_traj, cfg.eval_length)
    states = fit.init(jax.random.PRNGKey(0))
    key = jax.random.PRNGKey(1)
    for _ in range(UPDATES):
        key, k = jax.random.split(key)
        states, m = fit.train(states, data, k, 1)
    ref = reference_spread(held)

    def scores(broken: bool):
        p = jax.device_get(fit.probe(states, data, held, jax.random.PRNGKey(2), np.bool_(broken)))
        out = {}
        for name, streams in p.items():
            d = streams["rand"]
            s = summarise(d["mae"][0], d["baseline"][0], ref, fit.spec)
            out[name] = {g: v["mae_norm"] for g, v in s["groups"].items()}
            out[name]["constant"] = s["groups"]["velocity"]["baseline_norm"]
        return out

    return scores(False), scores(True)


def passes(s: dict) -> bool:
    """The check: velocity clearly beaten, position decodable."""
    return s["velocity"] < 0.8 and s["position"] < 0.5


def test_only_sequences_decode_velocity(fitted) -> None:
    good, _ = fitted
    print(json.dumps(good, indent=1))
    for name in SEQUENTIAL:
        assert passes(good[name]), (name, good[name])
    assert good["vae"]["velocity"] > 0.9, good["vae"]
    assert good["vae"]["position"] < 0.5, good["vae"]
    assert 0.8 < good["vae"]["constant"] < 1.2


def test_broken_latent_fails_the_check(fitted) -> None:
    _, broken = fitted
    print(json.dumps(broken, indent=1))
    for name in SEQUENTIAL + ("vae",):
        assert not passes(broken[name]), (name, broken[name])
        assert broken[name]["velocity"] > 0.9 and broken[name]["position"] > 0.9


def test_fit_cli_end_to_end(tmp_path) -> None:
    """`bulbjax fit` on tiny sizes: cache, curves, table, reconstructions; a second run reads
    the cached dataset."""
    from bulbjax.cli import main
    args = ["fit", "--env", synthetic.NAME, "--learners", "vae", "--small", "--seeds", "2",
            "--updates", "4", "--probe-every", "2", "--data-worlds", "8", "--data-steps", "16",
            "--heldout-steps", "8", "--resolution", "16", "--out", str(tmp_path / "a"),
            "--cache-dir", str(tmp_path / "cache")]
    assert main(args) == 0
    recs = [json.loads(x) for x in open(tmp_path / "a" / "curves.jsonl")]
    assert [r["update"] for r in recs] == [0, 0, 2, 2, 4, 4]
    g = recs[-1]["probes"]["vae"]["rand"]["groups"]
    assert set(g) == {"position", "velocity"} and np.isfinite(g["position"]["mae_norm"])
    assert 0.0 <= recs[-1]["probe_inputs_clamped"]["vae"]["rand"] <= 1.0
    for f in ("curves.png", "recon.png", "table.md", "config.json"):
        assert os.path.getsize(tmp_path / "a" / f) > 100
    assert len(os.listdir(tmp_path / "cache")) == 2
    # second run: the cached data set, and a --max-minutes budget already spent: it stops
    # cleanly after the first probe and still writes its plots
    b = args[:-4] + ["--out", str(tmp_path / "b"), "--cache-dir", str(tmp_path / "cache"), "--max-minutes", "0.001"]
    assert main(b) == 0
    assert [json.loads(x)["update"] for x in open(tmp_path / "b" / "curves.jsonl")] == [0, 0]
    assert os.path.getsize(tmp_path / "b" / "curves.png") > 100
    assert len(os.listdir(tmp_path / "cache")) == 2
    assert main(["fit", "--learners", "vae", "--out", str(tmp_path / "c")]) == 2  # no env
    # a fit cut in two calls (2 updates, then --resume to 4) gives the straight fit's curves
    r = args[:-4] + ["--out", str(tmp_path / "r"), "--cache-dir", str(tmp_path / "cache")]
    assert main([*r[:r.index("--updates") + 1], "2", *r[r.index("--updates") + 2:]]) == 0
    assert os.path.isdir(tmp_path / "r" / "checkpoints")
    assert main(r + ["--resume"]) == 0
    resumed = [json.loads(x) for x in open(tmp_path / "r" / "curves.jsonl")]
    assert [x["update"] for x in resumed] == [0, 0, 2, 2, 4, 4]
    for x, y in zip(recs, resumed):
        assert x["probes"] == y["probes"], (x["update"], x["seed"])
    # other settings on resume: a clear error (exit 2), nothing overwritten
    assert main(r + ["--resume", "--seed", "1"]) == 2
    assert main(args[:-4] + ["--out", str(tmp_path / "nothing"), "--resume"]) == 2


def test_dataset_cache_names_the_object_version(tmp_path) -> None:
    """Two fits sharing a `--cache-dir` read one file only when it holds their data: a
    multi-object domain's versions are other scenes (fig3-rearrange-geom against its random
    version), so the version is in the name; version 0 keeps the names caches already have."""
    from bulbjax.epoch.offline import Source
    from bulbjax.run.offline import dataset_path

    src = Source("ReacherRearrangeGeomMulticolour", (), (64, 64, 3), 2, lambda k, n: None)
    paths = {v: dataset_path(OfflineConfig(base=ExperimentConfig(env="ReacherRearrangeGeom", version=v)),
                             src, str(tmp_path), "train", 100)
             for v in (0, 1, "random")}
    assert len(set(paths.values())) == 3, paths
    worlds = OfflineConfig(base=ExperimentConfig(env="ReacherRearrangeGeom")).data_worlds
    assert os.path.basename(paths[0]) == f"ReacherRearrangeGeomMulticolour_64px_{worlds}x100_seed0_train.npz"
    assert "_vrandom_" in paths["random"] and "_v1_" in paths[1]
