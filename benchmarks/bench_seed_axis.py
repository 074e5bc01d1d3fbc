"""How the seed axis of the learner updates costs on an accelerator (issue 13): `vmap` over seeds
(what `Experiment.learn_phase` does) against `lax.map` over seeds (one seed at a time, each a
plain batch-1,024 update) and one seed alone, for one learner at the paper's sizes.

Why: in the fig2-invpend epoch profile (benchmarks/README.md) a frame VAE's 10 updates for 6
seeds take 0.48 s, 8 ms per seed-update, against 4.1 ms for the same update alone in
`bench_throughput.py`. vmapping an update over per-seed parameters turns every convolution into a
grouped one (feature groups = seeds), which cuDNN may run far slower than S ordinary ones. This
measures that, on random uint8 frames held on the device (the gather from a [S, 5000, 64, 64, 3]
replay buffer included, as in the epoch).

    python benchmarks/bench_seed_axis.py --bf16 --out "$OUT"                    # GPU
    python benchmarks/bench_seed_axis.py --small                                # CPU smoke (~1 min)

Writes <out>/seed_axis_<device>_<stamp>.json and prints a table.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bulbjax.experiment.loop import train_learner  # noqa: E402
from bulbjax.learners import LearnerConfig, make_learner  # noqa: E402
from timing import time_fn as timed  # noqa: E402  (first call, then median/min of repeats)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--learner", default="vae")
    p.add_argument("--seeds", type=int, default=6)
    p.add_argument("--updates", type=int, default=10, help="updates per call (the epoch's learner_batches)")
    p.add_argument("--capacity", type=int, default=5000, help="frames per seed in the sampled buffer")
    p.add_argument("--bf16", action="store_true")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--small", action="store_true", help="CPU smoke sizes")
    p.add_argument("--out", default=os.path.join(HERE, "results"))
    a = p.parse_args(argv)
    res, seeds = 64, a.seeds
    over: dict[str, Any] = {"lr": 1e-4}
    if a.bf16:
        over["compute_dtype"] = "bfloat16"
    if a.small:
        over.update(batch_size=16, conv_features=(8, 8, 16, 16), hidden=32)
        a.capacity, a.updates, a.repeats, seeds = 64, 2, 1, 2
    learner = make_learner(a.learner, 8, LearnerConfig(**over))
    batch = learner.config.batch_size
    k = jax.random.PRNGKey(0)
    frames = jax.random.randint(k, (seeds, a.capacity, res, res, 3), 0, 256, dtype=jnp.int32).astype(jnp.uint8)
    states = jax.vmap(lambda kk: learner.init(kk, (res, res, 3)))(jax.random.split(k, seeds))

    def train_one(state: Any, buf: jax.Array, key: jax.Array) -> Any:
        sample = lambda kk: buf[jax.random.randint(kk, (batch,), 0, buf.shape[0])]  # noqa: E731
        return train_learner(learner, state, sample, key, a.updates)[0]

    keys = jax.random.split(jax.random.fold_in(k, 1), seeds)
    vmapped = jax.jit(jax.vmap(train_one))
    mapped = jax.jit(lambda st, fr, ks: jax.lax.map(lambda x: train_one(*x), (st, fr, ks)))
    single = jax.jit(train_one)
    st0 = jax.tree.map(lambda x: x[0], states)
    out: dict[str, Any] = {"learner": a.learner, "seeds": seeds, "batch": batch, "updates": a.updates,
                           "compute_dtype": learner.config.compute_dtype, "device_kind": jax.devices()[0].device_kind,
                           "jax": jax.__version__, "argv": sys.argv if argv is None else argv}
    out["vmap"] = timed(lambda: vmapped(states, frames, keys), a.repeats)
    out["lax_map"] = timed(lambda: mapped(states, frames, keys), a.repeats)
    out["single_seed"] = timed(lambda: single(st0, frames[0], keys[0]), a.repeats)
    for name in ("vmap", "lax_map", "single_seed"):
        n = seeds if name != "single_seed" else 1
        out[name]["ms_per_seed_update"] = 1e3 * out[name]["median_s"] / (n * a.updates)
    out["vmap_over_lax_map"] = out["vmap"]["median_s"] / out["lax_map"]["median_s"]
    slug = out["device_kind"].lower().replace(" ", "_")
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, f"seed_axis_{slug}_{dt.datetime.now():%Y%m%d_%H%M%S}.json")
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print(f"{a.learner} ({out['compute_dtype']}), {seeds} seeds x {a.updates} updates of {batch} frames "
          f"on {out['device_kind']}:")
    for name in ("vmap", "lax_map", "single_seed"):
        v = out[name]
        print(f"  {name:12} {v['median_s']:.3f} s per call, {v['ms_per_seed_update']:.2f} ms per seed-update "
              f"(first call {v['first_s']:.1f} s)")
    print(f"  vmap / lax.map time: {out['vmap_over_lax_map']:.2f}\nwrote {path}")
    return out


if __name__ == "__main__":
    main()
