"""Why does the stream's PPO forget? Its per-epoch scalars, read back from a run's metrics.

Reads one or more run folders' `metrics.jsonl.gz` (or `metrics.jsonl`; the committed ones under
`docs/results/` keep every epoch's scalars) and prints, per seed: the epoch at which the return
first reached `--threshold` and the share of later epochs at or above it, the policy's log-std
(from the Gaussian entropy, `log_std = entropy/A - 0.5 (1 + log 2 pi)`, or the logged
`log_std_mean` where the run has it), approx KL and clip fraction at a few epochs, and the value
loss just before each drop below the threshold against its median over the run. The numbers of
docs/ppo.md ("Why the solved pendulum forgets") come from these runs' metrics, in git history
since the runs were superseded (`git show 45add11:docs/results/fig2_invpend_h100_1000/seed0/metrics.jsonl.gz > docs/results/fig2_invpend_h100_1000/seed0/metrics.jsonl.gz`,
seed1 the same), and

    python benchmarks/diagnostics/ppo_curves.py docs/results/fig2_invpend_h100_1000/seed0 \
        docs/results/fig2_invpend_h100_1000/seed1 --threshold 950
"""

from __future__ import annotations

import argparse
import gzip
import json
import math
import os
from collections import defaultdict

import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from ppo_stability import carry_forward, stability  # noqa: E402  (benchmarks/ppo_stability.py)

_GAUSS = 0.5 * (1.0 + math.log(2.0 * math.pi))


def read_scalars(run_dir: str) -> dict[int, dict[str, np.ndarray]]:
    """Per seed: epoch-ordered arrays of `rl_return` and each `ppo` scalar of a run folder."""
    path = os.path.join(run_dir, "metrics.jsonl.gz")
    opener = gzip.open if os.path.exists(path) else open
    path = path if os.path.exists(path) else os.path.join(run_dir, "metrics.jsonl")
    rows: dict[int, list[dict]] = defaultdict(list)
    with opener(path, "rt") as f:
        for line in f:
            r = json.loads(line)
            if "seed" in r and "epoch" in r:
                rows[r["seed"]].append(dict(epoch=r["epoch"], rl_return=r.get("rl_return", float("nan")),
                                            **r.get("ppo", {})))
    out = {}
    for seed, rs in rows.items():
        rs.sort(key=lambda r: r["epoch"])
        keys = set().union(*rs)
        out[seed] = {k: np.asarray([r.get(k, np.nan) for r in rs], np.float64) for k in keys}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", help="run folders (each with metrics.jsonl[.gz])")
    p.add_argument("--threshold", type=float, default=950.0)
    p.add_argument("--action-size", type=int, default=1, help="to read log-std from the entropy")
    p.add_argument("--at", default="10,50,100,200,500,999", help="epochs to print the scalars at")
    a = p.parse_args()
    at = [int(x) for x in a.at.split(",")]
    for run in a.runs:
        for seed, m in sorted(read_scalars(run).items()):
            ret = carry_forward(m["rl_return"])
            log_std = m["log_std_mean"] if "log_std_mean" in m else m["entropy"] / a.action_size - _GAUSS
            st = stability(ret, a.threshold)
            first, share = st["first_epoch"], st["share_after"]
            drops = [i for i in range(1, len(ret)) if ret[i] < a.threshold <= ret[i - 1]]
            vl = m["value_loss"]
            med = float(np.nanmedian(vl))
            before = [float(vl[i - 1]) / med for i in drops if i >= 1]
            print(f"{run} seed {seed}: first >= {a.threshold:g} at epoch {first}, "
                  f"share of later epochs >= it {share if share is None else round(share, 3)}, "
                  f"{len(drops)} drops; value loss before a drop / median: "
                  f"median {np.median(before) if before else float('nan'):.1f}, "
                  f"max {max(before) if before else float('nan'):.1f} (median value loss {med:.3g})")
            for e in at:
                if e < len(ret):
                    print(f"    epoch {e:4d}: return {ret[e]:7.1f}  log_std {log_std[e]:+.2f}  "
                          f"kl {m['approx_kl'][e]:.4f}  clip {m['clip_frac'][e]:.3f}  "
                          f"value_loss {vl[e]:.3g}")
            for lo, hi in ((0, 50), (50, 100), (100, 300), (300, 1000)):
                if lo < len(ret):
                    sl = slice(lo, hi)
                    print(f"    epochs {lo}-{hi - 1}: mean kl {np.nanmean(m['approx_kl'][sl]):.4f}  "
                          f"clip {np.nanmean(m['clip_frac'][sl]):.3f}  "
                          f"log_std {np.nanmean(log_std[sl]):+.2f}  "
                          f"share >= threshold {np.mean(ret[sl] >= a.threshold):.2f}")


if __name__ == "__main__":
    main()
