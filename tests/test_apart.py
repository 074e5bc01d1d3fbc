"""The learners apart (`ExperimentConfig.overlap="apart"`): the pipelined epoch as programs on two
devices gives the plain epoch's numbers, and its state lies on the side that owns each part. The
CPU shows as two devices only in a process started so (`XLA_FLAGS`), hence a subprocess."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCRIPT = textwrap.dedent("""
    import dataclasses, json, sys
    import jax, numpy as np
    from bulbjax.epoch import Experiment, Programs
    from bulbjax.eval.probe import ProbeConfig
    from bulbjax.config import ExperimentConfig
    from bulbjax.learners import LearnerConfig
    from bulbjax.rl.ppo import PPOConfig

    cfg = ExperimentConfig(
        env="CartPole", learners=("vae", "pred"), seeds=1, epochs=3, num_envs=4, resolution=32,
        ppo=PPOConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1), ppo_updates_per_epoch=1,
        frames_per_epoch=8, replay_capacity=32, sequence_length=4,
        learner=LearnerConfig(batch_size=8, conv_features=(8, 8, 8, 8), hidden=16, lr=1e-3, pred_horizon=2),
        learner_batches=1, eval_frames=8, probe_train_frames=16,
        probe=ProbeConfig(hidden=(16,), steps=20, batch_size=16), reference_steps=16,
        probe_variants=("common",))
    devs = jax.devices()
    assert len(devs) == 2, devs

    def run(c, devices, timed_last=False):
        exp = Experiment(c, devices=devices)
        progs = Programs(exp, (True, False))
        rs = progs.init(jax.random.PRNGKey(0))
        keys = jax.random.split(jax.random.PRNGKey(1), 4)
        if exp.pipelined:
            rs = progs.prime(rs, keys[0])
        out = []
        for t, probe in enumerate((True, False, True)):
            k = keys[t + 1] if exp.pipelined else keys[t]
            if timed_last and t == 2:  # the programs one after another, each timed (profile_epoch.py)
                exp.apart.timings = {}
            rs, m = progs.epoch(rs, k, probe=probe)
            out.append(jax.device_get(m))
        if timed_last:
            run.timings = {n: len(v) for n, v in exp.apart.timings.items()}
        where = {f: sorted({d.id for leaf in jax.tree.leaves(getattr(rs, f)) for d in leaf.devices()})
                 for f in ("ppo", "train_env", "learners", "buffers", "windows", "pending")}
        where.update({f"learners.{n}": sorted({d.id for leaf in jax.tree.leaves(s) for d in leaf.devices()})
                      for n, s in rs.learners.items()})
        return exp, out, jax.device_get(rs.learners), where

    _, plain, plain_learners, plain_where = run(cfg, devs[:1])
    exp, apart, apart_learners, where = run(dataclasses.replace(cfg, overlap="apart", apart_env_learners="none"), devs)
    # pred updated on the environment's device, on copies of its window buffer kept there
    _, near, near_learners, near_where = run(dataclasses.replace(cfg, overlap="apart", apart_env_learners="pred"), devs,
                                             timed_last=True)

    def diff(a, b):
        return max((float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)))) if np.size(x) else 0.0)
                   for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))

    res = {"structure": [jax.tree.structure(a) == jax.tree.structure(p) for a, p in zip(apart, plain)],
           "metrics": [diff(a, p) for a, p in zip(apart, plain)],
           "learners": diff(apart_learners, plain_learners), "where": where, "plain_where": plain_where,
           "near_structure": [jax.tree.structure(a) == jax.tree.structure(p) for a, p in zip(near, plain)],
           "near_metrics": [diff(a, p) for a, p in zip(near, plain)],
           "near_learners": diff(near_learners, plain_learners), "near_where": near_where,
           "near_timed": run.timings,
           "nan_probes": [bool(np.all(np.isnan(m["probes"]["vae"]["curr"]["mae"]))) if "probes" in m else None
                          for m in apart]}
    print("RESULT " + json.dumps(res))
""")


def test_the_learners_apart_give_the_plain_epochs(tmp_path):
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu",
               BULBJAX_COMPILE_CACHE="off")
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(next(line for line in proc.stdout.splitlines() if line.startswith("RESULT "))[7:])
    # three epochs (probing, not, probing): the plain epochs' metrics, the same learners after them
    assert all(res["structure"]), res
    assert res["nan_probes"] == [False, None, False], res  # probes only where probing, and real ones
    assert max(res["metrics"]) <= 1e-4 and res["learners"] <= 1e-5, res
    # each side's state on its own device: the environment's on the first, the learners' on the second
    env_dev, learner_dev = 0, 1
    assert res["where"]["ppo"] == res["where"]["train_env"] == [env_dev], res["where"]
    assert res["where"]["learners"] == res["where"]["buffers"] == res["where"]["windows"] == [learner_dev], res["where"]
    assert res["where"]["pending"] == [learner_dev]
    assert res["plain_where"]["learners"] == [env_dev]  # the plain run: one device for all
    # pred on the environment's side (--apart-env-learners pred): the same numbers, pred's state there,
    # and its third epoch, each program run alone and timed, the same numbers too
    assert res["near_timed"] == {"env": 1, "near": 1, "learn": 1, "finish": 1}, res["near_timed"]
    assert all(res["near_structure"]), res
    assert max(res["near_metrics"]) <= 1e-4 and res["near_learners"] <= 1e-5, res
    near = res["near_where"]
    assert near["learners.pred"] == [env_dev] and near["learners.vae"] == [learner_dev], near
    assert near["windows"] == near["buffers"] == [learner_dev], near  # the copies are not in the state


@pytest.mark.slow
def test_a_run_with_the_learners_apart_resumes(tmp_path):
    """`bulbjax run --overlap apart` as a user runs it (two devices shown to JAX on the CPU; pred
    on the environment's device): it says where the learners are, checkpoints the state of both
    devices, resumes from it (pred's buffer copied there again) and writes every epoch's records
    once; with one device it is one line that says what to do."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu",
               BULBJAX_COMPILE_CACHE="off")
    out = str(tmp_path / "run")
    base = [sys.executable, "-m", "bulbjax", "run"]
    first = subprocess.run([*base, "--env", "CartPole", "--learners", "vae,pred", "--seeds", "1", "--epochs", "2",
                            "--small", "--overlap", "apart", "--apart-env-learners", "pred", "--probe-every", "1",
                            "--out", out],
                           cwd=ROOT, env=env, capture_output=True, text=True, timeout=1200)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "1 for the learners (--overlap apart)" in first.stdout
    again = subprocess.run([*base, "--resume", out, "--epochs", "3"], cwd=ROOT, env=env, capture_output=True,
                           text=True, timeout=1200)
    assert again.returncode == 0, again.stderr[-3000:]
    with open(os.path.join(out, "metrics.jsonl")) as f:
        records = [json.loads(line) for line in f if line.strip()]
    assert [r["epoch"] for r in records] == [0, 1, 2] and all(r["probes"] for r in records)
    one = dict(env, XLA_FLAGS="")
    refused = subprocess.run([*base, "--env", "CartPole", "--learners", "vae", "--small", "--overlap", "apart",
                              "--epochs", "1", "--out", str(tmp_path / "one")], cwd=ROOT, env=one,
                             capture_output=True, text=True, timeout=600)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines()[-1].startswith("bulbjax: error: --overlap apart puts the learners")


def test_which_learners_run_on_the_environments_device():
    """`apart_env_learners`: auto by default, which takes pred where it is a unit of its own beside
    three others (a locomotion preset's), a VAE group moves whole or not at all, and a name the
    run does not have is one line that says what to give."""
    from bulbjax.config import ExperimentConfig
    from bulbjax.epoch.apart import near_units

    assert ExperimentConfig(env="CartPole").apart_env_learners == "auto"  # and refused by nothing
    fig2 = [("vae", "vae_rpl", "beta_vae"), ("svae",), ("pred",), ("dsa",)]
    assert near_units(fig2, "auto") == [("pred",)]
    assert near_units([("vae",), ("pred",)], "auto") == [] and near_units(fig2, "none") == []
    assert near_units(fig2, "svae,pred") == [("svae",), ("pred",)]
    assert near_units(fig2, "vae,vae_rpl,beta_vae") == [fig2[0]]
    with pytest.raises(ValueError, match="vae, vae_rpl, beta_vae share one update program"):
        near_units(fig2, "vae")
    with pytest.raises(ValueError, match="give auto, none or learners of this run"):
        ExperimentConfig(env="CartPole", learners=("vae", "pred"), apart_env_learners="dsa", overlap="apart")
    with pytest.raises(ValueError, match="give --overlap apart too"):
        ExperimentConfig(env="CartPole", learners=("vae", "pred"), apart_env_learners="pred")
