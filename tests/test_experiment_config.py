"""The epoch's configuration without running an epoch: the seed-loop and program-form choices,
bad settings refused, the presets and the command line's overrides, and the records' helpers
the reports use (the 90% band, the return of epochs without a finished episode)."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from bulbjax.epoch import ExperimentConfig
from bulbjax.epoch.seeds import learner_loop, with_seed_loop
from bulbjax.learners import LearnerConfig, make_learner
from bulbjax.report import records

from tiny_experiment import ALL, tiny_config


def test_seed_loop_choice():
    from bulbjax.epoch.devices import make_mesh
    from bulbjax.epoch.seeds import resolve_seed_loop

    mesh = make_mesh(jax.devices()[:1], 2, 4)
    assert resolve_seed_loop("auto", mesh) == ("vmap" if jax.default_backend() == "cpu" else "hybrid")
    assert resolve_seed_loop("map", mesh) == "map"
    assert resolve_seed_loop("hybrid", mesh) == "hybrid"
    # hybrid: DSA vmapped (its convolutions looping over seeds), the others mapped
    dsa, svae, pred = (make_learner(n, 4, LearnerConfig(), 1) for n in ("dsa", "svae", "pred"))
    assert learner_loop("hybrid", with_seed_loop(dsa, "hybrid")) == "vmap"
    for other in (svae, pred):
        assert learner_loop("hybrid", with_seed_loop(other, "hybrid")) == "map"
    assert learner_loop("hybrid", None) == "map" and learner_loop("vmap", dsa) == "vmap"
    assert not with_seed_loop(dsa, "map").per_seed_frames
    with pytest.raises(ValueError, match="learner_seed_loop"):
        resolve_seed_loop("loop", mesh)
    with pytest.raises(ValueError, match="learner_seed_loop"):
        dataclasses.replace(tiny_config(), learner_seed_loop="pmap")


def test_program_form_choice():
    from types import SimpleNamespace

    from bulbjax.epoch.devices import make_mesh
    from bulbjax.epoch.programs import resolve_programs

    mesh = make_mesh(jax.devices()[:1], 2, 4)
    assert tiny_config().programs == "fused"
    assert resolve_programs("split", mesh) == "split" and resolve_programs("fused", mesh) == "fused"
    two = SimpleNamespace(size=2, devices=np.array(jax.devices()[:1] * 2))
    assert resolve_programs("fused", two) == "fused"
    with pytest.raises(ValueError, match="one device"):
        resolve_programs("split", two)
    with pytest.raises(ValueError, match="programs must be one of"):
        dataclasses.replace(tiny_config(), programs="auto")


def test_config_rejects_bad_settings():
    with pytest.raises(ValueError, match="unknown learners"):
        ExperimentConfig(learners=("vea",))
    with pytest.raises(ValueError, match="multiple of num_envs"):
        dataclasses.replace(tiny_config(), frames_per_epoch=6)
    with pytest.raises(ValueError, match="rollout steps"):
        dataclasses.replace(tiny_config(), frames_per_epoch=64, replay_capacity=64)


def test_ci90_matches_student_t():
    v = np.array([[1.0], [2.0], [3.0]])
    mean, half = records.ci90(v)
    assert mean[0] == pytest.approx(2.0)
    assert half[0] == pytest.approx(2.920 * 1.0 / np.sqrt(3))


def test_return_of_epochs_without_a_finished_episode():
    """InvertedPendulum's 1,000-step episodes end every ~8 epochs: an epoch's return is NaN when
    none ended. The table reports the latest finished episodes instead, without a warning."""
    import warnings

    recs = [{"epoch": e, "seed": s, "rl_return": r}
            for e, rets in enumerate([(10.0, 20.0), (float("nan"), 40.0), (float("nan"), float("nan"))])
            for s, r in enumerate(rets)]
    ret, fell_back = records.last_returns(recs, [1])
    assert ret.tolist() == [10.0, 40.0] and fell_back  # seed 0 falls back to epoch 0
    ret, fell_back = records.last_returns(recs, [0, 1])
    assert ret.tolist() == [10.0, 30.0] and not fell_back
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ret, fell_back = records.last_returns(recs, [2])
        assert ret.tolist() == [10.0, 40.0] and fell_back
        assert np.isnan(records.ci90(np.full((3, 2), np.nan))[0]).all()
    later = recs + [{"epoch": 3, "seed": s, "rl_return": 99.0} for s in (0, 1)]
    ret, fell_back = records.last_returns(later, [2])  # an episode after them is not 'latest'
    assert ret.tolist() == [10.0, 40.0] and fell_back
    ret, fell_back = records.last_returns(later, [0])
    assert ret.tolist() == [10.0, 20.0] and not fell_back
    ret, fell_back = records.last_returns(later, [])
    assert ret.tolist() == [99.0, 99.0] and fell_back
    # an episode that ended between two asked epochs counts (HalfCheetah: epochs 0 and 10 probed,
    # episodes ending at epoch 7)
    ret, fell_back = records.last_returns(later, [2, 5])
    assert ret.tolist() == [99.0, 99.0] and fell_back
    ret, fell_back = records.last_returns([{"epoch": 0, "seed": 0, "rl_return": float("nan")}], [0])
    assert np.isnan(ret).all() and not fell_back  # no finished episode at all: NaN, not 0


def test_presets_and_cli_overrides():
    from bulbjax.cli import build_config, main
    from bulbjax.config import PRESETS, preset

    cart = preset("fig2-cartpole")
    assert cart.learners == ALL and cart.seeds == 6 and cart.multicolour
    assert (cart.learner_batches, cart.learner.lr, cart.seq_len, cart.learner.batch_size) == (10, 1e-4, 24, 1024)
    assert preset("fig2-invpend").env == "InvertedPendulum"
    loco = preset("fig2-halfcheetah")
    assert (loco.learner_batches, loco.seq_len, loco.learner.sequence_length) == (50, 16, 16)
    assert preset("fig2-ant").window_length == 16 + loco.learner.pred_horizon
    assert set(PRESETS) == {"fig2-cartpole", "fig2-invpend", "fig2-halfcheetah", "fig2-ant", "fig3-rearrange-geom",
                            "fig3-rearrange-geom-random", "fig5-rearrange-ycb"}
    fig3 = preset("fig3-rearrange-geom")
    assert (fig3.env, fig3.version, fig3.seeds, fig3.window_length) == ("ReacherRearrangeGeom", 6, 3, 0)
    assert {"vae_rpl", "spair", "spair6"} <= set(fig3.learners)
    from bulbjax.learners import resolve_config
    assert (resolve_config("spair6").spair_grid, resolve_config("spair").spair_grid) == (6, 4)
    with pytest.raises(ValueError, match="fig2-cartpole"):
        preset("fig3")
    import argparse
    ns = dict(preset="fig2-cartpole", env=None, learners=None, seeds=2, epochs=3, sequence_length=None,
              multicolour=False, small=True, ppo_updates=None, lr=None, bf16=True)
    cfg = build_config(argparse.Namespace(**ns))
    assert (cfg.seeds, cfg.epochs, cfg.learners, cfg.learner.compute_dtype) == (2, 3, ALL, "bfloat16")
    assert cfg.num_envs == 16 and cfg.seq_len == 8 and cfg.learner.sequence_length == 8
    assert build_config(argparse.Namespace(**{**ns, "version": "random"})).version == "random"
    assert build_config(argparse.Namespace(**{**ns, "version": "3"})).version == 3
    with pytest.raises(ValueError, match="--version"):
        build_config(argparse.Namespace(**{**ns, "version": "-1"}))
    opt = build_config(argparse.Namespace(**{**ns, "learner_option": ["channel_pad=1", "bias_grad=reduce"]}))
    assert (opt.learner.channel_pad, opt.learner.bias_grad, opt.learner.compute_dtype) == (1, "reduce", "bfloat16")
    with pytest.raises(ValueError, match="KEY one of"):
        build_config(argparse.Namespace(**{**ns, "learner_option": ["channelpad=1"]}))
    assert build_config(argparse.Namespace(**{**ns, "ppo_option": ["ent_coef=0.02"]})).ppo.ent_coef == 0.02
    assert cfg.graph_mode is None  # MJX's default unless --graph-mode is given
    assert build_config(argparse.Namespace(**{**ns, "graph_mode": "jax"})).graph_mode == "jax"
    with pytest.raises(ValueError, match="version"):
        dataclasses.replace(cart, version="all")
    assert main(["run", "--preset", "nope", "--out", "/tmp/bulbjax_nope"]) == 2
