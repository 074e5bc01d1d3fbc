"""Host-side reports of a run: the final table and the report files of a run folder (`fig2.png`,
`table.md`, `findings.md`, `objects.png`; an offline fit's `curves.png` and `table.md`), written
during a run, redrawn (`bulbjax report`), over the merged seeds of several runs, or comparing the
PPO returns of runs. The plots: `report_plots`; the records they read: `records`."""

from __future__ import annotations

import json
import os
from typing import Any, Sequence

import numpy as np

from bulbjax.config import read_run_config
from bulbjax.eval import objects
from bulbjax.eval.spec import StateEntry
from bulbjax.report import findings
from bulbjax.report.records import (STREAMS, VARIANT_SOURCES, band, ci90, epochs_to_reach, excluded_groups, groups_of,
                                    has_linear, has_objects, last_returns, metrics_path, per_seed_error, probed,
                                    read_jsonl, rl_curve, variants_of)
from bulbjax.report.report_plots import OLD_NORM_NOTE, has_reference_spread, norm_note, plot, plot_objects, rl_band


def table(records: Sequence[dict[str, Any]], spec: Sequence[StateEntry], last: int = 1,
          x_key: str = "epoch", streams: Sequence[tuple[str, str]] = STREAMS) -> str:
    """Markdown table of the final normalised group errors (mean +- 90% CI over seeds, averaged
    over the `last` probed epochs) per learner and stream, with the constant predictor, the RL
    return over the same epochs, and a line saying what the errors are divided by. Rows
    `<learner>` are the MLP probe's; rows `<learner> (linear)` the linear (ridge) probe's on the
    same pairs, when the records have one."""
    epochs = sorted({r[x_key] for r in probed(records)})[-last:]
    recs = [r for r in records if r[x_key] in epochs]
    groups = groups_of(spec)
    learners = list(recs[0]["probes"])
    head = "| learner | stream | " + " | ".join(f"{g} (norm. MAE)" for g in groups) + " | overall |"
    lines = [head, "|" + "---|" * (3 + len(groups))]
    if not has_reference_spread(records):  # a run from before issue 12: say what its errors are
        lines = [f"> Error definition used here (before issue 12): {OLD_NORM_NOTE}. Later runs divide "
                 "by a fixed random-policy reference spread (README, \"How errors are reported\").",
                 ""] + lines
    seeds = sorted({r["seed"] for r in recs})
    gone = excluded_groups(recs)

    linear = has_linear(recs)

    def cell(name: str, stream: str, g: str, probes: str = "probes") -> str:
        if g in gone:
            return "excluded"
        v = per_seed_error(recs, name, stream, None if g == "overall" else g, epochs, x_key, probes)
        mean, half = ci90(v)
        return band(mean, half, int(np.isfinite(v).sum()))

    for stream, label in streams:
        for name in learners + ["constant"]:
            cells = [cell(name, stream, g) for g in groups + ["overall"]]
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
        for name in learners if linear else []:
            cells = [cell(name, stream, g, "linear_probes") for g in groups + ["overall"]]
            lines.append(f"| {name} (linear) | {label} | " + " | ".join(cells) + " |")
        for variant in ("common", "window"):  # probe-protocol variants, where the run has them
            key = VARIANT_SOURCES[variant][0]
            for name in [n for n in learners if any(n in r.get(key, {}) for r in recs)]:
                cells = [cell(name, stream, g, key) for g in groups + ["overall"]]
                lines.append(f"| {name} ({variant}) | {label} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(f"{x_key} {', '.join(str(e) for e in epochs)}; "
                 + (f"mean ± 90% CI over {len(seeds)} seeds." if len(seeds) > 1 else "1 seed: no band over seeds."))
    if gone:
        lines.append(f"excluded: {', '.join(g for g in groups if g in gone)} (every entry constant over the run, "
                     "reference spread ~0: nothing to predict, no normalised error).")
    if "rl_return" in recs[0]:
        ret, fell_back = last_returns(records, epochs, x_key)
        mean, half = ci90(ret)
        shown = band(mean, half, len(seeds), digits=1)
        where = (f"the last {len(epochs)} probed epoch(s)" if not fell_back else
                 f"the last {len(epochs)} probed epoch(s), or a seed's latest finished episode up to "
                 "the last of them where none ended in them")
        lines.append(f"PPO return over {where}: {shown}" + (f" (90% CI over {len(seeds)} seeds)" if len(seeds) > 1 else ""))
    clamped = clamped_shares(recs)
    if clamped:
        lines.append("Held-out steps whose latent the probes clamped to their fit range (most of any seed and "
                     "stream, `docs/probes.md`): " + ", ".join(f"{n} {v:.1%}" for n, v in clamped.items()) + ".")
    lines.append("")
    if linear:
        lines.append("Rows `<learner>`: the MLP probe; `<learner> (linear)`: closed-form ridge regression on the "
                     "same pairs and validation split, regulariser chosen per entry on it "
                     "(`bulbjax.eval.linear`).")
    if {"common", "window"} & set(variants_of(recs)):
        lines.append("Rows `<learner> (common)`: the probe fit on the common probe set (the same "
                     "pairs for every learner of a seed); `<learner> (window)`: sequential learners' "
                     "whole-window probe, every learner scored on the held-out windows' last steps "
                     "(docs/probes.md, \"Variants of the protocol\").")
    lines.append(f"Errors: {norm_note(records)}; raw MAE in each entry's unit in metrics.jsonl.")
    if "raw" in variants_of(recs):
        raw = raw_table(recs, groups, epochs, x_key, streams)
        lines += ["", "## Raw MAE (probe variant `raw`)", "", raw]
    return "\n".join(lines)


def raw_table(recs: Sequence[dict[str, Any]], groups: Sequence[str], epochs: Sequence[int],
              x_key: str = "epoch", streams: Sequence[tuple[str, str]] = STREAMS) -> str:
    """The present probe's MAE per group in the state's units (`probes_raw`,
    `records.raw_summary`): mean ± 90% band over seeds, with the constant predictor's."""
    learners = list(dict.fromkeys(n for r in recs for n in r.get("probes_raw", {})))
    units = next(iter(next(r for r in recs if r.get("probes_raw"))["probes_raw"].values()))
    units = next(iter(units.values()))
    head = [f"{g} ({', '.join(units['groups'][g]['units'])})" for g in groups] + ["overall"]
    lines = ["| learner | stream | " + " | ".join(head) + " |", "|" + "---|" * (2 + len(head))]
    for stream, label in streams:
        for name in learners + ["constant"]:
            cells = []
            for g in list(groups) + ["overall"]:
                v = per_seed_error(recs, name, stream, None if g == "overall" else g, epochs, x_key,
                                   "probes_raw", "mae")
                mean, half = ci90(v)
                cells.append(band(mean, half, int(np.isfinite(v).sum())))
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
    lines += ["", "Plain mean of the group's entries' MAE, each in its own unit (a group mixing "
              "units, e.g. m and rad, adds them as the paper's mean absolute error does); no "
              "normalisation, every entry counted."]
    return "\n".join(lines)


def clamped_shares(records: Sequence[dict[str, Any]]) -> dict[str, float]:
    """Per learner, the largest share of held-out steps whose latent its probes clamped
    (`probe_inputs_clamped`, `bulbjax.eval.probe.standardise`) over `records`' seeds and streams;
    {} for records made before the clamp."""
    out: dict[str, float] = {}
    for r in records:
        for name, streams in r.get("probe_inputs_clamped", {}).items():
            for v in streams.values():
                if v is not None and np.isfinite(v):
                    out[name] = max(out.get(name, 0.0), float(v))
    return out


def title_of(cfg: Any, epochs_done: int) -> str:
    return (f"{cfg.env}{' (multicolour)' if cfg.multicolour else ''}: {cfg.seeds} seeds, "
            f"{epochs_done} epochs")


def write_reports(run_dir: str, records: Sequence[dict[str, Any]], cfg: Any,
                  spec: Sequence[StateEntry], solved_return: float | None = None,
                  footer: str = "", figures: bool = True, source_dir: str | None = None) -> str:
    """`fig2.png`, `table.md`, `findings.md` (the paper's Fig. 2 claims checked, `findings`) (and
    `objects.png` when learners with boxes were probed in a domain with objects) of a run from its
    records (all epochs written so far); returns the table. Epochs whose seeds are not all
    written yet (a run in progress) are left out, and so are the probes of epochs that only some
    seeds were probed at (merged runs whose metrics were reduced differently): the table says
    which. `figures=False` writes the Markdown files only (tests of the committed results).
    `source_dir`: the run folder whose `regions_<epoch>.json` the object findings read, where
    the reports go elsewhere (default `run_dir`)."""
    seeds = sorted({r["seed"] for r in records})
    per_epoch: dict[int, int] = {}
    for r in records:
        per_epoch[r["epoch"]] = per_epoch.get(r["epoch"], 0) + 1
    records = [r for r in records if per_epoch[r["epoch"]] == len(seeds)]
    records, partial = drop_partial_probes(records, len(seeds))
    if not probed(records):
        raise ValueError(f"{source_dir or run_dir} has no probed epoch yet: nothing to plot "
                         "(wait for the first epoch)")
    done = len({r["epoch"] for r in records})
    title = title_of(cfg, done)
    if figures:
        plot(records, spec, os.path.join(run_dir, "fig2.png"), title, solved_return=solved_return)
    last = min(3, len(probed(records)) // len(seeds))
    tab = table(records, spec, last=last)
    if partial:
        tab += ("\n\nProbed at only some seeds, left out of this table, the findings and the "
                f"plots: epoch(s) {', '.join(map(str, partial))}.")
    obj = objects.comparison_table(records, spec, last=last)
    if obj:
        tab += f"\n\n## Objects\n\n{obj}"
    if obj and has_objects(records) and figures:
        plot_objects(records, os.path.join(run_dir, "objects.png"), title)
    with open(os.path.join(run_dir, "table.md"), "w") as f:
        f.write(f"# {title}\n\n{tab}\n" + (f"\n{footer}\n" if footer else ""))
    if "Rearrange" in cfg.env:  # the multi-object scenes of Figs. 3 and 5: their claims
        from bulbjax.report import findings_objects

        from bulbjax.eval import regions

        newest = regions.newest(source_dir or run_dir)
        verdicts, epochs = findings_objects.check_objects(records, cfg.env, cfg.version, last=last,
                                                          regions=newest)
        verdicts += findings.added_learner_rows(records, spec, epochs)
        body = findings_objects.markdown(verdicts, epochs, len(seeds))
        which = "Figs. 3 and 5"
    else:
        verdicts, epochs = findings.check(records, spec, cfg.env, last=last)
        body, which = findings.markdown(verdicts, epochs, len(seeds)), "Fig. 2"
        if len(variants_of(records)) > 1:  # probe-protocol variants: every claim under each
            sets, epochs = findings.variant_checks(records, spec, cfg.env, last=last)
            body += ("\n\n## The claims under the probe protocol's variants\n\n"
                     + findings.variants_markdown(sets, epochs, len(seeds)))
    with open(os.path.join(run_dir, "findings.md"), "w") as f:
        f.write(f"# {title}: the paper's {which} findings\n\n{body}\n")
    return tab


MTIME_SLACK_S = 1.0
REPORT_FILES = (("plot", "fig2.png"), ("plot", "curves.png"), ("objects", "objects.png"), ("table", "table.md"),
                ("findings", "findings.md"))


def files_written(folder: str, since: float = 0.0) -> str:
    """'plot: PATH' lines, one per report file in `folder` written since `since` (a `time.time()`
    taken before writing, less `MTIME_SLACK_S`: the kernel stamps files from a coarser clock;
    `REPORT_FILES`: a run's fig2.png, an offline fit's curves.png, objects.png, table.md,
    findings.md), for the commands to say where they wrote (and not a file an earlier report
    left there)."""
    paths = [(what, os.path.join(folder, name)) for what, name in REPORT_FILES]
    return "\n".join(f"{what}: {path}" for what, path in paths
                     if os.path.exists(path) and os.path.getmtime(path) >= since - MTIME_SLACK_S)


def drop_partial_probes(records: Sequence[dict[str, Any]], seeds: int
                        ) -> tuple[list[dict[str, Any]], list[int]]:
    """`records` with the probe results of epochs probed at fewer than `seeds` seeds removed (the
    records stay, as unprobed ones), and those epochs. A run probes all its seeds at the same
    epochs; pooled runs whose metrics kept different probed epochs would otherwise be averaged
    over a subset of seeds while the reports name all of them."""
    probed_at: dict[int, int] = {}
    for r in probed(records):
        probed_at[r["epoch"]] = probed_at.get(r["epoch"], 0) + 1
    partial = sorted(e for e, n in probed_at.items() if n < seeds)
    if not partial:
        return list(records), []
    gone = ("linear_probes", "objects", "probe_inputs_clamped",
            *(key for key, _ in VARIANT_SOURCES.values()))  # "probes" and the variants' keys
    out = [r if r["epoch"] not in partial
           else {**{k: v for k, v in r.items() if k not in gone}, "probes": {}} for r in records]
    return out, partial


def report_spec(state_spec: Sequence[StateEntry], records: Sequence[dict]) -> tuple[StateEntry, ...]:
    """The entries a run's probes regressed: the state and its derived targets
    (`probing.probe_targets`), or the state alone for records written before the derived
    targets existed (their `ref_spread` has one number per state entry)."""
    from bulbjax.epoch import probe_targets

    spec = probe_targets(state_spec).spec
    widths = {len(r["ref_spread"]) for r in records if "ref_spread" in r}
    return tuple(state_spec) if widths == {len(state_spec)} else spec


def redraw(run_dir: str, out_dir: str | None = None, figures: bool = True) -> str:
    """`bulbjax report RUN_DIR [--out OUT]`: the reports again from config.json and metrics.jsonl
    (also while the run is still writing them: incomplete epochs are left out), into `out_dir`
    (created; default the run folder itself); an offline fit's folder (`bulbjax fit`: config.json
    with `offline`, `curves.jsonl`) gets its `curves.png` and `table.md` again
    (`redraw_offline`). `figures=False`: the Markdown files only."""
    from bulbjax.envs.registry import env_class

    if is_offline(run_dir):
        if out_dir is not None and os.path.abspath(out_dir) != os.path.abspath(run_dir):
            raise ValueError(f"{run_dir} is an offline fit's folder: `bulbjax report` redraws it in place "
                             "(leave out --out)")
        with open(os.path.join(run_dir, "config.json")) as f:
            return redraw_offline(run_dir, json.load(f), figures)
    cfg, _ = read_run_config(run_dir)
    records = read_jsonl(metrics_path(run_dir), tolerate_partial=True)
    cls = env_class(cfg.env)
    out_dir = run_dir if out_dir is None else out_dir
    os.makedirs(out_dir, exist_ok=True)
    return write_reports(out_dir, records, cfg, report_spec(cls.state_spec, records),
                         cls.solved_return, source_dir=run_dir, figures=figures,
                         footer=f"redrawn by `bulbjax report` from {len(records)} records")


def is_offline(run_dir: str) -> bool:
    """Whether `run_dir` is an offline fit's folder (`bulbjax fit`: its config.json has
    `offline`)."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.exists(path):
        return False
    with open(path) as f:
        return "offline" in json.load(f)


OFFLINE_STREAMS = (("rand", "held-out π_rand"),)


def write_offline_reports(out_dir: str, records: Sequence[dict[str, Any]],
                          spec: Sequence[StateEntry], title: str, footer: str = "",
                          figures: bool = True) -> str:
    """An offline fit's `curves.png` (normalised error against updates per group and learner,
    the constant predictor dotted) and `table.md` (the last probe), footer last; returns the
    table."""
    if figures:
        plot(records, spec, os.path.join(out_dir, "curves.png"), title, x_key="update",
             streams=OFFLINE_STREAMS)
    tab = table(records, spec, last=1, x_key="update", streams=OFFLINE_STREAMS)
    with open(os.path.join(out_dir, "table.md"), "w") as f:
        f.write(f"# {title}\n\n{tab}\n" + (f"\n{footer}\n" if footer else ""))
    return tab


def offline_title(source: str, seeds: int, records: Sequence[dict[str, Any]]) -> str:
    return f"{source} offline: {seeds} seeds, {max(r['update'] for r in records)} updates"


def redraw_offline(run_dir: str, raw: dict[str, Any], figures: bool = True) -> str:
    """`bulbjax report FIT_DIR` of an offline fit: `curves.png` and `table.md` from its
    config.json (`offline`, `base`, `source`, `seed`) and `curves.jsonl` (or `.gz`). The
    reconstruction grid needs the learners: `bulbjax fit --resume` draws it."""
    import dataclasses

    from bulbjax.config import config_from_dict
    from bulbjax.offline_config import OfflineConfig
    from bulbjax.data import synthetic
    from bulbjax.envs.registry import env_class

    base = config_from_dict(raw["base"])
    if base.env == synthetic.NAME:
        movers = raw["offline"].get("movers")
        fields = {f.name for f in dataclasses.fields(OfflineConfig)} - {"base", "movers"}
        oc = OfflineConfig(base=base, movers=synthetic.MoversConfig(**movers) if movers else None,
                           **{k: v for k, v in raw["offline"].items() if k in fields})
        state_spec = oc.movers_config().state_spec
    else:
        state_spec = env_class(base.env).state_spec
    path = os.path.join(run_dir, "curves.jsonl")
    path = next((p for p in (path, path + ".gz") if os.path.exists(p)), None)
    if path is None:
        raise ValueError(f"{run_dir}/curves.jsonl (or .gz) does not exist: is {run_dir} the --out "
                         "folder of a `bulbjax fit`?")
    records = read_jsonl(path, tolerate_partial=True)
    if not records:
        raise ValueError(f"{path} has no probe yet: nothing to draw (wait for the first)")
    return write_offline_reports(run_dir, records, report_spec(state_spec, records),
                                 offline_title(raw["source"], base.seeds, records),
                                 footer=f"redrawn by `bulbjax report` from {len(records)} records",
                                 figures=figures)


def rl_compare(run_dirs: Sequence[str], out_dir: str, solved_return: float | None = None) -> str:
    """PPO return curves of several runs in one plot, labelled by what PPO observed
    (`rl_input`: state, pixels, latent:<learner>; with `rl_frames` K > 1, "last K frames"), and
    a table with the final return and, with `solved_return` (default: the env's), the epochs each
    seed needed to reach it (issue 15).
    Writes `rl_compare.png` and `rl_compare.md` into `out_dir`; returns the table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bulbjax.envs.registry import env_class

    if not run_dirs:
        raise ValueError("rl_compare needs at least one run folder")
    os.makedirs(out_dir, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 4))
    rows = ["| run | PPO observes | seeds | epochs | final return (90% CI) | epochs to reach "
            f"{'the solved return' if solved_return is None else solved_return} (per seed) |",
            "|---|---|---|---|---|---|"]
    targets: dict[str, float | None] = {}  # env -> the return counted as solved
    for d in run_dirs:
        cfg, _ = read_run_config(d)
        target = targets.setdefault(cfg.env, solved_return if solved_return is not None
                                    else env_class(cfg.env).solved_return)
        records = read_jsonl(metrics_path(d), tolerate_partial=True)
        if not records:
            raise ValueError(f"{metrics_path(d)} has no epoch yet")
        epochs, r = rl_curve(records)
        ep, mean, half = rl_band(epochs, r)
        observes = cfg.rl_input + (f", last {cfg.rl_frames} frames" if cfg.rl_frames > 1 else "")
        line, = ax.plot(ep, mean, label=observes)
        ax.fill_between(ep, mean - half, mean + half, color=line.get_color(), alpha=0.2)
        reach = epochs_to_reach(r, epochs, target) if target is not None else []
        rows.append(f"| {os.path.basename(os.path.normpath(d))} | {observes} | {r.shape[0]} | "
                    f"{r.shape[1]} | {mean[-1]:.1f} ± {half[-1]:.1f} | "
                    f"{', '.join('never' if x is None else str(x) for x in reach) or 'n/a'} |")
    envs = sorted(targets)
    for target in {t for t in targets.values() if t is not None}:
        ax.axhline(target, color="k", ls="--", lw=0.8, label="solved")
    ax.set_xlabel("epoch")
    ax.set_ylabel("PPO episode return (mean, 90% CI over seeds)")
    ax.set_title(f"{', '.join(envs)}: PPO from state, pixels and latents")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out_dir, "rl_compare.png"), dpi=120)
    plt.close(fig)
    tab = "\n".join(rows)
    with open(os.path.join(out_dir, "rl_compare.md"), "w") as f:
        f.write(f"# PPO return by observation ({', '.join(envs)})\n\n{tab}\n")
    return tab
