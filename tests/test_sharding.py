"""Several devices: the seed axis and the world axis sharded over a mesh give the results of one
device. XLA's host platform is split into 4 CPU devices in a subprocess (the flag must be set
before JAX starts); the same tiny experiment (2 seeds) runs on 1 device and on 4 (mesh 2 x 2: one
seed per row of devices, each seed's worlds split over two devices), which exercises both axes
in one compile (the 2 x 1 mesh of 2 devices, seeds only, gave bit-identical buffers and learner
losses after one epoch when checked by hand).

Equal within float tolerance, not bit for bit: the simulators' worlds, their frames, the replay
contents and PPO's first epoch returns are bit-identical, but XLA:CPU compiles the vmapped learner
and PPO updates for one seed per device instead of two, and reductions over worlds split across
devices (e.g. the held-out states' spread) sum in another order (relative differences ~1e-7 after
one epoch), and such differences grow through training.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import dataclasses, json, sys
    import jax, numpy as np
    from bulbjax.epoch import Experiment, ExperimentConfig
    from bulbjax.eval.probe import ProbeConfig
    from bulbjax.learners import LearnerConfig
    from bulbjax.rl.ppo import PPOConfig

    cfg = ExperimentConfig(
        env="CartPole", learners=("vae_rpl", "svae"), seeds=2, epochs=1, num_envs=4, resolution=32,
        ppo=PPOConfig(num_envs=4, num_steps=8, num_minibatches=2, update_epochs=1),
        ppo_updates_per_epoch=1, frames_per_epoch=8, replay_capacity=32, sequence_length=4,
        learner=LearnerConfig(batch_size=8, conv_features=(8, 8, 8, 8), hidden=16, lr=1e-3),
        learner_batches=1, eval_frames=8, probe_train_frames=16,
        probe=ProbeConfig(hidden=(16,), steps=20, batch_size=16), reference_steps=16)
    out = {}
    for n in (1, 4):
        exp = Experiment(cfg, devices=jax.devices()[:n])
        rs0 = exp.init(exp.put_key(jax.random.PRNGKey(0)))
        init = jax.device_get({"buffers": rs0.buffers, "windows": rs0.windows,
                               "obs": rs0.train_env.obs, "ref": rs0.ref_spread})
        rs, m = exp.epoch(rs0, exp.put_key(jax.random.PRNGKey(1)))
        shard = rs.learners["vae_rpl"].params
        out[n] = {"mesh": dict(exp.mesh.shape), "local_worlds": exp.env.num_envs,
                  "param_devices": len(jax.tree.leaves(shard)[0].sharding.device_set),
                  "init": [np.asarray(x).tolist() for x in jax.tree.leaves(init)],
                  "metrics": jax.tree.map(lambda x: np.asarray(x, np.float64).tolist(), jax.device_get(m)),
                  "frames": np.asarray(rs.buffers["retain_0.5"].frames).tolist()}
    json.dump(out, sys.stdout)
""")


def test_sharded_equals_single_device():
    import numpy as np
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4", "JAX_PLATFORMS": "cpu"}
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=1500)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    one, four = out["1"], out["4"]
    assert one["mesh"] == {"seeds": 1, "worlds": 1} and one["local_worlds"] == 8
    assert four["mesh"] == {"seeds": 2, "worlds": 2} and four["local_worlds"] == 2
    assert four["param_devices"] == 4  # per-seed parameters: split over seeds, copied over worlds
    other = four
    # simulators, frames and buffers: bit for bit
    assert len(one["init"]) == len(other["init"]) > 4
    for a, b in zip(one["init"], other["init"]):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(one["frames"]), np.asarray(other["frames"]))
    m1, m2 = one["metrics"], other["metrics"]
    np.testing.assert_array_equal(m1["rl_return"], m2["rl_return"])
    for name in ("vae_rpl", "svae"):
        np.testing.assert_allclose(m1["learners"][name]["loss"], m2["learners"][name]["loss"], rtol=1e-4)
        for stream in ("curr", "rand"):
            p1, p2 = m1["probes"][name][stream], m2["probes"][name][stream]
            # same held-out states; their spread is a mean over worlds split across devices
            np.testing.assert_allclose(p1["spread"], p2["spread"], rtol=1e-5)
            np.testing.assert_allclose(p1["mae"], p2["mae"], rtol=0.05, atol=1e-3)
