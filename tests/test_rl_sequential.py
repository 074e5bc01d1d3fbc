"""PPO from a sequential learner's latent (`rl_input="latent:<svae|pred|dsa>"`, issue 15): the
latent PPO sees at a step is the learner's `encode` of the window of the last L steps ending at
that step, cut at the episode's start as training windows are cut (checked against a direct
`encode` call, right after episode resets too); the worlds' windows (`PolicyHistory`) are run
state, so a two-epoch run works and resumes bit for bit. DSA: its bidirectional encoders make
each step's latent depend on the whole window, padding included, the strictest layout check
(SVAE and PRED share the code path: tests/test_sequential_learners.py checks `encode_features`
for all three)."""

from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.data import sequence
from bulbjax.epoch import Experiment, ExperimentConfig
from bulbjax.epoch.rollouts.policy import push_window
from bulbjax.epoch.programs import Programs
from bulbjax.eval.probe import ProbeConfig
from bulbjax.learners import LearnerConfig
from bulbjax.rl.ppo import PPOConfig

L = 4


def tiny(learner: str) -> ExperimentConfig:
    return ExperimentConfig(
        env="CartPole", learners=(learner,), seeds=2, epochs=2, num_envs=4, resolution=32,
        ppo=PPOConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1),
        ppo_updates_per_epoch=1, frames_per_epoch=8, replay_capacity=32, sequence_length=L,
        learner=LearnerConfig(batch_size=8, conv_features=(8, 8, 8, 8), hidden=16, lr=1e-3),
        learner_batches=1, eval_frames=8, probe_train_frames=16,
        probe=ProbeConfig(hidden=(16,), steps=20, batch_size=16), reference_steps=16,
        rl_input=f"latent:{learner}")


def test_push_window_layout() -> None:
    """Steps held first, then padding (the newest repeated, or zeros); full windows slide; a
    fresh episode restarts the window at its first step."""
    x = jnp.array([[[1, 2, 2, 2], [1, 2, 3, 4], [1, 2, 3, 4]]])  # [S=1, N=3, L=4]
    count = jnp.array([[2, 4, 4]])
    fresh = jnp.array([[False, False, True]])
    new = jnp.array([[7, 7, 7]])
    np.testing.assert_array_equal(push_window(x, new, count, fresh, True),
                                  [[[1, 2, 7, 7], [2, 3, 4, 7], [7, 7, 7, 7]]])
    np.testing.assert_array_equal(push_window(x, new, count, fresh, False),
                                  [[[1, 2, 7, 0], [2, 3, 4, 7], [7, 0, 0, 0]]])


@pytest.fixture(scope="module")
def exp() -> Experiment:
    return Experiment(tiny("dsa"))  # one compile of init serves both tests below


def test_latent_is_encode_of_the_window_ending_at_the_step(exp: Experiment) -> None:
    """DSA (its bidirectional encoders see the whole window, padding included, so the layout
    must match a training window exactly): 30 policy steps of 8 worlds, each step's latent
    against `encode` on the window built from the same frames and actions by
    `sequence.cut_windows` (the training windows' cutting), the episode's end put right after
    the step."""
    cfg = exp.config
    learner = exp.learners["dsa"]
    assert exp.policy.rl_sequential and exp.ppo.obs_size == learner.latent_dim
    rs = Programs.of(exp, (True,)).init(jax.random.PRNGKey(0))  # the init the run below reuses (one compile)
    S, N, T = cfg.seeds, cfg.num_envs, 30
    step = jax.jit(lambda es, w, k: exp.policy.step(rs.ppo, es, k, False, rs.learners, w))
    window = jax.jit(exp.policy.window)(rs.learners, rs.policy_history["train"])
    es = rs.train_env
    render = jax.jit(exp.env.render_frames)
    frames = [np.asarray(render(es.render_input))]  # frame t, [S*N, H, W, 3]
    actions = [np.zeros((S * N, exp.action_dim), np.float32)]  # the action into frame t
    starts = [np.ones(S * N, bool)]  # frame t is an episode's first
    obs, counts = [], []
    for k in jax.random.split(jax.random.PRNGKey(1), T):
        counts.append(np.asarray(window.history.count).reshape(-1))
        es, o, action, _, _, window, _ = step(es, window, k)
        obs.append(np.asarray(o).reshape(S * N, -1))
        frames.append(np.asarray(render(es.render_input)))
        actions.append(np.asarray(exp.policy.action_features(action)))
        starts.append(np.asarray(es.done) > 0)
    frames, actions, starts = np.stack(frames[:T]), np.stack(actions[:T]), np.stack(starts[:T])
    resets = [(t, n) for t in range(1, T) for n in range(S * N) if starts[t, n]]
    assert resets, "no episode ended in the test's steps: nothing checked right after a reset"
    # frames padded at the end so that every window start is in range (cut_windows clamps starts)
    pad = lambda x: np.concatenate([x, np.repeat(x[-1:], L, 0)])  # noqa: E731
    cut = jax.jit(sequence.cut_windows, static_argnums=5)
    encode = jax.jit(jax.vmap(learner.encode))  # every seed's windows with its own params
    checked = {"short": 0, "full": 0, "after_reset": 0}
    for t in range(T):
        ep_start = np.array([max(j for j in range(t + 1) if starts[j, n]) for n in range(S * N)])
        start = np.maximum(ep_start, t - L + 1)
        dones = np.zeros((T + L, S * N), np.float32)
        dones[t + 1:] = 1  # a training window whose episode ends at t
        dones[:T][starts] = 1
        dones[0] = 0
        w = cut(jnp.asarray(pad(frames)), jnp.zeros((T + L, S * N, 1)), jnp.asarray(pad(actions)),
                jnp.asarray(dones), jnp.asarray(start), L)
        k = t - start + 1  # steps held; the current step is k - 1
        np.testing.assert_array_equal(counts[t], k)
        np.testing.assert_array_equal(np.asarray(w.valid).sum(1), k)
        z = np.asarray(encode(rs.learners["dsa"].params, jax.tree.map(lambda x: x.reshape((S, N) + x.shape[1:]), w)))
        direct = z.reshape((S * N,) + z.shape[2:])[np.arange(S * N), k - 1]  # [S*N, Z]
        np.testing.assert_allclose(obs[t], direct, rtol=1e-4, atol=1e-5, err_msg=f"step {t}")
        checked["short"] += int((k < L).sum())
        checked["full"] += int((k == L).sum())
        checked["after_reset"] += sum(1 for (tt, n) in resets if tt == t)
    assert all(v > 0 for v in checked.values()), checked
    # the seeds' learners differ, so their latents do
    assert not np.allclose(obs[0][:N], obs[0][N:])


def _lines(d: str) -> list[str]:
    with open(os.path.join(d, "metrics.jsonl")) as f:
        return f.read().splitlines()


def test_two_epochs_and_exact_resume(exp: Experiment, tmp_path) -> None:
    """Two epochs of the run loop with PPO on DSA's latent: finite metrics, the worlds' windows
    in the checkpoint, the same records after a stop and a resume."""
    from bulbjax.config import RunOptions
    from bulbjax.run import run
    from bulbjax.run.checkpoint import Checkpointer

    d0 = str(tmp_path / "straight")
    run(exp.config, RunOptions(checkpoint_every=1), d0, experiment=exp, progress=False, log=lambda s: None)
    recs = [json.loads(x) for x in _lines(d0)]
    assert sorted({r["epoch"] for r in recs}) == [0, 1] and len(recs) == 2 * exp.config.seeds
    for r in recs:
        assert np.all(np.isfinite(list(r["ppo"].values()))), r["ppo"]
        assert np.isfinite(r["rl_return"]) or r["rl_episodes"] == 0
    # the worlds' windows are in the checkpoint
    ck = Checkpointer(d0)
    state, _, _ = ck.restore({"run": exp.abstract_state(), "key": exp.abstract_key()})
    ck.close()
    hist = state["run"].policy_history
    assert set(hist) == {"train", "curr"} and hist["train"].frames.shape[:3] == (2, 4, L)
    assert np.asarray(hist["train"].frames).any() and 1 <= int(hist["train"].count.min())
    # the figures' held-out rollout goes on from the current-policy worlds' windows
    from bulbjax.run.recon import RunFigures
    w = RunFigures(exp).held_out(state["run"], 2)
    assert w.frames.shape[1] == L and w.valid[:, 0].all()
    # stopped after one epoch and resumed: the same records, bit for bit
    d = str(tmp_path / "resumed")
    run(exp.config, RunOptions(stop_after=1), d, experiment=exp, progress=False, log=lambda s: None)
    run(exp.config, RunOptions(), d, resume=True, experiment=exp, progress=False, log=lambda s: None)
    assert _lines(d) == _lines(d0)
