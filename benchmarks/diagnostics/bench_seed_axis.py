"""How the seed axis of the learner updates costs on an accelerator (issue 13): `vmap` over seeds
(what `Learning.learn_phase` does with seed loop vmap) against `lax.map` over seeds (one seed at a time, each a
plain batch-1,024 update) and one seed alone, for one learner at the paper's sizes.

Why: in the fig2-invpend epoch profile (benchmarks/README.md) a frame VAE's 10 updates for 6
seeds take 0.48 s, 8 ms per seed-update, against 4.1 ms for the same update alone in
`bench_throughput.py`. vmapping an update over per-seed parameters turns every convolution into a
grouped one (feature groups = seeds), which cuDNN may run far slower than S ordinary ones. This
measures that, on random uint8 frames held on the device (the gather from a [S, 5000, 64, 64, 3]
replay buffer included, as in the epoch). Sequential learners (svae, pred, dsa) train on windows
of random frames (`--capacity` windows of `sequence_length` steps per seed); svae and dsa add the
forms "hybrid_remat" (what `--seed-loop hybrid` of the experiment runs for DSA) and
"hybrid_saved": vmapped over seeds, the frame networks one seed at a time (`per_seed_frames`,
the conv stack's forward recomputed in its backward loop or its activations saved), the LSTMs
batched.

    python benchmarks/diagnostics/bench_seed_axis.py --bf16 --out "$OUT"                    # GPU
    python benchmarks/diagnostics/bench_seed_axis.py --learner dsa --bf16 --rnn-unroll 4 --capacity 200 \
        --trace "$OUT/trace_dsa" --out "$OUT"                                  # + a profiler trace
    python benchmarks/diagnostics/bench_seed_axis.py --small                                # CPU smoke (~1 min)

With `--trace DIR`, the timed calls of each form run inside a host annotation `bj_timed_<form>`;
`trace_summary.py DIR --window bj_timed_<form>` gives each one's device time and busy share. The
trace starts before anything runs on the device: begun after the first computations, it crashed
on the H100 with CUDA_ERROR_LAUNCH_FAILED (2026-11-25, as `profile_epoch.py --trace` did; starting
first is what `--trace-from-start` does there). Not yet run on the GPU since.

Writes <out>/seed_axis_<device>_<stamp>.json and prints a table.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime as dt
import json
import os
import sys
import time
from typing import Any

BENCH = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(BENCH))
sys.path.insert(0, BENCH)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bulbjax.data.sequence import Windows  # noqa: E402
from bulbjax.experiment.learning import train_learner  # noqa: E402
from bulbjax.learners import LearnerConfig, is_sequential, make_learner  # noqa: E402
from timing import time_fn as timed  # noqa: E402  (first call, then median/min of repeats)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--learner", default="vae")
    p.add_argument("--seeds", type=int, default=6)
    p.add_argument("--updates", type=int, default=10, help="updates per call (the epoch's learner_batches)")
    p.add_argument("--capacity", type=int, default=5000,
                   help="frames (windows for a sequential learner) per seed in the sampled buffer")
    p.add_argument("--bf16", action="store_true")
    p.add_argument("--rnn-unroll", type=int, default=0, help="LSTM unroll (default: LearnerConfig's)")
    p.add_argument("--forms", default="", help="comma-separated forms to time (default: all)")
    p.add_argument("--trace", default="", help="JAX profiler trace of the timed calls into this folder")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--small", action="store_true", help="CPU smoke sizes")
    p.add_argument("--out", default=os.path.join(BENCH, "results"))
    a = p.parse_args(argv)
    res, seeds = 64, a.seeds
    over: dict[str, Any] = {"lr": 1e-4}
    if a.bf16:
        over["compute_dtype"] = "bfloat16"
    if a.rnn_unroll:
        over["rnn_unroll"] = a.rnn_unroll
    if a.small:
        over.update(batch_size=16, conv_features=(8, 8, 16, 16), hidden=32, sequence_length=4)
        a.capacity, a.updates, a.repeats, seeds = 16, 2, 1, 2
    learner = make_learner(a.learner, 8, LearnerConfig(**over), action_dim=1)
    seq = is_sequential(learner)
    batch = learner.batch_size
    k = jax.random.PRNGKey(0)
    steps = (learner.window_length,) if seq else ()
    if a.trace:  # before anything runs on the device (see the module docstring)
        jax.profiler.start_trace(a.trace)
    frames = jax.random.randint(k, (seeds, a.capacity) + steps + (res, res, 3), 0, 256,
                                dtype=jnp.int32).astype(jnp.uint8)
    if seq:  # random windows: actions, states and valid as the learner's input checks want them
        shape = (seeds, a.capacity) + steps
        frames = Windows(frames, jnp.ones(shape + (1,), jnp.float32), jnp.zeros(shape + (1,), jnp.float32),
                         jnp.ones(shape, bool))
    states = jax.vmap(lambda kk: learner.init(kk, (res, res, 3)))(jax.random.split(k, seeds))

    def train_one(learner: Any, state: Any, buf: Any, key: jax.Array) -> Any:
        def sample(kk: jax.Array) -> Any:
            idx = jax.random.randint(kk, (batch,), 0, a.capacity)
            return jax.tree.map(lambda x: x[idx], buf)
        return train_learner(learner, state, sample, key, a.updates)[0]

    keys = jax.random.split(jax.random.fold_in(k, 1), seeds)
    forms = {"vmap": jax.jit(jax.vmap(lambda *x: train_one(learner, *x))),
             "lax_map": jax.jit(lambda *x: jax.lax.map(lambda y: train_one(learner, *y), x))}
    if a.learner in ("svae", "dsa"):  # learners with LSTMs
        for how in ("remat", "saved"):  # the conv stack's activations recomputed / saved
            looped = dataclasses.replace(learner, per_seed_frames=how)
            forms[f"hybrid_{how}"] = jax.jit(jax.vmap(lambda *x, looped=looped: train_one(looped, *x)))
    single = jax.jit(lambda *x: train_one(learner, *x))
    st0, fr0 = jax.tree.map(lambda x: x[0], (states, frames))
    out: dict[str, Any] = {"learner": a.learner, "seeds": seeds, "batch": batch, "updates": a.updates,
                           "compute_dtype": learner.config.compute_dtype, "rnn_unroll": learner.config.rnn_unroll,
                           "device_kind": jax.devices()[0].device_kind,
                           "jax": jax.__version__, "argv": sys.argv if argv is None else argv}
    calls = {**{n: (lambda f=f: f(states, frames, keys)) for n, f in forms.items()},
             "single_seed": lambda: single(st0, fr0, keys[0])}
    if a.forms:
        calls = {n: c for n, c in calls.items() if n in a.forms.split(",")}
    for name, call in calls.items():
        t0 = time.perf_counter()
        jax.block_until_ready(call())  # compile and run outside the annotation
        compile_s = time.perf_counter() - t0
        span = jax.profiler.TraceAnnotation(f"bj_timed_{name}") if a.trace else contextlib.nullcontext()
        with span:
            out[name] = timed(call, a.repeats)
        out[name]["compile_and_first_s"] = compile_s
    if a.trace:
        jax.profiler.stop_trace()
    for name in calls:
        n = seeds if name != "single_seed" else 1
        out[name]["ms_per_seed_update"] = 1e3 * out[name]["median_s"] / (n * a.updates)
    if "vmap" in out and "lax_map" in out:
        out["vmap_over_lax_map"] = out["vmap"]["median_s"] / out["lax_map"]["median_s"]
    slug = out["device_kind"].lower().replace(" ", "_")
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, f"seed_axis_{slug}_{dt.datetime.now():%Y%m%d_%H%M%S}.json")
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print(f"{a.learner} ({out['compute_dtype']}), {seeds} seeds x {a.updates} updates of {batch} "
          f"{'windows' if seq else 'frames'} on {out['device_kind']}:")
    for name in calls:
        v = out[name]
        print(f"  {name:12} {v['median_s']:.3f} s per call, {v['ms_per_seed_update']:.2f} ms per seed-update "
              f"(compile + first call {v['compile_and_first_s']:.1f} s)")
    if "vmap_over_lax_map" in out:
        print(f"  vmap / lax.map time: {out['vmap_over_lax_map']:.2f}")
    print(f"wrote {path}")
    return out


if __name__ == "__main__":
    main()
