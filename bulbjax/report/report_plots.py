"""The plots of a run's reports: the Fig. 2-style plot (`plot`: normalised error against epoch per
learner and state group, PPO's return below) and the object-probe plot (`plot_objects`), with
y-limits that stay readable when one probe spikes (`plot_limits`); and what the plotted and
tabled errors divide by (`norm_note`). `report` writes them into run folders."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from bulbjax.eval.spec import StateEntry
from bulbjax.report.plot_limits import OFF_AXIS_NOTE, Curve, limit_axis
from bulbjax.report.records import (NORM_NOTE, STREAMS, ci90, curves, excluded_groups, groups_of, has_linear, nanmean,
                                    object_curves, probed, rl_curve)

# What the errors of runs made before issue 12 (records without `ref_spread`) divide by.
OLD_NORM_NOTE = ("normalised error = MAE / spread of the stream being scored (mean absolute deviation "
                 "around the median of that stream's held-out states, per epoch); sequential learners "
                 "probed on z_t alone")


def has_reference_spread(records: Sequence[dict[str, Any]]) -> bool:
    """Whether the probed records carry the run's fixed reference spread (`ref_spread`): runs made
    before issue 12 divided each stream's error by that stream's own spread instead."""
    return any("ref_spread" in r for r in probed(records))


def norm_note(records: Sequence[dict[str, Any]]) -> str:
    """What the normalised errors of `records` divide by: `NORM_NOTE`, or `OLD_NORM_NOTE` for
    records made before the fixed reference spread."""
    return NORM_NOTE if has_reference_spread(records) else OLD_NORM_NOTE


def plot(records: Sequence[dict[str, Any]], spec: Sequence[StateEntry], path: str, title: str,
         solved_return: float | None = None, x_key: str = "epoch",
         streams: Sequence[tuple[str, str]] = STREAMS) -> int:
    """Fig. 2 of the paper for one domain: normalised MAE against epoch for each learner (mean and
    90% band over seeds), rows pi_curr / pi_rand, one column per state group, RL return below
    (when the records have one). The dotted black line is the constant (median) predictor: an
    error is read against it. Solid lines and bands: the MLP probe; dashed lines (mean over
    seeds): the linear (ridge) probe of the same pairs, when the records have one. Offline fits
    plot against `x_key="update"`, one stream. An error axis whose curves spike at a point ends
    above the rest, the spike marked with its value (`plot_limits`); returns how many points
    were marked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = groups_of(spec)
    learners = list(probed(records)[0]["probes"])
    linear = has_linear(records)
    has_rl = "rl_return" in records[0]
    rows = len(streams) + has_rl
    fig, axes = plt.subplots(rows, len(groups), figsize=(4.2 * len(groups), 2.9 * rows + 0.6),
                             squeeze=False, sharex=True)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    gone = excluded_groups(records)
    marked = 0
    for row, (stream, label) in enumerate(streams):
        for col, group in enumerate(groups):
            ax = axes[row, col]
            if group in gone:
                ax.set_title(f"{label}: {group}")
                ax.text(0.5, 0.5, "excluded\n(constant over the run:\nnothing to predict)", ha="center",
                        va="center", transform=ax.transAxes, color="0.4")
                continue
            drawn = []
            for i, name in enumerate(learners):
                ep, v = curves(records, name, stream, group, x_key=x_key)
                mean, half = ci90(v)
                ax.plot(ep, mean, color=colours[i % len(colours)], label=name, marker="." if len(ep) < 30 else None)
                ax.fill_between(ep, mean - half, mean + half, color=colours[i % len(colours)], alpha=0.2)
                drawn.append(Curve.of(ep, mean, half, colours[i % len(colours)]))
                if linear:
                    ep, v = curves(records, name, stream, group, x_key=x_key, probes="linear_probes")
                    ax.plot(ep, nanmean(v, 0), color=colours[i % len(colours)], ls="--", lw=1.0,
                            label=f"{name} (linear)")
                    drawn.append(Curve.of(ep, nanmean(v, 0), colour=colours[i % len(colours)]))
            ep, b = curves(records, learners[0], stream, group, key="baseline_norm", x_key=x_key)
            ax.plot(ep, nanmean(b, 0), "k:", label="constant predictor")
            drawn.append(Curve.of(ep, nanmean(b, 0)))
            ax.set_title(f"{label}: {group}")
            ax.set_ylabel("MAE / π_rand reference spread")
            marked += limit_axis(ax, drawn)  # one spiking seed-epoch does not flatten the rest
            if not has_rl and row == rows - 1:
                ax.set_xlabel(x_key)
    if has_rl:  # one panel across the bottom row
        for ax in axes[-1]:
            ax.remove()
        _plot_rl(fig.add_subplot(axes[0, 0].get_gridspec()[-1, :], sharex=axes[0, 0]), records,
                 solved_return)
    axes[0, 0].legend(fontsize=8)
    import textwrap
    probes_note = "solid: MLP probe (90% band); dashed: linear (ridge) probe. " if linear else ""
    off_axis = f". {OFF_AXIS_NOTE}" if marked else ""
    note = "\n".join(textwrap.wrap(probes_note + norm_note(records) + off_axis, 55 * len(groups)))
    fig.suptitle(f"{title}\n{note}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return marked


def plot_objects(records: Sequence[dict[str, Any]], path: str, title: str,
                 streams: Sequence[tuple[str, str]] = STREAMS) -> int:
    """The object-level probes against epoch (issue 11), mean and 90% band over seeds: for the
    learners with boxes (SPAIR) the mean distance from each true object to the nearest present box
    centre (px) and the share of objects found within the radius; for every learner the MLP
    probe's normalised error on the `object_position` group, with the constant predictor dotted.
    Rows pi_curr / pi_rand. Spikes as in `plot`; returns how many points were marked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    boxed = list(dict.fromkeys(n for r in records for n in r.get("objects", {})))
    learners = list(probed(records)[0]["probes"])
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colour = {n: colours[i % len(colours)] for i, n in enumerate(learners)}
    radius = next(o["radius"] for r in records for d in r.get("objects", {}).values() for o in d.values())
    fig, axes = plt.subplots(len(streams), 3, figsize=(13, 3.0 * len(streams) + 0.5), squeeze=False, sharex=True)
    marked = 0
    for row, (stream, label) in enumerate(streams):
        for col, (key, ylabel) in enumerate((("error_mean", "px"), ("found_share", f"share within {radius:.1f} px"))):
            ax = axes[row, col]
            drawn = []
            for name in boxed:
                ep, v = object_curves(records, name, stream, key)
                mean, half = ci90(v)
                ax.plot(ep, mean, color=colour.get(name), label=name)
                ax.fill_between(ep, mean - half, mean + half, color=colour.get(name), alpha=0.2)
                drawn.append(Curve.of(ep, mean, half, colour.get(name)))
            ax.set_title(f"{label}: boxes, {'distance to nearest box' if col == 0 else 'objects found'}")
            ax.set_ylabel(ylabel)
            if col == 0:
                marked += limit_axis(ax, drawn)
            else:
                ax.set_ylim(0, 1.02)
        ax = axes[row, 2]
        drawn = []
        for name in learners:
            ep, v = curves(records, name, stream, "object_position")
            mean, half = ci90(v)
            ax.plot(ep, mean, color=colour[name], label=name)
            ax.fill_between(ep, mean - half, mean + half, color=colour[name], alpha=0.2)
            drawn.append(Curve.of(ep, mean, half, colour[name]))
        ep, b = curves(records, learners[0], stream, "object_position", key="baseline_norm")
        ax.plot(ep, nanmean(b, 0), "k:", label="constant predictor")
        drawn.append(Curve.of(ep, nanmean(b, 0)))
        ax.set_title(f"{label}: MLP probe, object_position")
        ax.set_ylabel("MAE / π_rand reference spread")
        marked += limit_axis(ax, drawn)  # one spiking seed-epoch does not flatten the rest
    for ax in axes[-1]:
        ax.set_xlabel("epoch")
    axes[0, 0].legend(fontsize=8)
    axes[0, 2].legend(fontsize=8)
    fig.suptitle(f"{title}: object-level probes" + (f"\n{OFF_AXIS_NOTE}" if marked else ""), fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return marked


def rl_band(ep: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of `rl_curve`'s epochs and `[seeds, epochs]` returns: the epochs with a return, the mean
    return and its 90% CI half-width over seeds."""
    mean, half = ci90(r)
    # epochs in which no episode ended (long locomotion episodes) have no return: join the others
    ok = np.isfinite(mean)
    return np.asarray(ep)[ok], mean[ok], np.nan_to_num(half[ok])


def _plot_rl(ax: Any, records: Sequence[dict[str, Any]], solved_return: float | None) -> None:
    """The PPO return panel of the Fig. 2 plot: the mean and its 90% band over seeds, and each
    seed's own curve (thin), which with few seeds says more than the band (over two seeds the
    t-band is the mean ± 6.3 standard errors: CartPole's reaches below 0 and above 200)."""
    epochs, r = rl_curve(records)
    ep, mean, half = rl_band(epochs, r)
    seeds = len(r)
    ax.plot(ep, mean, color="tab:green", marker=".",
            label="PPO return" + (f" (mean, 90% band over {seeds} seeds)" if seeds > 1 else ""))
    ax.fill_between(ep, mean - half, mean + half, color="tab:green", alpha=0.2)
    if seeds > 1:
        for i, row in enumerate(np.asarray(r, float)):
            ok = np.isfinite(row)
            ax.plot(np.asarray(epochs)[ok], row[ok], color="tab:green", lw=0.6, alpha=0.5,
                    label="each seed" if i == 0 else None)
    if solved_return is not None:
        ax.axhline(solved_return, color="k", ls="--", lw=0.8, label="solved")
    ax.set_xlabel("epoch")
    ax.set_ylabel("episode return")
    ax.legend(fontsize=8)
