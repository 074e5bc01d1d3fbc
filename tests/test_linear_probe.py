"""The linear (ridge) probe (`bulbjax.eval.linear`) on targets whose answers are known: exact on a
noiseless linear target, at the constant predictor on pure noise with a large regulariser
chosen, chosen on the MLP probe's own validation split; and its place in records, the table and
the findings."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from bulbjax.envs.registry import env_class
from bulbjax.epoch.probing import fit_and_score
from bulbjax.eval import linear, probe
from bulbjax.report import findings, report
from bulbjax.report.records import epoch_records

fit = jax.jit(linear.fit, static_argnames="lambdas")
predict = jax.jit(linear.predict)


def _data(key: jax.Array, rows: int, z: int, d: int) -> tuple[jax.Array, jax.Array]:
    kx, ky = jax.random.split(key)
    return jax.random.normal(kx, (rows, z)) * 2.0 + 0.5, jax.random.normal(ky, (rows, d)) * 3.0 + 1.0


def test_exact_on_a_noiseless_linear_target() -> None:
    k = jax.random.split(jax.random.PRNGKey(0), 4)
    z, _ = _data(k[0], 600, 12, 1)
    a = jax.random.normal(k[1], (12, 5))
    b = jnp.arange(5.0)
    y = z @ a + b
    val = probe.validation_rows(k[2], 600)
    p = fit(z, y, val)
    zt, _ = _data(k[3], 1000, 12, 1)
    yt = zt @ a + b
    err = probe.mae(predict(p, zt), yt) / probe.spread(yt)
    assert np.all(np.asarray(err) < 2e-3), err  # ~0: only the smallest regulariser's shrinkage
    np.testing.assert_array_equal(p.log10_lambda, np.full(5, -4.0))  # the smallest one chosen


def test_at_the_constant_on_noise_with_a_large_regulariser() -> None:
    """Targets independent of a wide latent (64 columns, 480 training rows: an unregularised fit
    memorises): the probe chooses large regularisers and scores the constant predictor's error."""
    for seed in range(3):
        k = jax.random.split(jax.random.PRNGKey(seed), 4)
        z, y = _data(k[0], 600, 64, 16)
        p = fit(z, y, probe.validation_rows(k[1], 600))
        zt, yt = _data(k[2], 2000, 64, 16)
        ratio = np.asarray(probe.mae(predict(p, zt), yt) / probe.constant_baseline(y, yt))
        assert ratio.mean() < 1.02 and ratio.max() < 1.08, ratio
        lam = np.asarray(p.log10_lambda)
        assert np.median(lam) >= 1.0 and lam.min() >= -2.0, lam
        # the least regularised fit would be clearly worse than the constant: selection matters
        weak = fit(z, y, probe.validation_rows(k[1], 600), lambdas=(1e-4,))
        weak_ratio = np.asarray(probe.mae(predict(weak, zt), yt) / probe.constant_baseline(y, yt))
        assert weak_ratio.mean() > 1.03, weak_ratio


def test_uses_only_training_rows_and_constant_columns() -> None:
    """Validation rows do not enter the fit (corrupting them changes nothing but the choice of
    regulariser, here fixed); a constant latent column and a constant target are harmless."""
    k = jax.random.split(jax.random.PRNGKey(3), 3)
    z, _ = _data(k[0], 200, 6, 1)
    z = z.at[:, 2].set(7.0)
    y = jnp.stack([z[:, 0] - z[:, 1], jnp.full(200, 4.0)], -1)
    val = probe.validation_rows(k[1], 200)
    p1 = fit(z, y, val, lambdas=(1e-3,))
    p2 = fit(jnp.where(val[:, None], 1e3, z), jnp.where(val[:, None], -5.0, y), val, lambdas=(1e-3,))
    np.testing.assert_allclose(p1.w, p2.w, rtol=1e-5, atol=1e-6)
    pred = np.asarray(linear.predict(p1, z))
    assert np.all(np.isfinite(pred))
    np.testing.assert_allclose(pred[:, 1], 4.0, atol=1e-5)
    np.testing.assert_allclose(pred[:, 0], np.asarray(z[:, 0] - z[:, 1]), atol=2e-2)


def test_same_split_as_the_mlp() -> None:
    """`validation_rows` is the split `probe.fit` selects on (recomputed from its key), whole
    worlds on one side when the pairs carry world ids."""
    key = jax.random.PRNGKey(4)
    groups = jnp.arange(300) % 10
    v1 = probe.validation_rows(key, 300, probe.ProbeConfig(), groups)
    v2 = probe._validation_mask(jax.random.split(key, 3)[0], 300, 0.2, groups)
    np.testing.assert_array_equal(v1, v2)
    g_val = set(np.asarray(groups)[np.asarray(v1)])
    assert g_val and g_val.isdisjoint(set(np.asarray(groups)[~np.asarray(v1)]))  # whole worlds


def test_in_fit_and_score_records_table_and_findings() -> None:
    """Through the epoch's probe half (vmapped over seeds as in the run): the linear probe's error
    per entry, recorded under `linear_probes`, shown in the table and the findings."""
    spec = env_class("InvertedPendulum").state_spec
    d, seeds = len(spec), 3

    def one_seed(key):
        k = jax.random.split(key, 4)
        state = jax.random.normal(k[0], (400, d))
        lat = jnp.concatenate([state @ jnp.eye(d) * 2.0, jax.random.normal(k[1], (400, 4))], -1)
        hs = jax.random.normal(k[2], (8, 10, d))
        held_lat = jnp.concatenate([hs * 2.0, jax.random.normal(k[3], (8, 10, 4))], -1)
        return {"tz": lat, "ts": state, "groups": None, "held": {"rand": held_lat, "curr": held_lat}}, hs

    from bulbjax.data.sequence import Windows
    keys = jax.random.split(jax.random.PRNGKey(5), seeds)
    lats, hss = jax.vmap(one_seed)(keys)

    def score(lat, hs, k):
        w = Windows(frames=jnp.zeros((8, 10, 1, 1, 3), jnp.uint8), actions=jnp.zeros((8, 10, 1)),
                    states=hs, valid=jnp.ones((8, 10), bool))
        return fit_and_score(lat, {"rand": w, "curr": w}, k,
                             probe.ProbeConfig(hidden=(8,), steps=10, batch_size=16))

    out = jax.jit(jax.vmap(score))(lats, hss, keys)
    r = out["rand"]
    assert r["linear_mae"].shape == r["mae"].shape == (seeds, d)
    assert np.all(np.asarray(r["linear_mae"]) < 1e-3 * np.asarray(r["spread"]))  # exact: a linear latent
    assert np.all(np.asarray(r["linear_mae"]) < np.asarray(r["mae"]))  # a 10-step MLP is not
    metrics = {"rl_return": np.ones(seeds), "rl_episodes": np.ones(seeds), "ppo": {}, "learners": {},
               "replay_dropped": {}, "ref_spread": np.asarray(r["spread"]),
               "probes": {"toy": out}}
    recs = [x for e in range(3) for x in epoch_records(e, metrics, spec)]
    lp = recs[0]["linear_probes"]["toy"]["rand"]
    assert set(lp) >= {"entries", "groups", "overall"}
    assert lp["overall"]["mae_norm"] < 1e-3 < recs[0]["probes"]["toy"]["rand"]["overall"]["mae_norm"]
    assert set(next(iter(lp["entries"].values()))) == {"mae", "mae_norm", "log10_lambda"}
    share = recs[0]["probe_inputs_clamped"]["toy"]
    assert set(share) == {"rand", "curr"} and all(0.0 <= v <= 1.0 for v in share.values())
    tab = report.table(recs, spec)
    assert "| toy (linear) | π_rand |" in tab and "| toy (linear) | π_curr |" in tab
    assert "the probes clamped to their fit range" in tab and "toy " in tab.split("fit range")[-1]
    verdicts, _ = findings.check(recs, spec, "InvertedPendulum")
    agree = [v for v in verdicts if v.claim.startswith("probes agree for toy")]
    # the MLP (10 Adam steps) is far above an exact linear probe: the check flags it
    assert len(agree) == 1 and agree[0].verdict == "does not hold", agree
    # records without a linear probe (runs made before it) give neither rows nor verdicts
    old = [{k: v for k, v in x.items() if k != "linear_probes"} for x in recs]
    assert "(linear)" not in report.table(old, spec)
    assert not [v for v in findings.check(old, spec, "InvertedPendulum")[0] if v.claim.startswith("probes agree")]
