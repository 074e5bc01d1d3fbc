"""Plan folders from several hosts gathered into one (`bulbjax reproduce --out OUT --gather DIR,...`).

A host held for a limited time, or a SLURM task on scratch that is wiped, runs its share of a plan
in a folder of its own (a copy of OUT, or an empty one), and only that folder comes back. Gathering
copies into OUT what each folder finished that OUT has not: the job's run folder (or Fig. 4's
figure folder) and its console log, and each stretch's `summary*.json`, named by when that stretch
finished, so the results page lists every stretch's GPU time once. A job finished in both is kept
as OUT has it; a job a folder holds unfinished is left there (a run is continued only from its
checkpoint, on the host that has it). The folders must hold OUT's plan (or the plan OUT's grows
from or into: `plan.grown_from`), or a plan of fewer figures whose jobs are OUT's (`plan.part_of`:
a host that ran `--figures fig2-cartpole`), or one of more figures of which OUT's is a part (OUT's
plan becomes it).
"""

from __future__ import annotations

import json
import os
import shutil
from typing import Any, Callable, Sequence

from bulbjax.reproduce import jobs as J
from bulbjax.reproduce.plan import IDENTITY, PLAN_FILE, job_of, part_of, plan_differences, read_plan


def gather(out: str, sources: Sequence[str], log: Callable[[str], None] = print,
           dry_run: bool = False) -> dict[str, list[str]]:
    """Copy into `out` the jobs each of `sources` finished that `out` has not, with their logs and
    the sources' stretch summaries; returns the job ids `taken`, `kept` (finished in `out` and in
    a source: `out`'s kept), `unfinished` (begun in a source, not finished there: not taken) and
    `not_begun` (the plan's jobs with no folder in `out` or any source: named, so that a shard
    never run is seen).
    `dry_run`: say what would be taken, copy nothing. Raises ValueError, naming the folder, for a
    missing folder, a source without a plan or with another plan, and an `out` that holds
    something other than a plan."""
    plan = _plan_of(out, sources)
    jobs = [job_of(d) for d in plan["jobs"]]
    path = os.path.join(out, PLAN_FILE)
    before = {d["id"] for d in read_plan(path)["jobs"]} if os.path.exists(path) else None
    added = [j.id for j in jobs if before is not None and j.id not in before]
    if added:
        log(f"{out}'s plan grows to that of the folders gathered: {len(added)} job(s) added ({', '.join(added)})")
    if not dry_run:
        os.makedirs(out, exist_ok=True)
        with open(path, "w") as f:
            json.dump(plan, f, indent=1)
    found: dict[str, list[str]] = {"taken": [], "kept": [], "unfinished": []}
    for src in sources:
        for job in jobs:
            if J.is_done(src, job):
                if job.id in found["taken"] or J.is_done(out, job):
                    if job.id not in found["kept"] + found["taken"]:
                        found["kept"].append(job.id)
                    continue
                if J.begun(out, job):
                    log(f"{job.id}: {out} held it unfinished (epoch {J.epochs_done(out, job)} of {job.epochs}); "
                        f"replaced by the finished one from {src}")
                if not dry_run:
                    _copy_job(src, out, job)
                found["taken"].append(job.id)
            elif J.begun(src, job):
                found["unfinished"].append(job.id)
        for name in ([] if dry_run else _copy_summaries(src, out)):
            log(f"{src}: stretch summary {name}")
    done_here = {j.id for j in jobs if J.is_done(out, j)}
    found["unfinished"] = [i for i in dict.fromkeys(found["unfinished"])
                           if i not in done_here and i not in found["taken"]]
    begun = set(found["taken"]) | set(found["unfinished"]) | {j.id for j in jobs if J.begun(out, j)}
    found["not_begun"] = [j.id for j in jobs if j.id not in begun]
    log(f"{'would gather' if dry_run else 'gathered'} into {out}: {len(found['taken'])} job(s) taken"
        + (f" ({', '.join(found['taken'])})" if found["taken"] else "")
        + (f"; {len(found['kept'])} finished here already, kept as they are" if found["kept"] else "")
        + (f"; unfinished in their folders, not taken (they run again): {', '.join(found['unfinished'])}"
           if found["unfinished"] else "")
        + (f"; {len(found['not_begun'])} job(s) of the plan begun nowhere: {_some(found['not_begun'])}"
           if found["not_begun"] else "; every job of the plan begun"))
    return found


def _some(ids: Sequence[str], k: int = 6) -> str:
    """The first `k` of `ids`, and how many more."""
    return ", ".join(ids[:k]) + (f" and {len(ids) - k} more" if len(ids) > k else "")


def gather_and_report(out: str, sources: Sequence[str], log: Callable[[str], None] = print,
                      dry_run: bool = False) -> str | None:
    """`gather`, then the results page of the gathered folder (`results.write`); its path (None
    with `dry_run`, which writes nothing)."""
    from bulbjax.reproduce import results

    if not sources:
        raise ValueError("--gather needs the plan folders to gather (DIR,DIR,...), brought back from other hosts")
    gather(out, sources, log, dry_run)
    if dry_run:
        return None
    page = results.write(out, results.read_summary(out), out_name=out)
    log(f"results: {page}")
    return page


def _plan_of(out: str, sources: Sequence[str]) -> dict[str, Any]:
    """The plan the gathered folder holds: `out`'s, or the first source's where `out` has none;
    a source's plan that `out`'s grows into (a newer "all") replaces it."""
    path = os.path.join(out, PLAN_FILE)
    plan = read_plan(path) if os.path.exists(path) else None
    if plan is None and os.path.isdir(out) and os.listdir(out):
        raise ValueError(f"{out} is not empty and holds no reproduce plan: gather into a plan's folder or an "
                         "empty one")
    for src in sources:
        if not os.path.isdir(src):
            raise ValueError(f"--gather {src}: no such folder")
        if os.path.abspath(src) == os.path.abspath(out):
            raise ValueError(f"--gather {src}: that is the --out folder itself; give the folders brought back")
        p = os.path.join(src, PLAN_FILE)
        if not os.path.exists(p):
            raise ValueError(f"--gather {src}: no reproduce plan there ({PLAN_FILE}); give plan folders that "
                             "`bulbjax reproduce --out` wrote")
        theirs = read_plan(p)
        if plan is None or not plan_differences(theirs, plan):
            plan = plan or theirs
        elif not plan_differences(plan, theirs):
            plan = theirs  # the source's plan is this one grown: its jobs begin with ours
        elif part_of(theirs, plan):
            pass  # a plan of fewer figures, its jobs ours: its finished ones are taken
        elif part_of(plan, theirs):
            plan = theirs  # ours is a part of the source's: the gathered folder holds the larger plan
        else:
            what = [f"{k} {theirs.get(k)!r} there, {plan.get(k)!r} in {out}" for k in IDENTITY
                    if theirs.get(k) != plan.get(k)]
            raise ValueError(f"--gather {src}: its plan differs from {out}'s ({'; '.join(what)}): gather folders "
                             "of one plan, or of plans whose jobs are the same (a host's --figures a part of "
                             "another's, the same --scale)")
    assert plan is not None
    return plan


def _copy_job(src: str, out: str, job: Any) -> None:
    """`job`'s folder (checkpoints too, where the source kept them) and console log into `out`,
    replacing an unfinished attempt there."""
    dest = J.job_dir(out, job)
    if os.path.exists(dest):
        shutil.rmtree(dest)
    shutil.copytree(J.job_dir(src, job), dest)
    name = job.id.replace("/", "_") + ".txt"
    log_src = os.path.join(src, "logs", name)
    if os.path.exists(log_src):
        os.makedirs(os.path.join(out, "logs"), exist_ok=True)
        shutil.copy2(log_src, os.path.join(out, "logs", name))


def _copy_summaries(src: str, out: str) -> list[str]:
    """Each stretch summary of `src` not already in `out`, as `summary_<finished UTC>.json` (the
    name a stretch that selected its jobs writes, from its end rather than its start, so the
    summaries of hosts that started at once do not collide); the names written. A summary that
    `out` holds under any name (a folder started from a copy of `src`, then gathered from it) is
    not written twice: the page sums the GPU time of every summary."""
    def summaries_in(folder: str) -> list[str]:
        return sorted(n for n in os.listdir(folder) if n.startswith("summary") and n.endswith(".json"))

    held = set()
    for name in summaries_in(out):
        with open(os.path.join(out, name)) as f:
            held.add(f.read())
    written = []
    for name in summaries_in(src):
        with open(os.path.join(src, name)) as f:
            text = f.read()
        if text in held:
            continue
        finished = json.loads(text).get("finished_utc", "")
        stamp = finished[:19].replace("-", "").replace(":", "")
        base = f"summary_{stamp}Z" if stamp else name[:-len(".json")]
        dest, k = f"{base}.json", 1
        while os.path.exists(os.path.join(out, dest)):
            k += 1
            dest = f"{base}_{k}.json"
        with open(os.path.join(out, dest), "w") as f:
            f.write(text)
        held.add(text)
        written.append(dest)
    return written
