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
from bulbjax.experiment import report
from bulbjax.experiment.records import band, excluded_groups

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
    from bulbjax.experiment.run import _postfix

    recs = _records(seeds)
    text = _postfix([r for r in recs if r["epoch"] == 10], recs)
    assert all("nan" not in v for v in text.values()), text
    # every group excluded: the bar says so instead of nan
    for r in recs:
        for st in r["probes"]["vae"].values():
            st["overall"]["mae_norm"] = float("nan")
    assert _postfix([r for r in recs if r["epoch"] == 10], recs)["vae/rand"] == "excluded"
