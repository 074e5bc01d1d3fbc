"""Bring what GPU allocations ran into the paper campaign's committed plan folder (issue 64:
docs/results/paper_h200), in the steps its README gives, so that none is left out from one
session to the next:

1. in each folder brought back (a plan folder of `bulbjax reproduce` without its checkpoints), the
   runs it finished that the committed folder lacks get their metrics reduced as the committed
   runs' are (`reduce_results.py --unprobed minimal --probed-every 100 --entries read`), written gzipped
   (`metrics.jsonl.gz`), and lose their own `fig2.png` (the page draws each preset's merged one)
   and their reconstructions and SPAIR's boxes but the last epoch's (`last_pictures_only`; those
   kept and `objects.png` become palette PNGs where faithful);
2. `bulbjax reproduce --out DEST --gather SRC,...` takes them, with the stretches' summaries, and
   writes the results page again (a preset whose seeds are all in is merged and drawn);
3. the consoles it copied (`DEST/logs`) go (not committed), and the merged presets' `fig2.png`
   and Fig. 4's reconstructions (`fig4/<preset>/recon_*.png`, ~245 KB -> ~50 KB for a locomotion
   grid) become palette PNGs where faithful (`reduce_results.reduce_png`); a merged preset's
   pooled `metrics.jsonl` stays out of git (.gitignore: it is read again from the runs).

    python benchmarks/campaign_gather.py docs/results/paper_h200 /tmp/l6a/paper /tmp/l6b/paper

It says what it took and the size of DEST; the README's allocations row, the campaign's JSON and
`epoch_times.json`'s rows stay for a person to write (they need what the allocation held).
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import os
import shutil
import sys
from typing import Sequence

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # the repository: bulbjax without an install
PROBED_EVERY = 100  # the committed runs' reduction (docs/results/paper_h200/README.md)


def _reduce_results():
    path = os.path.join(HERE, "reduce_results.py")
    spec = importlib.util.spec_from_file_location("reduce_results", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def shrink(run_dir: str, rr=None) -> None:
    """One run folder as the campaign commits it: its metrics reduced and gzipped (a run writes
    `metrics.jsonl`; one already gzipped is reduced in place), its own `fig2.png` gone."""
    rr = rr or _reduce_results()
    plain = os.path.join(run_dir, "metrics.jsonl")
    if os.path.exists(plain):
        rr.reduce_metrics(plain, unprobed="minimal", probed_every=PROBED_EVERY, entries="read")
        rr._replace(plain + ".gz", rr.encode(rr.read_records(plain), gz=True))
        os.remove(plain)
    elif os.path.exists(plain + ".gz"):
        rr.reduce_metrics(plain + ".gz", unprobed="minimal", probed_every=PROBED_EVERY, entries="read")
    png = os.path.join(run_dir, "fig2.png")
    if os.path.exists(png):
        os.remove(png)
    for png in last_pictures_only(run_dir):
        rr.reduce_png(png)


def last_pictures_only(run_dir: str) -> list[str]:
    """A run's pictures as the campaign keeps them: of its reconstructions and SPAIR's boxes only
    the last epoch's (a Fig. 5 seed draws them every 250 epochs: ~1.4 MB of PNGs a seed, ~0.4 MB
    kept; the page shows seed 0's last), with `objects.png`; returns those kept, for reduce_png."""
    from bulbjax.reproduce.results import drawn_pictures

    kept = []
    for kind in ("recon", "boxes"):
        drawn = drawn_pictures(run_dir, kind)
        last = max(drawn, default=None)
        kept += drawn.get(last, [])
        for path in (p for epoch, paths in drawn.items() if epoch != last for p in paths):
            os.remove(path)
    objects = os.path.join(run_dir, "objects.png")
    return kept + ([objects] if os.path.exists(objects) else [])


def campaign_gather(dest: str, sources: Sequence[str], log=print) -> list[str]:
    """Steps 1-3 of the module doc; returns the job ids taken."""
    from bulbjax.reproduce import jobs as J
    from bulbjax.reproduce.gather import gather, gather_and_report

    rr = _reduce_results()
    new = gather(dest, sources, log=lambda _: None, dry_run=True)["taken"]
    for src in sources:
        for job in _jobs_of(src):
            if job.id in new and J.is_done(src, job):
                shrink(J.job_dir(src, job), rr)
    gather_and_report(dest, list(sources), log=log)
    shutil.rmtree(os.path.join(dest, "logs"), ignore_errors=True)
    pngs = glob.glob(os.path.join(dest, "*", "*", "fig2.png"))
    pngs += glob.glob(os.path.join(dest, "fig4", "*", "recon_*.png"))
    for png in sorted(pngs):
        if os.sep + "runs" + os.sep not in png:
            rr.reduce_png(png)
    size = sum(os.path.getsize(os.path.join(d, n)) for d, _, names in os.walk(dest) for n in names
               if n != "metrics.jsonl")  # a merged preset's pooled metrics: not committed
    log(f"{dest}: {len(new)} job(s) taken ({', '.join(new) or 'none'}); {size / 1e6:.2f} MB as "
        "committed")
    return new


def _jobs_of(folder: str):
    from bulbjax.reproduce.plan import PLAN_FILE, job_of, read_plan

    return [job_of(d) for d in read_plan(os.path.join(folder, PLAN_FILE))["jobs"]]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], epilog=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dest", help="the committed plan folder (docs/results/paper_h200)")
    ap.add_argument("sources", nargs="+", help="plan folders brought back from the allocations")
    a = ap.parse_args(argv)
    campaign_gather(a.dest, a.sources)
    return 0


if __name__ == "__main__":
    sys.exit(main())
