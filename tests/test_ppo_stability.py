"""PPO's stability options (issue 42): the lr anneal's values and its effect on the step, the
log-std floor, the observation-normaliser freeze, the KL early stop, options at inert values
computing what the defaults compute bit for bit, the presets' settings, and
benchmarks/ppo_stability.py end to end at CPU size."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bulbjax.rl import PPO, PPOConfig, Transition, lr_factor, mean_log_std

HERE = os.path.dirname(os.path.abspath(__file__))
CFG = PPOConfig(num_envs=8, num_steps=4, num_minibatches=2, update_epochs=2)


def _traj(ppo: PPO, state, key, obs_loc: float = 1.0, quadratic_reward: bool = False):
    """A rollout [T=4, N=8] of the policy at random observations around `obs_loc`; the reward
    is random, or -|a|^2 (rewards a narrower policy: pushes the log-std down)."""
    k1, k2, k3 = jax.random.split(key, 3)
    obs = obs_loc + 2.0 * jax.random.normal(k1, (4, 8, 5))
    action, logp, value = jax.vmap(ppo.act, (None, 0, 0))(state, obs, jax.random.split(k2, 4))
    if quadratic_reward:
        reward = -jnp.sum(jnp.atleast_3d(action) ** 2, -1) * 10.0
    else:
        reward = jax.random.normal(k3, (4, 8))
    z = jnp.zeros((4, 8))
    return Transition(obs, action, reward, z, z, logp, value), obs[-1]


def _run(cfg: PPOConfig, updates: int, discrete: bool = False, quadratic_reward: bool = False, state=None):
    ppo = PPO(cfg, obs_size=5, num_actions=2 if discrete else None, action_size=1)
    s = ppo.init(jax.random.PRNGKey(0)) if state is None else state
    upd = jax.jit(ppo.update)
    roll = jax.jit(lambda s, k, loc: _traj(ppo, s, k, loc, quadratic_reward))
    states, metrics = [s], []
    for i in range(updates):
        traj, last = roll(s, jax.random.PRNGKey(10 + i), 1.0 + i)
        s, m = upd(s, traj, last, jax.random.PRNGKey(100 + i))
        states.append(s)
        metrics.append(m)
    return ppo, states, metrics


def test_lr_factor_values():
    lin = PPOConfig(anneal_updates=2000, lr_floor=0.1)
    cos = dataclasses.replace(lin, lr_schedule="cosine")
    for u, want in ((0, 1.0), (500, 0.775), (1000, 0.55), (2000, 0.1), (5000, 0.1)):
        assert float(lr_factor(lin, u)) == pytest.approx(want, abs=1e-6)
    for u, want in ((0, 1.0), (500, 0.1 + 0.45 * (1 + math.cos(math.pi / 4))), (1000, 0.55), (2000, 0.1), (3000, 0.1)):
        assert float(lr_factor(cos, u)) == pytest.approx(want, abs=1e-6)
    assert float(lr_factor(PPOConfig(), 10_000)) == 1.0  # no anneal: constant
    # to 0 (the old linear schedule) by default
    assert float(lr_factor(PPOConfig(anneal_updates=100), 50)) == pytest.approx(0.5)
    assert float(lr_factor(PPOConfig(anneal_updates=100), 100)) == 0.0


def test_anneal_scales_the_step_and_is_logged():
    """Past the anneal, the step is the one of a constant lr * lr_floor (Adam is linear in lr)."""
    annealed = dataclasses.replace(CFG, anneal_updates=3, lr_floor=0.1)
    low = dataclasses.replace(CFG, lr=CFG.lr * 0.1)
    ppo = PPO(annealed, obs_size=5, action_size=1)
    s0 = ppo.init(jax.random.PRNGKey(0)).replace(step=jnp.asarray(7, jnp.int32))
    traj, last = _traj(ppo, s0, jax.random.PRNGKey(1))
    s_a, m_a = jax.jit(ppo.update)(s0, traj, last, jax.random.PRNGKey(2))
    s_l, m_l = jax.jit(PPO(low, obs_size=5, action_size=1).update)(s0, traj, last, jax.random.PRNGKey(2))
    for a, b in zip(jax.tree.leaves(s_a.params), jax.tree.leaves(s_l.params)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-8)
    assert float(m_a["lr"]) == pytest.approx(1e-4) and float(m_l["lr"]) == pytest.approx(1e-4)
    # the step is smaller than the full lr's
    s_f, _ = jax.jit(PPO(CFG, obs_size=5, action_size=1).update)(s0, traj, last, jax.random.PRNGKey(2))
    d = lambda s: sum(float(jnp.abs(a - b).sum()) for a, b in zip(jax.tree.leaves(s.params), jax.tree.leaves(s0.params)))  # noqa: E731
    assert d(s_a) < 0.5 * d(s_f)
    # during the anneal the logged lr falls update by update
    _, _, ms = _run(dataclasses.replace(CFG, anneal_updates=4, lr_floor=0.25), 4)
    lrs = [float(m["lr"]) for m in ms]
    assert lrs[0] < CFG.lr and all(a > b for a, b in zip(lrs, lrs[1:])) and lrs[-1] > 0.25 * CFG.lr


def test_log_std_floor_holds():
    fast = dataclasses.replace(CFG, lr=0.05)
    floored = dataclasses.replace(fast, min_log_std=-0.125)
    _, free_states, free_m = _run(fast, 6, quadratic_reward=True)
    _, states, ms = _run(floored, 6, quadratic_reward=True)
    assert float(mean_log_std(free_states[-1].params)) < -0.125  # the reward does push it down
    for s, m in zip(states[1:], ms):
        assert float(jnp.min(s.params["params"]["log_std"])) >= -0.125
        assert float(m["log_std_mean"]) == pytest.approx(float(mean_log_std(s.params)))
    # a policy below the floor (e.g. resumed) is raised to it by its next update
    low = dataclasses.replace(floored, init_log_std=-1.0)
    _, st, _ = _run(low, 1)
    assert float(st[0].params["params"]["log_std"][0]) == -1.0
    assert float(jnp.min(st[1].params["params"]["log_std"])) >= -0.125


def test_obs_normaliser_frozen_after_n_updates():
    cfg = dataclasses.replace(CFG, obs_norm_updates=2)
    _, states, ms = _run(cfg, 4)
    stats = [s.obs_stats for s in states]
    for i in (0, 1):  # updated while fewer than 2 updates are done
        assert not np.allclose(stats[i + 1].mean, stats[i].mean)
        assert float(ms[i]["obs_mean_shift"]) > 0 and float(ms[i]["obs_std_shift"]) > 0
    for i in (2, 3):  # then frozen: the same arrays, count included
        for a, b in zip(jax.tree.leaves(stats[i + 1]), jax.tree.leaves(stats[2])):
            np.testing.assert_array_equal(a, b)
        assert float(ms[i]["obs_mean_shift"]) == 0.0 and float(ms[i]["obs_std_shift"]) == 0.0
    # without the option the statistics keep moving (the observations drift by +1 per update)
    _, free, _ = _run(CFG, 4)
    assert not np.allclose(free[4].obs_stats.mean, free[2].obs_stats.mean)


def _adam_count(opt_state) -> int:
    counts = [int(x) for p, x in jax.tree_util.tree_flatten_with_path(opt_state)[0]
              if getattr(p[-1], "name", None) == "count"]
    assert counts, "no Adam count in the optimiser state"
    return counts[0]


@pytest.mark.parametrize("discrete", [True, False])
def test_target_kl_stops_the_update(discrete):
    fast = dataclasses.replace(CFG, lr=0.05, update_epochs=4)
    steps = fast.update_epochs * fast.num_minibatches
    _, free, fm = _run(fast, 1, discrete=discrete)
    assert float(fm[0]["update_frac"]) == 1.0 and _adam_count(free[1].opt_state) == steps
    _, stopped, sm = _run(dataclasses.replace(fast, target_kl=1e-4), 1, discrete=discrete)
    applied = _adam_count(stopped[1].opt_state)
    assert 1 <= applied < steps  # the first step (on-policy, KL ~0) is applied, later ones are not
    assert float(sm[0]["update_frac"]) == pytest.approx(applied / steps)
    # the parameters moved less than without the stop
    d = lambda s: sum(float(jnp.abs(a - b).sum()) for a, b in zip(jax.tree.leaves(s[1].params), jax.tree.leaves(s[0].params)))  # noqa: E731
    assert 0 < d(stopped) < d(free)


@pytest.mark.parametrize("discrete", [True, False])
def test_inert_options_compute_the_defaults(discrete):
    """Each option switched on at a value that changes nothing gives the defaults' numbers, up
    to float rounding (XLA fuses the extra ops differently: ~1e-9 on the Gaussian head). The
    defaults themselves are the code before the options bit for bit (checked against it)."""
    inert = dataclasses.replace(CFG, anneal_updates=10, lr_floor=1.0, min_log_std=-1e9,
                                target_kl=1e9, obs_norm_updates=1000)
    _, a, ma = _run(CFG, 3, discrete=discrete)
    _, b, mb = _run(inert, 3, discrete=discrete)
    for x, y in zip(jax.tree.leaves(a[-1]), jax.tree.leaves(b[-1])):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-8)
    for k in ma[-1]:
        np.testing.assert_allclose(ma[-1][k], mb[-1][k], rtol=1e-4, atol=1e-8)


def test_config_checks_its_options():
    for kw, msg in ((dict(lr_schedule="step"), "lr_schedule"), (dict(lr_floor=1.5), "lr_floor"),
                    (dict(anneal_updates=-1), "anneal_updates"), (dict(target_kl=0.0), "target_kl")):
        with pytest.raises(ValueError, match=msg):
            PPOConfig(**kw)


def test_presets_carry_the_domain_settings():
    from bulbjax.run.settings import resolve

    for name, anneal, freeze in (("fig2-cartpole", 2000, 400), ("fig2-invpend", 500, 100)):
        p = resolve(name).ppo
        assert (p.anneal_updates, p.lr_floor, p.min_log_std, p.lr, p.obs_norm_updates) == (anneal, 0.1, -2.0, 1e-3, freeze)
    hc = resolve("fig2-halfcheetah").ppo
    assert hc.obs_norm_updates == 0  # measured only on the pendulums
    # from latents or pixels the inputs move as the learners train: the normaliser keeps following
    for rl_input in ("latent:vae_rpl", "pixels"):
        assert resolve("fig2-invpend", overrides={"rl_input": rl_input}).ppo.obs_norm_updates == 0
    assert (hc.lr, hc.num_steps, hc.min_log_std, hc.anneal_updates) == (3e-4, 128, -1.5, 2000)
    assert resolve("fig2-ant").ppo.min_log_std is None  # no measurements there: PPO's defaults
    # a run saved before the options reads back with them off (its config.json lacks them)
    from bulbjax.config import config_from_dict

    saved = dataclasses.asdict(resolve("fig2-invpend"))
    for f in ("lr_schedule", "lr_floor", "min_log_std", "target_kl", "obs_norm_updates"):
        del saved["ppo"][f]
    saved["ppo"]["anneal_updates"] = 0
    old = config_from_dict(saved).ppo
    assert old.min_log_std is None and old.obs_norm_updates == 0


def _bench():
    spec = importlib.util.spec_from_file_location("ppo_stability", os.path.join(os.path.dirname(HERE), "benchmarks",
                                                                                "ppo_stability.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_stability_figure():
    mod = _bench()
    nan = float("nan")
    s = mod.stability(np.array([10, 960, nan, 1000, 500, 990]), 950)  # the NaN epoch counts as 960
    assert s == dict(first_epoch=1, share_after=0.75, epochs_after=4)
    assert mod.stability(np.array([10.0, 20.0]), 950)["first_epoch"] is None
    old = mod.old_ppo(PPOConfig(anneal_updates=5, lr_floor=0.2, min_log_std=-1.0, target_kl=0.1, lr=3e-4))
    assert old == PPOConfig(lr=3e-4)
    assert mod.parse_sets(["target_kl=0.02", "min_log_std=none", "lr_schedule=cosine", "obs_norm_updates=7"]) == \
        dict(target_kl=0.02, min_log_std=None, lr_schedule="cosine", obs_norm_updates=7)


def test_ppo_stability_runs_small(tmp_path):
    mod = _bench()
    args = ["--preset", "fig2-cartpole", "--small", "--seeds", "1", "--chunk", "1", "--ppo-updates", "1",
            "--variant", "both", "--state", str(tmp_path / "state.pkl")]
    assert mod.main(args + ["--epochs", "2", "--out", str(tmp_path / "a")]) == 0
    (path,) = (tmp_path / "a").glob("ppo_stability_*.json")
    res = json.loads(path.read_text())
    assert res["stopped"] == "done" and set(res["variants"]) == {"old", "new"}
    old, new = res["variants"]["old"], res["variants"]["new"]
    assert (old["ppo"]["anneal_updates"], new["ppo"]["anneal_updates"]) == (0, 2000)
    for v in (old, new):
        assert v["epochs"] == 2 and len(v["returns"]) == 1 and len(v["returns"][0]) == 2
        assert v["stability"]["threshold"] == 195.0 and len(v["stability"]["per_seed"]) == 1
        assert all(len(v["ppo_metrics"][k][0]) == 2 for k in ("lr", "approx_kl", "clip_frac", "value_loss"))
        assert sum(v["episodes"][0]) > 0  # CartPole's random-ish early episodes end within 64 steps
    assert old["ppo_metrics"]["lr"][0] == [1e-3, 1e-3]
    assert new["ppo_metrics"]["lr"][0][1] < new["ppo_metrics"]["lr"][0][0] < 1e-3  # annealing
    # a later call with the same arguments continues from the state file: one more epoch
    assert mod.main(args + ["--epochs", "3", "--out", str(tmp_path / "b")]) == 0
    (path,) = (tmp_path / "b").glob("ppo_stability_*.json")
    more = json.loads(path.read_text())["variants"]
    for name in ("old", "new"):
        assert more[name]["epochs"] == 3
        assert more[name]["returns"][0][:2] == res["variants"][name]["returns"][0]
        assert more[name]["ppo_metrics"]["lr"][0][:2] == res["variants"][name]["ppo_metrics"]["lr"][0]
    assert more["new"]["ppo_metrics"]["lr"][0][2] < more["new"]["ppo_metrics"]["lr"][0][1]
    with pytest.raises(SystemExit, match="other arguments"):  # other settings refuse the state
        mod.main(args + ["--epochs", "3", "--seed", "5", "--out", str(tmp_path / "c")])
