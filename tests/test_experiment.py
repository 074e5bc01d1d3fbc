"""The jitted epoch on a tiny configuration: runs vmapped over 2 seeds, keeps the replay
semantics, is deterministic under a key, and its reports (JSON lines, plot, table) are sound."""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import numpy as np
import pytest

from bulbjax.epoch import Experiment
from bulbjax.epoch.seeds import buffer_key, update_groups, with_seed_loop
from bulbjax.report import records, report

from tiny_experiment import ALL, SEEDS, tiny_six_config


@pytest.fixture(scope="module")
def run():
    """Two epochs of all six learners side by side (one compile serves every test here: the
    frame-learner tests read vae/vae_rpl, the sequential ones the window buffer)."""
    exp = Experiment(tiny_six_config())
    rs0 = exp.init(jax.random.PRNGKey(0))
    retained0 = jax.device_get(rs0.buffers[buffer_key(0.5)])
    windows0 = jax.device_get(rs0.windows[buffer_key(0.5)])
    rs1, m1 = exp.epoch(rs0, jax.random.PRNGKey(1))
    # a host copy for the tests (the epoch donates rs1); the epoch takes rs1 on the device as it
    # left it (host arrays compiled the epoch a second time)
    rs1_host = jax.tree.map(np.array, rs1)
    rs, m2 = exp.epoch(rs1, jax.random.PRNGKey(2))
    return exp, retained0, jax.device_get(rs), jax.device_get(m1), jax.device_get(m2), windows0, rs1_host


def test_epoch_shapes_over_seeds(run):
    exp, _, rs, m1, *_ = run
    d = exp.env.state_dim
    assert int(rs.epoch) == 2
    assert exp.epoch._cache_size() == 1  # the second epoch ran the first's program
    assert m1["rl_return"].shape == (SEEDS,)
    for name in ("vae", "vae_rpl"):
        assert m1["learners"][name]["loss"].shape == (SEEDS,)
        assert np.all(np.isfinite(m1["learners"][name]["loss"]))
        for stream in ("curr", "rand"):
            p = m1["probes"][name][stream]
            assert p["mae"].shape == p["baseline"].shape == p["spread"].shape == (SEEDS, d)
            assert np.all(np.isfinite(p["mae"])) and np.all(p["mae"] >= 0)
    # every seed has its own learner: the parameters of the two seeds differ
    leaf = jax.tree.leaves(rs.learners["vae"].params)[0]
    assert leaf.shape[0] == SEEDS and not np.allclose(leaf[0], leaf[1])


def test_replay_retention_and_sharing(run):
    exp, before, rs, m1, *_ = run
    # vae keeps nothing, vae_rpl keeps half of the initial random-policy frames: two buffers
    assert set(rs.buffers) == {buffer_key(0.0), buffer_key(0.5)}
    kept = rs.buffers[buffer_key(0.5)]
    assert np.all(kept.retained.sum(1) == 16)
    mask = before.retained
    np.testing.assert_array_equal(kept.frames[mask], before.frames[mask])  # never overwritten
    assert np.all(kept.size == 32) and np.all(rs.buffers[buffer_key(0.0)].retained.sum(1) == 0)
    # the non-retained part did receive the epochs' new frames
    assert not np.array_equal(kept.frames[~mask], before.frames[~mask])
    assert all(np.all(v == 0) for v in m1["replay_dropped"].values())
    # Each slot keeps the world its frame came from (the probe's validation split groups by it):
    # after init, slot i holds the fill's frame i, of world i % N; later frames keep theirs.
    np.testing.assert_array_equal(before.extras["world"], np.broadcast_to(np.arange(32) % 4, (SEEDS, 32)))
    w = kept.extras["world"]
    assert w.dtype == np.int32 and w.min() >= 0 and w.max() < 4
    np.testing.assert_array_equal(w[mask], before.extras["world"][mask])


def test_epoch_is_deterministic_under_a_key(run):
    exp, _, _, m1, *_ = run
    rs = exp.init(jax.random.PRNGKey(0))
    _, again = exp.epoch(rs, jax.random.PRNGKey(1))
    again = jax.device_get(again)
    np.testing.assert_allclose(again["learners"]["vae"]["loss"], m1["learners"]["vae"]["loss"], rtol=1e-5)
    np.testing.assert_allclose(again["probes"]["vae_rpl"]["rand"]["mae"], m1["probes"]["vae_rpl"]["rand"]["mae"],
                               rtol=1e-4, atol=1e-6)


def test_seed_loop_map_equals_vmap(run):
    """The learners' updates run over the seed axis with `lax.map` (one seed at a time; the
    default before "hybrid"), `vmap` (the default on the CPU) or "hybrid" (the default on one
    GPU: DSA vmapped with its convolutions one seed at a time): the same numbers every way."""
    exp, *_, rs1 = run
    saved = exp.learners
    names = ("vae_rpl", "svae", "dsa")  # a frame learner, a mapped and a vmapped sequential one
    out = {}
    for loop in ("vmap", "map", "hybrid"):
        team = dataclasses.replace(exp.team, learners={n: with_seed_loop(saved[n], loop) for n in names},
                                   seed_loop=loop)  # as the loop makes them
        assert team.learners["dsa"].per_seed_frames == ("remat" if loop == "hybrid" else "")
        learning = dataclasses.replace(exp.learning, team=team)
        learners = {n: rs1.learners[n] for n in team.learners}
        out[loop] = jax.device_get(jax.jit(learning.learn_phase)(learners, rs1.buffers, jax.random.PRNGKey(7),
                                                                 rs1.windows))
    for name in names:
        a = out["vmap"][0][name].params
        before = jax.tree.leaves(rs1.learners[name].params)[0]
        assert not np.allclose(jax.tree.leaves(a)[0], before)  # the updates did move the weights
        for loop in ("map", "hybrid"):
            b = out[loop][0][name].params
            jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=2e-4, atol=2e-5), a, b)
            np.testing.assert_allclose(out["vmap"][1][name]["loss"], out[loop][1][name]["loss"], rtol=1e-4)


@pytest.fixture(scope="module")
def held(run):
    """Held-out windows of one `eval_phase` (compiled once for the probe-phase tests)."""
    exp, *_, rs1 = run
    return jax.jit(exp.streams.eval_phase)(rs1.ppo, rs1.curr_env, rs1.rand_env, jax.random.PRNGKey(3))[2]


def test_probe_phase_same_under_either_seed_loop(run, held):
    """Probes: the learners' encodings follow the seed loop, the probe MLPs are vmapped over
    seeds either way (`probe_over_seeds`); the scores agree, and differ between seeds."""
    exp, *_, rs1 = run
    saved = exp.learners
    out = {}
    for loop in ("vmap", "map", "hybrid"):
        team = dataclasses.replace(exp.team, learners={n: with_seed_loop(saved[n], loop) for n in ("vae_rpl", "dsa")},
                                   seed_loop=loop)
        probing = dataclasses.replace(exp.probing, team=team)
        out[loop] = jax.device_get(jax.jit(probing.probe_phase)(rs1.learners, rs1.buffers, held,
                                                                jax.random.PRNGKey(4), rs1.windows))
    for name in ("vae_rpl", "dsa"):
        for stream in ("curr", "rand"):
            a = out["vmap"][name][stream]["mae"]
            assert a.shape == (SEEDS, exp.env.state_dim) and np.all(np.isfinite(a))
            for loop in ("map", "hybrid"):
                np.testing.assert_allclose(a, out[loop][name][stream]["mae"], rtol=1e-3, atol=1e-5)
            assert not np.allclose(a[0], a[1])


def test_shared_updates_equal_separate_ones(run, held):
    """vae, vae_rpl and beta_vae share one update and one probe-encoding program
    (`update_groups`, each member with its beta and its replay buffer): the same weights,
    losses and probe scores as three separate programs, under either seed loop."""
    exp, *_, rs1 = run
    names = ("vae", "vae_rpl", "beta_vae")
    saved = exp.learners
    three = {n: saved[n] for n in names}
    assert update_groups(three) == [names]
    assert update_groups(three, share=False) == [(n,) for n in names]
    learners = {n: rs1.learners[n] for n in names}
    out = {}
    for share, loop in ((False, "vmap"), (True, "vmap"), (True, "map")):
        team = dataclasses.replace(exp.team, learners=three, shared_updates=share, seed_loop=loop)
        learning = dataclasses.replace(exp.learning, team=team)
        probing = dataclasses.replace(exp.probing, team=team)
        learnt = jax.jit(learning.learn_phase)(learners, rs1.buffers, jax.random.PRNGKey(7))
        probes = jax.jit(probing.probe_phase)(learners, rs1.buffers, held, jax.random.PRNGKey(4))
        out[share, loop] = jax.device_get((learnt, probes))
    (ref_states, ref_m), ref_p = out[False, "vmap"]
    assert set(ref_states) == set(names) and saved["beta_vae"].config.beta == 5.0
    for n in names:  # the updates did move the weights, so agreeing with them is not trivial
        assert not np.allclose(jax.tree.leaves(ref_states[n].params)[0], jax.tree.leaves(learners[n].params)[0])
    for key in ((True, "vmap"), (True, "map")):
        (states, m), p = out[key]
        assert set(states) == set(names) and set(p) == set(names)
        for n in names:
            # each member's own KL weight reached it inside the group (beta_vae: 5, the others 1)
            beta = saved[n].config.beta
            np.testing.assert_allclose(m[n]["loss"], m[n]["recon"] + beta * m[n]["kl"], rtol=1e-5)
            jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=2e-4, atol=2e-5),
                         states[n].params, ref_states[n].params)
            np.testing.assert_allclose(m[n]["loss"], ref_m[n]["loss"], rtol=1e-4)
            for stream in ("curr", "rand"):
                np.testing.assert_allclose(p[n][stream]["mae"], ref_p[n][stream]["mae"], rtol=1e-3, atol=1e-5)


def _max_abs_diff(a, b) -> float:
    return max((float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)))) if np.size(x) else 0.0)
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


@pytest.mark.slow  # the slow tier: `make test-all` runs it, `make test` does not (tests/conftest.py)
def test_split_programs_give_the_fused_epoch(run):
    """Init and the epoch as several programs (`Stages`, `programs="split"`) give the fused
    programs' run state and metrics: the probing epoch from the same init
    and key as the fixture's first, then a non-probing one (no held-out rollouts, no `probes`)
    whose updates equal the fixture's second epoch's."""
    from bulbjax.epoch.programs import Programs

    exp, _, rs2, m1, m2, _, rs1 = run
    progs = Programs(exp, (True, False), split=True)
    assert progs.split and progs.names[:2] == ["init/env", "init/learner/vae"]
    assert "epoch/learn/vae+vae_rpl+beta_vae" in progs.names and "epoch/probe/dsa" in progs.names
    with pytest.raises(KeyError, match="no single program"):
        progs.lowered("epoch")
    rs = progs.init(jax.random.PRNGKey(0))
    fused0 = jax.device_get(exp.init(jax.random.PRNGKey(0)))
    assert jax.tree.structure(jax.device_get(rs)) == jax.tree.structure(fused0)
    assert _max_abs_diff(jax.device_get(rs), fused0) == 0.0
    rs, m = progs.epoch(rs, jax.random.PRNGKey(1), probe=True)
    rs, m = jax.device_get((rs, m))
    assert jax.tree.structure(m) == jax.tree.structure(m1) and int(rs.epoch) == 1
    assert _max_abs_diff(rs, rs1) <= 1e-5 and _max_abs_diff(m, m1) <= 1e-4
    assert np.all(np.isfinite(m["probes"]["dsa"]["curr"]["mae"]))
    # a non-probing epoch: the same updates as the fixture's second (probing) epoch, the
    # held-out worlds left where they were
    rs_n, m_n = jax.device_get(progs.epoch(rs, jax.random.PRNGKey(2), probe=False))
    assert "probes" not in m_n
    same = ("ppo", "learners", "buffers", "windows", "train_env")
    assert _max_abs_diff([getattr(rs_n, f) for f in same], [getattr(rs2, f) for f in same]) <= 1e-5
    assert _max_abs_diff({k: v for k, v in m_n.items()}, {k: v for k, v in m2.items() if k != "probes"}) <= 1e-4
    assert _max_abs_diff(rs_n.curr_env, rs.curr_env) == 0.0
    assert not np.allclose(rs2.curr_env.obs, rs.curr_env.obs)  # (a probing epoch moves them on)


def test_reports(run, tmp_path):
    exp, _, _, m1, m2, *_ = run
    recs = records.epoch_records(0, m1, exp.spec) + records.epoch_records(1, m2, exp.spec)
    path = tmp_path / "metrics.jsonl"
    records.write_jsonl(str(path), recs)
    back = records.read_jsonl(str(path))
    assert len(back) == 2 * SEEDS
    g = back[0]["probes"]["vae"]["curr"]["groups"]
    assert set(g) == {"position", "velocity"}
    e = back[0]["probes"]["vae"]["curr"]["entries"]["x"]
    assert e["unit"] == "m" and e["mae"] == pytest.approx(float(m1["probes"]["vae"]["curr"]["mae"][0, 2]))
    # fixed scale: both streams divided by the run's reference spread (random policy, at init)
    ref = np.asarray(rs_ref := m1["ref_spread"])
    assert ref.shape == (SEEDS, exp.env.state_dim) and np.all(ref[0] == ref[1]) and np.all(ref > 0)
    for stream in ("curr", "rand"):
        e = back[0]["probes"]["vae"][stream]["entries"]["x"]
        assert e["ref_spread"] == pytest.approx(float(rs_ref[0, 2]))
        assert e["mae_norm"] == pytest.approx(e["mae"] / e["ref_spread"])
    # an epoch without a probe (--probe-every) is recorded, plotted and tabled around
    m_np = {k: v for k, v in m2.items() if k != "probes"}
    recs += records.epoch_records(2, m_np, exp.spec)
    assert recs[-1]["probes"] == {} and len(records.probed(recs)) == 2 * SEEDS
    report.plot(recs, exp.spec, str(tmp_path / "fig.png"), "test", solved_return=190)
    assert os.path.getsize(tmp_path / "fig.png") > 10_000
    tab = report.table(recs, exp.spec)
    assert "| vae_rpl | π_rand |" in tab and "| constant | π_curr |" in tab
    assert "epoch 1;" in tab and "reference spread" in tab
    # a scene without objects (CartPole) has no object probe: no section in the metrics, the
    # records, the written table or the figures (the object probe's own run: test_object_probe)
    from bulbjax.eval.objects import comparison_table

    assert exp.probing.objects is None
    assert all("objects" not in d for d in m1["probes"]["vae_rpl"].values())
    assert all("objects" not in r for r in recs)
    written = report.write_reports(str(tmp_path), recs, exp.config, exp.spec)
    assert "Objects" not in written and "Objects" not in (tmp_path / "table.md").read_text()
    assert not (tmp_path / "objects.png").exists()
    assert comparison_table(recs, exp.spec) == ""


# ---------------------------------------------------------------- all six learners, presets
def test_six_learners_in_one_epoch(run):
    exp, _, _, m, _, before, rs = run
    d = exp.env.state_dim
    assert set(m["learners"]) == set(ALL) and set(m["probes"]) == set(ALL)
    for name in ALL:
        assert np.all(np.isfinite(m["learners"][name]["loss"])), name
        for stream in ("curr", "rand"):
            p = m["probes"][name][stream]
            assert p["mae"].shape == (SEEDS, d) and np.all(np.isfinite(p["mae"])), (name, stream)
    # equalised compute: 8 frames per batch, 8 // 4 = 2 windows of 4 steps
    assert exp.learners["vae"].batch_size == 8 and exp.learners["svae"].batch_size == 2
    # one window buffer (all sequential learners retain 0.5), windows of L + k = 6 steps
    assert set(rs.windows) == {buffer_key(0.5)} and exp.window_length == 6
    w = rs.windows[buffer_key(0.5)]
    assert w.windows.frames.shape == (SEEDS, 32 // 6, 6, 32, 32, 3)
    assert np.all(w.retained.sum(1) == round(0.5 * (32 // 6)))
    np.testing.assert_array_equal(w.windows.frames[before.retained], before.windows.frames[before.retained])
    assert np.all(w.windows.actions.sum(-1)[w.windows.valid] == 1)  # CartPole: one-hot actions
    # every learner is probed on the same held-out pairs: the same constant-predictor spread
    for stream in ("curr", "rand"):
        np.testing.assert_allclose(m["probes"]["svae"][stream]["spread"], m["probes"]["vae"][stream]["spread"])
    assert all(np.all(v == 0) for v in m["replay_dropped"].values())


# ---------------------------------------------------------------- probe-protocol variants (issue 59)
VARIANTS = ("common", "window", "raw")
# a prefix of ALL, so the same draws as `run`'s (learner i draws with key i), with svae and pred
# (sequential learners, for the window variant); pred also keeps `run`'s window length (L + pred's
# horizon: without it the windows are 4 steps, not 6, and every draw after differs); dsa left out
# for its compile time
WITH_VARIANTS = ALL[:5]


@pytest.fixture(scope="module")
def run_variants():
    """The fixture `run`'s experiment with every probe variant and its first five learners: its init and first
    epoch under the same keys (learner i of a run draws with key i: a prefix of `run`'s learners
    gets `run`'s draws)."""
    cfg = dataclasses.replace(tiny_six_config(), learners=WITH_VARIANTS, probe_variants=VARIANTS)
    exp = Experiment(cfg)
    rs0 = exp.init(jax.random.PRNGKey(0))
    probe_set0 = jax.device_get(rs0.probe_set)
    rs1, m1 = exp.epoch(rs0, jax.random.PRNGKey(1))
    return exp, probe_set0, jax.device_get(rs1), jax.device_get(m1)


def test_variants_leave_the_present_probe_unchanged(run, run_variants):
    """The records of a tiny run with every probe variant equal those of the run without them
    (same keys), bit for bit, up to the variants' own keys; so does the run state."""
    exp, _, _, m1, *_, rs1 = run
    expv, _, rsv, mv = run_variants
    def keep(m: dict) -> dict:  # the metrics of `WITH_VARIANTS`
        return {k: ({n: v[n] for n in WITH_VARIANTS} if k in ("learners", "probes") else v)
                for k, v in m.items()}

    plain = records.epoch_records(0, keep(m1), exp.spec)
    withv = records.epoch_records(0, mv, expv.spec, VARIANTS)
    assert len(plain) == len(withv) == SEEDS
    for a, b in zip(plain, withv):
        assert set(b) - set(a) == {"probes_common", "probes_window", "probes_raw"}
        assert json.dumps({k: b[k] for k in a}, sort_keys=True) == json.dumps(a, sort_keys=True)
        for key in ("probes_common", "probes_window", "probes_raw"):
            assert set(b[key]) == set(WITH_VARIANTS) and set(b[key]["vae"]) == {"curr", "rand"}
    same = lambda x: {n: x.learners[n] for n in WITH_VARIANTS}  # noqa: E731
    assert _max_abs_diff((same(rsv), rsv.buffers, rsv.windows, rsv.ppo),
                         (same(rs1), rs1.buffers, rs1.windows, rs1.ppo)) == 0.0


def test_common_probe_set_is_the_same_pairs_for_every_learner(run, run_variants):
    """Every learner of a seed, frame or sequential, fits the common variant's probe on the same
    pairs: the same constant predictor (their states' median) and spread, where each learner's
    own buffer gives the present probes different ones. The random-policy part is a fixed draw
    of init's windows, kept unchanged."""
    _, _, _, _, _, windows0, _ = run
    exp, set0, rs1, m = run_variants
    common = {n: m["probes"][n]["variants"]["common"] for n in WITH_VARIANTS}
    present = {n: m["probes"][n]["rand"]["baseline"] for n in WITH_VARIANTS}
    for stream in ("curr", "rand"):
        first = common["vae"][stream]
        for n in WITH_VARIANTS[1:]:
            np.testing.assert_array_equal(common[n][stream]["baseline"], first["baseline"])
            np.testing.assert_array_equal(common[n][stream]["spread"], first["spread"])
        assert not all(np.array_equal(common[n][stream]["mae"], first["mae"]) for n in WITH_VARIANTS)
    assert not all(np.array_equal(present[n], present["vae"]) for n in WITH_VARIANTS)
    # the random-policy part: ceil(16 / 2 / 4) = 2 windows of L = 4 steps per seed, from init's windows
    w = set0.windows
    assert w.frames.shape == (SEEDS, 2, 4, 32, 32, 3) and set0.rand_windows == 2
    assert np.all((set0.world >= 0) & (set0.world < exp.N))
    init = windows0.windows.frames[:, :, :4]  # init's window buffer before any epoch: its windows
    for s in range(SEEDS):
        for i in range(2):
            assert any(np.array_equal(w.frames[s, i], init[s, j]) for j in range(init.shape[1]))
    jax.tree.map(np.testing.assert_array_equal, rs1.probe_set, set0)  # kept, never overwritten


def test_whole_window_latent_has_the_learners_window_size(run):
    """The window variant's latent is the learner's whole window: its L per-step latents in order,
    L x Z numbers, paired with the state at the window's last step; the held-out windows' per-step
    latents are recovered from the present probe's context latents."""
    from bulbjax.epoch import probe_variants as pv
    from bulbjax.eval import probe

    exp, *_, rs1 = run
    buf = jax.tree.map(lambda x: x[0], rs1.windows[buffer_key(0.5)])
    for name in ("svae", "pred", "dsa"):
        learner, params = exp.learners[name], jax.tree.map(lambda x: x[0], rs1.learners[name].params)
        pairs = jax.jit(lambda p, b: (pv.window_pairs(learner, p, b), learner.encode(p, b.windows)))
        (tz, ts), z = pairs(params, buf)
        l, c = learner.sequence_length, buf.capacity
        assert l == 4 and tz.shape == (c, l * learner.latent_dim) and ts.shape == (c, exp.env.state_dim)
        np.testing.assert_array_equal(tz.reshape(z.shape), z)
        np.testing.assert_array_equal(ts, buf.windows.states[:, l - 1])
        context = pv.context_of(learner, exp.config.probe)
        ctx = probe.context_latents(z, context)
        np.testing.assert_array_equal(pv.held_step_latents(ctx, context), z)


@pytest.mark.slow
def test_the_pipelined_epoch_gives_the_plain_epochs(run):
    """`overlap="pipeline"`: one program does epoch t's learner updates and probes and epoch t+1's
    PPO work and replay inserts. From the same init and epoch keys as the fixture's two epochs it
    gives their metrics and their learners (its state carries the next epoch's environment work,
    `RunState.pending`). Through `epoch_flag`, as a run probing every k epochs calls it: the first
    epoch probing, the second not (its updates still the fixture's second epoch's)."""
    exp, _, rs2, m1, m2, _, rs1 = run
    pipe = Experiment(dataclasses.replace(exp.config, overlap="pipeline"))
    assert pipe.pipelined
    rs = pipe.init(jax.random.PRNGKey(0))
    assert rs.pending == {}
    rs = pipe.prime(rs, jax.random.PRNGKey(1))  # epoch 0's environment work, with epoch 0's key
    assert set(rs.pending) >= {"metrics", "k_learn", "k_eval", "k_probe"} and int(rs.epoch) == 0
    rs, m = jax.device_get(pipe.epoch_flag(rs, jax.random.PRNGKey(2), pipe.put_flag(True)))  # epoch 1's key
    assert int(rs.epoch) == 1 and jax.tree.structure(m) == jax.tree.structure(m1)
    assert _max_abs_diff(m, m1) <= 1e-4
    assert _max_abs_diff(rs.learners, rs1.learners) <= 1e-5
    assert _max_abs_diff([rs.curr_env, rs.rand_env], [rs1.curr_env, rs1.rand_env]) <= 1e-5
    rs, m = jax.device_get(pipe.epoch_flag(rs, jax.random.PRNGKey(3), pipe.put_flag(False)))
    assert _max_abs_diff({k: v for k, v in m.items() if k != "probes"},
                         {k: v for k, v in m2.items() if k != "probes"}) <= 1e-4
    assert _max_abs_diff(rs.learners, rs2.learners) <= 1e-5
    assert np.all(np.isnan(m["probes"]["vae"]["curr"]["mae"]))  # not probed
    with pytest.raises(ValueError, match="PPO observes vae's latent"):
        dataclasses.replace(exp.config, overlap="pipeline", rl_input="latent:vae")
    with pytest.raises(ValueError, match="overlap must be one of"):
        dataclasses.replace(exp.config, overlap="always")
