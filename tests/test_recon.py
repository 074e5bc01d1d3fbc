"""Reconstruction figures of a run: `RunOptions(recon_every=N)` / `bulbjax run --recon-every N`
writes recon_<epoch>.png and (with SPAIR) boxes_<epoch>.png from held-out frames, without
changing the run's metrics; `bulbjax recon RUN_DIR` redraws the same figures from a checkpoint.
A tiny CPU config (CartPole 32x32, a VAE and a small SPAIR)."""

from __future__ import annotations

import dataclasses
import os

import matplotlib.image as mpimg
import numpy as np
import pytest

from bulbjax.config import RunOptions
from bulbjax.epoch import Experiment, ExperimentConfig
from bulbjax.run import RunFigures, redraw_figures, run

from tiny_experiment import tiny_config


def tiny() -> ExperimentConfig:
    """The shared tiny config with VAE_rpl and a small SPAIR."""
    base = tiny_config()
    return base.replace(learners=("vae_rpl", "spair"), learner_batches=1,
                        learner=dataclasses.replace(base.learner, spair_grid=4, spair_glimpse=8, spair_what_dim=4))


@pytest.fixture(scope="module")
def exp():
    return Experiment(tiny())


@pytest.fixture(scope="module")
def runs(exp, tmp_path_factory):
    """The same 2 epochs without and with figures every epoch."""
    quiet = dict(experiment=exp, progress=False, log=lambda s: None)
    plain = str(tmp_path_factory.mktemp("plain"))
    run(exp.config, RunOptions(), plain, **quiet)
    figs = str(tmp_path_factory.mktemp("figs"))
    run(exp.config, RunOptions(recon_every=1, checkpoint_every=1), figs, **quiet)
    return plain, figs


def test_recon_every_writes_figures(exp, runs) -> None:
    plain, d = runs
    names = sorted(f for f in os.listdir(d) if f.endswith(".png") and f != "fig2.png")
    assert names == ["boxes_1.png", "boxes_2.png", "recon_1.png", "recon_2.png"]
    assert not [f for f in os.listdir(plain) if f.startswith(("recon_", "boxes_"))]
    assert not [f for f in os.listdir(d) if f.startswith("regions_")]  # CartPole: no objects, no region errors
    # drawing figures leaves the run alone: the metrics are those of the run without them
    assert open(os.path.join(plain, "metrics.jsonl")).read() == open(os.path.join(d, "metrics.jsonl")).read()
    # the recon grid's top row is the held-out frames it was drawn from; rows: true, vae_rpl, spair
    from bulbjax.report import figures
    from bulbjax.run.checkpoint import Checkpointer

    ck = Checkpointer(d)
    state, _, epoch = ck.restore({"run": exp.abstract_state(), "key": exp.abstract_key()}, 2)
    ck.close()
    w = RunFigures(exp).held_out(state["run"], epoch)
    frames = np.asarray(w.frames).reshape((-1,) + w.frames.shape[2:])[:8]
    png = mpimg.imread(os.path.join(d, "recon_2.png"))[..., :3]
    lay = figures.Layout(rows=3, cols=frames.shape[0], height=32, width=32, scale=2)
    assert png.shape[:2] == lay.shape
    for j in range(frames.shape[0]):
        y, x = lay.origin(0, j)
        np.testing.assert_allclose(png[y: y + 64: 2, x: x + 64: 2], frames[j] / 255.0, atol=1 / 255 + 1e-6)
    # a fresh run in the same folder is refused without --overwrite, and with it removes the old figures
    from bulbjax.run.rundir import RunFolderExists
    with pytest.raises(RunFolderExists):
        run(exp.config, RunOptions(stop_after=1), d, experiment=exp, progress=False, log=lambda s: None)
    assert [f for f in os.listdir(d) if f.startswith(("recon_", "boxes_"))]
    run(exp.config, RunOptions(stop_after=1), d, overwrite=True, experiment=exp, progress=False, log=lambda s: None)
    assert not [f for f in os.listdir(d) if f.startswith(("recon_", "boxes_"))]


def test_recon_redraws_from_checkpoint(exp, tmp_path) -> None:
    d = str(tmp_path / "run")
    run(exp.config, RunOptions(recon_every=2, checkpoint_every=1), d, experiment=exp,
        progress=False, log=lambda s: None)
    drawn = mpimg.imread(os.path.join(d, "recon_2.png"))
    boxes = mpimg.imread(os.path.join(d, "boxes_2.png"))
    out = str(tmp_path / "redrawn")
    paths = redraw_figures(d, out_dir=out, experiment=exp, log=lambda s: None)
    assert [os.path.basename(p) for p in paths] == ["recon_2.png", "boxes_2.png"]
    np.testing.assert_array_equal(mpimg.imread(paths[0]), drawn)  # the same figure, pixel for pixel
    np.testing.assert_array_equal(mpimg.imread(paths[1]), boxes)
    # an older checkpoint draws other reconstructions of the same kind of grid
    p1 = redraw_figures(d, epoch=1, learners=["vae_rpl"], out_dir=out, experiment=exp, log=lambda s: None)
    assert [os.path.basename(p) for p in p1] == ["recon_1.png"]
    assert mpimg.imread(p1[0]).shape[0] < drawn.shape[0]  # two rows instead of three
    with pytest.raises(ValueError, match="not in this run; it has vae_rpl, spair"):
        redraw_figures(d, learners=["dsa"], experiment=exp, log=lambda s: None)
    with pytest.raises(ValueError, match=r"no checkpoint of epoch 7 .* \[1, 2\]"):
        redraw_figures(d, epoch=7, experiment=exp, log=lambda s: None)


def test_cli(tmp_path, monkeypatch) -> None:
    """`--recon-every` reaches the run options; `bulbjax recon` errors say what to do."""
    import bulbjax.run as run_mod  # the face `bulbjax run` calls `run` through
    from bulbjax import cli

    got = {}
    monkeypatch.setattr(run_mod, "run", lambda cfg, opts, out, **kw: got.update(opts=opts))
    assert cli.main(["run", "--env", "CartPole", "--learners", "vae", "--recon-every", "3",
                     "--out", str(tmp_path / "x")]) == 0
    assert got["opts"].recon_every == 3
    assert cli.main(["recon", str(tmp_path / "nothing")]) == 2
    os.makedirs(tmp_path / "r")
    import json

    # the config.json of a run that never checkpointed
    with open(tmp_path / "r" / "config.json", "w") as f:
        json.dump({"experiment": dataclasses.asdict(tiny()), "run": {"seed": 0, "probe_every": 1}}, f)
    with pytest.raises(ValueError, match="no checkpoint in .*--resume"):
        redraw_figures(str(tmp_path / "r"))
    assert not os.path.exists(tmp_path / "r" / "checkpoints")
