"""Are the verdicts the latent's or the probe's? The Fig. 2 claims of several runs under every
probe-protocol variant side by side (issue 59): one table per domain, one row per claim, one
column per variant (present probe, common probe set, whole window, raw MAE; runs made with
`--probe-variants`, `ExperimentConfig.probe_variants`) and a column "fp32 run" for a second run
of the domain whose learners computed in fp32 (its present probe), each cell the verdict with
the paired difference that decides it (`findings.variant_cell`).

`probe_protocol_table(runs, fp32, out_dir)` writes `out_dir/table.md`, e.g.
`docs/results/probe_protocol/table.md` from the CartPole and InvertedPendulum runs.
"""

from __future__ import annotations

import os
from typing import Sequence

from bulbjax.config import read_run_config
from bulbjax.report import findings
from bulbjax.report.merge import run_records
from bulbjax.report.records import probed
from bulbjax.report.report import report_spec


def _load(run_dir: str) -> tuple[object, list[dict], tuple]:
    """A run folder's config, its records of complete epochs (every seed written) and its spec (a
    merged folder without its metrics: its runs pooled again, `merge.run_records`)."""
    from bulbjax.envs.registry import env_class

    cfg, _ = read_run_config(run_dir)
    recs = run_records(run_dir)
    seeds = {r["seed"] for r in recs}
    count: dict[int, int] = {}
    for r in recs:
        count[r["epoch"]] = count.get(r["epoch"], 0) + 1
    recs = [r for r in recs if count[r["epoch"]] == len(seeds)]
    if not probed(recs):
        raise ValueError(f"{run_dir} has no probed epoch: nothing to check")
    return cfg, recs, report_spec(env_class(cfg.env).state_spec, recs)


def _dtype(cfg: object) -> str:
    return getattr(getattr(cfg, "learner", None), "compute_dtype", "?")


def domain_table(run_dir: str, fp32_dir: str | None = None, last: int = 3) -> str:
    """One run's section: its claims under each variant its records carry, and the fp32 run's
    present-probe verdicts (`fp32_dir`, same domain) as a last column."""
    cfg, recs, spec = _load(run_dir)
    seeds = len({r["seed"] for r in recs})
    sets, epochs = findings.variant_checks(recs, spec, cfg.env, last=last)
    note = f"run `{run_dir}` ({_dtype(cfg)} learners, {seeds} seeds)"
    if fp32_dir is not None:
        cfg32, recs32, spec32 = _load(fp32_dir)
        if cfg32.env != cfg.env:
            raise ValueError(f"the fp32 run {fp32_dir} is of {cfg32.env}, the run {run_dir} of "
                             f"{cfg.env}: give each domain's fp32 run beside its own")
        sets["fp32"], epochs32 = findings.check(recs32, spec32, cfg32.env, last=last)
        seeds32 = len({r["seed"] for r in recs32})
        note += (f"; fp32 run `{fp32_dir}` ({_dtype(cfg32)} learners, {seeds32} seeds, "
                 f"epochs {', '.join(map(str, epochs32))})")
    else:
        note += "; no fp32 run of this domain given (--fp32): no fp32 column"
    if len(sets) == 1:
        note += "; the run carries no probe variant (made without --probe-variants)"
    return f"## {cfg.env}\n\n{note}.\n\n" + findings.variants_markdown(sets, epochs, seeds)


def probe_protocol_table(runs: Sequence[str], fp32: Sequence[str] = (), out_dir: str | None = None,
                         last: int = 3) -> str:
    """The claims of `runs` (one run folder per domain, made with `--probe-variants`) under each
    variant, each domain's fp32 run (among `fp32`, matched by its env) as the last column;
    written to `out_dir/table.md` when given. Returns the markdown."""
    envs = {read_run_config(d)[0].env: d for d in fp32}
    if len(envs) != len(fp32):
        raise ValueError("give at most one fp32 run per domain")
    sections = []
    for run_dir in runs:
        env = read_run_config(run_dir)[0].env
        sections.append(domain_table(run_dir, envs.pop(env, None), last))
    if envs:
        raise ValueError(f"fp32 runs of {', '.join(envs)} have no run of their domain among the "
                         "runs given")
    text = ("# Probe protocol: the Fig. 2 claims under each variant of the probe\n\n"
            "Is a verdict the latent's or the probe's? Each claim checked with the present probe "
            "and with each variant computed in the same run (docs/probes.md, \"Variants of the "
            "protocol\")" + (", and with the present probe of a second run whose learners "
                               "computed in fp32" if fp32 else "") + ".\n\n" + "\n\n".join(sections) + "\n")
    if out_dir is not None:
        os.makedirs(out_dir, exist_ok=True)
        with open(os.path.join(out_dir, "table.md"), "w") as f:
            f.write(text)
    return text
