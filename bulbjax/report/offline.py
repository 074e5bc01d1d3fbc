"""An offline fit's records and reports (`bulbjax fit`): one record per probe and seed
(`records_of`, kept in `curves.jsonl`), the log line of a probe (`summary_line`), and the files
a fit leaves (`write_outputs`: `curves.png`, `table.md`, `recon.png`). The fit's programs are
`bulbjax.epoch.offline`, driving it `bulbjax.run.offline`."""

from __future__ import annotations

import os
from typing import Any

import jax
import numpy as np

from bulbjax.data.sequence import Windows
from bulbjax.eval import probe
from bulbjax.eval.spec import StateEntry
from bulbjax.report import figures
from bulbjax.report.records import clamped_share, linear_summary, nanmean
from bulbjax.report.report import offline_title, write_offline_reports


def records_of(update: int, probes: Any, losses: Any, ref_spread: np.ndarray,
               spec: tuple[StateEntry, ...], seeds: int) -> list[dict[str, Any]]:
    """One JSON-able record per seed for a probe after `update` updates."""
    p, lm = jax.device_get(probes), jax.device_get(losses)
    out = []
    for s in range(seeds):
        rec: dict[str, Any] = {"update": update, "seed": s, "ref_spread": [float(x) for x in ref_spread],
                               "learners": {n: {k: float(v[s]) for k, v in m.items()} for n, m in lm.items()},
                               "probes": {}}
        for name, streams in p.items():
            rec["probes"][name] = {st: probe.summarise(d["mae"][s], d["baseline"][s], ref_spread, spec,
                                                        spread_D=d["spread"][s])
                                   for st, d in streams.items()}
            if any("linear_mae" in d for d in streams.values()):
                rec.setdefault("linear_probes", {})[name] = {
                    st: linear_summary(d, s, ref_spread, spec) for st, d in streams.items()}
            if clamped := clamped_share(streams, s):
                rec.setdefault("probe_inputs_clamped", {})[name] = clamped
        out.append(rec)
    return out


def _norm_text(v: float) -> str:
    """A normalised error for the log line; "excluded" for a group none of whose entries can be
    normalised (NaN: every entry constant in the data)."""
    return f"{v:.2f}" if np.isfinite(v) else "excluded"


def summary_line(recs: list[dict]) -> str:
    """A probe's log line: every learner's normalised error per group (the mean over seeds), then
    the constant predictor's, e.g. `vae 0.41/0.93; constant 1.00/1.00  (position/velocity)`."""
    parts = []
    for name in recs[0]["probes"]:
        g = recs[0]["probes"][name]["rand"]["groups"]
        vals = {k: nanmean([r["probes"][name]["rand"]["groups"][k]["mae_norm"] for r in recs]) for k in g}
        parts.append(f"{name} " + "/".join(_norm_text(v) for v in vals.values()))
    base = recs[0]["probes"][next(iter(recs[0]["probes"]))]["rand"]["groups"]
    parts.append("constant " + "/".join(_norm_text(g["baseline_norm"]) for g in base.values()))
    return "; ".join(parts) + f"  ({'/'.join(base)})"


def write_outputs(fit: Any, records: list[dict], states: dict, held: Windows, out_dir: str,
                  wall: float, t_data: float) -> None:
    """`curves.png` (normalised error against updates per group and learner, constant
    predictor dotted), `table.md` (last probe) and `recon.png` (held-out frames and every
    learner's reconstruction, seed 0)."""
    c = fit.config
    title = offline_title(fit.source.name, fit.S, records)
    timing = (f"wall time {wall:.1f} s (data {t_data:.1f} s) on {jax.devices()[0].device_kind}; "
              f"batch {c.base.learner.batch_size} frames, sequential {c.base.seq_len}-step windows")
    write_offline_reports(out_dir, records, fit.spec, title, footer=timing)
    save_recon_grid(fit, states, held, os.path.join(out_dir, "recon.png"))


def save_recon_grid(fit: Any, states: dict, held: Windows, path: str, n: int = 8) -> None:
    """Row 0: `n` consecutive held-out frames (one window); then one row per learner that has
    `reconstruct` (seed 0; the contrastive ones and others without it have none, and with none
    at all no figure is written). Drawn by `figures` (the paper's Fig. 4 layout)."""
    learners = {n: x for n, x in fit.learners.items() if hasattr(x, "reconstruct")}
    if not learners:
        if os.path.exists(path):  # an earlier fit's, in an overwritten folder
            os.remove(path)
        return
    figures.recon_figure(path, learners, figures.seed_params(states, 0), held,
                         figures.FigureConfig(frames=n), title=f"{fit.source.name}: held-out frames, seed 0")
