"""Epoch throughput of one run on all local devices against one device.

For each seed count of `--seeds` (default 6 and 12) and each device count of `--devices`
(default 1 and all), builds the run's `SeedGroups(preset, devices=first n)` (as `bulbjax run`
does: one seed group per device, `bulbjax.epoch.groups`), times build + compile + `init`,
the first epoch and then `--epochs` epochs one by one (each waits for the metrics on the host, as
the run loop does), and reports the median epoch time, epochs/s, seed-epochs/s and the speedup in
seed-epochs/s over one device (goals on 2 GPUs: >= 1.8x at 12 seeds, >= 1.6x at 6).

Written after every measurement (a run cut short keeps what it had) to
`<out-dir>/multigpu_<device>_<timestamp>.json`: command line, settings, provenance (versions,
git commit, device kind and count) and the figures.

GPU (2 GPUs; 4 compiles of the six-learner preset, so split across calls if one is too long):
    python benchmarks/bench_multigpu.py --preset fig2-cartpole --bf16
    python benchmarks/bench_multigpu.py --seeds 6 --bf16 ; python benchmarks/bench_multigpu.py --seeds 12 --bf16
One process per GPU (`--processes`: every case in its own processes, those of a multi-device case
joined by `jax.distributed` on localhost, each seeing one GPU through CUDA_VISIBLE_DEVICES, as
`bulbjax run --num-processes` runs them; in one process every MJX-Warp call of every GPU goes
through Warp's FFI callback under the Python GIL and one global lock, `warp/_src/jax/ffi.py`):
    python benchmarks/bench_multigpu.py --seeds 6,12 --bf16 --processes --devices 1,2
CPU smoke run (2 host devices):
    XLA_FLAGS=--xla_force_host_platform_device_count=2 python benchmarks/bench_multigpu.py --small \
        --learners vae --seeds 2 --epochs 2
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import re
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # this working tree's bulbjax

import jax  # noqa: E402

from bulbjax import compile_cache  # noqa: E402
from bulbjax.epoch.groups import SeedGroups  # noqa: E402
from bulbjax.local_processes import free_port  # noqa: E402
from bulbjax.run.provenance import provenance  # noqa: E402
from bulbjax.run.settings import resolve  # noqa: E402


def measure(cfg, devices, epochs: int, probe: bool = True) -> dict:
    """Init, first epoch (compile) and `epochs` timed epochs of `cfg` on `devices`; `probe=False`
    times the epoch without held-out rollouts and probes (what `--probe-every k` runs k-1 times
    in k)."""
    t = time.perf_counter()
    groups = SeedGroups(cfg, devices=devices).programs((probe,)).prepare("init", "epoch")
    rs = groups.init(jax.random.PRNGKey(0))
    jax.block_until_ready(rs)
    t_init = time.perf_counter() - t
    key = groups.put_key(jax.random.PRNGKey(1))
    times = []
    for i in range(epochs + 1):
        key, k = jax.random.split(key)
        t = time.perf_counter()
        rs, m = groups.epoch(rs, k, probe=probe)  # metrics on the host: the epoch is done
        times.append(time.perf_counter() - t)
    med = statistics.median(times[1:])
    return {"devices": len(devices), "layout": groups.describe(), "seeds": cfg.seeds,
            "probe": probe, "build_init_s": t_init, "first_epoch_s": times[0], "epoch_s": times[1:],
            "median_epoch_s": med, "epochs_per_s": 1.0 / med, "seed_epochs_per_s": cfg.seeds / med}


def _gpu_name() -> str:
    """The first GPU's name without initialising a JAX backend here (nvidia-smi; else "processes")."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                             text=True, timeout=30).stdout.splitlines()
        return out[0].strip() if out else "processes"
    except (OSError, subprocess.SubprocessError):
        return "processes"


def in_processes(argv: list[str], seeds: int, n: int) -> dict:
    """The case (`seeds`, `n` devices) as n worker processes of this script, one GPU each; the run's
    epoch is as slow as its slowest process (they gather metrics every epoch)."""
    port = free_port()
    procs = []
    for i in range(n):
        env = dict(os.environ)
        if "CUDA_VISIBLE_DEVICES" not in os.environ or n > 1:
            env["CUDA_VISIBLE_DEVICES"] = str(i)
        cmd = [sys.executable, os.path.abspath(__file__), *argv, "--seeds", str(seeds), "--worker", f"{i},{n},{port}"]
        procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    results = []
    for i, pr in enumerate(procs):
        for line in pr.stdout:
            if line.startswith("WORKER_RESULT "):
                results.append(json.loads(line[len("WORKER_RESULT "):]))
            else:
                print(f"[worker {i}] {line}", end="", flush=True)
        pr.wait()
    if len(results) != n:
        return {"devices": n, "seeds": seeds, "layout": f"{n} processes", "error": f"{n - len(results)} workers failed"}
    med = max(r["median_epoch_s"] for r in results)
    return {"devices": n, "layout": f"{n} processes x 1 GPU", "seeds": seeds, "probe": results[0]["probe"],
            "build_init_s": max(r["build_init_s"] for r in results),
            "first_epoch_s": max(r["first_epoch_s"] for r in results),
            "epoch_s": [max(t) for t in zip(*(r["epoch_s"] for r in results))],
            "median_epoch_s": med, "epochs_per_s": 1.0 / med, "seed_epochs_per_s": seeds / med,
            "workers": [{k: v for k, v in r.items() if k != "epoch_s"} for r in results]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="fig2-cartpole", help="six-learner preset (default fig2-cartpole)")
    p.add_argument("--seeds", default="6,12", help="seed counts, comma-separated")
    p.add_argument("--devices", default=None, help="device counts, comma-separated (default 1 and all)")
    p.add_argument("--epochs", type=int, default=5, help="timed epochs after the first (compile) one")
    p.add_argument("--learners", default=None, help="override the preset's learners (smoke runs)")
    p.add_argument("--bf16", action="store_true", help="bf16 learner compute (GPU)")
    p.add_argument("--rnn-unroll", type=int, default=1,
                   help="sequential learners' LSTM unroll (4 on a GPU: docs/performance.md)")
    p.add_argument("--no-probe", action="store_true",
                   help="time epochs without probing (the epochs between probes; a third of the compile)")
    p.add_argument("--small", action="store_true", help="CPU-sized settings (not the paper's)")
    p.add_argument("--out-dir", default=os.path.join(HERE, "results"))
    p.add_argument("--compile-cache", default=None, help="persistent XLA cache folder (default bulbjax's)")
    p.add_argument("--processes", action="store_true",
                   help="each case in its own processes, one GPU each (needs --devices, e.g. 1,2)")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # "index,count,port" of a --processes case
    raw = list(sys.argv[1:] if argv is None else argv)
    args = p.parse_args(argv)
    if args.compile_cache:
        os.environ["BULBJAX_COMPILE_CACHE"] = args.compile_cache
    compile_cache.enable()
    if args.processes:  # this process never holds GPU memory the workers need
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    if args.processes and not args.devices:
        raise SystemExit("--processes needs --devices (e.g. 1,2): this process never touches the GPUs")
    learner = {"rnn_unroll": args.rnn_unroll, **({"compute_dtype": "bfloat16"} if args.bf16 else {})}
    if args.worker:  # one process of a --processes case: join the others, measure, report on stdout
        i, n, port = (int(x) for x in args.worker.split(","))
        if n > 1:
            jax.config.update("jax_cpu_collectives_implementation", "gloo")
            jax.distributed.initialize(coordinator_address=f"localhost:{port}", num_processes=n, process_id=i)
        cfg = resolve(args.preset, overrides={"learners": args.learners} if args.learners else {},
                      learner=learner, small=args.small).replace(seeds=int(args.seeds))
        r = measure(cfg, jax.devices(), args.epochs, probe=not args.no_probe)
        print("WORKER_RESULT " + json.dumps(r), flush=True)
        return 0
    if args.processes:
        keep = []
        skip = False
        for a in raw:  # the workers get the same flags but --seeds, --processes, --devices
            if skip:
                skip = False
                continue
            if a in ("--seeds", "--devices"):
                skip = True
                continue
            if a == "--processes" or a.startswith("--seeds=") or a.startswith("--devices="):
                continue
            keep.append(a)
        all_devs = None
    else:
        all_devs = jax.local_devices()
    counts = ([int(x) for x in args.devices.split(",")] if args.devices
              else sorted({1, len(all_devs)}, reverse=True))
    if all_devs is not None and max(counts) > len(all_devs):
        raise SystemExit(f"--devices {args.devices}: only {len(all_devs)} local devices")
    # the preset as `bulbjax run` resolves it (the domain's PPO settings, --small, the flags given)
    base = resolve(args.preset, overrides={"learners": args.learners} if args.learners else {},
                   learner=learner, small=args.small)
    kind = all_devs[0].device_kind if all_devs else _gpu_name()
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    os.makedirs(args.out_dir, exist_ok=True)
    path = os.path.join(args.out_dir, f"multigpu_{re.sub(r'[^a-z0-9]+', '_', kind.lower())}_{stamp}.json")
    out = {"settings": vars(args), "config": dataclasses.asdict(base), "provenance": provenance() if all_devs else {"gpus": _gpu_name(), "note": "workers' devices: see results"},
           "results": []}
    for seeds in [int(s) for s in args.seeds.split(",")]:
        cfg = base.replace(seeds=seeds)
        mine = []
        for n in counts:
            try:
                r = (in_processes(keep, seeds, n) if args.processes
                     else measure(cfg, all_devs[:n], args.epochs, probe=not args.no_probe))
            except Exception as err:  # recorded, the other cases go on
                r = {"devices": n, "seeds": seeds, "error": f"{type(err).__name__}: {err}"}
            mine.append(r)
            one = next((x for x in mine if x["devices"] == 1 and "error" not in x), None)
            for x in mine:  # in whichever order the device counts ran
                if one is not None and "error" not in x:
                    x["speedup_vs_1"] = x["seed_epochs_per_s"] / one["seed_epochs_per_s"]
            out["results"].append(r)
            print(json.dumps({k: v for k, v in r.items() if k != "epoch_s"}), flush=True)
            with open(path, "w") as f:
                json.dump(out, f, indent=1)
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
