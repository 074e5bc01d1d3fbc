"""Shrink committed results in place: reduced metrics and palette PNGs.

Why: the GPU runs under `docs/results/` kept every epoch's full record (probe errors of every
state entry with float64 digits, learner and PPO scalars) and matplotlib's truecolour PNGs; the
tracked tree had grown to 36 MB, most of it these files. What a reader needs from them is what
`bulbjax report` (fig2.png, table.md, findings.md, objects.png, `--merge-seeds`,
`--compare-rl`) and `benchmarks/before_after.py compare` read, plus the scalar history of each
epoch. Git history keeps the full files.

Metrics (`metrics.jsonl`, `metrics.jsonl.gz`, `*_metrics.jsonl.gz`, offline `curves.jsonl`),
each rewritten in place in its own format (gzip with a fixed header, so a rerun gives the same
bytes):

* probed records (a non-empty `probes` or `objects`: the epochs the reports read, and every
  offline record) keep every field (per-entry, group and overall errors, objects, the reference
  spread), floats rounded to `--digits` significant digits (default 5), the numbers tables and
  findings average before printing 3 decimals (PPO return, group and overall probe errors,
  object-probe summaries) to `--report-digits` (default 7, so that the reports come out as
  before: at 5, a mean near a rounding boundary moved by 0.001 in the last printed digit);
* records of the epochs in between keep `epoch`, `seed`, `rl_return`, `rl_episodes`,
  `nonfinite_resets` (where the run wrote it), `ppo`, each learner's `loss` (not its kl, recon or valid_frac), `replay_dropped` and an empty
  `probes`, rounded the same; the reference spread they repeated (the same list in every record
  of a run, kept in the probed ones) goes. No report reads ppo, learners or replay_dropped.
  `--unprobed minimal` keeps only epoch, seed, rl_return, rl_episodes (what the plots' RL row,
  the tables' return and the epoch count in the titles read). Every (epoch, seed) record
  stays: the reports count epochs and drop epochs missing a seed. `--probed-every N` (runs that
  probed every epoch, ~200 KB a record on the Rearrange scenes) keeps whole only the probed
  records of every Nth epoch and those the tables and findings read (`kept_probed_epochs`),
  merged reports beside the run included (`merged_read_epochs`). `--entries read` keeps each
  state entry's errors (`entries`, ~70% of a probed record) only in the probed records the reports
  read them from (`entry_epochs`: the first, the last 3, in scenes with objects the object
  findings' early ones); the other probed records keep their group and overall errors, what the
  curves plot (the campaign's locomotion seeds: ~365 KB to ~140 KB each).

PNGs: quantised to a 256-colour palette (no dithering; Pillow's median cut or fast octree,
whichever file is smaller), kept only when it stays faithful (mean error per channel at most
`--max-mean-error` levels of 255 and at most `--max-off-share` of pixels off by more than 16
levels in a channel: true of the plots, not of reconstruction frames with smooth shading, which
are only re-saved losslessly with `optimize`); a file is replaced only when the new one is smaller.
Images with transparency are left alone. Running the script again changes nothing.

    python benchmarks/reduce_results.py                      # docs/results and docs/images
    python benchmarks/reduce_results.py docs/results/fig2_invpend_h100_6seeds --dry-run
"""

from __future__ import annotations

import argparse
import gzip
import io
import json
import math
import os
import sys
from typing import Any, Iterable, Sequence

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)  # kept_probed_epochs reads bulbjax.report.findings_objects
DEFAULT_PATHS = ("docs/results", "docs/images")
SCALARS = ("epoch", "seed", "rl_return", "rl_episodes", "nonfinite_resets", "ppo", "learners", "replay_dropped",
           "probes")
MINIMAL = ("epoch", "seed", "rl_return", "rl_episodes", "probes")
PROBE_KEYS = ("probes", "linear_probes")  # and the variants' `probes_*`: what `without_entries` strips
ENTRIES = ("all", "read")  # `--entries`: which probed records keep their per-entry errors


# ---------------------------------------------------------------------------- metrics
def round_floats(v: Any, digits: int = 5, report_digits: int | None = None,
                 path: tuple[str, ...] = ()) -> Any:
    """`v` (a record, or a part of one at `path`) with every finite float rounded to `digits`
    significant digits, those the reports average (`is_report_value`) to `report_digits`
    (default: `digits`); NaN, inf, ints, bools and strings as they are."""
    if isinstance(v, float):
        d = report_digits if report_digits is not None and is_report_value(path) else digits
        return float(f"{v:.{d}g}") if math.isfinite(v) else v
    if isinstance(v, dict):
        return {k: round_floats(x, digits, report_digits, path + (k,)) for k, x in v.items()}
    if isinstance(v, list):
        return [round_floats(x, digits, report_digits, path) for x in v]
    return v


def is_report_value(path: tuple[str, ...]) -> bool:
    """Whether the number at `path` of a record is one that tables and findings average over
    seeds and epochs before printing 3 decimals: the PPO return, a probe's group and overall
    errors (`probes/<learner>/<stream>/groups|overall/...`, the same under `linear_probes`) and
    the object-probe summaries; the probe variants' likewise (`probes_common`, ...)."""
    probes = (("probes",), ("linear_probes",), ("probes_common",), ("probes_window",), ("probes_raw",))
    return (path[:1] == ("rl_return",) or path[:1] == ("objects",)
            or (path[:1] in probes and len(path) > 3 and path[3] in ("groups", "overall")))


def is_probed(record: dict[str, Any]) -> bool:
    return bool(record.get("probes") or record.get("objects"))


def reduce_record(record: dict[str, Any], digits: int = 5, unprobed: str = "scalars",
                  report_digits: int | None = 7) -> dict[str, Any]:
    """One record reduced: a probed one whole, another with the keys of `unprobed`
    ("scalars": SCALARS, "minimal": MINIMAL); floats rounded (`round_floats`)."""
    if is_probed(record) or "epoch" not in record:  # offline curves (by update) are all probed
        return round_floats(record, digits, report_digits)
    keep = SCALARS if unprobed == "scalars" else MINIMAL
    out = {k: record[k] for k in keep if k in record}
    if "learners" in out:  # each learner's loss; its parts (kl, recon, valid_frac) at probed epochs
        out["learners"] = {n: {k: v for k, v in m.items() if k == "loss"} for n, m in out["learners"].items()}
    return round_floats(out, digits, report_digits)


def read_records(path: str) -> list[dict[str, Any]]:
    with (gzip.open(path, "rt") if path.endswith(".gz") else open(path)) as f:
        return [json.loads(line) for line in f if line.strip()]


def encode(records: Iterable[dict[str, Any]], gz: bool) -> bytes:
    text = "".join(json.dumps(r, allow_nan=True) + "\n" for r in records).encode()
    return gzip.compress(text, compresslevel=9, mtime=0) if gz else text


def kept_probed_epochs(epochs: Iterable[int], every: int) -> set[int]:
    """Of a run's probed `epochs`, those `--probed-every every` keeps whole: the multiples of
    `every`, the last 3 (the tables and findings average over them) and the object findings'
    early ones (`findings_objects.early_epochs`: what "SPAIR's localisation does not improve"
    compares the last ones with), so that the reports read the same numbers as before."""
    from bulbjax.report.findings_objects import early_epochs

    epochs = sorted(set(epochs))
    return {e for e in epochs if e % every == 0} | set(epochs[-3:]) | set(early_epochs(epochs))


def merged_read_epochs(run_dir: str, every: int) -> set[int]:
    """The probed epochs of `run_dir` that merged folders beside it (`bulbjax report
    --merge-seeds`, committed as `seed0/ seed1/ merged/`; `merge.merge_sources` finds their
    halves) read: `kept_probed_epochs` of the epochs at which every seed of every half was
    probed, and the epochs among those that any half keeps by its own rule (so that every half
    keeps the same ones there: the merged reports leave out epochs probed at some seeds only).
    A merge reads the last epochs *all* halves have, which for a half that ran longer are not
    its own last ones (fig2_invpend_h100_6seeds: seed0's metrics end at 943, so the merge reads
    920-940, which seed1's own rule, keeping 980-999, dropped)."""
    from bulbjax.report.merge import merge_sources
    from bulbjax.report.records import metrics_path

    here, parent = os.path.abspath(run_dir), os.path.dirname(os.path.abspath(run_dir))
    out: set[int] = set()
    for name in sorted(os.listdir(parent)):
        cfg = os.path.join(parent, name, "config.json")
        if not os.path.isfile(cfg):
            continue
        with open(cfg) as f:
            if "merged_from" not in json.load(f):
                continue
        halves = merge_sources(os.path.join(parent, name))
        if here not in {os.path.abspath(h) for h in halves}:
            continue
        common: set[int] | None = None
        own: set[int] = set()  # what each half keeps by its own rule
        for half in halves:
            recs = read_records(metrics_path(half))
            seeds = {r["seed"] for r in recs}
            probed_seeds: dict[int, set[int]] = {}
            for r in recs:
                if "epoch" in r and is_probed(r):
                    probed_seeds.setdefault(r["epoch"], set()).add(r["seed"])
            full = {e for e, s in probed_seeds.items() if s == seeds}
            common = full if common is None else common & full
            own |= kept_probed_epochs(full, every)
        out |= kept_probed_epochs(common or (), every) | (own & (common or set()))
    return out


def _merges_read(path: str, every: int) -> set[int]:
    """For a run folder's metrics file, the epochs merged folders beside the run read of it
    (`merged_read_epochs`); for any other file (a fit's curves, a merged folder's), none."""
    if os.path.basename(path).startswith("metrics.jsonl"):
        return merged_read_epochs(os.path.dirname(path), every)
    return set()


def read_epochs(path: str, records: Sequence[dict[str, Any]], every: int) -> set[int]:
    """The probed epochs of one metrics file that `--probed-every every` keeps whole:
    `kept_probed_epochs`, and for a run folder's file the epochs merged folders beside it read
    (`merged_read_epochs`)."""
    probed = [r["epoch"] for r in records if "epoch" in r and is_probed(r)]
    return kept_probed_epochs(probed, every) | _merges_read(path, every)


def entry_epochs(path: str, records: Sequence[dict[str, Any]]) -> set[int]:
    """The probed epochs whose per-entry errors the reports read: the first (the object findings
    take the objects' names from it), the last 3 (the tables and findings), and in a scene with
    objects (entries `obj*`) the object findings' early ones; for a run folder's file, also what
    merged folders beside it read (`merged_read_epochs`, no multiples). `excluded_groups` needs
    any one record."""
    from bulbjax.report.findings_objects import early_epochs

    recs = [r for r in records if "epoch" in r and is_probed(r)]
    epochs = sorted({r["epoch"] for r in recs})
    if not epochs:
        return set()
    keep = {epochs[0]} | set(epochs[-3:])
    names = {n for r in recs[:1] for k in PROBE_KEYS for st in (r.get(k) or {}).values()
             for x in st.values() for n in x.get("entries", {})}
    if any(n.startswith("obj") for n in names):
        keep |= set(early_epochs(epochs))
    return keep | _merges_read(path, sys.maxsize)


def without_entries(record: dict[str, Any]) -> dict[str, Any]:
    """`record` with each probe's per-entry errors (`entries`, under `probes`, `linear_probes` and
    the variants' `probes_*`) left out; groups, overall and the excluded entries' names stay."""
    def strip(probes: dict) -> dict:  # {learner: {stream: {entries, groups, overall, ...}}}
        return {name: {stream: {k: v for k, v in x.items() if k != "entries"}
                       for stream, x in streams.items()}
                for name, streams in probes.items()}

    return {k: strip(v) if k in PROBE_KEYS or k.startswith("probes_") else v for k, v in record.items()}


def reduce_metrics(path: str, digits: int = 5, unprobed: str = "scalars", report_digits: int | None = 7,
                   dry_run: bool = False, probed_every: int = 0, entries: str = "all") -> tuple[int, int]:
    """Rewrite one metrics file reduced (same name and format); returns (bytes before, after).
    `probed_every` > 0: probed records outside `kept_probed_epochs` (and outside the epochs
    merged folders beside the run read of it, `merged_read_epochs`) are reduced as unprobed
    ones (long runs; runs that probed every epoch, whose per-entry errors are ~200 KB a record
    on the Rearrange scenes). `entries="read"`: the probed records kept keep their per-entry
    errors only where the reports read them (`entry_epochs`); elsewhere their groups and overall
    stay (the curves)."""
    if entries not in ENTRIES:
        raise ValueError(f"entries must be one of {', '.join(ENTRIES)}, got {entries!r}")
    before = os.path.getsize(path)
    records = read_records(path)
    if probed_every > 0:
        keep = read_epochs(path, records, probed_every)
        # outside `keep`: no probes and no objects, so reduce_record keeps only the unprobed keys
        records = [r if "epoch" not in r or r["epoch"] in keep else {**r, "probes": {}, "objects": {}}
                   for r in records]
    if entries == "read":
        whole = entry_epochs(path, records)
        records = [r if "epoch" not in r or r["epoch"] in whole or not is_probed(r) else without_entries(r)
                   for r in records]
    records = [reduce_record(r, digits, unprobed, report_digits) for r in records]
    data = encode(records, path.endswith(".gz"))
    if not dry_run and len(data) < before:
        _replace(path, data)
    return before, min(len(data), before)


# ---------------------------------------------------------------------------- PNGs
def _errors(a: Any, b: Any) -> tuple[float, float]:
    """Mean absolute error (levels of 255) and share of pixels off by more than 16 in a channel."""
    import numpy as np

    e = np.abs(np.asarray(a, np.int16) - np.asarray(b, np.int16)).max(-1)
    return float(np.abs(np.asarray(a, np.int16) - np.asarray(b, np.int16)).mean()), float((e > 16).mean())


def _png_bytes(img: Any) -> bytes:
    b = io.BytesIO()
    img.save(b, "PNG", optimize=True)
    return b.getvalue()


def reduce_png(path: str, max_mean_error: float = 2.0, max_off_share: float = 0.01,
               dry_run: bool = False) -> tuple[int, int, str]:
    """Re-save one PNG as a 256-colour palette image if faithful (see the module doc), else
    losslessly optimised; replaced only if smaller. Returns (bytes before, after, what)."""
    import numpy as np
    from PIL import Image

    before = os.path.getsize(path)
    with Image.open(path) as im:
        im.load()
    if im.mode == "P" or im.mode in ("L", "1"):
        candidates = [(_png_bytes(im), "optimised")]
    else:
        if "A" in im.getbands() and np.asarray(im.getchannel("A")).min() < 255:
            return before, before, "kept (transparency)"
        rgb = im.convert("RGB")
        ref = np.asarray(rgb)
        candidates = [(_png_bytes(rgb), "lossless")]
        for name, method in (("median cut", Image.Quantize.MEDIANCUT), ("octree", Image.Quantize.FASTOCTREE)):
            q = rgb.quantize(256, method=method, dither=Image.Dither.NONE)
            pal = q.getpalette()[: 3 * 256]
            # octree lands white backgrounds on 254: near-white entries become white again
            q.putpalette([255 if min(pal[i - i % 3: i - i % 3 + 3]) >= 252 else c for i, c in enumerate(pal)])
            mean, off = _errors(ref, q.convert("RGB"))
            if mean <= max_mean_error and off <= max_off_share:
                candidates.append((_png_bytes(q), f"palette ({name}, mean error {mean:.2f}, {100 * off:.2f}% > 16)"))
    data, what = min(candidates, key=lambda c: len(c[0]))
    if len(data) >= before:
        return before, before, "kept (no smaller form)"
    if not dry_run:
        _replace(path, data)
    return before, len(data), what


# ---------------------------------------------------------------------------- files
def _replace(path: str, data: bytes) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def is_metrics(name: str) -> bool:
    return name in ("metrics.jsonl", "metrics.jsonl.gz", "curves.jsonl") or name.endswith("_metrics.jsonl.gz")


def files_under(paths: Iterable[str]) -> list[str]:
    out = []
    for p in paths:
        if os.path.isfile(p):
            out.append(p)
            continue
        if not os.path.isdir(p):
            raise SystemExit(f"reduce_results: {p} is neither a file nor a folder")
        for d, dirs, names in os.walk(p):
            dirs[:] = sorted(x for x in dirs if x != "checkpoints")
            out += [os.path.join(d, n) for n in sorted(names)]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("paths", nargs="*", help=f"run folders, folders above them or files (default: "
                                             f"{' '.join(DEFAULT_PATHS)} of the repository)")
    ap.add_argument("--digits", type=int, default=5, help="significant digits of the floats kept (default 5)")
    ap.add_argument("--report-digits", type=int, default=7,
                    help="significant digits of the numbers tables and findings average (PPO return, "
                         "group and overall probe errors, object probes; default 7: the reports come "
                         "out as before)")
    ap.add_argument("--unprobed", choices=("scalars", "minimal"), default="scalars",
                    help="what records of unprobed epochs keep (default scalars: see the doc)")
    ap.add_argument("--probed-every", type=int, default=0, metavar="N",
                    help="keep whole only the probed records of every Nth epoch, the last 3 and the 3 the object "
                         "findings compare them with; reduce the other probed ones as unprobed (long runs, runs "
                         "that probed every epoch; default 0: keep every probed record)")
    ap.add_argument("--entries", choices=ENTRIES, default="all",
                    help="which probed records keep each state entry's errors: all (default), or read: only "
                         "those the reports read them from (the first and last 3 probed epochs, with objects "
                         "the object findings' early ones); the others keep their group and overall errors")
    ap.add_argument("--no-metrics", action="store_true", help="leave the metrics files alone")
    ap.add_argument("--no-png", action="store_true", help="leave the PNGs alone")
    ap.add_argument("--max-mean-error", type=float, default=2.0,
                    help="a palette PNG is kept when its mean error is at most this (levels of 255)")
    ap.add_argument("--max-off-share", type=float, default=0.01,
                    help="... and at most this share of pixels is off by more than 16 levels")
    ap.add_argument("--dry-run", action="store_true", help="report the sizes, write nothing")
    a = ap.parse_args(argv)
    if a.digits < 1 or a.report_digits < a.digits:
        ap.error("--digits must be >= 1 and --report-digits >= --digits")
    if a.probed_every < 0:
        ap.error("--probed-every must be >= 1 (every Nth probed epoch kept whole) or 0 (all kept)")
    paths = a.paths or [os.path.join(ROOT, p) for p in DEFAULT_PATHS]
    total = [0, 0]
    for path in files_under(paths):
        name = os.path.basename(path)
        if is_metrics(name) and not a.no_metrics:
            b, n = reduce_metrics(path, a.digits, a.unprobed, a.report_digits, a.dry_run, a.probed_every,
                                  a.entries)
            what = "metrics"
        elif name.lower().endswith(".png") and not a.no_png:
            b, n, what = reduce_png(path, a.max_mean_error, a.max_off_share, a.dry_run)
        else:
            continue
        total[0] += b
        total[1] += n
        print(f"{os.path.relpath(path)}: {b / 1e3:.0f} -> {n / 1e3:.0f} KB, {what}")
    print(f"total: {total[0] / 1e6:.2f} -> {total[1] / 1e6:.2f} MB{' (dry run)' if a.dry_run else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
