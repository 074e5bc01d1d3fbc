"""Y-limits of the report plots that stay readable when one probe spikes.

A probe's error can jump for one seed at one probed epoch (issue 57: in the fig3-rearrange-geom
run on the fixed scene one seed-epoch of spair6 reached ~150x the reference spread, back to
normal at the next probe): with matplotlib's own limits the axis then spans the spike and every
learner's curve lies flat at the bottom. Here a point is a *spike* when it lies more than
`factor` times above its neighbours on both sides (`spikes`: a jump up and back down, not a
learning curve's early fall). The axis ends a little above the
highest point that is no spike; only when the spikes would stretch it by more than `slack`, so a
plot without spikes keeps its usual limits. Every point above the axis is marked at its top edge
in its curve's colour with its value printed: a filled triangle where the mean is off the axis,
an open one where only the 90% band's top is. Nothing is dropped: the values stay in the
records and tables.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

OFF_AXIS_NOTE = "▲ filled: a mean above the axis, open: a band's top above it (value printed)."


@dataclass(frozen=True)
class Curve:
    """One plotted curve: its x, mean and the top of its band (the mean where it has none),
    drawn in `colour`."""

    x: np.ndarray
    mean: np.ndarray
    top: np.ndarray
    colour: Any = "k"

    @staticmethod
    def of(x: Any, mean: Any, half: Any = None, colour: Any = "k") -> "Curve":
        mean = np.asarray(mean, float)
        top = mean if half is None else mean + np.nan_to_num(np.asarray(half, float))
        return Curve(np.asarray(x), mean, top, colour)


def spikes(y: Any, factor: float = 4.0, reach: int = 2) -> np.ndarray:
    """Mask of the points of `y` (a curve over epochs) more than `factor` x the lowest finite
    value within `reach` points on *each* side: a jump up and back down (two spiking epochs in
    a row included). The ends of a curve, NaN and points without a finite neighbour on both
    sides are no spikes (a learning curve starts high: that is the curve, not a spike)."""
    y = np.asarray(y, float)
    out = np.zeros(y.shape, bool)
    for i, v in enumerate(y):
        if not np.isfinite(v) or v <= 0:
            continue
        left, right = y[max(0, i - reach):i], y[i + 1:i + 1 + reach]
        left, right = left[np.isfinite(left)], right[np.isfinite(right)]
        if left.size and right.size:
            out[i] = v > factor * max(float(left.min()), float(right.min()), 0.0)
    return out


def upper_limit(curves: Sequence[Curve], factor: float = 4.0, reach: int = 2, slack: float = 1.3,
                headroom: float = 1.08) -> float | None:
    """The top of a y-axis that starts at 0 for `curves`: `headroom` x the highest mean or band
    top that is no spike (`spikes`), or None (matplotlib's own limit) when no spike rises more
    than `slack` x above that."""
    kept, every = [], []
    for c in curves:
        for y in (c.mean, c.top):
            ok = np.isfinite(y)
            every.append(y[ok])
            kept.append(y[ok & ~spikes(y, factor, reach)])
    kept_all, all_all = np.concatenate(kept or [np.zeros(0)]), np.concatenate(every or [np.zeros(0)])
    if not kept_all.size or not all_all.size:
        return None
    bulk, peak = float(kept_all.max()), float(all_all.max())
    if bulk <= 0 or peak <= slack * headroom * bulk:
        return None
    return headroom * bulk


def limit_axis(ax: Any, curves: Sequence[Curve], **kw: Any) -> int:
    """Set `ax`'s y-axis to start at 0 and end at `upper_limit(curves, **kw)`, marking each
    point above it (see the module doc); returns how many points were marked (0: matplotlib's
    own top)."""
    top = upper_limit(curves, **kw)
    if top is None:
        ax.set_ylim(bottom=0)
        return 0
    ax.set_ylim(0, top)
    marked = 0
    for c in curves:
        for x, m, t in zip(c.x, c.mean, c.top):
            if not (np.isfinite(t) and t > top):
                continue
            whole = np.isfinite(m) and m > top
            ax.plot([x], [top], marker="^", ms=5, color=c.colour, mfc=c.colour if whole else "white",
                    clip_on=False, zorder=5)
            # the value inside the axes, beside the marker (above it lies the panel's title)
            ax.annotate(f"{m if whole else t:.3g}", (x, top), xytext=(4, -2), textcoords="offset points",
                        ha="left", va="top", fontsize=7, color=c.colour, annotation_clip=False,
                        bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.8})
            marked += 1
    return marked
