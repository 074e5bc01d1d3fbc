"""The table `bulbjax reproduce` estimates with (`bulbjax/reproduce/epoch_times.json`), measured.

For each preset: one seed's job run twice in a row on one GPU (the first starts cold, the second
finds the first's programs in the compile cache and starts warm), and with `--extra-seed` a job of
two seeds (what one more seed in a process adds to an epoch), each for `--epochs` epochs with the
plan's settings (bf16, probes every 10th epoch; on the CPU the tiny scale's `--small` runs). The
jobs go through the plan's own queue (`bulbjax.reproduce.queue`), which measures each one's
start-up (launch to first epoch) and seconds per epoch (from its first record to its last: the
last checkpoint and the exit after them, its `end_s`, are left out, ~10 s that a short job would
spread over its few epochs). Or `--from-summary OUT/summary.json` takes
the same figures from a `bulbjax reproduce` run. Writes `results/epoch_times_<device>_<stamp>.json`;
`--write` also rewrites the device's entries of the package table (and docs/reproduce.md's copy
of it), marking each `measured`.

GPU: python benchmarks/epoch_times.py --presets fig2-invpend,fig2-cartpole --epochs 60 --write
CPU smoke run: python benchmarks/epoch_times.py --presets fig2-cartpole --epochs 2
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import re
import statistics
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
sys.path.insert(0, REPO)

from bulbjax.reproduce import estimate  # noqa: E402
from bulbjax.reproduce.main import slots_of  # noqa: E402
from bulbjax.reproduce.plan import PLAN_FILE, Job, figure_specs, job_of, read_plan  # noqa: E402
from bulbjax.reproduce.queue import Queue  # noqa: E402

TABLE = os.path.join(REPO, "bulbjax", "reproduce", estimate.TIMES_FILE)
DOC = os.path.join(REPO, "docs", "reproduce.md")


def jobs_for(presets: list[str], epochs: int, cpu: bool, extra_seed: bool) -> list[Job]:
    """Per preset: seed 0 (cold), seed 1 (warm), and with `extra_seed` seeds 2-3 in one job."""
    scale = "tiny" if cpu else "paper"
    specs = figure_specs(scale)
    out = []
    for p in presets:
        spec = next(s for s in specs.values() if p in s.presets)
        flags = spec.flags
        for seed, seeds in [(0, 1), (1, 1)] + ([(2, 2)] if extra_seed else []):
            name = f"seed{seed}" if seeds == 1 else f"seeds{seed}-{seed + 1}"
            out.append(Job(f"{p}/{name}", spec.name, "run", p, seed, epochs, f"runs/{p}/{name}", 10, 0, flags,
                           seeds=seeds, checkpoint_every=epochs))
    return out


def measured(summary: dict, jobs: list[Job]) -> dict[str, dict]:
    """Per preset: epoch_s (one seed), startup cold (its first job) and warm (the next one's),
    extra_seed_s (the two-seed job's epoch time over one seed's), from the queue's summary."""
    out: dict[str, dict] = {}
    for p in dict.fromkeys(j.preset for j in jobs):
        rec = {j.id: (j, summary["jobs"].get(j.id, {})) for j in jobs if j.preset == p}
        ones = [r for j, r in rec.values() if j.seeds == 1 and r.get("epoch_s")]
        firsts = [r.get("startup_s") for j, r in rec.values() if j.seeds == 1]
        entry: dict = {}
        if ones:
            entry["epoch_s"] = round(statistics.median(r["epoch_s"] for r in ones), 3)
        if firsts and firsts[0]:
            entry["startup_cold_s"] = round(firsts[0])
        if len(firsts) > 1 and firsts[1]:
            entry["startup_warm_s"] = round(firsts[1])
        two = [r for j, r in rec.values() if j.seeds == 2 and r.get("epoch_s")]
        if two and "epoch_s" in entry:
            entry["extra_seed_s"] = round(max(0.0, two[0]["epoch_s"] - entry["epoch_s"]), 3)
        out[p] = entry
    return out


def from_summary(path: str) -> tuple[str, dict[str, dict]]:
    """Per-row figures from a `bulbjax reproduce` summary.json (its jobs of one seed): each job's
    row as the estimate keys it (`estimate.timing_key`: an fp32 job's `<preset> fp32`; a stretch
    with the learners apart: `<row> apart`), read from the plan.json beside it; without one, the
    preset its id begins with."""
    with open(path) as f:
        s = json.load(f)
    if (s.get("jobs_per_gpu") or 1) > 1:
        raise SystemExit(f"{path}: its jobs ran {s['jobs_per_gpu']} to a GPU (--jobs-per-gpu), so their epoch "
                         "times are not one job's alone: give the summary of a stretch of one job per GPU")
    plan_path = os.path.join(os.path.dirname(os.path.abspath(path)), PLAN_FILE)
    planned = {d["id"]: job_of(d) for d in read_plan(plan_path)["jobs"]} if os.path.exists(plan_path) else {}
    by: dict[str, list[dict]] = {}
    for jid, r in s["jobs"].items():
        if "/seed" in jid and r.get("epoch_s"):
            row = estimate.timing_key(planned[jid]) if jid in planned else jid.split("/")[0]
            if s.get("learners_apart"):  # two GPUs a job: the row `estimate.apart_times` reads
                row = estimate.APART_ROW.format(preset=row)
            by.setdefault(row, []).append(r)
    out = {p: {"epoch_s": round(statistics.median(r["epoch_s"] for r in rs), 3),
               **({"startup_cold_s": round(max(r["startup_s"] for r in rs if r.get("startup_s")))}
                  if any(r.get("startup_s") for r in rs) else {})} for p, rs in by.items()}
    return s["device_kind"], out


def write_table(kind: str, found: dict[str, dict], note: str) -> None:
    """Rewrite `kind`'s measured entries of the package table and the docs' copy of it."""
    with open(TABLE) as f:
        table = json.load(f)
    mine = table["kinds"].setdefault(kind, {})
    for p, e in found.items():
        # a new fp32 row (`<preset> fp32`) starts from its preset's bf16 row: the fields this
        # measurement lacks (warm start-up, a further seed) stay as that row has them
        old = dict(mine.get(p) or mine.get(p.split(" ")[0], {}))
        old.pop("derived", None)
        mine[p] = {**old, **e, "measured": note}
    lines = ["{", f' "about": {json.dumps(table["about"])},', ' "kinds": {']
    kinds = list(table["kinds"])
    for i, k in enumerate(kinds):
        rows = [f'   {json.dumps(p)}: {json.dumps(t)}' for p, t in table["kinds"][k].items()]
        lines += [f"  {json.dumps(k)}: {{", ",\n".join(rows), "  }" + ("," if i < len(kinds) - 1 else "")]
    lines += [" },", f' "fallback": {json.dumps(table["fallback"])}', "}"]
    with open(TABLE, "w") as f:
        f.write("\n".join(lines) + "\n")
    with open(DOC, encoding="utf-8") as f:
        doc = f.read()
    doc = re.sub(r"(<!-- epoch-times.*?-->\n).*?(\n<!-- /epoch-times -->)",
                 lambda m: m.group(1) + estimate.times_markdown() + m.group(2), doc, flags=re.S)
    with open(DOC, "w", encoding="utf-8") as f:
        f.write(doc)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", default="fig2-cartpole,fig2-invpend,fig2-halfcheetah,fig2-ant")
    p.add_argument("--epochs", type=int, default=40)
    p.add_argument("--gpus", type=int, default=1, help="slots the jobs share (1: cold then warm, one after another)")
    p.add_argument("--extra-seed", action="store_true", help="also a two-seed job per preset")
    p.add_argument("--from-summary", default=None, help="a `bulbjax reproduce` summary.json instead of running")
    p.add_argument("--write", action="store_true", help="rewrite this device's entries of the package table")
    p.add_argument("--out-dir", default=os.path.join(HERE, "results"))
    a = p.parse_args(argv)
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    if a.from_summary:
        kind, found = from_summary(a.from_summary)
        note = f"bulbjax reproduce, {os.path.basename(os.path.dirname(os.path.abspath(a.from_summary)))}, {stamp[:8]}"
        summary = None
    else:
        slots, kind = slots_of(a.gpus)
        times, _ = estimate.load_times(kind)
        jobs = jobs_for([x for x in a.presets.split(",") if x], a.epochs, kind == "cpu", a.extra_seed)
        with tempfile.TemporaryDirectory() as tmp:
            summary = Queue(tmp, jobs, jobs, slots, times, progress_every=60).run()
        found = measured(summary, jobs)
        note = f"benchmarks/epoch_times.py, {a.epochs} epochs, {stamp[:8]}"
    print(json.dumps(found, indent=1))
    slug = "".join(c if c.isalnum() else "_" for c in kind.lower()).strip("_")
    os.makedirs(a.out_dir, exist_ok=True)
    path = os.path.join(a.out_dir, f"epoch_times_{slug}_{stamp}.json")
    with open(path, "w") as f:
        json.dump({"command": " ".join(sys.argv), "device_kind": kind, "found": found, "queue": summary}, f, indent=1)
    print(f"wrote {path}")
    if a.write:
        write_table(kind, found, note)
        print(f"rewrote {TABLE} and the table in {DOC}")
    return found


if __name__ == "__main__":
    main()
