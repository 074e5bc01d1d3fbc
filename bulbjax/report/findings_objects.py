"""The paper's multi-object findings (Sec. IV.C, Figs. 3 and 5), checked on a Rearrange run's
metrics with 90% bands over seeds, as `findings` checks Fig. 2's.

Claims (issue 37): VAE_rpl encodes the main joint (j0) better than the constant predictor;
VAE_rpl encodes the largest object's position and its major-axis angle; VAE_rpl beats SPAIR on
the largest object's orientation; SPAIR encodes every object's position (MLP probe and box
probe); SPAIR's localisation does not improve after its first few hundred epochs; SPAIR 4x4
aligns better than 6x6; on YCB no learner's reconstruction is clear (the reconstruction error
per object region of the newest `regions_<epoch>.json`, `bulbjax.eval.regions`, written by runs
with `--recon-every N`: per learner and object the ratio to the mean image's error, "clear" when
its 90% band over seeds lies below `regions.CLEAR`).

Comparisons are paired by seed, as in `findings`: "A below B" holds when the 90% Student-t band
of the per-seed `B - A` lies above 0, does not hold when it lies below 0, else undecided.
Errors: normalised MAE (MAE / reference spread) averaged over the named entries (position: x
and y; the joint: sin and cos), the probe's mean major-axis angle error in rad
(`records.angle_summary`), the box probe's distance in px.

"The largest object" of a fixed scene is the one of greatest volume (`largest_object`); in a
random-version run an index names a different object from episode to episode, so the
per-object claims are not tested there.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import numpy as np

from bulbjax.eval import regions as region_errors
from bulbjax.report.findings import Verdict, _combine, paired_verdict, stream_label
from bulbjax.report.records import ci90, nanmean, probed

# Approximate YCB sizes (cm; the YCB object set's published dimensions) before bulb's scale:
# ("cyl", diameter, height), ("box", a, b, c) or ("ell", a, b, c) (ellipsoid diameters).
_YCB_SHAPES = {
    "002_master_chef_can": ("cyl", 10.2, 13.9), "005_tomato_soup_can": ("cyl", 6.6, 10.1),
    "007_tuna_fish_can": ("cyl", 8.5, 3.3), "004_sugar_box": ("box", 3.8, 8.9, 17.5),
    "008_pudding_box": ("box", 3.5, 11.0, 8.9), "009_gelatin_box": ("box", 2.8, 8.5, 7.3),
    "013_apple": ("ell", 7.5, 7.5, 7.5), "014_lemon": ("ell", 5.4, 5.4, 6.8), "016_pear": ("ell", 6.6, 6.6, 10.0),
    "017_orange": ("ell", 9.4, 9.4, 9.4), "018_plum": ("ell", 5.2, 5.2, 5.2)}
EARLY_EPOCH = 300  # "the first few hundred epochs" of SPAIR's localisation
NO_GAIN = 0.05  # normalised error: an improvement below this is "no improvement"


def early_epochs(epochs: Sequence[int], last: int = 3) -> list[int]:
    """The probed epochs "SPAIR's localisation does not improve" compares the last ones with: the
    `last` at or before EARLY_EPOCH, or before half the run where it is shorter."""
    epochs = sorted(set(epochs))
    if not epochs:
        return []
    early_at = min(EARLY_EPOCH, epochs[-1] // 2)
    return [e for e in epochs if e <= early_at][-last:]


def object_volume(name: str) -> float:
    """Volume (m^3) of a Rearrange object: geoms exactly (bulb's dims), YCB approximately."""
    from bulbjax.envs.objects.rearrange_scene import GEOM_INFO, SHAPE_BOX, SHAPE_CYLINDER

    if name in GEOM_INFO:
        g = GEOM_INFO[name]
        a, b, c = g.dims
        if g.shape == SHAPE_BOX:
            return 8 * a * b * c
        if g.shape == SHAPE_CYLINDER:
            return math.pi * a * a * 2 * c
        return 4 / 3 * math.pi * a ** 3
    from bulbjax.assets import YCB_INFO

    kind, *d = _YCB_SHAPES[name]
    sx, sy, sz = YCB_INFO[name].scale
    if kind == "cyl":
        v = math.pi * (d[0] / 2) ** 2 * d[1]
    elif kind == "box":
        v = d[0] * d[1] * d[2]
    else:
        v = 4 / 3 * math.pi * d[0] * d[1] * d[2] / 8
    return v * sx * sy * sz * 1e-6


def largest_object(env: str, version: int | str) -> tuple[int, str] | None:
    """Index and name of the largest object (by volume) of a fixed Rearrange scene; None for a
    random version or another domain."""
    from bulbjax.envs.objects.rearrange_scene import NUM_LISTS, OBJECT_LISTS

    variant = next((v for v in ("OneGeom", "OneYcb", "Geom", "Ycb") if env.endswith(f"Rearrange{v}")), None)
    if variant is None or not isinstance(version, int):
        return None
    names = OBJECT_LISTS[variant][version % NUM_LISTS]
    i = int(np.argmax([object_volume(n) for n in names]))
    return i, names[i]


def _per_seed(records: Sequence[dict[str, Any]], epochs: Sequence[int], value: Callable[[dict], Any]) -> np.ndarray:
    """`[seeds]`: each seed's mean over its records at `epochs` of `value(record)` (None/NaN skipped)."""
    seeds = sorted({r["seed"] for r in records})
    out = np.full(len(seeds), np.nan)
    for i, s in enumerate(seeds):
        vals = [value(r) for r in records if r["seed"] == s and r["epoch"] in epochs]
        vals = [v for v in vals if v is not None and np.isfinite(v)]
        if vals:
            out[i] = float(np.mean(vals))
    return out


def entries_error(records, learner: str, stream: str, names: Sequence[str], epochs, key: str = "mae_norm") -> np.ndarray:
    """`[seeds]` normalised error over entries `names` (mean of the finite ones); `learner=
    "constant"`: the constant predictor's (`baseline_norm`)."""
    def value(r):
        if not r.get("probes"):
            return None
        name = next(iter(r["probes"])) if learner == "constant" else learner
        e = r["probes"].get(name, {}).get(stream, {}).get("entries", {})
        k = "baseline_norm" if learner == "constant" else key
        v = [e[n][k] for n in names if n in e and np.isfinite(e[n][k])]
        return float(np.mean(v)) if v else None
    return _per_seed(records, epochs, value)


def angle_error(records, learner: str, stream: str, obj: str, epochs) -> np.ndarray:
    """`[seeds]` mean major-axis angle error (rad); `learner="constant"`: the constant's."""
    def value(r):
        a = r.get("angles", {})
        name = next(iter(a), None) if learner == "constant" else learner
        x = a.get(name, {}).get(stream, {}).get(obj)
        return None if x is None else x["baseline" if learner == "constant" else "mae"]
    return _per_seed(records, epochs, value)


def box_error(records, learner: str, stream: str, obj: str, epochs) -> np.ndarray:
    """`[seeds]` box-probe distance (px) from the object to the nearest present box."""
    def value(r):
        x = r.get("objects", {}).get(learner, {}).get(stream, {}).get("per_object", {}).get(obj)
        return None if x is None else x["error"]
    return _per_seed(records, epochs, value)


def _paired(lower: np.ndarray, higher: np.ndarray, a: str, b: str, what: str, unit: str = "") -> tuple[str, str]:
    """Verdict of "a (errors `lower`) below b (errors `higher`)" paired over seeds, and numbers."""
    verdict, mean, half = paired_verdict(lower, higher)
    return verdict, (f"{what}: {a} {nanmean(lower):.3f}{unit}, {b} {nanmean(higher):.3f}{unit}; "
                     f"{b} - {a} = {mean:+.3f} ± {half:.3f}")


def check_objects(records: Sequence[dict[str, Any]], env: str, version: int | str,
                  last: int = 3, regions: dict[str, Any] | None = None) -> tuple[list[Verdict], list[int]]:
    """The Fig. 3/5 claims on the last `last` probed epochs; returns the verdicts and those epochs.
    `regions`: the run's newest per-object reconstruction errors (`regions.newest`), for the YCB
    reconstruction claim."""
    recs = probed(records)
    all_epochs = sorted({r["epoch"] for r in recs})
    epochs = all_epochs[-last:]
    have = set(recs[0]["probes"]) if recs else set()
    streams = ("rand", "curr")
    out: list[Verdict] = []
    big = largest_object(env, version)
    ycb = "Ycb" in env

    def missing(*names: str) -> str | None:
        lack = [n for n in names if n not in have]
        return f"not tested (the run has no {', '.join(lack)})" if lack else None

    def both(fn) -> tuple[str, str]:
        parts = [fn(s) for s in streams]
        return _combine([v for v, _ in parts]), "; ".join(d for _, d in parts)

    claim = "VAE_rpl encodes the main joint (j0) better than the constant predictor"
    out.append(Verdict(claim, *(((m, "") if (m := missing("vae_rpl")) else both(lambda s: _paired(
        entries_error(recs, "vae_rpl", s, ("j0_sin", "j0_cos"), epochs),
        entries_error(recs, "constant", s, ("j0_sin", "j0_cos"), epochs),
        "vae_rpl", "constant", f"j0 sin/cos, {stream_label(s)}"))))))

    obj = f"obj{big[0]}" if big else None
    tag = f" ({obj}: {big[1]})" if big else ""
    no_big = "not tested (random versions: no one largest object)" if big is None else None
    claim = f"VAE_rpl encodes the largest object's position{tag} (x, y below the constant)"
    m = no_big or missing("vae_rpl")
    out.append(Verdict(claim, *((m, "") if m else both(lambda s: _paired(
        entries_error(recs, "vae_rpl", s, (f"{obj}_x", f"{obj}_y"), epochs),
        entries_error(recs, "constant", s, (f"{obj}_x", f"{obj}_y"), epochs),
        "vae_rpl", "constant", f"{obj} x/y, {stream_label(s)}")))))

    def has_angle() -> bool:
        return any(np.isfinite(angle_error(recs, "constant", s, obj, epochs)).any() for s in streams)

    claim = f"VAE_rpl encodes the largest object's major-axis angle{tag} (angle error below the constant's)"
    m = no_big or missing("vae_rpl") or (None if has_angle() else "not tested (the largest object has no major-axis "
                                         "target: a sphere or a YCB mesh)")
    out.append(Verdict(claim, *((m, "") if m else both(lambda s: _paired(
        angle_error(recs, "vae_rpl", s, obj, epochs), angle_error(recs, "constant", s, obj, epochs),
        "vae_rpl", "constant", f"{obj} angle, {stream_label(s)}", " rad")))))

    claim = f"VAE_rpl beats SPAIR on the largest object's orientation{tag} (angle error below spair's)"
    m = no_big or missing("vae_rpl", "spair") or (None if has_angle() else "not tested (no major-axis target)")
    out.append(Verdict(claim, *((m, "") if m else both(lambda s: _paired(
        angle_error(recs, "vae_rpl", s, obj, epochs), angle_error(recs, "spair", s, obj, epochs),
        "vae_rpl", "spair", f"{obj} angle, {stream_label(s)}", " rad")))))

    objs = sorted({n.split("_")[0] for r in recs[:1] for st in r["probes"].values() for x in st.values()
                   for n in x["entries"] if n.startswith("obj") and n.endswith("_x")})
    claim = "SPAIR encodes every object's position (MLP probe: x, y below the constant, each object)"
    m = missing("spair") or ("not tested (random versions)" if big is None else None)
    out.append(Verdict(claim, *((m, "") if m else _all(objs, lambda o: _paired(
        entries_error(recs, "spair", "rand", (f"{o}_x", f"{o}_y"), epochs),
        entries_error(recs, "constant", "rand", (f"{o}_x", f"{o}_y"), epochs),
        "spair", "constant", f"{o} x/y, π_rand")))))

    claim = "SPAIR encodes every object's position (box probe: nearest box within the radius, each object)"
    radius = next((x.get("radius") for r in recs for x in r.get("objects", {}).get("spair", {}).values()), None)
    m = missing("spair") or ("not tested (no box probe in the records)" if radius is None else None)
    out.append(Verdict(claim, *((m, "") if m else _all(objs, lambda o: _paired(
        box_error(recs, "spair", "rand", o, epochs), np.full(len({r["seed"] for r in recs}), radius),
        "spair box", "radius", f"{o}, π_rand", " px")))))

    claim = (f"SPAIR's localisation does not improve after its first few hundred epochs (object_position "
             f"error near epoch {EARLY_EPOCH} minus the last epochs' below {NO_GAIN})")
    early = early_epochs(all_epochs, last)
    pos = tuple(f"{o}_{a}" for o in objs for a in "xy")
    m = missing("spair") or ("not tested (too few probed epochs)" if not early or set(early) & set(epochs) else None)
    if m:
        out.append(Verdict(claim, m, ""))
    else:
        e0 = entries_error(recs, "spair", "rand", pos, early)
        e1 = entries_error(recs, "spair", "rand", pos, epochs)
        gain = e0 - e1
        gain = gain[np.isfinite(gain)]
        mean, half = ci90(gain) if gain.size >= 2 else (nanmean(gain) if gain.size else np.nan, np.inf)
        verdict = "holds" if mean + half < NO_GAIN else "does not hold" if mean - half > NO_GAIN else "undecided"
        out.append(Verdict(claim, verdict, f"object x/y, π_rand: epochs {early[0]}-{early[-1]} {nanmean(e0):.3f}, "
                                           f"last {nanmean(e1):.3f}; gain {mean:+.3f} ± {half:.3f}"))

    claim = "SPAIR 4x4 aligns better than 6x6 (spair's object x/y error below spair6's)"
    m = missing("spair", "spair6")
    out.append(Verdict(claim, *((m, "") if m else both(lambda s: _paired(
        entries_error(recs, "spair", s, pos, epochs), entries_error(recs, "spair6", s, pos, epochs),
        "spair", "spair6", f"object x/y, {stream_label(s)}")))))

    claim = (f"on YCB no learner's reconstruction is clear (per object region: error / the mean image's, "
             f"clear below {region_errors.CLEAR})")
    if not ycb:
        out.append(Verdict(claim, "not tested (not a YCB scene)", ""))
    elif not regions:
        out.append(Verdict(claim, "not tested (no regions_<epoch>.json: run with --recon-every N, or "
                                  "`bulbjax recon RUN_DIR`)", ""))
    else:
        out.append(Verdict(claim, *reconstruction_clear(regions)))
    return out, epochs


def reconstruction_clear(regions: dict[str, Any]) -> tuple[str, str]:
    """Verdict of "no learner's reconstruction is clear" from `RunFigures.regions`' output: per
    learner and object the 90% band over seeds of the ratio; a region is clear when the band lies
    below `regions.CLEAR`, not clear when above it. Holds when no region is clear and every one is
    not clear; does not hold when some region is clear (it is named); else undecided."""
    clear_below = float(regions.get("clear_below", region_errors.CLEAR))
    names = regions["objects"]
    verdicts, parts = [], []
    for learner, scores in sorted(regions["learners"].items()):
        ratio = np.asarray(scores["ratio"], np.float64)  # [S, M]
        cells = []
        for j, obj in enumerate(names):
            r = ratio[:, j]
            r = r[np.isfinite(r)]
            if r.size == 0:
                cells.append(f"{obj} not in view")
                continue
            mean, half = ci90(r) if r.size >= 2 else (float(r.mean()), math.inf)
            verdicts.append("does not hold" if mean + half < clear_below else
                            "holds" if mean - half > clear_below else "undecided")
            cells.append(f"{obj} {mean:.2f} ± {half:.2f}")
        parts.append(f"{learner}: " + ", ".join(cells))
    if not verdicts:
        return "not tested (no object in view in the held-out frames)", "; ".join(parts)
    verdict = ("does not hold" if "does not hold" in verdicts else
               "holds" if all(v == "holds" for v in verdicts) else "undecided")
    detail = (f"epoch {regions.get('epoch')}, {regions.get('frames')} held-out frames per seed, "
              f"{regions.get('seeds')} seeds, discs of {regions.get('radius_px')} px; " + "; ".join(parts))
    return verdict, detail


def _all(objs: Sequence[str], one: Callable[[str], tuple[str, str]]) -> tuple[str, str]:
    parts = [one(o) for o in objs]
    return _combine([v for v, _ in parts]), "; ".join(d for _, d in parts)


def markdown(verdicts: Sequence[Verdict], epochs: Sequence[int], seeds: int) -> str:
    """The verdicts as a markdown table, with the rule that decides them."""
    lines = ["| claim (paper, Sec. IV.C, Figs. 3, 5) | verdict | numbers (difference ± 90% band) |", "|---|---|---|"]
    lines += [f"| {v.claim} | **{v.verdict}** | {v.detail} |" for v in verdicts]
    lines += ["", f"Epochs {', '.join(map(str, epochs))}; each seed's error averaged over them; differences "
              f"paired by seed ({seeds} seed{'s' if seeds != 1 else ''}), 90% Student-t band. Errors: normalised "
              "MAE, angle errors in rad (|θ̂ − θ| mod π), box distances in px. A claim holds when the band lies on "
              "its side of 0, does not hold when it lies on the other side, and is undecided when it contains 0."]
    return "\n".join(lines)
