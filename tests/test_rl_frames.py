"""PPO observing the last K frames (`rl_frames`, issue 41): with a frame learner's latent, the
latents of the last K frames of the world's episode concatenated oldest first, the episode's
first frame repeated until K are held; with pixels, the frames stacked along the channels.
Why: one frame holds positions, not velocities (docs/ppo.md, "From a latent or pixels")."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from bulbjax.epoch import ExperimentConfig, small_config
from bulbjax.epoch.loop import Experiment
from bulbjax.epoch.state import PolicyHistory


def _config(rl_input: str, learner: str = "vae_rpl") -> ExperimentConfig:
    cfg = small_config(ExperimentConfig(env="CartPole", learners=(learner,), seeds=2, epochs=1,
                                        rl_input=rl_input, rl_frames=2))
    return cfg.replace(num_envs=8, ppo=dataclasses.replace(cfg.ppo, num_envs=8, num_steps=8, update_epochs=1,
                                                           num_minibatches=2),
                       ppo_updates_per_epoch=1, frames_per_epoch=64, replay_capacity=256)


@pytest.mark.parametrize("kw, match", [
    (dict(rl_frames=0), "rl_frames must be >= 1"),
    (dict(rl_frames=2), "stacks frames"),  # the state
    (dict(rl_frames=2, learners=("vae_rpl", "dsa"), rl_input="latent:dsa"), "sequential learner"),
])
def test_bad_rl_frames(kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ExperimentConfig(**{"learners": ("vae_rpl",), **kw})
    assert ExperimentConfig(learners=("vae_rpl",), rl_input="pixels", rl_frames=3).rl_frames == 3
    # ST-DIM trains on windows but its latent is one frame's: its latents can be stacked
    assert ExperimentConfig(learners=("stdim",), rl_input="latent:stdim", rl_frames=2).rl_frames == 2


def test_cli_flag_reaches_the_config(capsys) -> None:
    from bulbjax.cli import main

    assert main(["run", "--env", "CartPole", "--learners", "vae_rpl", "--small", "--epochs", "1",
                 "--rl-frames", "2", "--out", "/tmp/never"]) == 2
    assert "stacks frames" in capsys.readouterr().err


# stdim in the slow tier: make test runs ST-DIM's latent into PPO in test_contrastive's epoch
@pytest.mark.parametrize("name", ["vae_rpl", pytest.param("stdim", marks=pytest.mark.slow)])
def test_latents_of_the_last_two_frames(name: str) -> None:
    """A frame learner's latents (`encode`), or ST-DIM's, which trains on windows but encodes each
    frame alone (`frame_features`), of the previous and the current frame, step by step."""
    exp = Experiment(_config(f"latent:{name}", name))
    policy, learner = exp.policy, exp.learners[name]
    z = learner.latent_dim
    assert policy.keeps_history and not policy.rl_sequential and exp.ppo.obs_size == 2 * z
    rs = exp.init(jax.random.PRNGKey(0))
    hist = rs.policy_history["train"]
    S, N = exp.S, exp.N
    assert isinstance(hist, PolicyHistory) and hist.frames.shape[:3] == (S, N, 2)
    encode = learner.frame_features if name == "stdim" else learner.encode
    enc = lambda s, frames: np.asarray(encode(jax.tree.map(lambda x: x[s], rs.learners[name].params),  # noqa: E731
                                              frames))

    def frames_of(es):
        return np.asarray(exp.env.render_frames(es.render_input)).reshape((S, N) + exp.env.frame_shape)

    obs0 = np.asarray(jax.jit(policy.obs)(rs.train_env, rs.learners, hist))
    f0 = frames_of(rs.train_env)
    assert obs0.shape == (S, N, 2 * z)
    for s in range(S):  # a fresh episode: its first frame twice
        np.testing.assert_allclose(obs0[s, :, :z], enc(s, f0[s]), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(obs0[s, :, z:], enc(s, f0[s]), rtol=1e-5, atol=1e-5)
    step = jax.jit(lambda es, k, view: policy.step(rs.ppo, es, k, False, rs.learners, view))
    es, view = rs.train_env, hist
    ended = np.zeros((S, N), bool)
    for i in range(12):  # until some world has ended an episode (CartPole under a fresh policy)
        prev = frames_of(es)
        es, *_, view, _ = step(es, jax.random.PRNGKey(10 + i), view)
        done = np.asarray(es.done).reshape(S, N) > 0
        ended |= done
        cur = frames_of(es)
        obs = np.asarray(jax.jit(policy.obs)(es, rs.learners, view))
        for s in range(S):
            older = np.where(done[s][:, None, None, None], cur[s], prev[s])  # a new episode: its first frame twice
            np.testing.assert_allclose(obs[s, :, :z], enc(s, older), rtol=1e-5, atol=1e-5)
            np.testing.assert_allclose(obs[s, :, z:], enc(s, cur[s]), rtol=1e-5, atol=1e-5)
        if ended.any() and i >= 2:
            break
    assert ended.any() and not ended.all()
    # an epoch's PPO phase on the stacked latents: finite losses, the history handed on
    out = jax.jit(policy.rl_phase)(rs.ppo, rs.train_env, jax.random.PRNGKey(1), rs.learners, hist)
    assert np.all(np.isfinite(np.asarray(out[2]["total_loss"])))
    assert isinstance(out[-1], PolicyHistory) and out[-1].frames.shape == hist.frames.shape


def test_pixels_stack_along_the_channels() -> None:
    exp = Experiment(_config("pixels"))
    h, w, c = exp.env.frame_shape
    assert exp.ppo.pixels and exp.ppo.frame_shape == (h, w, 2 * c)
    rs = exp.init(jax.random.PRNGKey(0))
    hist = rs.policy_history["train"]
    # a history holding two different frames: the previous (slot 0) and the current (slot 1)
    frames = np.array(hist.frames)
    frames[:, :, 0] = 255 - frames[:, :, 1]
    two = hist.replace(frames=frames, count=np.full(hist.count.shape, 2, np.int32))
    obs = np.asarray(jax.jit(exp.policy.obs)(rs.train_env, rs.learners, two))
    assert obs.shape == (exp.S, exp.N, h, w, 2 * c) and obs.dtype == np.uint8
    np.testing.assert_array_equal(obs[..., :c], frames[:, :, 0])  # oldest first
    np.testing.assert_array_equal(obs[..., c:], frames[:, :, 1])


def test_compare_names_the_frames(tmp_path) -> None:
    """`bulbjax report --compare-rl` says how many frames PPO observed."""
    import json

    from bulbjax.report import records
    from bulbjax.report.report import rl_compare

    runs = []
    for k in (1, 2):
        d = tmp_path / f"k{k}"
        d.mkdir()
        cfg = ExperimentConfig(env="InvertedPendulum", learners=("vae_rpl",), seeds=1, rl_input="latent:vae_rpl",
                               rl_frames=k)
        (d / "config.json").write_text(json.dumps({"experiment": dataclasses.asdict(cfg)}))
        records.write_jsonl(str(d / "metrics.jsonl"), [{"epoch": e, "seed": 0, "rl_return": 100.0 * e} for e in range(3)])
        runs.append(str(d))
    rows = rl_compare(runs, str(tmp_path / "cmp")).splitlines()
    assert any(r.startswith("| k1 | latent:vae_rpl |") for r in rows)
    assert any(r.startswith("| k2 | latent:vae_rpl, last 2 frames |") for r in rows)


def test_two_epochs_resume_with_the_frames_in_the_checkpoint(tmp_path) -> None:
    """The worlds' last frames are run state: in the checkpoint, and a run stopped after one epoch
    and resumed writes the same records as one run straight through, bit for bit."""
    import json

    from bulbjax.config import RunOptions
    from bulbjax.eval.probe import ProbeConfig
    from bulbjax.learners import LearnerConfig
    from bulbjax.rl.ppo import PPOConfig
    from bulbjax.run import run
    from bulbjax.run.checkpoint import Checkpointer

    cfg = ExperimentConfig(
        env="CartPole", learners=("vae_rpl",), seeds=2, epochs=2, num_envs=4, resolution=32,
        ppo=PPOConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1),
        ppo_updates_per_epoch=1, frames_per_epoch=8, replay_capacity=32,
        learner=LearnerConfig(batch_size=8, conv_features=(8, 8, 8, 8), hidden=16, lr=1e-3),
        learner_batches=1, eval_frames=8, probe_train_frames=16,
        probe=ProbeConfig(hidden=(16,), steps=20, batch_size=16), reference_steps=16,
        rl_input="latent:vae_rpl", rl_frames=2)
    exp = Experiment(cfg)
    lines = lambda d: (tmp_path / d / "metrics.jsonl").read_text().splitlines()  # noqa: E731
    run(cfg, RunOptions(checkpoint_every=1), str(tmp_path / "straight"), experiment=exp, progress=False,
        log=lambda s: None)
    recs = [json.loads(x) for x in lines("straight")]
    assert sorted({r["epoch"] for r in recs}) == [0, 1] and all(np.isfinite(list(r["ppo"].values())).all() for r in recs)
    ck = Checkpointer(str(tmp_path / "straight"))
    state, _, _ = ck.restore({"run": exp.abstract_state(), "key": exp.abstract_key()})
    ck.close()
    hist = state["run"].policy_history
    assert set(hist) == {"train", "curr"} and hist["train"].frames.shape[:3] == (2, 4, 2)
    assert 1 <= int(np.min(hist["train"].count)) and int(np.max(hist["train"].count)) <= 2
    run(cfg, RunOptions(stop_after=1), str(tmp_path / "resumed"), experiment=exp, progress=False, log=lambda s: None)
    run(cfg, RunOptions(), str(tmp_path / "resumed"), resume=True, experiment=exp, progress=False, log=lambda s: None)
    assert lines("resumed") == lines("straight")
