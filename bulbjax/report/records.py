"""A run's metrics as records: one JSON-able record per epoch and seed (`epoch_records`), the
`metrics.jsonl` file they are kept in, and the statistics the reports and findings take of them
(per-seed errors and returns, curves over epochs, 90% confidence bands over seeds).

Records are appended a whole epoch at a time with one `write` (`append_whole`: a failed write is
cut back to the file's previous end), and a resume cuts a half-written last line (`ends_mid_line`:
from a process killed in an older version's buffered append, or a disk that filled) before it
appends again."""

from __future__ import annotations

import gzip
import json
import math
import os
import sys
import warnings
from typing import Any, Sequence

import numpy as np

from bulbjax.eval import objects
from bulbjax.eval.probe import summarise
from bulbjax.eval.spec import StateEntry

STREAMS = (("curr", "π_curr"), ("rand", "π_rand"))
# Student-t 95th percentiles (two-sided 90% band) for n-1 degrees of freedom.
_T95 = {1: 6.314, 2: 2.920, 3: 2.353, 4: 2.132, 5: 2.015, 6: 1.943, 7: 1.895, 8: 1.860, 9: 1.833}

# What the normalised errors of these reports divide by (written into tables and plots).
NORM_NOTE = ("normalised error = MAE / reference spread of each state entry (mean absolute deviation "
             "around the median under the random policy, measured once per run at init); 1.0 = "
             "predicting the random-policy median on π_rand frames")


# The probe-protocol variants' errors in a record (`ExperimentConfig.probe_variants`): key of
# the per-learner, per-stream summaries and the value read as a learner's error (the constant
# predictor's: `baseline` in place of `mae`). "present" is the present probe's.
VARIANT_SOURCES: dict[str, tuple[str, str]] = {
    "present": ("probes", "mae_norm"), "common": ("probes_common", "mae_norm"),
    "window": ("probes_window", "mae_norm"), "raw": ("probes_raw", "mae")}


def epoch_records(epoch: int, metrics: Any, spec: Sequence[StateEntry],
                  variants: Sequence[str] = ()) -> list[dict[str, Any]]:
    """One JSON-able record per seed from the epoch's metrics (arrays with a leading seed axis).
    Epochs without a probe (`--probe-every`) have an empty `probes`. The linear (ridge) probe of
    the same pairs is under `linear_probes[learner][stream]` (`linear_summary`: groups and
    overall as in `probes`; absent in epochs without a probe). Learners with an object-level
    probe (SPAIR in multi-object domains) also get `objects[learner][stream]`
    (`bulbjax.eval.objects.summary_of`: per object and averaged); other records have no `objects`.
    `probe_inputs_clamped[learner][stream]`: the share of held-out steps whose latent the probes
    clamped to their fit range (`bulbjax.eval.probe.standardise`). Probe-protocol variants
    (`VARIANT_SOURCES`): the device's `"common"` and `"window"` scores as `probes_common` and
    `probes_window` (summarised as `probes`), and with "raw" in `variants` `probes_raw`
    (`raw_summary` of `probes`)."""
    m = _to_numpy(metrics)
    seeds = len(m["rl_return"])
    names = objects.object_names(spec)
    out = []
    for s in range(seeds):
        rec: dict[str, Any] = {
            "epoch": epoch, "seed": s,
            "rl_return": _f(m["rl_return"][s]), "rl_episodes": _f(m["rl_episodes"][s]),
            # PPO's worlds reset this epoch because their physics went non-finite
            **({"nonfinite_resets": int(m["nonfinite_resets"][s])} if "nonfinite_resets" in m else {}),
            "ppo": {k: _f(v[s]) for k, v in m["ppo"].items()},
            "learners": {n: {k: _f(v[s]) for k, v in lm.items()} for n, lm in m["learners"].items()},
            "replay_dropped": {k: int(v[s]) for k, v in m["replay_dropped"].items()},
            "probes": {},
        }
        rec["ref_spread"] = [float(x) for x in m["ref_spread"][s]]
        for name, streams in m.get("probes", {}).items():
            extra = streams.get("variants", {})
            streams = {k: v for k, v in streams.items() if k != "variants"}
            for v, per_stream in extra.items():
                rec.setdefault(VARIANT_SOURCES[v][0], {})[name] = {
                    st: summarise(d["mae"][s], d["baseline"][s], m["ref_spread"][s], spec,
                                  spread_D=d["spread"][s])
                    for st, d in per_stream.items()}
            rec["probes"][name] = {
                stream: summarise(d["mae"][s], d["baseline"][s], m["ref_spread"][s], spec,
                                  spread_D=d["spread"][s])
                for stream, d in streams.items()}
            if any("linear_mae" in d for d in streams.values()):
                rec.setdefault("linear_probes", {})[name] = {
                    stream: linear_summary(d, s, m["ref_spread"][s], spec) for stream, d in streams.items()}
            if clamped := clamped_share(streams, s):
                rec.setdefault("probe_inputs_clamped", {})[name] = clamped
            for stream, d in streams.items():
                if "angle" in d:
                    rec.setdefault("angles", {}).setdefault(name, {})[stream] = angle_summary(
                        {k: v[s] for k, v in d["angle"].items()}, spec)
                if "objects" in d:
                    one = {k: v[s] for k, v in d["objects"].items()}
                    rec.setdefault("objects", {}).setdefault(name, {})[stream] = objects.summary_of(one, names)
            if "raw" in variants:
                rec.setdefault("probes_raw", {})[name] = {st: raw_summary(x)
                                                          for st, x in rec["probes"][name].items()}
        out.append(rec)
    return out


def raw_summary(summary: dict[str, Any]) -> dict[str, Any]:
    """The "raw" probe variant of one learner's stream (`summarise`'s output): per group and
    overall the plain mean of its entries' MAE and of the constant predictor's, in the state's
    units (no normalisation, every entry counted, excluded ones too; `units`: those it mixes, as
    the paper's mean absolute error does), and `n` entries."""
    entries = summary["entries"]

    def mean(names: list[str]) -> dict[str, Any]:
        return {"n": len(names), "units": sorted({entries[n]["unit"] for n in names}),
                "mae": float(np.mean([entries[n]["mae"] for n in names])),
                "baseline": float(np.mean([entries[n]["baseline"] for n in names]))}

    groups: dict[str, list[str]] = {}
    for n, e in entries.items():
        groups.setdefault(e["group"], []).append(n)
    return {"groups": {g: mean(ns) for g, ns in groups.items()}, "overall": mean(list(entries))}


def variants_of(records: Sequence[dict[str, Any]]) -> list[str]:
    """The probe variants (`VARIANT_SOURCES`, "present" first) whose errors the probed records
    carry."""
    recs = probed(records)
    return [v for v, (k, _) in VARIANT_SOURCES.items() if any(r.get(k) for r in recs)]


def linear_summary(d: dict[str, Any], s: int, ref_spread_D: Any, spec: Sequence[StateEntry]) -> dict[str, Any]:
    """The linear (ridge) probe's part of a record for seed `s` of one stream's probe output `d`
    (`probing.fit_and_score`): `summarise` of its `linear_mae` against the same constant and
    reference spread as the MLP's, each entry cut to `mae`, `mae_norm` and the regulariser it
    chose, `log10_lambda` (the rest is the MLP record's, under `probes`)."""
    out = summarise(d["linear_mae"][s], d["baseline"][s], ref_spread_D, spec, spread_D=d["spread"][s])
    lam = np.asarray(d["linear_log10_lambda"][s], np.float64)
    out["entries"] = {name: {"mae": e["mae"], "mae_norm": e["mae_norm"], "log10_lambda": float(lam[i])}
                      for i, (name, e) in enumerate(out["entries"].items())}
    return out


def clamped_share(streams: dict[str, Any], s: int) -> dict[str, float]:
    """`{stream: share}` for seed `s` of one learner's probe output (`probing.fit_and_score`):
    the share of held-out steps whose latent the probes clamped to their fit range
    (`bulbjax.eval.probe.standardise`); {} for outputs without it."""
    return {st: _f(d["inputs_clamped"][s]) for st, d in streams.items() if "inputs_clamped" in d}


def angle_summary(angle: dict[str, Any], spec: Sequence[StateEntry]) -> dict[str, dict[str, float]]:
    """Per object with a major-axis angle target (entries `<obj>_axis_cos2` in `spec`, in spec
    order), the probe's and the constant predictor's mean angle error (rad) of one seed's stream
    (`probing.fit_and_score`'s `"angle"`): `{obj: {"mae", "baseline"}}`, NaN where no held-out
    step had a defined angle (a sphere: none ever)."""
    objs = [e.name[: -len("_axis_cos2")] for e in spec if e.name.endswith("_axis_cos2")]
    mae, base = (np.asarray(angle[k], np.float64).reshape(-1) for k in ("mae", "baseline"))
    return {o: {"mae": _f(mae[i]), "baseline": _f(base[i])} for i, o in enumerate(objs)}


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def append_whole(path: str, data: bytes) -> None:
    """Append `data` (whole lines) to `path` with one `write` call (a loop only if the kernel
    writes less): a process killed around it leaves all of it or none. If the write fails (disk
    full), the file is cut back to where it ended, so no half line stays behind."""
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        end = os.fstat(fd).st_size
        try:
            _write_all(fd, data)
        except BaseException:
            os.ftruncate(fd, end)
            raise
    finally:
        os.close(fd)


def ends_mid_line(path: str) -> bool:
    """Whether `path` ends in a half-written line (no final newline)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            if f.tell() == 0:
                return False
            f.seek(-1, os.SEEK_END)
            return f.read(1) != b"\n"
    except OSError:
        return False


def write_jsonl(path: str, records: Sequence[dict[str, Any]]) -> None:
    """Append `records` as JSON lines, all of them or none (`append_whole`: one write, cut back if
    it fails), so a killed or failing run never leaves half a record."""
    append_whole(path, "".join(json.dumps(r, allow_nan=True) + "\n" for r in records).encode())


def read_jsonl(path: str, tolerate_partial: bool = False) -> list[dict[str, Any]]:
    """The records of a JSON-lines file (gzip-compressed if `path` ends in .gz). A line that is
    not JSON is a one-line ValueError naming the file and the line (a corrupt file: the JSON
    parser's own message names neither), except, with `tolerate_partial`, the last one: what a
    run stopped while writing it leaves (`write_jsonl` writes whole records, but a killed process
    can leave part of one), skipped with one warning line on stderr naming the file and the line,
    so that a report or a resume works on the whole records before it."""
    with (gzip.open(path, "rt") if path.endswith(".gz") else open(path)) as f:
        lines = f.read().split("\n")
    last = max((i for i, line in enumerate(lines) if line.strip()), default=-1)
    out = []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError as err:
            if tolerate_partial and i == last:
                print(f"bulbjax: warning: {path}:{i + 1}: skipped its last line, cut short (a run "
                      f"stopped while writing it); read the {len(out)} whole records before it",
                      file=sys.stderr, flush=True)
                break
            raise ValueError(f"{path}:{i + 1}: not a whole JSON record ({err.msg}, column {err.colno}): "
                             "the file is corrupt; repair or delete that line") from None
    return out


def write_jsonl_atomic(path: str, records: Sequence[dict[str, Any]]) -> None:
    """Replace `path` with `records` (a temporary file renamed over it)."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as f:
        for r in records:
            f.write(json.dumps(r, allow_nan=True) + "\n")
    os.replace(tmp, path)


def nanmean(values: Any, axis: int | None = None) -> Any:
    """`np.nanmean` that gives NaN for an all-NaN slice without a warning: epochs in which no PPO
    episode ended have no return (InvertedPendulum's 1,000-step episodes end every ~8 epochs)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Mean of empty slice", RuntimeWarning)
        return np.nanmean(values, axis=axis)


def ci90(values: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and half-width of a 90% Student-t confidence interval over `axis` (seeds)."""
    n = values.shape[axis]
    mean = nanmean(values, axis=axis)
    if n < 2:
        return mean, np.zeros_like(mean)
    t = _T95.get(n - 1, 1.645)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Degrees of freedom <= 0", RuntimeWarning)
        return mean, t * np.nanstd(values, axis=axis, ddof=1) / math.sqrt(n)


def last_returns(records: Sequence[dict[str, Any]], epochs: Sequence[int],
                 x_key: str = "epoch") -> tuple[np.ndarray, bool]:
    """Each seed's PPO return: the mean over its records at `epochs` in which an episode ended,
    else (no episode ended there) its latest finished episode's up to the last of them (one that
    ended between two asked epochs counts; a later one does not). Returns `[seeds]` and whether
    any seed needed the fallback (NaN for a seed with no finished episode at all)."""
    seeds = sorted({r["seed"] for r in records})
    out, fell_back = np.full(len(seeds), np.nan), False
    for i, s in enumerate(seeds):
        mine = sorted((r for r in records if r["seed"] == s and np.isfinite(r.get("rl_return", np.nan))),
                      key=lambda r: r[x_key])
        now = [r["rl_return"] for r in mine if r[x_key] in epochs]
        before = [r for r in mine if r[x_key] <= max(epochs, default=np.inf)]  # no epochs: any
        if now:
            out[i] = float(np.mean(now))
        elif before:
            out[i], fell_back = before[-1]["rl_return"], True
    return out, fell_back


def _seed_epoch_matrix(records: Sequence[dict[str, Any]], value: Any,
                       x_key: str = "epoch") -> tuple[np.ndarray, np.ndarray]:
    """Epochs (or `x_key` values, e.g. updates) and a `[seeds, epochs]` matrix of
    `value(record)` (NaN where it gives None)."""
    epochs = sorted({r[x_key] for r in records})
    seeds = sorted({r["seed"] for r in records})
    v = np.full((len(seeds), len(epochs)), np.nan)
    for r in records:
        x = value(r)
        if x is not None:
            v[seeds.index(r["seed"]), epochs.index(r[x_key])] = x
    return np.array(epochs), v


def probed(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The records of epochs with a probe evaluation."""
    return [r for r in records if r.get("probes")]


def curves(records: Sequence[dict[str, Any]], learner: str, stream: str, group: str | None,
           key: str = "mae_norm", x_key: str = "epoch", probes: str = "probes") -> tuple[np.ndarray, np.ndarray]:
    """Probed epochs and `[seeds, epochs]` values of a group's error (or `baseline_norm`);
    `group=None`: the overall error (as in `per_seed_error`). `probes="linear_probes"`: the
    linear probe's (NaN in records without one)."""
    def value(r: dict[str, Any]) -> Any:
        x = r.get(probes, {}).get(learner, {}).get(stream)
        if x is None:
            return None
        g = x["overall"] if group is None else x["groups"].get(group)
        return None if g is None else g[key]
    return _seed_epoch_matrix(probed(records), value, x_key)


def rl_curve(records: Sequence[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """Epochs and `[seeds, epochs]` PPO returns."""
    return _seed_epoch_matrix(records, lambda r: r["rl_return"])


def groups_of(spec: Sequence[StateEntry]) -> list[str]:
    return list(dict.fromkeys(e.group for e in spec))


def object_curves(records: Sequence[dict[str, Any]], learner: str, stream: str,
                  key: str) -> tuple[np.ndarray, np.ndarray]:
    """Probed epochs and `[seeds, epochs]` of an object-probe summary value (`error_mean`,
    `found_share`, ...; `bulbjax.eval.objects.summary_of`) of a learner with boxes; an infinite
    error (no present box in any frame) is NaN."""
    def value(r: dict[str, Any]) -> Any:
        v = r.get("objects", {}).get(learner, {}).get(stream, {}).get(key)
        return None if v is None or not np.isfinite(v) else v
    return _seed_epoch_matrix([r for r in records if r.get("objects")], value)


def has_linear(records: Sequence[dict[str, Any]]) -> bool:
    """Whether the records carry the linear probe (`linear_probes`; runs made before it did not)."""
    return any(r.get("linear_probes") for r in records)


def has_objects(records: Sequence[dict[str, Any]]) -> bool:
    return any(r.get("objects") for r in records)


def per_seed_error(records: Sequence[dict[str, Any]], learner: str, stream: str, group: str | None,
                   at: Sequence[int], x_key: str = "epoch", probes: str = "probes",
                   value: str = "mae_norm") -> np.ndarray:
    """`[seeds]` normalised error of `learner` on `stream` (`group`, or overall when None), each
    seed's mean over its probed records whose `x_key` is in `at` (NaN for a seed without any);
    `learner="constant"` gives the constant predictor's (`baseline_norm`). `probes` names the
    probe: `"probes"` (the MLP) or `"linear_probes"` (the ridge probe; records of runs made
    before it existed have none: NaN), or a probe variant's (`VARIANT_SOURCES`: its key and
    `value`, e.g. `"probes_raw"` and `"mae"`; the constant's is `baseline` in place of `mae`)."""
    seeds = sorted({r["seed"] for r in records})
    out = np.full(len(seeds), np.nan)
    for i, s in enumerate(seeds):
        vals = []
        for r in records:
            if r["seed"] != s or r[x_key] not in at or not r.get(probes):
                continue
            name = next(iter(r[probes])) if learner == "constant" else learner
            if name not in r[probes]:
                continue
            x = r[probes][name][stream]
            x = x["overall"] if group is None else x["groups"][group]
            vals.append(x["baseline" + value[3:] if learner == "constant" else value])
        if vals:
            out[i] = float(nanmean(vals))
    return out


def excluded_groups(records: Sequence[dict[str, Any]]) -> set[str]:
    """The groups none of whose entries could be normalised in any probed record: every entry's
    reference spread ~0 (`probe.normalisable`; e.g. `object_static` on one fixed version, whose
    object properties never change, or a sphere's major-axis angle). Their normalised errors are
    NaN by construction: reports say "excluded" instead of a number. Records without per-entry
    errors (committed runs keep them only where the reports read them: `reduce_results.py
    --entries read`) are passed over."""
    out: set[str] | None = None
    for r in probed(records):
        for streams in r["probes"].values():
            for x in streams.values():
                if "entries" not in x:
                    continue
                gone = {g for g, v in x["groups"].items() if not np.isfinite(v.get("mae_norm", np.nan))
                        and all(x["entries"][n]["group"] != g or n in x["excluded"] for n in x["entries"])}
                out = gone if out is None else out & gone
    return out or set()


def band(mean: float, half: float, seeds: int, digits: int = 3) -> str:
    """A mean and its 90% band over seeds as table text: "m ± h"; "m (1 seed)" for one seed (no
    band: a "± 0.000" would claim a certainty one seed cannot give); "–" for no value."""
    if not np.isfinite(mean):
        return "–"
    if seeds < 2:
        return f"{mean:.{digits}f} (1 seed)"
    return f"{mean:.{digits}f} ± {half:.{digits}f}"


def scalars(record: dict[str, Any]) -> dict[str, float]:
    """Every number of one metrics.jsonl record as `seed<s>/<path>` tags (TensorBoard): RL
    return, PPO and learner metrics, replay drops, the reference spread and every probe error
    (per entry, group and overall; units and group names, being text, left out)."""
    out: dict[str, float] = {}

    def walk(prefix: str, v: Any) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                walk(f"{prefix}/{k}", x)
        elif isinstance(v, (list, tuple)):
            for i, x in enumerate(v):
                walk(f"{prefix}/{i}", x)
        elif isinstance(v, (bool, int, float, np.integer, np.floating)) and v is not None:
            out[prefix] = float(v)

    for k, v in record.items():
        if k not in ("epoch", "seed"):
            walk(f"seed{record['seed']}/{k}", v)
    return out


def metrics_path(run_dir: str) -> str:
    """A run's metrics file: `metrics.jsonl`, else `metrics.jsonl.gz` (committed results keep
    long runs' metrics compressed); a clear error if neither is there."""
    path = os.path.join(run_dir, "metrics.jsonl")
    for p in (path, path + ".gz"):
        if os.path.exists(p):
            return p
    raise ValueError(f"{path} (or .gz) does not exist: is {run_dir} the --out folder of a `bulbjax run`?")


def _to_numpy(tree: Any) -> Any:
    if isinstance(tree, dict):
        return {k: _to_numpy(v) for k, v in tree.items()}
    return np.asarray(tree)


def _f(x: Any) -> float:
    return float(np.asarray(x))


def epochs_to_reach(returns: np.ndarray, epochs: np.ndarray, target: float) -> list[int | None]:
    """Per seed (rows of `[seeds, epochs]`), the first epoch whose PPO return is >= `target`
    (None if never)."""
    out: list[int | None] = []
    for row in returns:
        hit = np.nonzero(np.nan_to_num(row, nan=-np.inf) >= target)[0]
        out.append(int(epochs[hit[0]]) if hit.size else None)
    return out
