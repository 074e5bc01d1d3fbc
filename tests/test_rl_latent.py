"""PPO from a learner's latent (`rl_input="latent:<learner>"`, issue 15): the observation PPO
gets is the learner's encoding of that step's frame with that seed's current parameters; a
two-epoch run works; PPO from pixels (`rl_input="pixels"`) sees that step's frame and trains its
conv torso; bad inputs are clear errors. Sequential learners' latents: tests/test_rl_sequential.py."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from bulbjax.epoch import ExperimentConfig, small_config
from bulbjax.epoch.loop import Experiment
from bulbjax.epoch.programs import Programs
from bulbjax.epoch.state import Rendered


@pytest.mark.slow  # the slow tier (tests/conftest.py)
def test_latent_fed_to_ppo_is_the_learners_encoding(tmp_path) -> None:
    from bulbjax.config import RunOptions
    from bulbjax.run import run

    import dataclasses

    cfg = small_config(ExperimentConfig(env="CartPole", learners=("vae_rpl",), seeds=2, epochs=2,
                                        rl_input="latent:vae_rpl"))
    # fewer worlds, steps and frames than --small: what is checked does not depend on the sizes
    # (32 steps of 8 worlds still end CartPole episodes in both epochs)
    cfg = cfg.replace(num_envs=8, ppo=dataclasses.replace(cfg.ppo, num_envs=8, num_steps=32), ppo_updates_per_epoch=1,
                      frames_per_epoch=64, replay_capacity=256, eval_frames=32, probe_train_frames=128,
                      probe=dataclasses.replace(cfg.probe, steps=50), reference_steps=32)
    exp = Experiment(cfg)
    rs = Programs.of(exp, (True,)).init(jax.random.PRNGKey(0))  # the init the run below reuses (one compile)
    learner = exp.learners["vae_rpl"]
    assert exp.policy.rl_learner == "vae_rpl"
    assert exp.ppo.obs_size == learner.latent_dim == 2 * exp.env.state_dim
    obs = jax.jit(exp.policy.obs)(rs.train_env, rs.learners)
    S, N = cfg.seeds, cfg.num_envs
    assert obs.shape == (S, N, learner.latent_dim) and obs.dtype == np.float32
    frames = exp.env.render_frames(rs.train_env.render_input)  # this step's frames, [S*N, H, W, 3]
    for s in range(S):
        params = jax.tree.map(lambda x: x[s], rs.learners["vae_rpl"].params)
        direct = learner.encode(params, frames[s * N:(s + 1) * N])
        np.testing.assert_allclose(np.asarray(obs[s]), np.asarray(direct), rtol=1e-5, atol=1e-5)
    # the two seeds' learners differ, so their latents differ
    assert not np.allclose(np.asarray(obs[0]), np.asarray(obs[1]))
    # the policy's rollouts keep the frames it rendered for replay and windows: those of each step
    (es, _), stored = jax.jit(lambda k: exp.policy.rollout(rs.ppo, rs.train_env, k, 3, False, rs.learners))(
        jax.random.PRNGKey(2))
    assert isinstance(stored[0], Rendered) and stored[0].frames.shape == (3,) + frames.shape
    np.testing.assert_array_equal(np.asarray(stored[0].frames[-1]),
                                  np.asarray(exp.env.render_frames(es.render_input)))
    # two epochs of the run loop on this experiment: PPO trains on the latents
    out = tmp_path / "run"
    run(cfg, RunOptions(), str(out), experiment=exp, progress=False, log=lambda m: None)
    recs = [json.loads(x) for x in open(out / "metrics.jsonl")]
    assert sorted({r["epoch"] for r in recs}) == [0, 1] and len(recs) == 2 * S
    for r in recs:
        assert r["rl_episodes"] > 0 and np.isfinite(r["rl_return"])
    with open(out / "config.json") as f:
        assert "latent:vae_rpl" in f.read()


def test_cli_flag_reaches_the_config(capsys) -> None:
    from bulbjax.cli import main

    # a learner the run does not train is refused with the config's message: the flag got there
    assert main(["run", "--env", "CartPole", "--learners", "vae_rpl,dsa", "--small", "--epochs", "1",
                 "--rl-input", "latent:svae", "--out", "/tmp/never"]) == 2
    assert "does not train" in capsys.readouterr().err


@pytest.mark.slow  # the slow tier (tests/conftest.py)
def test_pixels_policy_sees_the_frame_and_trains_its_torso() -> None:
    import dataclasses

    cfg = small_config(ExperimentConfig(env="CartPole", learners=("vae",), seeds=2, epochs=1,
                                        rl_input="pixels"))
    # one short PPO update: conv gradients inside XLA:CPU loops run ~5-15x slower than unrolled
    cfg = cfg.replace(ppo=dataclasses.replace(cfg.ppo, num_steps=8, update_epochs=1, num_minibatches=2),
                      ppo_updates_per_epoch=1, frames_per_epoch=64)
    exp = Experiment(cfg)
    assert exp.ppo.pixels and exp.ppo.frame_shape == exp.env.frame_shape
    rs = exp.init(jax.random.PRNGKey(0))
    obs = jax.jit(exp.policy.obs)(rs.train_env, rs.learners)
    S, N = cfg.seeds, cfg.num_envs
    assert obs.shape == (S, N) + exp.env.frame_shape and obs.dtype == np.uint8
    frames = np.asarray(exp.env.render_frames(rs.train_env.render_input))
    np.testing.assert_array_equal(np.asarray(obs).reshape(frames.shape), frames)
    ppo, _, m, _, _, _, _ = jax.jit(exp.policy.rl_phase)(rs.ppo, rs.train_env, jax.random.PRNGKey(1), rs.learners)
    conv0 = lambda p: p.params["params"]["PixelTorso_0"]["Conv_0"]["kernel"]
    assert np.all(np.isfinite(np.asarray(m["total_loss"])))
    for s in range(S):  # every seed's conv torso moved under the PPO loss
        assert not np.allclose(np.asarray(conv0(rs.ppo)[s]), np.asarray(conv0(ppo)[s]))


@pytest.mark.parametrize("value, match", [("latent:dsa", "does not train"), ("latent:beta_vae", "does not train"),
                                          ("pixel", "latent:<learner>")])
def test_bad_rl_input(value: str, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ExperimentConfig(learners=("vae_rpl",), rl_input=value)
    # sequential learners' latents are accepted (tests/test_rl_sequential.py)
    assert ExperimentConfig(learners=("vae_rpl", "dsa"), rl_input="latent:dsa").rl_learner == "dsa"


def test_rl_compare_plot_and_epochs_to_solve(tmp_path) -> None:
    """`bulbjax report --compare-rl`: one curve per run labelled by what PPO observed, and the
    first epoch each seed reached the solved return (computed from the records, never-reached
    seeds said so)."""
    import dataclasses

    from bulbjax.cli import main
    from bulbjax.report import records

    ep = np.arange(5)
    np.testing.assert_equal(records.epochs_to_reach(np.array([[1., 5, 9, 9, 9], [1., 2, 3, np.nan, 4]]), ep, 8.0),
                            [2, None])
    runs = []
    for kind, seed_returns in (("state", [[100, 960, 1000], [200, 500, 990]]),
                               ("latent:vae_rpl", [[50, 60, 70], [40, 955, 30]])):
        d = tmp_path / kind.replace(":", "_")
        d.mkdir()
        cfg = ExperimentConfig(env="InvertedPendulum", learners=("vae_rpl",), seeds=2, rl_input=kind)
        with open(d / "config.json", "w") as f:
            json.dump({"experiment": dataclasses.asdict(cfg)}, f)
        recs = [{"epoch": e, "seed": s, "rl_return": float(v)}
                for s, row in enumerate(seed_returns) for e, v in enumerate(row)]
        records.write_jsonl(str(d / "metrics.jsonl"), recs)
        runs.append(str(d))
    assert main(["report", "--compare-rl", *runs, "--out", str(tmp_path / "cmp")]) == 0
    md = (tmp_path / "cmp" / "rl_compare.md").read_text()
    assert (tmp_path / "cmp" / "rl_compare.png").stat().st_size > 1000
    state_row = next(l for l in md.splitlines() if l.startswith("| state |"))
    latent_row = next(l for l in md.splitlines() if "latent:vae_rpl" in l)
    assert "| 1, 2 |" in state_row and "995.0" in state_row  # InvertedPendulum solved at 950
    assert "| never, 1 |" in latent_row
    assert main(["report", *runs]) == 2  # two runs without --compare-rl: a clear error
