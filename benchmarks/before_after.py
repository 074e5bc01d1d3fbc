"""Same seeds, same curves? One short run of the code before issue 13's speed changes against the
code after them (issue 13: "no result changes meaning").

`run` builds one config (a preset with its domain's PPO settings, `--small`, `--seeds`,
`--epochs`, the decoder form `--deconv-impl`) and runs it with base seed 0, importing bulbjax
from `--code` (a source tree, e.g. a `git worktree` of an older commit), so both versions run
exactly the same settings. `compare` reads two such runs and writes, per learner and stream, the
normalised error of each version over the last `--last` probed epochs (mean and 90% band over
seeds) and the paired per-seed difference after - before with its 90% band, plus a plot of both
versions' curves: `before_after.md`, `before_after.png`, `before_after.json`.

    git worktree add /tmp/before 90433af     # before: the LSTMs as flax nn.RNN cells
    python benchmarks/before_after.py run --code /tmp/before --deconv-impl transpose --out runs/ba_before
    python benchmarks/before_after.py run --code . --out runs/ba_after            # subpixel, hoisted LSTMs
    python benchmarks/before_after.py compare runs/ba_before runs/ba_after --out docs/results/before_after
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def cmd_run(a: argparse.Namespace) -> None:
    sys.path.insert(0, os.path.abspath(a.code))  # this tree's bulbjax, not the installed one
    import dataclasses

    import bulbjax
    from bulbjax.config import RunOptions, preset, small_config
    from bulbjax.envs import registry
    from bulbjax.run import run

    print(f"bulbjax from {os.path.dirname(bulbjax.__file__)}")
    cfg = preset(a.preset)
    cfg = cfg.replace(ppo=registry.ppo_config_for(cfg.env, cfg.ppo))
    cfg = small_config(cfg).replace(seeds=a.seeds, epochs=a.epochs)
    cfg = cfg.replace(learner=dataclasses.replace(cfg.learner, deconv_impl=a.deconv_impl))
    if a.learner_option:  # LearnerConfig fields, e.g. channel_pad=8 (a tree that has them)
        from bulbjax.learners import parse_learner_options

        cfg = cfg.replace(learner=dataclasses.replace(cfg.learner, **parse_learner_options(a.learner_option)))
    run(cfg, RunOptions(seed=0), a.out, argv=sys.argv, progress=False)


def _errors(run_dir: str, last: int) -> tuple[dict[str, np.ndarray], list[int], list[str], Any]:
    """Per (learner, stream): `[seeds]` overall normalised error over the last `last` probed
    epochs; the epochs; the learners; all records."""
    sys.path.insert(0, ROOT)
    from bulbjax.report import records

    recs = records.read_jsonl(records.metrics_path(run_dir))
    epochs = sorted({r["epoch"] for r in records.probed(recs)})[-last:]
    learners = list(records.probed(recs)[0]["probes"])
    out = {(n, s): records.per_seed_error(recs, n, s, None, epochs) for n in learners for s, _ in records.STREAMS}
    return out, epochs, learners, recs


def cmd_compare(a: argparse.Namespace) -> None:
    sys.path.insert(0, ROOT)
    from bulbjax.report import records

    before, ep_b, learners, rec_b = _errors(a.before, a.last)
    after, ep_a, _, rec_a = _errors(a.after, a.last)
    if ep_a != ep_b:
        raise SystemExit(f"the runs' last probed epochs differ ({ep_b} vs {ep_a}): same config needed")
    os.makedirs(a.out, exist_ok=True)
    rows, lines = [], ["| learner | stream | before | after | after - before (paired) | within noise |",
                       "|---|---|---|---|---|---|"]
    for (n, s), b in before.items():
        x = after[(n, s)]
        mb, hb = records.ci90(b)
        ma, ha = records.ci90(x)
        md, hd = records.ci90(x - b)
        same = bool(abs(md) <= hd)
        rows.append({"learner": n, "stream": s, "before": [float(mb), float(hb)], "after": [float(ma), float(ha)],
                     "diff": [float(md), float(hd)], "within_noise": same,
                     "before_seeds": b.tolist(), "after_seeds": x.tolist()})
        lines.append(f"| {n} | {dict(records.STREAMS)[s]} | {mb:.3f} ± {hb:.3f} | {ma:.3f} ± {ha:.3f} | "
                     f"{md:+.3f} ± {hd:.3f} | {'yes' if same else 'no'} |")
    n_seeds = len(next(iter(before.values())))
    key = lambda r: (r["epoch"], r["seed"])  # noqa: E731
    ret_b = np.array([r["rl_return"] for r in sorted(rec_b, key=key)], float)
    ret_a = np.array([r["rl_return"] for r in sorted(rec_a, key=key)], float)
    same_rl = ret_b.shape == ret_a.shape and bool(np.array_equal(ret_b, ret_a, equal_nan=True))
    head = (f"Overall normalised error, epochs {', '.join(map(str, ep_b))}; mean ± 90% CI over {n_seeds} "
            f"seeds; the difference is paired by seed (same base seed in both runs). Within noise: "
            f"the 90% band of the difference contains 0. PPO's returns (on the true state, so the frame "
            f"stream the learners see): {'identical in every epoch and seed' if same_rl else 'NOT identical'} "
            f"in the two runs.")
    with open(os.path.join(a.out, "before_after.md"), "w") as f:
        f.write(f"# Before / after: {a.before} -> {a.after}\n\n{head}\n\n" + "\n".join(lines) + "\n")
    with open(os.path.join(a.out, "before_after.json"), "w") as f:
        json.dump({"before": a.before, "after": a.after, "epochs": ep_b, "ppo_returns_identical": same_rl,
                   "rows": rows}, f, indent=1)

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(records.STREAMS), len(learners), figsize=(2.6 * len(learners), 5),
                             squeeze=False, sharey=True)
    for j, n in enumerate(learners):
        for i, (s, label) in enumerate(records.STREAMS):
            ax = axes[i][j]
            for recs, version, c in ((rec_b, "before", "tab:gray"), (rec_a, "after", "tab:blue")):
                ep, v = records.curves(recs, n, s, None)
                m, h = records.ci90(v)
                ax.plot(ep, m, color=c, label=version)
                ax.fill_between(ep, m - h, m + h, color=c, alpha=0.2)
            ax.set_title(f"{n} {label}", fontsize=8)
            if j == 0:
                ax.set_ylabel("norm. error")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(a.out, "before_after.png"), dpi=110)
    print("\n".join(lines))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--code", default=ROOT, help="source tree whose bulbjax runs")
    r.add_argument("--preset", default="fig2-invpend")
    r.add_argument("--seeds", type=int, default=3)
    r.add_argument("--epochs", type=int, default=8)
    r.add_argument("--deconv-impl", default="subpixel")
    r.add_argument("--learner-option", action="append", default=[], metavar="KEY=VALUE",
                   help="a LearnerConfig field (repeatable), e.g. channel_pad=8")
    r.add_argument("--out", required=True)
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    c.add_argument("--last", type=int, default=3, help="probed epochs averaged at the end")
    c.add_argument("--out", required=True)
    a = p.parse_args(argv)
    (cmd_run if a.cmd == "run" else cmd_compare)(a)


if __name__ == "__main__":
    main()
