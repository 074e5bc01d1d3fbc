"""Seeds of several runs pooled into one report (`bulbjax report --merge-seeds`), and a merged
folder's records read back: from its own `metrics.jsonl`, or, where that was left out (committed
results keep only the pooled runs' metrics, not a second copy), pooled again from the runs it
names, found where they are now (`merge_sources`).

Imports the report (`report.write_reports`) and the layers below; the report never imports it."""

from __future__ import annotations

import dataclasses
import glob
import json
import os
from typing import Any, Sequence

from bulbjax.config import computed_config, form_of, read_run_config, run_options_of
from bulbjax.eval import regions
from bulbjax.report.records import metrics_path, read_jsonl, write_jsonl_atomic
from bulbjax.report.report import report_spec, write_reports


Records = list[dict[str, Any]]


def pool(run_dirs: Sequence[str]) -> tuple[Any, dict[str, Any], Records, Records]:
    """The runs' records as one run's: (merged config, its run options, the records with seeds
    renumbered run after run, where each seed came from, with how each computed). Runs that
    differ in what they compute (`config.computed_config`: anything but `seeds`, `epochs` and the
    fields that say only how), or share a base seed (their seeds would be the same draws), are an
    error; the merged config takes the first run's form."""
    runs = [(d, *read_run_config(d)) for d in run_dirs]
    d0, c0, raw0 = runs[0]
    opts0 = run_options_of(raw0)
    ref = computed_config(c0)
    base_seeds: dict[int, str] = {}
    merged: list[dict[str, Any]] = []
    sources: list[dict[str, Any]] = []
    for d, c, raw in runs:
        mine = computed_config(c)
        diff = sorted(k for k in ref if ref[k] != mine[k])
        opts = run_options_of(raw)
        if opts["probe_every"] != opts0["probe_every"]:
            diff.append("probe_every")
        if diff:
            raise ValueError(f"--merge-seeds: {d} differs from {d0} in {', '.join(diff)}; only "
                             "runs of one configuration (seeds, epochs and how they compute aside) "
                             "can be merged")
        seed = opts["seed"] if opts["seed"] is not None else 0
        if seed in base_seeds:
            raise ValueError(f"--merge-seeds: {d} and {base_seeds[seed]} share base seed {seed}: "
                             "their seeds are the same draws; rerun one with another --seed")
        base_seeds[seed] = d
        # by config: a run may not have written every seed yet
        offset = sum(s["seeds"] for s in sources)
        recs = read_jsonl(metrics_path(d), tolerate_partial=True)
        merged += [{**r, "seed": offset + r["seed"]} for r in recs]
        sources.append({"run_dir": d, "base_seed": seed, "seeds": c.seeds,
                        "merged_seeds": [offset, offset + c.seeds - 1], "form": form_of(c),
                        "provenance": raw.get("provenance")})
    cfg = c0.replace(seeds=sum(c.seeds for _, c, _ in runs))
    return cfg, {**opts0, "seed": None}, merged, sources


def merge_seeds(run_dirs: Sequence[str], out_dir: str, figures: bool = True) -> str:
    """`bulbjax report RUN_A RUN_B ... --merge-seeds --out DIR`: one report over the seeds of
    several runs of one configuration made with different base seeds (`--seed`): e.g. half the
    seeds on each of two GPUs side by side, or in two sessions. Seeds are renumbered run after
    run; the reports keep the epochs that every seed has written. Writes `config.json` (the
    merged config and where each seed came from), `metrics.jsonl` (replacing what a merge before
    wrote there: merging again gives the same folder) and the reports into `out_dir`; returns the
    table."""
    from bulbjax.envs.registry import env_class

    if len(run_dirs) < 2:
        raise ValueError("--merge-seeds needs two or more RUN_DIRs")
    if any(os.path.abspath(out_dir) == os.path.abspath(d) for d in run_dirs):
        raise ValueError("--merge-seeds writes a new folder: give an --out that is none of the "
                         "runs")
    cfg, opts, merged, sources = pool(run_dirs)
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(out_dir, "config.json"), "w") as f:
        json.dump({"experiment": dataclasses.asdict(cfg), "run": opts, "merged_from": sources}, f,
                  indent=1)
    write_jsonl_atomic(os.path.join(out_dir, "metrics.jsonl"), merged)
    stale = os.path.join(out_dir, "metrics.jsonl.gz")  # a compressed copy of an earlier merge
    if os.path.exists(stale):
        os.remove(stale)
    _pool_regions(run_dirs, out_dir)
    cls = env_class(cfg.env)
    names = ", ".join(f"{s['run_dir']} (seed {s['base_seed']}: {s['seeds']} seeds)"
                      for s in sources)
    footer = f"seeds of {len(run_dirs)} runs merged by `bulbjax report --merge-seeds`: {names}"
    return write_reports(out_dir, merged, cfg, report_spec(cls.state_spec, merged),
                         cls.solved_return, footer=footer, figures=figures)


def _pool_regions(run_dirs: Sequence[str], out_dir: str) -> None:
    """The runs' per-object reconstruction errors (`regions_<epoch>.json`) pooled into `out_dir`,
    whose findings read them (Fig. 5's "no reconstruction is clear" over every seed); an earlier
    merge's files there are replaced (merging again gives the same folder)."""
    for old in glob.glob(os.path.join(out_dir, regions.FILE.format(epoch="*"))):
        os.remove(old)
    pooled = regions.pooled(list(run_dirs))
    if pooled is not None:
        with open(os.path.join(out_dir, regions.FILE.format(epoch=pooled["epoch"])), "w") as f:
            json.dump(pooled, f)


def is_merged(run_dir: str) -> bool:
    """Whether `run_dir` is a `--merge-seeds` folder (its config.json names the runs it pooled)."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.isfile(path):
        return False
    with open(path) as f:
        return "merged_from" in json.load(f)


def run_records(run_dir: str) -> list[dict[str, Any]]:
    """A run folder's records: its metrics file (`metrics_path`); a merged folder without one,
    its runs pooled again (`merge_sources`, `pool`), the same records `merge_seeds` wrote."""
    try:
        path = metrics_path(run_dir)
    except ValueError:
        if is_merged(run_dir):
            return pool(merge_sources(run_dir))[2]
        raise
    return read_jsonl(path, tolerate_partial=True)


def _moved(recorded: str, merged_dir: str) -> list[str]:
    """Where a recorded run folder may be now: the recorded path's tail (its last 1, 2, ...
    parts) under each folder above the merged one, longest tail first. A plan folder of
    `bulbjax reproduce` merges `OUT/runs/<preset>/seedK` into `OUT/<figure>/<preset>`, and is
    then copied off the machine that merged it."""
    parts = [p for p in os.path.normpath(recorded).split(os.sep) if p]
    above, found = os.path.abspath(merged_dir), []
    for _ in range(4):
        above = os.path.dirname(above)
        found += [os.path.join(above, *parts[-k:]) for k in range(len(parts), 0, -1)]
    return found


def _identity(run_dir: str) -> tuple[int, int] | None:
    """(base seed, seeds) of a run folder; None for a merged or offline folder or no run."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.isfile(path):
        return None
    with open(path) as f:
        raw = json.load(f)
    if "merged_from" in raw or "offline" in raw:
        return None
    seed = run_options_of(raw)["seed"]
    return (0 if seed is None else seed), read_run_config(run_dir)[0].seeds


def merge_sources(merged_dir: str) -> list[str]:
    """The run folders a merged folder (`--merge-seeds --out`) pooled, in its order, found again
    where they are now: for each `merged_from` entry of its config.json, the one folder beside it
    whose config.json has that base seed and seed count (results are committed as `seed0/`,
    `seed1/`, `merged/` side by side; the recorded `run_dir` is the path on the machine that
    merged them), else the recorded path, else the recorded path's tail under a folder above
    (`_moved`: a `bulbjax reproduce` plan folder copied elsewhere), each with that base seed and
    seed count. A clear error when none is found."""
    with open(os.path.join(merged_dir, "config.json")) as f:
        sources = json.load(f).get("merged_from")
    if not sources:
        raise ValueError(f"{merged_dir} is no merged folder (its config.json has no merged_from)")
    parent = os.path.dirname(os.path.normpath(merged_dir))
    names = sorted(os.listdir(parent or "."))
    beside = [(d, _identity(d)) for d in (os.path.join(parent, n) for n in names)
              if not os.path.samefile(d, merged_dir)]
    out = []
    for s in sources:
        want = (s["base_seed"], s["seeds"])
        hits = [d for d, ident in beside if ident == want]
        if len(hits) != 1:
            places = [s["run_dir"], *_moved(s["run_dir"], merged_dir)]
            hits = [d for d in places if _identity(d) == want][:1]
        if not hits:
            raise ValueError(f"{merged_dir}: the run of base seed {s['base_seed']} ({s['seeds']} "
                             f"seeds, merged from {s['run_dir']}) is neither beside it, at that "
                             "path, nor under a folder above it")
        out.append(hits[0])
    return out
