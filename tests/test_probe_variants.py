"""The probe protocol's variants on the host (issue 59): raw MAE on a case with a known answer,
each claim's verdict under each variant on synthetic records (and the side-by-side tables, the
probe-protocol table with an fp32 run), the switch (config, CLI, old run folders). The device
half (the same pairs for every learner, the whole-window latent's size, the present probe
unchanged by the variants) is in tests/test_experiment.py, on its tiny runs."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from bulbjax.config import ExperimentConfig, config_from_dict, preset
from bulbjax.envs.registry import env_class
from bulbjax.eval.probe import summarise
from bulbjax.report import findings, protocol, records, report
from bulbjax.run.settings import resolve, resolve_offline

SPEC = env_class("InvertedPendulum").state_spec  # x, x_vel, theta_cos, theta_sin, theta_vel
FIG2 = ("vae", "vae_rpl", "beta_vae", "svae", "pred", "dsa")


def test_raw_mae_known_answer() -> None:
    """Raw MAE per group: the plain mean of its entries' MAE in their units, whatever their
    reference spread (the normalised errors divide each entry by its own)."""
    mae = np.array([0.1, 0.2, 0.3, 0.5, 0.4])
    base = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    ref = np.array([0.5, 1.0, 1e-9, 2.0, 4.0])  # theta_cos: spread ~0, excluded from the normalised
    s = summarise(mae, base, ref, SPEC)
    raw = records.raw_summary(s)
    pos, vel = raw["groups"]["position"], raw["groups"]["velocity"]
    assert pos["mae"] == pytest.approx((0.1 + 0.3 + 0.5) / 3)
    assert pos["baseline"] == pytest.approx(8.0 / 3)
    assert vel["mae"] == pytest.approx((0.2 + 0.4) / 2) and vel["baseline"] == pytest.approx(3.5)
    assert (pos["n"], pos["units"], vel["units"]) == (3, ["1", "m"], ["m/s", "rad/s"])
    assert raw["overall"]["mae"] == pytest.approx(0.3) and raw["overall"]["n"] == 5
    # the normalised group differs: entries divided by their spreads, theta_cos left out
    assert s["groups"]["position"]["mae_norm"] == pytest.approx((0.1 / 0.5 + 0.5 / 2.0) / 2)


def synthetic(errors: dict[str, dict[str, tuple[float, float]]], seeds: int = 6) -> list[dict]:
    """Three probed epochs of a run with every variant: `errors[variant][learner] = (position,
    velocity)` error (normalised; raw: in units), seeded noise shared by a seed's learners."""
    rng = np.random.default_rng(1)
    out = []
    for epoch in range(3):
        for s in range(seeds):
            shared = rng.normal(0, 0.2)
            rec = {"epoch": epoch, "seed": s, "rl_return": 1.0}
            for variant, per in errors.items():
                key, value = records.VARIANT_SOURCES[variant]
                rec[key] = {}
                for name, (pos, vel) in per.items():
                    p, v = (x + shared + rng.normal(0, 0.02) for x in (pos, vel))
                    g = {"position": {value: p, "baseline" + value[3:]: 1.5},
                         "velocity": {value: v, "baseline" + value[3:]: 1.2}}
                    stream = {"groups": g, "overall": {value: (p + v) / 2, "baseline" + value[3:]: 1.4}}
                    rec[key][name] = {"curr": stream, "rand": stream}
            out.append(rec)
    return out


PRESENT = {"vae": (1.0, 1.0), "vae_rpl": (0.4, 0.8), "beta_vae": (0.45, 0.8),
           "svae": (0.4, 0.5), "pred": (0.3, 0.3), "dsa": (0.4, 0.8)}
# the common probe set closes VAE_v0's gap; the whole window makes svae worse on velocity
COMMON = {**PRESENT, "vae": (0.4, 0.8)}
WINDOW = {**PRESENT, "svae": (0.6, 1.2)}


def _by_claim(verdicts) -> dict[str, str]:
    return {v.claim.split(" (")[0].split(":")[-1].strip(): v.verdict for v in verdicts}


def test_each_claim_under_each_variant() -> None:
    recs = synthetic({"present": PRESENT, "common": COMMON, "window": WINDOW, "raw": PRESENT})
    assert records.variants_of(recs) == ["present", "common", "window", "raw"]
    sets, epochs = findings.variant_checks(recs, SPEC, "InvertedPendulum")
    assert epochs == [0, 1, 2] and list(sets) == ["present", "common", "window", "raw"]
    got = {v: _by_claim(x) for v, x in sets.items()}
    assert got["present"]["replay fixes VAE_v0 on π_rand"] == "holds"
    assert got["common"]["replay fixes VAE_v0 on π_rand"] == "undecided"  # turns with the probe set
    assert got["present"]["svae below vae_rpl on velocity"] == "holds"
    assert got["window"]["svae below vae_rpl on velocity"] == "does not hold"
    assert got["raw"] == {k: v for k, v in got["present"].items()}  # same errors read as raw
    # the verdicts' parts carry the paired differences; the present probe's match its detail text
    v = sets["present"][0]
    assert v.learners == ("vae", "vae_rpl") and len(v.parts) == 1
    label, mean, half = v.parts[0]
    assert label == "vae - vae_rpl, overall, π_rand" and f"{mean:+.3f} ± {half:.3f}" in v.detail
    assert mean == pytest.approx(0.4, abs=0.05) and 0 < half < mean
    md = findings.variants_markdown(sets, epochs, 6)
    row = next(line for line in md.splitlines() if line.startswith("| replay fixes"))
    cells = [c.strip() for c in row.split("|")[2:-1]]
    assert cells[0].startswith("**holds** (vae - vae_rpl, overall, π_rand +0.")
    assert cells[1].startswith("**undecided**")
    assert cells[2] == "n/a (no sequential learner)"  # the window variant changes no frame learner
    assert "| present probe | common probe set | whole window (sequential) | raw MAE |" in md
    pred_row = next(line for line in md.splitlines() if line.startswith("| PRED best"))
    assert pred_row.count(" ± ") == 4  # one decisive difference per variant, not all five
    assert not any(x.claim.startswith("probes agree") for x in sets["common"])


def test_records_without_variants_report_as_before() -> None:
    recs = synthetic({"present": PRESENT})
    sets, _ = findings.variant_checks(recs, SPEC, "InvertedPendulum")
    assert list(sets) == ["present"]
    assert [(v.claim, v.verdict, v.detail) for v in sets["present"]] == \
        [(v.claim, v.verdict, v.detail) for v in findings.check(recs, SPEC, "InvertedPendulum")[0]]


def _run_folder(path, recs: list[dict], env: str = "InvertedPendulum", dtype: str = "bfloat16") -> str:
    cfg = ExperimentConfig(env=env, learners=FIG2, seeds=6, probe_variants=("common", "window", "raw"))
    cfg = cfg.replace(learner=dataclasses.replace(cfg.learner, compute_dtype=dtype))
    path.mkdir()
    spread = [1.0] * len(env_class(env).state_spec)
    with open(path / "config.json", "w") as f:
        json.dump({"experiment": dataclasses.asdict(cfg), "run": {"seed": 0, "probe_every": 1}}, f)
    records.write_jsonl(str(path / "metrics.jsonl"), [{**r, "ref_spread": spread} for r in recs])
    return str(path)


def test_probe_protocol_table(tmp_path) -> None:
    """One row per claim, one column per variant and one for the fp32 run, per domain."""
    run = _run_folder(tmp_path / "invpend", synthetic({"present": PRESENT, "common": COMMON,
                                                       "window": WINDOW, "raw": PRESENT}))
    fp32 = _run_folder(tmp_path / "invpend_fp32", synthetic({"present": {**PRESENT, "vae": (0.2, 0.5)}}),
                       dtype="float32")
    cart = _run_folder(tmp_path / "cartpole", synthetic({"present": PRESENT}), env="CartPole")
    text = protocol.probe_protocol_table([run, cart], [fp32], str(tmp_path / "out"))
    assert (tmp_path / "out" / "table.md").read_text() == text
    inv = text.split("## InvertedPendulum")[1].split("## CartPole")[0]
    assert "| present probe | common probe set | whole window (sequential) | raw MAE | fp32 run |" in inv
    row = next(line for line in inv.splitlines() if line.startswith("| replay fixes"))
    cells = [c.strip().split(" (")[0] for c in row.split("|")[2:-1]]
    assert cells == ["**holds**", "**undecided**", "n/a", "**holds**", "**does not hold**"]
    assert "float32 learners" in inv and "bfloat16 learners" in inv
    cp = text.split("## CartPole")[1]
    assert "carries no probe variant" in cp and "| claim (paper, Fig. 2) | present probe |" in cp
    with pytest.raises(ValueError, match="no run of their domain"):
        protocol.probe_protocol_table([cart], [fp32])
    from bulbjax.cli import main
    cli = ["report", run, cart, "--probe-protocol", "--fp32", fp32, "--out", str(tmp_path / "cli")]
    assert main(cli) == 0
    assert (tmp_path / "cli" / "table.md").read_text() == text
    assert main(["report", run, "--probe-protocol"]) == 2  # --out missing: a one-line error


def test_report_of_a_run_with_variants(tmp_path) -> None:
    """table.md gets the variants' rows and the raw section; findings.md the claims under each."""
    recs = synthetic({"present": PRESENT, "common": COMMON, "window": WINDOW})
    for r in recs:  # raw as epoch_records writes it: from the present probe's entries
        one = summarise(np.full(5, 0.3), np.ones(5), np.ones(5), SPEC)
        r["probes"] = {n: {"curr": one, "rand": one} for n in FIG2}
        r["probes_raw"] = {n: {"curr": records.raw_summary(one), "rand": records.raw_summary(one)}
                           for n in FIG2}
    tab = report.table(recs, SPEC, last=3)
    assert "| svae (window) | π_rand |" in tab and "| vae (common) | π_curr |" in tab
    assert "## Raw MAE (probe variant `raw`)" in tab and "position (1, m)" in tab
    raw = tab.split("## Raw MAE")[1]
    assert "| vae | π_rand | 0.300 ± 0.000 | 0.300 ± 0.000 | 0.300 ± 0.000 |" in raw


def test_the_switch_and_old_run_folders(tmp_path) -> None:
    assert ExperimentConfig().probe_variants == ()
    for name in ("fig2-cartpole", "fig2-invpend", "fig3-rearrange-geom"):  # +43% per probed epoch (CPU)
        assert preset(name).probe_variants == ()
    on = resolve("fig2-invpend", overrides={"probe_variants": "common,window,raw"})
    assert on.probe_variants == ("common", "window", "raw") and on.probe_variants_run == on.probe_variants
    # a config.json written before the field reads back without variants (resumes and reports as made)
    old = dataclasses.asdict(on)
    del old["probe_variants"]
    assert config_from_dict(old) == on.replace(probe_variants=())
    assert resolve("fig2-invpend", overrides={"probe_variants": "none"}).probe_variants == ()
    given = resolve(overrides={"learners": "vae,svae", "probe_variants": "window,raw"})
    assert given.probe_variants == ("window", "raw")
    # bulbjax fit: the present probe only
    assert resolve_offline("fig2-invpend", small=True).base.probe_variants == ()
    with pytest.raises(ValueError, match="probe_variants must be distinct names of common, window, raw"):
        resolve(overrides={"probe_variants": "common,linear"})
    # a run without sequential learners has no window variant to compute
    frames_only = resolve("fig2-invpend", overrides={"learners": "vae_rpl", "probe_variants": "common,window"})
    assert frames_only.probe_variants_run == ("common",)
    from bulbjax.cli import main
    assert main(["run", "--probe-variants", "commons", "--out", str(tmp_path / "r")]) == 2
