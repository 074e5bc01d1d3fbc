"""Does the stream's PPO keep what it learned? PPO alone, from the true state, as a preset runs it.

Runs the experiment's own policy phase (`bulbjax.epoch.rollouts.policy.Policy.rl_phase`: the
preset's worlds per seed, PPO updates per epoch and PPO settings, all seeds' worlds stepped at
once) with no representation learners, S seeds for E epochs, in jitted chunks of `--chunk`
epochs (a `lax.scan`; the host syncs only between chunks to print and check `--max-minutes`).
The key chain is the experiment's (init from `PRNGKey(seed)`, epoch keys split from
`PRNGKey(seed + 1)`), so `--variant old --seeds 3 --seed S` follows the PPO stream of a
`bulbjax run --preset P --seeds 3 --seed S` made with the settings before issue 42.

Variants: `old`, the preset's PPO with the stability options off (what the committed runs
used); `new`, the preset's PPO as it is now (`--new KEY=VALUE` changes it, e.g.
`--new target_kl=0.02 --new obs_norm_updates=400`); `both` interleaves their chunks, so a
`--max-minutes` stop leaves both at the same epoch. `--state PATH` keeps the variants' states
and records in PATH after every chunk and continues from it when it exists (same arguments), so
a run longer than one call goes on in the next on the same machine. Writes
`benchmarks/results/ppo_stability_<device>_<date>.json`: per variant the PPO settings, per-seed
per-epoch returns (mean of the episodes finished in the epoch, null where none finished),
episodes, PPO scalars (lr, log-std, KL, clip fraction, value loss, entropy, update share,
normaliser drift), and the stability figures of issue 42: per seed the first epoch at the
threshold (950 InvertedPendulum, 195 CartPole, 2,500 HalfCheetah) and the share of the later
epochs at or above it (an epoch without a finished episode counts with the last epoch's return).

    python benchmarks/ppo_stability.py --preset fig2-invpend --epochs 1000 --variant both --max-minutes 4.5
    python benchmarks/ppo_stability.py --preset fig2-halfcheetah --epochs 200 --variant new
    python benchmarks/ppo_stability.py --preset fig2-cartpole --small --seeds 2 --epochs 4 --chunk 2  # CPU
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pickle
import re
import sys
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
# issue 42's thresholds: the return a solved seed must keep (pendulums) or reach (HalfCheetah)
THRESHOLDS = {"InvertedPendulum": 950.0, "CartPole": 195.0, "HalfCheetah": 2500.0}
# the stability options (issue 42); `old` turns them off
STABILITY_FIELDS = ("anneal_updates", "lr_schedule", "lr_floor", "min_log_std", "target_kl", "obs_norm_updates")
SCALARS = ("lr", "log_std_mean", "approx_kl", "clip_frac", "value_loss", "entropy", "update_frac",
           "obs_mean_shift", "obs_std_shift")


def carry_forward(ret: np.ndarray) -> np.ndarray:
    """Returns with NaN (no episode finished in that epoch: a 1,000-step pendulum episode spans
    several epochs) replaced by the last epoch's; NaN until the first finished episode."""
    out = np.array(ret, np.float64)
    for i in range(1, len(out)):
        if np.isnan(out[i]):
            out[i] = out[i - 1]
    return out


def stability(ret: np.ndarray, threshold: float) -> dict[str, Any]:
    """Issue 42's figures of one seed's per-epoch returns: the first epoch at >= threshold and
    the share of the epochs after it at >= threshold (returns carried forward)."""
    r = carry_forward(ret)
    hit = np.nonzero(r >= threshold)[0]
    if not len(hit):
        return dict(first_epoch=None, share_after=None, epochs_after=0)
    rest = r[hit[0] + 1:]
    return dict(first_epoch=int(hit[0]), share_after=float((rest >= threshold).mean()) if len(rest) else None,
                epochs_after=int(len(rest)))


def old_ppo(ppo: Any) -> Any:
    """`ppo` with the stability options off (PPOConfig's defaults for them)."""
    from bulbjax.rl.ppo import PPOConfig

    base = PPOConfig()
    return dataclasses.replace(ppo, **{f: getattr(base, f) for f in STABILITY_FIELDS})


def parse_sets(items: list[str]) -> dict[str, Any]:
    """`["target_kl=0.02", "min_log_std=none"]` -> PPOConfig field values (`--new`)."""
    from bulbjax.rl.ppo_config import parse_ppo_options

    return parse_ppo_options(items)


class Variant:
    """One PPO setting's run: the experiment's `Policy` over `dev`'s worlds, its state, a
    compiled chunk of `chunk` epochs, and the per-epoch records so far."""

    def __init__(self, name: str, cfg: Any, dev: Any, seed: int, chunk: int):
        from bulbjax.epoch.rollouts.policy import Policy
        from bulbjax.epoch.seeds import Team

        self.name, self.cfg, self.chunk = name, cfg, chunk
        team = Team(learners={}, seed_loop="vmap", group=dev.group)
        self.policy = policy = Policy(cfg, dev, team)
        k_ppo, _, k_env, _, _ = jax.random.split(jax.random.PRNGKey(seed), 5)  # as Experiment.init_env
        self.state = (jax.vmap(policy.ppo.init)(team.seed_keys(k_ppo)),
                      dev.env_reset(jax.random.split(k_env, 4)[0]),
                      jax.random.PRNGKey(seed + 1))  # as run.py's epoch key chain

        def epoch(carry, _):
            ps, es, key = carry
            key, k = jax.random.split(key)
            k_rl = jax.random.split(k, 5)[0]  # as Experiment.env_stage
            ps, es, m, ret_sum, count, _, _ = policy.rl_phase(ps, es, k_rl)
            ret = jnp.where(count > 0, ret_sum / jnp.maximum(count, 1), jnp.nan)
            return (ps, es, key), dict(ret=ret, episodes=count, **{k: m[k] for k in SCALARS if k in m})

        def run_chunk(state):
            return jax.lax.scan(epoch, state, None, length=chunk)

        t0 = time.time()
        self.compiled = jax.jit(run_chunk).lower(self.state).compile()
        self.compile_s = time.time() - t0
        self.records: list[dict[str, np.ndarray]] = []
        self.chunk_s: list[float] = []

    @property
    def epochs(self) -> int:
        return self.chunk * len(self.records)

    def step(self) -> float:
        """Run one chunk; its wall time."""
        t0 = time.time()
        self.state, out = self.compiled(self.state)
        self.records.append(jax.device_get(out))
        self.chunk_s.append(time.time() - t0)
        return self.chunk_s[-1]

    def result(self, epochs: int, threshold: float) -> dict[str, Any]:
        cat = {k: np.concatenate([r[k] for r in self.records])[:epochs].T for k in self.records[0]}  # [S, E]
        nan_to_none = lambda a: [[None if not np.isfinite(x) else float(f"{float(x):.6g}") for x in row] for row in a]  # noqa: E731
        stab = [stability(row, threshold) for row in cat["ret"]]
        shares = [s["share_after"] for s in stab if s["share_after"] is not None]
        steady = self.chunk_s[1:] or self.chunk_s
        return dict(
            ppo=dataclasses.asdict(self.cfg.ppo), epochs=int(cat["ret"].shape[1]), compile_s=self.compile_s,
            epoch_s=float(np.median(steady)) / self.chunk, wall_s=float(sum(self.chunk_s)),
            returns=nan_to_none(cat["ret"]), episodes=cat["episodes"].astype(int).tolist(),
            ppo_metrics={k: nan_to_none(cat[k]) for k in SCALARS if k in cat},
            stability=dict(threshold=threshold, per_seed=stab,
                           min_share_after=min(shares) if shares else None,
                           seeds_reaching=sum(s["first_epoch"] is not None for s in stab),
                           seeds_share_ge_95=sum(s is not None and s >= 0.95 for s in shares)),
        )


def save_state(path: str, ident: dict, variants: list[Variant]) -> None:
    """The variants' states, records and chunk times in `path` (written whole, then renamed)."""
    data = dict(ident=ident, variants={v.name: dict(state=jax.device_get(v.state), records=v.records,
                                                    chunk_s=v.chunk_s) for v in variants})
    with open(path + ".tmp", "wb") as f:
        pickle.dump(data, f)
    os.replace(path + ".tmp", path)


def load_state(path: str, ident: dict) -> dict:
    """`save_state`'s file; made with other arguments than `ident` it is an error."""
    with open(path, "rb") as f:
        data = pickle.load(f)
    if data["ident"] != ident:
        raise SystemExit(f"{path} was made with other arguments: {data['ident']}")
    return data


def continue_from(data: dict, variants: list[Variant]) -> None:
    """Put `load_state`'s states, records and chunk times into `variants`."""
    for v in variants:
        d = data["variants"][v.name]
        v.state = jax.tree.map(jnp.asarray, d["state"])
        v.records, v.chunk_s = d["records"], d["chunk_s"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="fig2-invpend")
    p.add_argument("--seeds", type=int, default=None, help="default: the preset's")
    p.add_argument("--epochs", type=int, default=None, help="default: the preset's")
    p.add_argument("--ppo-updates", type=int, default=None, help="PPO updates per epoch (default: the preset's)")
    p.add_argument("--seed", type=int, default=0, help="the run's base seed (as bulbjax run --seed)")
    p.add_argument("--variant", choices=("old", "new", "both"), default="both")
    p.add_argument("--new", action="append", default=[], metavar="KEY=VALUE",
                   help="PPOConfig field for the new variant (repeatable), e.g. target_kl=0.02")
    p.add_argument("--chunk", type=int, default=50, help="epochs per jitted call")
    p.add_argument("--max-minutes", type=float, default=0.0, help="stop after this wall time (0: none)")
    p.add_argument("--threshold", type=float, default=None, help="default: 950 / 195 / 2,500 by domain")
    p.add_argument("--small", action="store_true", help="CPU sizes (the preset's --small)")
    p.add_argument("--out", default=RESULTS, help="folder of the JSON")
    p.add_argument("--state", default=None, help="keep / continue from the run's state in this file")
    a = p.parse_args(argv)
    t_start = time.time()
    from bulbjax import compile_cache

    compile_cache.enable()  # a later call of the same settings loads the chunk programs
    from bulbjax.epoch.devices import Devices
    from bulbjax.run.settings import resolve

    given = dict(seeds=a.seeds, epochs=a.epochs, ppo_updates_per_epoch=a.ppo_updates)
    overrides = {k: v for k, v in given.items() if v is not None}
    base = resolve(a.preset, overrides=overrides, small=a.small)
    threshold = a.threshold if a.threshold is not None else next(
        (v for k, v in THRESHOLDS.items() if base.env.startswith(k)), math.nan)
    new_ppo = dataclasses.replace(base.ppo, **parse_sets(a.new))
    configs = {"old": base.replace(ppo=old_ppo(base.ppo)), "new": base.replace(ppo=new_ppo)}
    names = ["old", "new"] if a.variant == "both" else [a.variant]
    chunk = max(1, min(a.chunk, base.epochs))
    n_chunks = math.ceil(base.epochs / chunk)
    device = jax.devices()[0].device_kind
    print(f"{a.preset}: {base.env}, {base.seeds} seeds x {base.num_envs} worlds, {base.ppo_updates_per_epoch} "
          f"PPO updates of {base.ppo.num_steps} steps per epoch, {base.epochs} epochs in chunks of {chunk}, "
          f"threshold {threshold:g}, on {device}", flush=True)
    ident = dict(preset=a.preset, seeds=base.seeds, seed=a.seed, chunk=chunk, small=a.small,
                 ppo={n: dataclasses.asdict(configs[n].ppo) for n in names},
                 ppo_updates_per_epoch=base.ppo_updates_per_epoch)
    saved = load_state(a.state, ident) if a.state and os.path.exists(a.state) else None
    dev = Devices(base)
    variants = []
    for name in names:
        v = Variant(name, configs[name], dev, a.seed, chunk)
        diff = {f: getattr(v.cfg.ppo, f) for f in STABILITY_FIELDS}
        print(f"  {name}: compiled in {v.compile_s:.1f} s; {diff}", flush=True)
        variants.append(v)
    if saved is not None:
        continue_from(saved, variants)
        print(f"  continuing from {a.state} at epoch {variants[0].epochs}", flush=True)
    stopped = "done"
    for c in range(variants[0].epochs // chunk, n_chunks):
        if a.max_minutes and time.time() - t_start > 60 * a.max_minutes:
            stopped = "max-minutes"
            break
        for v in variants:
            wall = v.step()
            last = np.concatenate([x["ret"] for x in v.records])[-1]
            ls = v.records[-1].get("log_std_mean")
            print(f"  {v.name} epochs {v.epochs - chunk}-{v.epochs - 1}: {wall:.1f} s ({wall / chunk * 1e3:.0f} ms "
                  f"per epoch); last epoch's return per seed {np.round(last, 0).tolist()}; "
                  f"lr {float(v.records[-1]['lr'][-1].mean()):.2e}"
                  + (f", log-std {float(ls[-1].mean()):+.2f}" if ls is not None else "")
                  + f", kl {float(v.records[-1]['approx_kl'][-1].mean()):.4f}", flush=True)
        if a.state:
            save_state(a.state, ident, variants)
    epochs = min(min(v.epochs for v in variants), base.epochs)
    res = dict(preset=a.preset, env=base.env, device=device, seeds=base.seeds, seed=a.seed, small=a.small,
               epochs_asked=base.epochs, stopped=stopped, wall_s=time.time() - t_start,
               num_envs=base.num_envs, ppo_updates_per_epoch=base.ppo_updates_per_epoch,
               variants={v.name: v.result(epochs, threshold) for v in variants})
    for name, r in res["variants"].items():
        s = r["stability"]
        print(f"{name}: {r['epochs']} epochs, {r['epoch_s'] * 1e3:.0f} ms per epoch; seeds reaching {threshold:g}: "
              f"{s['seeds_reaching']}/{base.seeds} (first epochs {[x['first_epoch'] for x in s['per_seed']]}); "
              f"share of later epochs >= it per seed "
              f"{[None if x['share_after'] is None else round(x['share_after'], 3) for x in s['per_seed']]}; "
              f">= 95%: {s['seeds_share_ge_95']} seeds", flush=True)
    os.makedirs(a.out, exist_ok=True)
    slug = re.sub(r"[^a-z0-9]+", "_", device.lower()).strip("_") or "unknown"
    path = os.path.join(a.out, f"ppo_stability_{slug}_{time.strftime('%Y%m%d_%H%M%S')}.json")
    with open(path, "w") as f:
        json.dump(res, f)
    print(f"wrote {path} ({stopped})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
