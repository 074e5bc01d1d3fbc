"""Host-side reporting: per-epoch JSON lines, the Fig. 2-style plot and the final table."""

from __future__ import annotations

import json
import math
import os
from typing import Any, Sequence

import numpy as np

from bulbjax.eval.probe import summarise
from bulbjax.eval.spec import StateEntry

STREAMS = (("curr", "π_curr"), ("rand", "π_rand"))
# Student-t 95th percentiles (two-sided 90% band) for n-1 degrees of freedom.
_T95 = {1: 6.314, 2: 2.920, 3: 2.353, 4: 2.132, 5: 2.015, 6: 1.943, 7: 1.895, 8: 1.860, 9: 1.833}


def epoch_records(epoch: int, metrics: Any, spec: Sequence[StateEntry]) -> list[dict[str, Any]]:
    """One JSON-able record per seed from the epoch's metrics (arrays with a leading seed axis)."""
    m = _to_numpy(metrics)
    seeds = len(m["rl_return"])
    out = []
    for s in range(seeds):
        rec: dict[str, Any] = {
            "epoch": epoch, "seed": s,
            "rl_return": _f(m["rl_return"][s]), "rl_episodes": _f(m["rl_episodes"][s]),
            "ppo": {k: _f(v[s]) for k, v in m["ppo"].items()},
            "learners": {n: {k: _f(v[s]) for k, v in lm.items()} for n, lm in m["learners"].items()},
            "replay_dropped": {k: int(v[s]) for k, v in m["replay_dropped"].items()},
            "probes": {},
        }
        for name, streams in m["probes"].items():
            rec["probes"][name] = {
                stream: summarise(d["mae"][s], d["baseline"][s], d["spread"][s], spec)
                for stream, d in streams.items()}
        out.append(rec)
    return out


def write_jsonl(path: str, records: Sequence[dict[str, Any]]) -> None:
    with open(path, "a") as f:
        for r in records:
            f.write(json.dumps(r, allow_nan=True) + "\n")


def read_jsonl(path: str) -> list[dict[str, Any]]:
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def ci90(values: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and half-width of a 90% Student-t confidence interval over `axis` (seeds)."""
    n = values.shape[axis]
    mean = np.nanmean(values, axis=axis)
    if n < 2:
        return mean, np.zeros_like(mean)
    t = _T95.get(n - 1, 1.645)
    return mean, t * np.nanstd(values, axis=axis, ddof=1) / math.sqrt(n)


def _seed_epoch_matrix(records: Sequence[dict[str, Any]],
                       value: Any) -> tuple[np.ndarray, np.ndarray]:
    """Epochs and a `[seeds, epochs]` matrix of `value(record)` (NaN where it gives None)."""
    epochs = sorted({r["epoch"] for r in records})
    seeds = sorted({r["seed"] for r in records})
    v = np.full((len(seeds), len(epochs)), np.nan)
    for r in records:
        x = value(r)
        if x is not None:
            v[seeds.index(r["seed"]), epochs.index(r["epoch"])] = x
    return np.array(epochs), v


def curves(records: Sequence[dict[str, Any]], learner: str, stream: str, group: str,
           key: str = "mae_norm") -> tuple[np.ndarray, np.ndarray]:
    """Epochs and `[seeds, epochs]` values of a group's error (or `baseline_norm`)."""
    def value(r: dict[str, Any]) -> Any:
        g = r["probes"][learner][stream]["groups"].get(group)
        return None if g is None else g[key]
    return _seed_epoch_matrix(records, value)


def rl_curve(records: Sequence[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """Epochs and `[seeds, epochs]` PPO returns."""
    return _seed_epoch_matrix(records, lambda r: r["rl_return"])


def groups_of(spec: Sequence[StateEntry]) -> list[str]:
    return list(dict.fromkeys(e.group for e in spec))


def plot(records: Sequence[dict[str, Any]], spec: Sequence[StateEntry], path: str, title: str,
         solved_return: float | None = None) -> None:
    """Fig. 2 of the paper for one domain: normalised MAE against epoch for each learner (mean and
    90% band over seeds), rows pi_curr / pi_rand, one column per state group, RL return below.
    The dotted black line is the constant (median) predictor: an error is read against it."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = groups_of(spec)
    learners = list(records[0]["probes"])
    fig, axes = plt.subplots(3, len(groups), figsize=(4.2 * len(groups), 8.5), squeeze=False,
                             sharex=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for row, (stream, label) in enumerate(STREAMS):
        for col, group in enumerate(groups):
            ax = axes[row, col]
            for i, name in enumerate(learners):
                ep, v = curves(records, name, stream, group)
                mean, half = ci90(v)
                ax.plot(ep, mean, color=colours[i % len(colours)], label=name)
                ax.fill_between(ep, mean - half, mean + half, color=colours[i % len(colours)], alpha=0.2)
            ep, b = curves(records, learners[0], stream, group, key="baseline_norm")
            ax.plot(ep, np.nanmean(b, 0), "k:", label="constant predictor")
            ax.set_title(f"{label}: {group}")
            ax.set_ylabel("MAE / spread")
            ax.set_ylim(bottom=0)
    ep, r = rl_curve(records)
    mean, half = ci90(r)
    # epochs in which no episode ended (long locomotion episodes) have no return: join the others
    ok = np.isfinite(mean)
    ep, mean, half = np.asarray(ep)[ok], mean[ok], np.nan_to_num(half[ok])
    for col in range(len(groups)):
        ax = axes[2, col]
        ax.plot(ep, mean, color="tab:green", marker=".", label="PPO return")
        ax.fill_between(ep, mean - half, mean + half, color="tab:green", alpha=0.2)
        if solved_return is not None:
            ax.axhline(solved_return, color="k", ls="--", lw=0.8, label="solved")
        ax.set_xlabel("epoch")
        ax.set_ylabel("episode return")
    axes[0, 0].legend(fontsize=8)
    axes[2, 0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def table(records: Sequence[dict[str, Any]], spec: Sequence[StateEntry], last: int = 1) -> str:
    """Markdown table of the final normalised group errors (mean +- 90% CI over seeds, averaged
    over the `last` epochs) per learner and stream, with the constant predictor and RL return."""
    epochs = sorted({r["epoch"] for r in records})[-last:]
    recs = [r for r in records if r["epoch"] in epochs]
    groups = groups_of(spec)
    learners = list(recs[0]["probes"])
    head = "| learner | stream | " + " | ".join(f"{g} (norm. MAE)" for g in groups) + " | overall |"
    lines = [head, "|" + "---|" * (3 + len(groups))]
    seeds = sorted({r["seed"] for r in recs})

    def cell(vals: list[list[float]]) -> str:
        v = np.array([np.nanmean(x) for x in vals])  # per seed, mean over the last epochs
        mean, half = ci90(v)
        return f"{mean:.3f} ± {half:.3f}"

    for stream, label in STREAMS:
        for name in learners + ["constant"]:
            cells = []
            for g in groups + ["overall"]:
                vals = []
                for s in seeds:
                    rs = [r for r in recs if r["seed"] == s]
                    src = [r["probes"][learners[0] if name == "constant" else name][stream] for r in rs]
                    pick = [(x["overall"] if g == "overall" else x["groups"][g]) for x in src]
                    vals.append([p["baseline_norm" if name == "constant" else "mae_norm"] for p in pick])
                cells.append(cell(vals))
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
    ret = np.array([np.nanmean([r["rl_return"] for r in recs if r["seed"] == s]) for s in seeds])
    mean, half = ci90(ret)
    lines.append("")
    lines.append(f"PPO return over the last {last} epoch(s): {mean:.1f} ± {half:.1f} (90% CI over {len(seeds)} seeds)")
    return "\n".join(lines)


def _to_numpy(tree: Any) -> Any:
    if isinstance(tree, dict):
        return {k: _to_numpy(v) for k, v in tree.items()}
    return np.asarray(tree)


def _f(x: Any) -> float:
    return float(np.asarray(x))
