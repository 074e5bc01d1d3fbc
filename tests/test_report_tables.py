"""Reports of runs with a group none of whose entries can be normalised (`object_static` on one
fixed Rearrange version: the objects' properties never change) and of 1-seed runs (issue 37):
the table says "excluded" and "1 seed", the plots draw the group as excluded, the progress
bar's text never shows "nan", and no "Mean of empty slice" warning is raised. Synthetic records
through the real `probe.summarise`; CPU only."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from bulbjax.eval.probe import summarise
from bulbjax.eval.spec import StateEntry
from bulbjax.report import report
from bulbjax.report.records import band, excluded_groups

SPEC = (StateEntry("j0_sin", "1", "robot"), StateEntry("j0_cos", "1", "robot"),
        StateEntry("obj0_mass", "[-1,1]", "object_static"), StateEntry("obj0_shape", "[-1,1]", "object_static"),
        StateEntry("obj0_x", "m", "object_position"), StateEntry("obj0_y", "m", "object_position"))


def _records(seeds: int, static_spread: float = 0.0) -> list[dict]:
    rng = np.random.default_rng(0)
    ref = np.array([0.5, 0.5, static_spread, static_spread, 0.2, 0.2])
    out = []
    for epoch in (5, 10):
        for s in range(seeds):
            probes = {}
            for name in ("vae", "vae_rpl"):
                mae = ref * rng.uniform(0.3, 0.9, 6)
                probes[name] = {st: summarise(mae, ref, ref, SPEC, spread_D=ref) for st in ("curr", "rand")}
            out.append({"epoch": epoch, "seed": s, "rl_return": 1.0, "probes": probes,
                        "ref_spread": ref.tolist()})
    return out


def test_an_all_excluded_group_reads_excluded_without_warnings(tmp_path):
    recs = _records(3)
    assert excluded_groups(recs) == {"object_static"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "Mean of empty slice" and friends fail the test
        tab = report.table(recs, SPEC, last=2)
        report.plot(recs, SPEC, str(tmp_path / "fig2.png"), "t")
    assert "nan" not in tab.lower()
    rows = [line for line in tab.splitlines() if line.startswith("| vae") or line.startswith("| constant")]
    assert len(rows) == 6 and all(line.split(" | ")[3] == "excluded" for line in rows)
    assert all("±" in line.split(" | ")[2] for line in rows)  # the other groups keep their bands
    assert "excluded: object_static" in tab and (tmp_path / "fig2.png").stat().st_size > 0
    # a group that varies is not excluded
    assert excluded_groups(_records(3, static_spread=0.3)) == set()


def test_a_one_seed_table_says_1_seed_not_plus_minus_zero():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tab = report.table(_records(1), SPEC, last=2)
    assert "± 0.000" not in tab and "(1 seed)" in tab and "1 seed: no band" in tab
    assert band(0.5, 0.0, 1) == "0.500 (1 seed)" and band(0.5, 0.1, 3) == "0.500 ± 0.100"
    assert band(float("nan"), 0.0, 3) == "–"


@pytest.mark.parametrize("seeds", [1, 3])
def test_progress_bar_text_has_no_nan(seeds):
    from bulbjax.run.loop import _postfix

    recs = _records(seeds)
    text = _postfix([r for r in recs if r["epoch"] == 10], recs)
    assert all("nan" not in v for v in text.values()), text
    # every group excluded: the bar says so instead of nan
    for r in recs:
        for st in r["probes"]["vae"].values():
            st["overall"]["mae_norm"] = float("nan")
    assert _postfix([r for r in recs if r["epoch"] == 10], recs)["vae/rand"] == "excluded"


def test_report_redraws_an_offline_fit_folder(tmp_path, capsys):
    """`bulbjax report FIT_DIR` on a `bulbjax fit` folder (config.json with `offline`, `base`,
    `source`, `seed`; `curves.jsonl`): curves.png and table.md again, through the same table code
    as the fit (issue 57: it failed with "ExperimentConfig has no fields ['base', 'offline', ...]").
    A SyntheticMovers fit: the state spec comes from its movers settings."""
    import dataclasses
    import json

    from bulbjax.cli import main
    from bulbjax.config import preset
    from bulbjax.offline_config import OfflineConfig
    from bulbjax.data import synthetic
    from bulbjax.epoch.probing import probe_targets
    from bulbjax.report.records import write_jsonl

    base = preset("fig2-invpend").replace(env=synthetic.NAME, learners=("vae", "svae"), seeds=2,
                                          resolution=32)
    oc = OfflineConfig(base=base, movers=synthetic.MoversConfig(num_objects=1))
    with open(tmp_path / "config.json", "w") as f:
        json.dump({"offline": {k: v for k, v in dataclasses.asdict(oc).items() if k != "base"},
                   "base": dataclasses.asdict(base), "source": synthetic.NAME, "seed": 0}, f)
    spec = probe_targets(oc.movers_config().state_spec).spec
    assert len(spec) == 4  # one mover: x, y, vx, vy
    rng = np.random.default_rng(0)
    ref = np.full(len(spec), 2.0)
    def probe() -> dict:
        return {"rand": summarise(ref * rng.uniform(0.2, 0.9, len(spec)), ref, ref, spec, spread_D=ref)}

    recs = [{"update": u, "seed": s, "ref_spread": ref.tolist(), "probes": {n: probe() for n in ("vae", "svae")}}
            for u in (0, 5, 10) for s in range(2)]
    write_jsonl(str(tmp_path / "curves.jsonl"), recs)
    want = report.table(recs, spec, last=1, x_key="update", streams=report.OFFLINE_STREAMS)
    assert main(["report", str(tmp_path)]) == 0
    assert "curves.png" in capsys.readouterr().out and (tmp_path / "curves.png").stat().st_size > 10_000
    table = (tmp_path / "table.md").read_text()
    assert table.startswith(f"# {synthetic.NAME} offline: 2 seeds, 10 updates\n\n{want}\n")
    assert "update 10; mean ± 90% CI over 2 seeds." in table and "| svae | held-out π_rand |" in table
