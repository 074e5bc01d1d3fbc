"""Each learner's update against the card's limits (issue 55): the FLOPs it computes, the bytes
it moves, its measured time, and from them the share of the card's bf16 peak and of its memory
bandwidth it reaches.

- FLOPs: XLA's cost analysis of the update as traced (before optimisation): the multiply-adds
  of its convolutions and matmuls and its elementwise work, counted from the program itself.
- Bytes: XLA's cost analysis of the compiled update (after fusion): what its kernels read and
  write, as XLA models them.
- Time: the median of `--steps` back-to-back jitted updates (donated state) after warm-up, and,
  with `--kernels`, the GPU's busy time per update from a profiler trace (launch gaps excluded).

A learner whose time is far above both limits' times (FLOPs / peak, bytes / bandwidth) is bound
by neither: by its kernels' efficiency on small shapes, or by launches. Writes
`<out-dir>/roofline_<device>_<stamp>.json` and prints a markdown table (docs/performance.md).

GPU: python benchmarks/learner_roofline.py --kernels
(XLA:GPU's cost analysis counts no FLOPs: take them from the lowered program on the CPU with
`--flops-only`, then `--merge ROOFLINE_JSON --flops-json FLOPS_JSON`.)
CPU smoke run: python benchmarks/learner_roofline.py --learners vae,pred --batch 16 --steps 2 --small
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import statistics
import sys
import time
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

import jax  # noqa: E402
import numpy as np  # noqa: E402

from bulbjax.learners import LearnerConfig, make_learner  # noqa: E402

# dense bf16 tensor-core peak (TFLOP/s) and memory bandwidth (TB/s) from the vendors' datasheets
PEAKS: dict[str, tuple[float, float]] = {
    "NVIDIA H100 80GB HBM3": (989.4, 3.35),
    "NVIDIA H200": (989.4, 4.8),
}
# which update each row times: vae_rpl and beta_vae run vae's update program (`VAE.update_key`)
ROWS = ("vae", "svae", "pred", "dsa", "spair", "stdim", "curl")


def cost(compiled_or_lowered: Any) -> dict[str, float]:
    c = compiled_or_lowered.cost_analysis()
    c = c[0] if isinstance(c, (list, tuple)) else c
    return {k: float(v) for k, v in (c or {}).items() if k in ("flops", "bytes accessed", "transcendentals")}


def measure(name: str, a: argparse.Namespace) -> dict[str, Any]:
    from bench_throughput import BenchSettings, kernel_breakdown, learner_batch

    small = dict(conv_features=(16, 32, 32, 64), hidden=128) if a.small else {}
    cfg = LearnerConfig(batch_size=a.batch, compute_dtype=a.dtype, sequence_length=a.sequence_length,
                        rnn_unroll=a.rnn_unroll, **small)
    learner = make_learner(name, latent_dim=a.latent_dim, config=cfg, action_dim=1)
    s = BenchSettings(vae_batch=a.batch, resolution=a.resolution, latent_dim=a.latent_dim, seed=0)
    shape = (a.resolution, a.resolution, 3)
    state = jax.jit(learner.init, static_argnums=1)(jax.random.PRNGKey(0), shape)
    batch = learner_batch(learner, name, s, np.random.default_rng(0))
    keys = list(jax.random.split(jax.random.PRNGKey(1), a.warmup + a.steps + 8))
    update = jax.jit(learner.update, donate_argnums=0)
    lowered = update.lower(state, batch, keys[0])
    t0 = time.perf_counter()
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0
    flops = cost(lowered).get("flops", float("nan"))  # XLA:GPU's analysis may have none: --flops-json
    moved = cost(compiled).get("bytes accessed", float("nan"))
    for k in keys[: a.warmup]:
        state, _ = compiled(state, batch, k)
    jax.block_until_ready(state)
    times = []
    for k in keys[a.warmup: a.warmup + a.steps]:
        t0 = time.perf_counter()
        state, m = compiled(state, batch, k)
        jax.block_until_ready(m)
        times.append(time.perf_counter() - t0)
    # back to back (no sync between): the rate a training loop sees
    t0 = time.perf_counter()
    for k in keys[a.warmup: a.warmup + a.steps]:
        state, m = compiled(state, batch, k)
    jax.block_until_ready((state, m))
    stream_s = (time.perf_counter() - t0) / a.steps
    row: dict[str, Any] = {
        "learner": name, "batch": learner.batch_size,
        "frames_per_update": learner.batch_size * getattr(learner, "window_length", 1),
        "dtype": a.dtype, "flops": flops, "bytes": moved, "compile_s": compile_s,
        "ms_per_update": 1e3 * stream_s, "ms_per_update_synced": 1e3 * statistics.median(times)}
    if a.kernels:
        k = kernel_breakdown(compiled, state, batch, keys[-6:], 10)
        dev = next((v for v in k.values() if isinstance(v, dict) and "busy_ms_per_update" in v), None)
        if dev:
            row["busy_ms_per_update"] = dev["busy_ms_per_update"]
            row["launches_per_update"] = dev["launches_per_update"]
            row["top_kernels"] = dev["top"][:5]
    return row


def lowered_flops(name: str, a: argparse.Namespace) -> float:
    """FLOPs of one update from its lowered (unoptimised) program: shapes only, no compile."""
    from bench_throughput import BenchSettings, learner_batch

    cfg = LearnerConfig(batch_size=a.batch, compute_dtype=a.dtype, sequence_length=a.sequence_length,
                        rnn_unroll=a.rnn_unroll)
    learner = make_learner(name, latent_dim=a.latent_dim, config=cfg, action_dim=1)
    s = BenchSettings(vae_batch=a.batch, resolution=a.resolution, latent_dim=a.latent_dim, seed=0)
    state = jax.eval_shape(lambda k: learner.init(k, (a.resolution, a.resolution, 3)), jax.random.PRNGKey(0))
    batch = learner_batch(learner, name, s, np.random.default_rng(0))
    return cost(jax.jit(learner.update).lower(state, batch, jax.random.PRNGKey(1)))["flops"]


def flops_only(a: argparse.Namespace) -> dict[str, Any]:
    out = {n: lowered_flops(n, a) for n in [x.strip() for x in a.learners.split(",") if x.strip()]}
    os.makedirs(a.out_dir, exist_ok=True)
    path = os.path.join(a.out_dir, f"flops_{dt.datetime.now().strftime('%Y%m%d_%H%M%S')}.json")
    with open(path, "w") as f:
        json.dump({"settings": vars(a), "flops": out}, f, indent=1)
    print(json.dumps(out, indent=1))
    return out


def merge(a: argparse.Namespace) -> dict[str, Any]:
    """An earlier run's rows with FLOPs from `--flops-json`, limits and table recomputed."""
    with open(a.merge) as f:
        run = json.load(f)
    with open(a.flops_json) as f:
        flops = json.load(f)["flops"]
    for r in run["rows"]:
        if "error" not in r and not r["flops"] == r["flops"]:  # NaN: the device's analysis had none
            r["flops"], r["flops_from"] = flops[r["learner"]], os.path.basename(a.flops_json)
        if "error" not in r:
            r["limits"] = limits(r, run["device_kind"])
    run["table"] = table(run["rows"], run["device_kind"])
    run["merged_with"] = os.path.basename(a.flops_json)
    print(run["table"])
    out = a.merge.replace(".json", "_flops.json")
    with open(out, "w") as f:
        json.dump(run, f, indent=1, default=str)
    print(f"wrote {out}", file=sys.stderr)
    return run


def limits(row: dict[str, Any], kind: str) -> dict[str, Any]:
    """The row's achieved rates and shares of the card's limits, and what bounds it."""
    t = 1e-3 * row.get("busy_ms_per_update", row["ms_per_update"])
    out = {"tflops": row["flops"] / t / 1e12, "tb_per_s": row["bytes"] / t / 1e12,
           "intensity_flop_per_byte": row["flops"] / row["bytes"] if row["bytes"] else float("nan")}
    if kind in PEAKS:
        peak, bw = PEAKS[kind]
        out["peak_share"], out["bandwidth_share"] = out["tflops"] / peak, out["tb_per_s"] / bw
        floor_ms = 1e3 * max(row["flops"] / (peak * 1e12), row["bytes"] / (bw * 1e12))
        out["floor_ms"] = floor_ms  # the roofline's time: the slower of the two limits
        out["bound"] = ("compute" if row["flops"] / peak > row["bytes"] / bw else "memory") + \
            (" (near the roof)" if floor_ms / (1e3 * t) > 0.5 else
             " by the roof, but at under half of it: kernel efficiency or launches")
    return out


def table(rows: list[dict[str, Any]], kind: str) -> str:
    lines = ["| learner | frames / update | GFLOP / update | GB moved / update | ms / update (busy) | "
             "TFLOP/s (share of peak) | TB/s (share of bandwidth) | roofline floor (ms) | bound |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['learner']} | error: {r['error'][:80]} |||||||| ")
            continue
        x = r["limits"]
        share = lambda key: f" ({x[key]:.0%})" if key in x else ""  # noqa: E731
        busy = r.get("busy_ms_per_update", r["ms_per_update"])
        lines.append(f"| {r['learner']} | {r['frames_per_update']} | {r['flops'] / 1e9:.0f} | {r['bytes'] / 1e9:.2f} | "
                     f"{r['ms_per_update']:.2f} ({busy:.2f}) | {x['tflops']:.0f}{share('peak_share')} | "
                     f"{x['tb_per_s']:.2f}{share('bandwidth_share')} | {x.get('floor_ms', float('nan')):.2f} | "
                     f"{x.get('bound', '-')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--learners", default=",".join(ROWS))
    p.add_argument("--dtype", default="bfloat16")
    p.add_argument("--batch", type=int, default=1024, help="frames per batch (sequential: // L windows)")
    p.add_argument("--sequence-length", type=int, default=24)
    p.add_argument("--rnn-unroll", type=int, default=4)
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--latent-dim", type=int, default=32)
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--kernels", action="store_true", help="GPU busy time and top kernels from a profiler trace")
    p.add_argument("--small", action="store_true", help="CPU-sized networks (a smoke run)")
    p.add_argument("--flops-only", action="store_true",
                   help="only each update's FLOPs from its lowered program (lowering, no compile: runs on the CPU); "
                        "writes flops_<stamp>.json for --flops-json")
    p.add_argument("--flops-json", default=None,
                   help="FLOPs per learner (a --flops-only file) where the device's cost analysis has none")
    p.add_argument("--merge", default=None, metavar="ROOFLINE_JSON",
                   help="recompute an earlier run's table with --flops-json (no measuring)")
    p.add_argument("--out-dir", default=os.path.join(HERE, "results"))
    a = p.parse_args(argv)
    if a.flops_only:
        return flops_only(a)
    if a.merge:
        return merge(a)
    dev = jax.devices()[0]
    kind = dev.device_kind
    rows = []
    for name in [n.strip() for n in a.learners.split(",") if n.strip()]:
        print(f"[roofline] {name} ...", file=sys.stderr, flush=True)
        try:
            r = measure(name, a)
            r["limits"] = limits(r, kind)
            print(f"[roofline] {name}: {r['ms_per_update']:.2f} ms/update, {r['limits']['tflops']:.1f} TFLOP/s",
                  file=sys.stderr, flush=True)
        except Exception as e:  # noqa: BLE001 - one learner's failure must not lose the others
            r = {"learner": name, "error": f"{type(e).__name__}: {e}"[:1000]}
        rows.append(r)
    md = table(rows, kind)
    print(md)
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    slug = "".join(c if c.isalnum() else "_" for c in kind.lower()).strip("_")
    out = {"command": " ".join(sys.argv), "device_kind": kind, "platform": dev.platform,
           "peaks": PEAKS.get(kind), "settings": vars(a), "rows": rows, "table": md,
           "versions": {"jax": jax.__version__}}
    os.makedirs(a.out_dir, exist_ok=True)
    path = os.path.join(a.out_dir, f"roofline_{slug}_{stamp}.json")
    with open(path, "w") as f:
        json.dump(out, f, indent=1, default=str)
    print(f"wrote {path}", file=sys.stderr)
    return out


if __name__ == "__main__":
    main()
