"""Report plots stay readable when one probe spikes (issue 57: in the fig3-rearrange-geom run one
seed-epoch of one learner reached ~150x the reference spread, and the axis scaled to it left every
curve flat at the bottom). Synthetic records through the real `probe.summarise`: one seed at one
epoch spikes; the axis of that panel ends near the other curves and the spike is marked at the
top edge with its value; the other panels keep matplotlib's own limits. And the PPO return is
one panel across the bottom row, each seed's curve beside the band. CPU only."""

from __future__ import annotations

import matplotlib
import matplotlib.figure
import numpy as np
import pytest

from bulbjax.eval.probe import summarise
from bulbjax.eval.spec import StateEntry
from bulbjax.report import plot_limits, report

matplotlib.use("Agg")

SPEC = (StateEntry("j0_sin", "1", "robot"), StateEntry("j0_cos", "1", "robot"),
        StateEntry("obj0_x", "m", "object_position"), StateEntry("obj0_y", "m", "object_position"))
EPOCHS, SEEDS, SPIKE_EPOCH, SPIKE = list(range(0, 200, 10)), 3, 120, 150.0


def _records(spike: float = SPIKE) -> list[dict]:
    """Every learner near 0.5-0.9 of the reference spread; spair's seed 1 at SPIKE_EPOCH `spike`
    x on object_position (both streams), and its box distance `spike` x too."""
    rng = np.random.default_rng(0)
    ref = np.array([0.5, 0.5, 0.2, 0.2])
    out = []
    for epoch in EPOCHS:
        for s in range(SEEDS):
            probes, boxes = {}, {}
            for name in ("vae", "spair"):
                streams = {}
                for st in ("curr", "rand"):
                    mae = ref * rng.uniform(0.5, 0.9, 4)
                    if name == "spair" and s == 1 and epoch == SPIKE_EPOCH:
                        mae[2:] *= spike
                    streams[st] = summarise(mae, ref, ref, SPEC, spread_D=ref)
                probes[name] = streams
            dist = 3.0 * (spike if s == 1 and epoch == SPIKE_EPOCH else 1.0)
            boxes["spair"] = {st: {"error_mean": dist + rng.uniform(0, 0.5), "found_share": 0.9,
                                   "radius": 6.4} for st in ("curr", "rand")}
            out.append({"epoch": epoch, "seed": s, "rl_return": 1.0, "probes": probes, "objects": boxes,
                        "ref_spread": ref.tolist()})
    return out


@pytest.fixture
def figures(monkeypatch):
    """The matplotlib figures the report plots save (kept open to read their axes)."""
    saved = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: saved.append(fig))
    return saved


def _panel(fig, title: str):
    return next(ax for ax in fig.axes if ax.get_title() == title)


def _marks(ax) -> list[str]:
    return [t.get_text() for t in ax.texts]


def test_spikes_and_limits_on_curves():
    flat = np.array([1.0, 1.1, 0.9, 150.0, 1.0, 1.05, np.nan, 0.95])
    assert plot_limits.spikes(flat).tolist() == [False, False, False, True, False, False, False, False]
    learning = np.array([12.0, 8.0, 5.0, 3.5, 2.5, 2.2, 2.1, 2.0])  # an early fall is no spike
    assert not plot_limits.spikes(learning).any()
    twice = np.array([1.0, 0.9, 60.0, 80.0, 1.1, 1.0])  # two spiking epochs in a row
    assert plot_limits.spikes(twice).tolist() == [False, False, True, True, False, False]
    assert not plot_limits.spikes([40.0, 1.0, 1.0, 1.0]).any()  # a curve's first point: its start
    x = np.arange(8)
    assert plot_limits.upper_limit([plot_limits.Curve.of(x, learning)]) is None  # matplotlib's own
    top = plot_limits.upper_limit([plot_limits.Curve.of(x, flat, np.full(8, 0.1))])
    assert 1.1 < top < 1.4  # the bulk's top (1.2 with its band) and a little room, not 150


def test_fig2_axis_ends_near_the_bulk_and_marks_the_spike(figures, tmp_path):
    recs = _records()
    marked = report.plot(recs, SPEC, str(tmp_path / "fig2.png"), "t")
    (fig,) = figures
    for label in ("π_curr", "π_rand"):
        ax = _panel(fig, f"{label}: object_position")
        assert ax.get_ylim()[0] == 0 and ax.get_ylim()[1] < 2.0, ax.get_ylim()  # not ~150
        spike_mean = np.mean([r["probes"]["spair"]["curr" if label == "π_curr" else "rand"]["groups"]
                              ["object_position"]["mae_norm"] for r in recs if r["epoch"] == SPIKE_EPOCH])
        assert f"{spike_mean:.3g}" in _marks(ax)  # the mean over seeds, printed at the top edge
        assert float(f"{spike_mean:.3g}") > 20  # ~150 x at one of 3 seeds
        tops = [line for line in ax.lines if list(line.get_xdata()) == [SPIKE_EPOCH]]
        assert tops and all(line.get_ydata()[0] == pytest.approx(ax.get_ylim()[1]) for line in tops)
        robot = _panel(fig, f"{label}: robot")  # no spike there: no marks, the usual limits
        assert not _marks(robot) and robot.get_ylim()[1] < 2.0
    assert marked >= 2 and "above the axis" in fig._suptitle.get_text()


def test_objects_plot_marks_the_spike(figures, tmp_path):
    marked = report.plot_objects(_records(), str(tmp_path / "objects.png"), "t")
    (fig,) = figures
    mlp = _panel(fig, "π_curr: MLP probe, object_position")
    boxes = _panel(fig, "π_curr: boxes, distance to nearest box")
    assert mlp.get_ylim()[1] < 2.0 and boxes.get_ylim()[1] < 6.0  # the box distance is ~3 px
    assert _marks(mlp) and _marks(boxes) and marked >= 4
    found = _panel(fig, "π_curr: boxes, objects found")
    assert found.get_ylim() == pytest.approx((0, 1.02)) and not _marks(found)


def test_without_a_spike_nothing_changes(figures, tmp_path):
    assert report.plot(_records(spike=1.0), SPEC, str(tmp_path / "fig2.png"), "t") == 0
    (fig,) = figures
    assert all(not _marks(ax) for ax in fig.axes)
    assert "above the axis" not in fig._suptitle.get_text()


def test_the_return_is_one_panel_with_each_seed(figures, tmp_path):
    """The PPO return is drawn once, in one panel across the bottom row (it was the same panel
    under every column), with each seed's own curve beside the mean and its band."""
    recs = [{**r, "rl_return": 10.0 * r["seed"] + r["epoch"]} for r in _records(spike=1.0)]
    report.plot(recs, SPEC, str(tmp_path / "fig2.png"), "t", solved_return=150.0)
    (fig,) = figures
    returns = [ax for ax in fig.axes if ax.get_ylabel() == "episode return"]
    assert len(returns) == 1
    (ax,) = returns
    errors = [a for a in fig.axes if a is not ax]
    assert len(errors) == 2 * 2  # π_curr, π_rand x robot, object_position
    width = max(a.get_position().x1 for a in errors) - min(a.get_position().x0 for a in errors)
    assert ax.get_position().width == pytest.approx(width, rel=0.05)
    seeds = [line for line in ax.lines if line.get_linewidth() == 0.6]
    assert len(seeds) == SEEDS
    assert [list(line.get_ydata()) for line in seeds] == [[10.0 * s + e for e in EPOCHS] for s in range(SEEDS)]
    assert "90% band over 3 seeds" in ax.get_legend_handles_labels()[1][0]
