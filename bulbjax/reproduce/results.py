"""A plan's results: each preset's seeds merged into one run folder (`bulbjax report
--merge-seeds`: its fig2.png, table.md, findings.md), Fig. 4's reconstructions, and one page
(`results.md`) over every figure: the figures, every claim's verdict with its band, the PPO
returns per seed, each preset's table. Written at the end of `bulbjax reproduce` and by
`bulbjax report OUT` on a plan's folder, from the runs' own metrics, so it can be redrawn at any
time and never says what the runs do not. The plan's fp32 entry adds its merged runs and a table
of each claim's verdict in bf16 (Fig. 2's runs) beside fp32, read from both merged findings.md."""

from __future__ import annotations

import glob
import json
import os
import shutil
from typing import Any, Sequence

import numpy as np

from bulbjax.eval import regions
from bulbjax.report import band, ci90, last_returns, merge_seeds, metrics_path, probed, read_jsonl, redraw
from bulbjax.reproduce import claims
from bulbjax.reproduce import jobs as J
from bulbjax.reproduce.estimate import hms, hours_unit
from bulbjax.reproduce.plan import ENTRIES, PLAN_FILE, TITLES, Job, job_of, read_plan

PAGE = "results.md"
PROTOCOL_DIR = "probe_protocol"  # the Fig. 2 claims under the probe variants, across domains


def plan_of(out: str) -> tuple[dict, list[Job]]:
    """The plan saved in a reproduce folder and its jobs; a clear error for any other folder."""
    path = os.path.join(out, PLAN_FILE)
    if not os.path.exists(path):
        raise ValueError(f"{out} holds no {PLAN_FILE}: give the --out folder of a `bulbjax reproduce`")
    plan = read_plan(path)
    return plan, [job_of(d) for d in plan["jobs"]]


def runs_by_preset(jobs: Sequence[Job]) -> dict[tuple[str, str], list[Job]]:
    """The run jobs of each (figure, preset), in seed order."""
    out: dict[tuple[str, str], list[Job]] = {}
    for j in jobs:
        if j.kind == "run":
            out.setdefault((j.figure, j.preset), []).append(j)
    return {k: sorted(v, key=lambda j: j.seed) for k, v in out.items()}


def merged_dir(out: str, figure: str, preset: str) -> str:
    return os.path.join(out, figure, preset)


def merge(out: str, figure: str, preset: str, seeds: Sequence[Job]) -> str | None:
    """Merge the finished seeds of one preset into `OUT/<figure>/<preset>` (their reports there,
    with their region errors pooled: `merge.merge_seeds`); returns that folder, or None while any
    seed is unfinished. One seed: its reports and region errors copied."""
    if not all(J.is_done(out, j) for j in seeds):
        return None
    dest = merged_dir(out, figure, preset)
    dirs = [J.job_dir(out, j) for j in seeds]
    if len(dirs) > 1:
        merge_seeds(dirs, dest)
    else:
        redraw(dirs[0])
        os.makedirs(dest, exist_ok=True)
        names = ["config.json", "fig2.png", "table.md", "findings.md", "objects.png"]
        names += [os.path.basename(p) for p in glob.glob(os.path.join(dirs[0], regions.FILE.format(epoch="*")))]
        for name in names:  # the region errors too: the copied findings were read from them
            if os.path.exists(os.path.join(dirs[0], name)):
                shutil.copy2(os.path.join(dirs[0], name), os.path.join(dest, name))
        shutil.copy2(metrics_path(dirs[0]), os.path.join(dest, os.path.basename(metrics_path(dirs[0]))))
    return dest


def _body(path: str) -> str:
    """A report file without its first heading (the page gives its own)."""
    with open(path) as f:
        lines = f.read().splitlines()
    if lines and lines[0].startswith("#"):
        lines = lines[1:]
    return "\n".join(lines).strip()


def ppo_returns(run_dir: str) -> str:
    """The PPO return of each seed over the last 3 probed epochs, and their mean ± 90% band."""
    records = read_jsonl(metrics_path(run_dir), tolerate_partial=True)
    epochs = sorted({r["epoch"] for r in probed(records)})[-3:]
    ret, _ = last_returns(records, epochs)
    if not np.isfinite(ret).any():
        return "PPO return: no episode finished."
    mean, half = ci90(ret[np.isfinite(ret)])
    seeds = ", ".join(f"seed {i}: {r:.1f}" for i, r in enumerate(ret))
    return (f"PPO return per seed (epochs {', '.join(map(str, epochs))}): {seeds}; "
            f"mean {band(mean, half, int(np.isfinite(ret).sum()), digits=1)}.")


def write(out: str, summary: dict[str, Any] | None = None, out_name: str | None = None) -> str:
    """Merge every finished preset and write `OUT/results.md`; returns its path. `summary`: the
    last stretch's (`summary.json`), said in one line; `out_name`: the folder as the user named
    it (default `out`)."""
    plan, jobs = plan_of(out)
    name = out_name or out
    lines = [f"# The paper's figures, reproduced ({plan['scale']} scale)", "",
             f"The plan of `bulbjax reproduce --figures {','.join(plan['figures'])} --scale {plan['scale']}"
             + "".join(f" --add-learner {a}" for a in plan.get("add_learners", [])) + f" --out {name}` "
             "(its jobs run on one host, or a share at a time with `--shard` or `--jobs` and brought "
             f"together with `--gather`: the column ran); redrawn by `bulbjax report {name}`. Errors are "
             "normalised MAEs (1 = the constant predictor's level on π_rand); verdicts use paired 90% "
             "bands over seeds (docs/probes.md).", ""]
    if summary:
        lines += [_summary_line(summary), ""]
    ran, stretches = job_times(out), summaries(out)
    # "CPU" where every stretch ran on CPU worker processes (`hours_unit`)
    unit = "CPU" if stretches and all(hours_unit(s.get("device_kind", "")) == "CPU-hours" for s in stretches) else "GPU"
    lines += [f"| job | figure | epochs done | state | ran | {unit} time | start-up | s / epoch | "
              "wall: estimated / measured (+: estimate over) |", "|---|---|---|---|---|---|---|---|---|"]
    for j in jobs:
        done, r = J.epochs_done(out, j), ran.get(j.id, {})
        per = f"{r['epoch_s']:.3f}" if r.get("epoch_s") else "-"
        lines.append(f"| {j.id} | {j.figure} | {done} / {j.epochs} | "
                     f"{'done' if J.is_done(out, j) else 'unfinished' if done else 'not started'} | "
                     f"{r.get('ran', '-')} | "
                     f"{hms(r['busy_s']) if r.get('busy_s') else '-'} | "
                     f"{hms(r['startup_s']) if r.get('startup_s') else '-'} | {per} | {_against(r)} |")
    if stretches:
        busy = sum(s.get("busy_s", 0.0) * gpu_share(s) for s in stretches)
        lines.append(f"\n{unit} time of the stretches that ran jobs ({len(stretches)}, `summary*.json`): "
                     f"{busy / 3600:.2f} {hours_unit(stretches[-1].get('device_kind', ''))}.")
    lines.append("")
    by_preset = runs_by_preset(jobs)
    merged = {k: merge(out, *k, seeds) for k, seeds in by_preset.items()}  # None: a seed unfinished
    for fig in ENTRIES:
        mine = {p: s for (f, p), s in by_preset.items() if f == fig}
        recon = [j for j in jobs if j.figure == fig and j.kind == "recon"]
        if not mine and not recon:
            continue
        lines += [f"## {TITLES[fig]}", ""]
        for preset, seeds in mine.items():
            lines += _preset_section(out, fig, preset, seeds, merged[(fig, preset)])
        if fig == "fig2":
            lines += _protocol_section(out, [merged_dir(out, fig, p) for p in mine],
                                       [d for (f, _), d in merged.items() if f == "fp32" and d])
        if fig == "fp32":
            for preset, seeds in mine.items():
                lines += precision_section(out, preset, by_preset.get(("fig2", preset), []), seeds)
        for j in recon:
            drawn = drawn_pictures(J.job_dir(out, j), "recon")
            if drawn:
                rel = os.path.relpath(drawn[max(drawn)][-1], out)
                lines += [f"### {j.preset}: seed 0 after {j.epochs} epochs", "", f"![{j.preset}]({rel})", ""]
            else:
                lines += [f"### {j.preset}", "", _undrawn(out, j, jobs), ""]
    path = os.path.join(out, PAGE)
    with open(path, "w") as f:
        f.write("\n".join(lines).rstrip() + "\n")
    return path


def _undrawn(out: str, recon: Job, jobs: Sequence[Job]) -> str:
    """Why a Fig. 4 job has no figure: its run is unfinished, or finished where its last
    checkpoint stayed (a host whose disk went with it)."""
    run = next((j for j in jobs if j.id == recon.after), None)
    if run is None or not J.is_done(out, run):
        return "Not drawn yet (its Fig. 2 run is unfinished)."
    if not J.finished_elsewhere(out, run):
        return "Not drawn yet (its run has finished; the Fig. 4 job has not run)."
    return (f"Not drawn: its Fig. 2 run ({run.id}) finished on a host that kept its last checkpoint; run it "
            f"again with this job (delete {run.run_dir}, then `--jobs {recon.id}`).")


def _preset_section(out: str, fig: str, preset: str, seeds: Sequence[Job], dest: str | None) -> list[str]:
    """One preset's section: its merged runs (`dest`, from `merge`; None while a seed is
    unfinished) as figure, findings, PPO returns and links."""
    done = sum(J.is_done(out, j) for j in seeds)
    name = seeds[0].id.rsplit("/", 1)[0]  # the preset, after its entry's prefix (fp32/fig2-invpend)
    head = f"### {name}: {sum(j.seeds for j in seeds)} seeds x {seeds[0].epochs} epochs"
    if dest is None:
        return [head, "", f"{done} of {len(seeds)} jobs finished: their seeds are merged once all are.", ""]
    rel = os.path.relpath(dest, out)
    lines = [head, "", f"![{preset}]({rel}/fig2.png)", ""]
    if os.path.exists(os.path.join(dest, "objects.png")):
        lines += [f"![{preset} objects]({rel}/objects.png)", ""]
    lines += [_body(os.path.join(dest, "findings.md")), "", ppo_returns(dest), "",
              f"Errors per learner and state group: [{rel}/table.md]({rel}/table.md).", ""]
    return lines + last_drawn(out, J.job_dir(out, seeds[0]))


def last_drawn(out: str, run_dir: str) -> list[str]:
    """The page's lines for a run's last drawn reconstructions and SPAIR's boxes (those of the
    largest epoch drawn, each boxes picture named by its learner), links relative to `out`."""
    lines = []
    for label, kind in (("reconstructions", "recon"), ("SPAIR's boxes", "boxes")):
        drawn = drawn_pictures(run_dir, kind)
        if drawn:
            last = max(drawn)
            links = " ".join(f"![{_picture_name(p, kind, label)}]({os.path.relpath(p, out)})"
                             for p in drawn[last])
            lines += [f"Seed 0's {label}, last drawn (epoch {last}): {links}", ""]
    return lines


def _picture_name(path: str, kind: str, label: str) -> str:
    """`boxes_<epoch>_<learner>.png` -> "<learner>'s boxes"; otherwise `label`."""
    parts = os.path.basename(path)[: -len(".png")].split("_", 2)
    return f"{parts[2]}'s boxes" if kind == "boxes" and len(parts) == 3 else label


def drawn_pictures(run_dir: str, kind: str) -> dict[int, list[str]]:
    """A run's pictures of one kind by the epoch they show: `recon_<epoch>.png`, or
    `boxes_<epoch>_<learner>.png` (one per learner with boxes), each epoch's paths sorted. By
    number, not by name: recon_1000 sorts before recon_250."""
    found: dict[int, list[str]] = {}
    for path in sorted(glob.glob(os.path.join(glob.escape(run_dir), f"{kind}_*.png"))):
        epoch = os.path.basename(path)[len(kind) + 1: -len(".png")].split("_", 1)[0]
        if epoch.isdecimal():
            found.setdefault(int(epoch), []).append(path)
    return found


def _protocol_section(out: str, dirs: Sequence[str], fp32: Sequence[str] = ()) -> list[str]:
    """The Fig. 2 claims under each probe variant, over the merged runs that carry the variants
    (`bulbjax report --probe-protocol`), into OUT/probe_protocol/table.md; nothing without them.
    `fp32`: the fp32 entry's merged runs; each one of a domain among those runs is its "fp32 run"
    column (`bulbjax report --probe-protocol --fp32`)."""
    from bulbjax.config import read_run_config
    from bulbjax.report import probe_protocol_table

    runs = [d for d in dirs if os.path.exists(os.path.join(d, "config.json"))
            and read_run_config(d)[0].probe_variants]
    if not runs:
        return []
    envs = {read_run_config(d)[0].env for d in runs}
    dest = os.path.join(out, PROTOCOL_DIR)
    probe_protocol_table(runs, [d for d in fp32 if read_run_config(d)[0].env in envs], out_dir=dest)
    rel = os.path.relpath(os.path.join(dest, "table.md"), out)
    return ["### The Fig. 2 claims under the probe protocol's variants", "",
            f"Is a verdict the latent's or the probe's? Every claim of every domain above with the "
            f"present probe, a common probe set, the sequential learners' whole window and raw MAE: "
            f"[{rel}]({rel}) (docs/probes.md, \"Variants of the protocol\").", ""]


SAME_CLAIMS_DROP = ("beyond the paper",)  # rows of findings.md that are not the paper's claims


def precision_section(out: str, preset: str, bf16: Sequence[Job], fp32: Sequence[Job]) -> list[str]:
    """`preset`'s claims in bf16 (its Fig. 2 jobs, `bf16`) beside fp32 (the fp32 entry's jobs,
    `fp32`): a row per claim of the paper this domain tests, each cell that side's verdict and
    bands as its merged findings.md says them (`claims.findings_rows`, `claims.cell`: the rows the
    sections above show, computed once by `bulbjax report`), and whether the two agree. One line
    while a side is unfinished or the plan has no Fig. 2 runs of the preset."""
    from bulbjax.config import read_run_config

    lines = [f"### {preset}: the claims in bf16 and in fp32", ""]
    if not bf16:
        return lines + [f"Not compared: the plan has no Fig. 2 runs of {preset} (plan them too: "
                        f"--figures fig2,fp32 or {preset},fp32).", ""]
    sides = (("Fig. 2's", "fig2", bf16), ("the fp32 entry's", "fp32", fp32))
    waiting = [f"{name} runs ({sum(J.is_done(out, j) for j in jobs)} of {len(jobs)} jobs finished)"
               for name, _, jobs in sides if not all(J.is_done(out, j) for j in jobs)]
    if waiting:
        return lines + [f"Not compared yet: {' and '.join(waiting)} unfinished; compared once both "
                        "sides are merged.", ""]
    dirs = [merged_dir(out, fig, preset) for _, fig, _ in sides]
    rows = [claims.findings_rows(d) for d in dirs]
    dtypes = [read_run_config(d)[0].learner.compute_dtype for d in dirs]
    names = [c for c in dict.fromkeys(k for r in rows for k in r)
             if not any(x in c for x in SAME_CLAIMS_DROP)
             and not all(r.get(c, ("not tested",))[0].startswith("not tested") for r in rows)]
    lines += [f"| claim (paper, Fig. 2) | Fig. 2 runs ({dtypes[0]} learners) | fp32 runs ({dtypes[1]} learners) | "
              "same verdict |", "|---|---|---|---|"]
    same = 0
    for c in names:
        a, b = (r.get(c) for r in rows)
        agree = a is not None and b is not None and a[0] == b[0]
        same += agree
        lines.append(f"| {c} | {claims.cell(*a) if a else '-'} | {claims.cell(*b) if b else '-'} | "
                     f"{'yes' if agree else '**no**'} |")
    rels = [os.path.relpath(os.path.join(d, "findings.md"), out) for d in dirs]
    lines += ["", f"{same} of {len(names)} verdicts the same; each cell from [{rels[0]}]({rels[0]}) and "
              f"[{rels[1]}]({rels[1]}) (the sections above).", ""]
    return lines


def _summary_line(s: dict[str, Any]) -> str:
    est = s.get("estimated_wall_s")
    shared = s.get("jobs_per_gpu") or 1
    gpus = s.get("gpus")
    where = (f"{gpus} {s.get('device_kind')} GPUs, {gpus // 2} slot(s) of two (each job's learners on "
             "the second)" if s.get("learners_apart") and isinstance(gpus, int)
             else f"{gpus} {s.get('device_kind')} slot(s)")
    return (f"The last stretch{_stretch_name(s)}: {where}"
            + (f" ({shared} jobs side by side on each)" if shared > 1 else "")
            + (" under an MPS daemon" if s.get("mps") else "") + ", "
            f"{hms(s.get('measured_wall_s', 0))} "
            f"wall (estimated {hms(est) if est is not None else '-'}), utilisation "
            f"{(s.get('utilisation') or 0):.0%}, {s.get('gpu_hours', 0):.2f} {hours_unit(s.get('device_kind', ''))}.")


def _stretch_name(s: dict[str, Any]) -> str:
    """" (shard K/N, ended 2026-11-30 04:52 UTC)" of a stretch's summary, what it has of these."""
    shard = s.get("shard")
    said = [f"shard {shard[0]}/{shard[1]}"] if shard else []
    if s.get("finished_utc"):
        said.append(f"ended {s['finished_utc'][:16].replace('T', ' ')} UTC")
    return f" ({', '.join(said)})" if said else ""


def gpus_held(learners_apart: bool, device_kind: str, jobs_per_gpu: int = 1) -> float:
    """GPUs one job holds: two with its learners apart (a CPU worker counts as one), a share of
    one beside others on its GPU (`jobs_per_gpu`), else one."""
    return (2 if learners_apart and device_kind != "cpu" else 1) / jobs_per_gpu


def gpu_share(s: dict[str, Any]) -> float:
    """GPUs one of a stretch's jobs held (`s`: its summary; `gpus_held`)."""
    return gpus_held(bool(s.get("learners_apart")), s.get("device_kind", ""), s.get("jobs_per_gpu") or 1)


def summaries(out: str) -> list[dict[str, Any]]:
    """Every stretch's summary in the plan's folder (`summary.json`, `summary_shard<K>of<N>.json`,
    `summary_<UTC time>.json`: one per host of a sharded plan or per stretch that selected its
    jobs), oldest first by their `finished_utc`."""
    out_ = []
    for path in glob.glob(os.path.join(glob.escape(out), "summary*.json")):
        with open(path) as f:
            out_.append(json.load(f))
    return sorted(out_, key=lambda s: s.get("finished_utc", ""))


def _against(r: dict[str, Any]) -> str:
    """A job's estimated wall time beside its measured one and how far off the estimate was, or
    "-" where a stretch that ran it kept no estimate (summaries before `estimated_s`)."""
    est, wall = r.get("estimated_s"), r.get("wall_s")
    if not est or not wall:
        return "-"
    return f"{hms(est)} / {hms(wall)} ({(est - wall) / wall:+.0%})"


def job_times(out: str) -> dict[str, dict[str, Any]]:
    """Each job's measured GPU time (`busy_s`, summed over the stretches that ran it, times the
    GPUs it held: `gpu_share`), where its last stretch ran it (`ran`: the day, the slot, the
    shard), its wall time on its slot
    (`wall_s`) and what the plans estimated for it (`estimated_s`, None unless every stretch that
    ran it kept one), its last start-up (`startup_s`) and seconds per epoch (`epoch_s`), from
    every stretch's summary."""
    times: dict[str, dict[str, Any]] = {}
    for s in summaries(out):
        for jid, r in (s.get("jobs") or {}).items():
            if not r.get("attempts"):
                continue
            t = times.setdefault(jid, {"busy_s": 0.0, "wall_s": 0.0, "estimated_s": 0.0})
            t["busy_s"] += (r.get("busy_s") or 0.0) * gpu_share(s)
            t["wall_s"] += r.get("busy_s") or 0.0
            est = r.get("estimated_s")
            t["estimated_s"] = None if est is None or t["estimated_s"] is None else t["estimated_s"] + est
            for k in ("startup_s", "epoch_s"):
                if r.get(k):
                    t[k] = r[k]
            when = s.get("finished_utc", "")[:10] or "?"
            t["ran"] = f"{when}, {r.get('slot') or '?'}" + (f", shard {s['shard'][0]}/{s['shard'][1]}"
                                                             if s.get("shard") else "")
    return times


def read_summary(out: str) -> dict[str, Any] | None:
    """The last stretch's summary (`summary.json`, else the newest `summary*.json`), or None."""
    path = os.path.join(out, "summary.json")
    if os.path.exists(path):
        with open(path) as f:
            return json.load(f)
    every = summaries(out)
    return every[-1] if every else None
