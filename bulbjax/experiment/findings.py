"""The paper's Fig. 2 findings, checked on a run's metrics with 90% bands.

Every learner of a seed sees the same PPO run and the same frames, so learners are compared by
their per-seed difference (paired over seeds): a claim "A's error is lower than B's" holds when
the 90% Student-t band of `err_B - err_A` over seeds lies above 0, does not hold when it lies
below 0, and is undecided when it contains 0. Errors are the normalised MAEs of the reports
(`report.table`), each seed's averaged over the last probed epochs.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from bulbjax.eval.spec import StateEntry
from bulbjax.experiment.records import STREAMS, ci90, excluded_groups, groups_of, per_seed_error, probed

PENDULUMS = ("CartPole", "InvertedPendulum")
LOCOMOTION = ("HalfCheetah", "Ant")
SEQUENTIAL = ("svae", "pred", "dsa")
CONTRASTIVE = ("stdim", "curl")


@dataclasses.dataclass(frozen=True)
class Verdict:
    """One claim: `holds`, `does not hold`, `undecided` or `not tested`, and the numbers."""

    claim: str
    verdict: str
    detail: str


def paired_verdict(lower: np.ndarray, higher: np.ndarray) -> tuple[str, float, float]:
    """The rule every claim row uses: "`lower` below `higher`" from their per-seed differences
    (seeds where both are finite), mean ± 90% band; holds when the band lies above 0, does not
    hold when below, undecided when it contains 0 (or fewer than two seeds give a band)."""
    diff = higher - lower
    diff = diff[np.isfinite(diff)]
    mean, half = ci90(diff) if diff.size >= 2 else (float(np.mean(diff)) if diff.size else np.nan, np.inf)
    verdict = "holds" if mean - half > 0 else "does not hold" if mean + half < 0 else "undecided"
    return verdict, mean, half


def _lower(records, a: str, b: str, stream: str, group: str | None, epochs) -> tuple[str, str]:
    """Verdict and numbers for "a's error is lower than b's" (paired over seeds)."""
    ea, eb = (per_seed_error(records, x, stream, group, epochs) for x in (a, b))
    verdict, mean, half = paired_verdict(ea, eb)
    what = group or "overall"
    return verdict, (f"{what}, {stream_label(stream)}: {a} {np.nanmean(ea):.3f}, {b} {np.nanmean(eb):.3f}; "
                     f"{b} - {a} = {mean:+.3f} ± {half:.3f}")


def stream_label(stream: str) -> str:
    return dict(STREAMS).get(stream, stream)


def _velocity_group(spec: Sequence[StateEntry]) -> str | None:
    return next((g for g in groups_of(spec) if "vel" in g.lower()), None)


def _combine(verdicts: Sequence[str]) -> str:
    """All parts hold -> holds; any part does not hold -> does not hold; else undecided."""
    if "does not hold" in verdicts:
        return "does not hold"
    return "holds" if all(v == "holds" for v in verdicts) else "undecided"


def check(records: Sequence[dict[str, Any]], spec: Sequence[StateEntry], env: str,
          last: int = 3) -> tuple[list[Verdict], list[int]]:
    """The Fig. 2 claims on the last `last` probed epochs; returns the verdicts and those epochs."""
    epochs = sorted({r["epoch"] for r in probed(records)})[-last:]
    have = set(probed(records)[0]["probes"]) if probed(records) else set()
    vel = _velocity_group(spec)
    out: list[Verdict] = []

    def missing(*names: str) -> str | None:
        lack = [n for n in names if n not in have]
        return f"not tested (the run has no {', '.join(lack)})" if lack else None

    claim = "replay fixes VAE_v0 on π_rand (vae_rpl's error below vae's)"
    if m := missing("vae", "vae_rpl"):
        out.append(Verdict(claim, m, ""))
    else:
        out.append(Verdict(claim, *_lower(records, "vae_rpl", "vae", "rand", None, epochs)))

    claim = "β-VAE no better than VAE_rpl (beta_vae's error not below vae_rpl's on either stream)"
    if m := missing("beta_vae", "vae_rpl"):
        out.append(Verdict(claim, m, ""))
    else:
        parts = [_lower(records, "beta_vae", "vae_rpl", s, None, epochs) for s in ("rand", "curr")]
        better = any(v == "holds" for v, _ in parts)  # beta_vae significantly lower somewhere
        seeds = len({r["seed"] for r in records})
        worse_or_same = "does not hold" if better else "holds" if seeds >= 2 else "undecided"
        out.append(Verdict(claim, worse_or_same, "; ".join(d for _, d in parts)))

    for name in SEQUENTIAL:
        claim = f"sequential learners better on velocity: {name} below vae_rpl on {vel or 'velocity'}"
        if vel is None:
            out.append(Verdict(claim, "not tested (no velocity group in this domain's state)", ""))
        elif m := missing(name, "vae_rpl"):
            out.append(Verdict(claim, m, ""))
        else:
            parts = [_lower(records, name, "vae_rpl", s, vel, epochs) for s in ("rand", "curr")]
            out.append(Verdict(claim, _combine([v for v, _ in parts]), "; ".join(d for _, d in parts)))

    claim = "PRED best on the pendulums (pred's error below every other learner's on π_rand)"
    if env not in PENDULUMS:
        out.append(Verdict(claim, "not tested (not a pendulum domain)", ""))
    elif m := missing("pred"):
        out.append(Verdict(claim, m, ""))
    else:
        parts = [_lower(records, "pred", o, "rand", None, epochs) for o in sorted(have - {"pred"})]
        out.append(Verdict(claim, _combine([v for v, _ in parts]), "; ".join(d for _, d in parts)))

    claim = "on locomotion PRED ahead of VAE_rpl on π_curr"
    if env not in LOCOMOTION:
        out.append(Verdict(claim, "not tested (not a locomotion domain)", ""))
    elif m := missing("pred", "vae_rpl"):
        out.append(Verdict(claim, m, ""))
    else:
        out.append(Verdict(claim, *_lower(records, "pred", "vae_rpl", "curr", None, epochs)))
    for name in CONTRASTIVE:  # beyond the paper: rows only where the run has the learner
        if name not in have:
            continue
        for group in [g for g in ("position", vel) if g and g in groups_of(spec)]:
            claim = f"contrastive vs VAE_rpl on {group}: {name} below vae_rpl (beyond the paper)"
            if m := missing("vae_rpl"):
                out.append(Verdict(claim, m, ""))
                continue
            parts = [_lower(records, name, "vae_rpl", s, group, epochs) for s in ("rand", "curr")]
            out.append(Verdict(claim, _combine([v for v, _ in parts]), "; ".join(d for _, d in parts)))
    out += added_learner_rows(records, spec, epochs)
    out += _probe_agreement(records, epochs)
    return out, epochs


# every learner the paper's figures (and this suite's contrastive additions) have claims about
PAPER_LEARNERS = ("vae", "vae_rpl", "beta_vae", *SEQUENTIAL, "spair", "spair6", *CONTRASTIVE)


def added_learner_rows(records: Sequence[dict[str, Any]], spec: Sequence[StateEntry],
                       epochs: Sequence[int]) -> list[Verdict]:
    """Rows for each learner beyond the paper's (`PAPER_LEARNERS`: a researcher's own, added with
    `--learners pkg.module:Name` or `bulbjax reproduce --add-learner`): per state group, its error
    below VAE_rpl's and below the constant predictor's, on both streams (paired over seeds), so a
    new method reads against the paper's baseline on every figure."""
    recs = probed(records)
    have = list(recs[0]["probes"]) if recs else []
    gone = excluded_groups(recs)
    out = []
    for name in [n for n in have if n not in PAPER_LEARNERS]:
        for group in [g for g in groups_of(spec) if g not in gone]:
            for other, label in (("vae_rpl", "VAE_rpl"), ("constant", "the constant predictor")):
                claim = f"{name} below {label} on {group} (added learner)"
                if other != "constant" and other not in have:
                    out.append(Verdict(claim, f"not tested (the run has no {other})", ""))
                    continue
                parts = [_lower(records, name, other, s, group, epochs) for s in ("rand", "curr")]
                out.append(Verdict(claim, _combine([v for v, _ in parts]), "; ".join(d for _, d in parts)))
    return out


def _probe_agreement(records: Sequence[dict[str, Any]], epochs: Sequence[int]) -> list[Verdict]:
    """Per learner with a linear probe: the MLP probe's error not above the linear probe's on
    the same pairs (overall, both streams), a check on the MLP's choices (an MLP that overfits
    or picks the wrong snapshot lands above the linear probe). Does not hold when the linear
    probe is lower on a stream (90% band of `mlp - linear` above 0); holds otherwise with 2 or
    more seeds. The numbers show how far the two probes agree."""
    linear = [r for r in probed(records) if r.get("linear_probes")]
    if not linear:
        return []
    out = []
    for name in linear[0]["linear_probes"]:
        verdicts, parts = [], []
        for stream in ("rand", "curr"):
            mlp = per_seed_error(records, name, stream, None, epochs)
            lin = per_seed_error(records, name, stream, None, epochs, probes="linear_probes")
            diff = (mlp - lin)[np.isfinite(mlp - lin)]
            mean, half = ci90(diff) if diff.size >= 2 else (float(np.mean(diff)) if diff.size else np.nan, np.inf)
            verdicts.append("does not hold" if mean - half > 0 else "holds" if diff.size >= 2 else "undecided")
            parts.append(f"overall, {stream_label(stream)}: MLP {np.nanmean(mlp):.3f}, linear {np.nanmean(lin):.3f}; "
                         f"MLP - linear = {mean:+.3f} ± {half:.3f}")
        out.append(Verdict(f"probes agree for {name}: MLP probe's error not above the linear probe's "
                           "(beyond the paper)", _combine(verdicts), "; ".join(parts)))
    return out


def markdown(verdicts: Sequence[Verdict], epochs: Sequence[int], seeds: int) -> str:
    """The verdicts as a markdown table, with the rule that decides them."""
    lines = ["| claim (paper, Fig. 2) | verdict | numbers (normalised MAE; difference ± 90% band) |",
             "|---|---|---|"]
    lines += [f"| {v.claim} | **{v.verdict}** | {v.detail} |" for v in verdicts]
    lines += ["", f"Epochs {', '.join(map(str, epochs))}; each seed's error averaged over them; "
              f"differences paired by seed ({seeds} seeds), 90% Student-t band. A claim holds when "
              "the band lies on its side of 0, does not hold when it lies on the other side, and is "
              "undecided when it contains 0."]
    return "\n".join(lines)
