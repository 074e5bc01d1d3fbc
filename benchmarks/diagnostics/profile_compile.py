"""Compile time of a run's init program (and optionally its epoch) under named XLA option sets
(issue 13: what a cold start spends its compile on). Each set compiles the same lowered program
in this process, one after the other, with JAX's persistent cache off unless `--compile-cache`
is given (XLA's per-fusion autotuning results live in that cache too: without it every compile
autotunes from scratch). Writes `<out-dir>/compile_<preset>_<device>_<timestamp>.json`.

    python benchmarks/diagnostics/profile_compile.py --preset fig2-invpend --bf16 --rnn-unroll 4 \
        --set default --set noautotune=xla_gpu_autotune_level:0
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import time

BENCH = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(BENCH))
sys.path.insert(0, BENCH)

import jax  # noqa: E402

from profile_epoch import add_config_args, build_config, parse_variant  # noqa: E402

from bulbjax.experiment.loop import Experiment  # noqa: E402
from bulbjax.experiment.programs import Programs  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_config_args(p)
    p.add_argument("--programs", default="init", help="comma-separated: init, epoch (the flag program)")
    p.add_argument("--set", action="append", default=[], metavar="NAME[=KEY:VALUE;...]",
                   help="a named set of XLA compile options (repeatable; default: one set, no options)")
    p.add_argument("--compile-cache", default="", help="JAX persistent cache folder (default: off)")
    p.add_argument("--out-dir", default=os.path.join(BENCH, "results"))
    a = p.parse_args(argv)
    if a.compile_cache:
        from bulbjax.compile_cache import enable
        enable(a.compile_cache)
    cfg = build_config(a)
    t0 = time.perf_counter()
    exp = Experiment(cfg)
    res: dict = {"preset": a.preset, "argv": sys.argv if argv is None else argv, "build_s": time.perf_counter() - t0,
                 "device_kind": jax.devices()[0].device_kind, "jax": jax.__version__,
                 "compile_cache": a.compile_cache or None, "programs": {}}
    progs = Programs.of(exp, (True, False))
    sets = dict(parse_variant(s) for s in a.set) or {"default": {}}
    for name in [x for x in a.programs.split(",") if x]:
        t0 = time.perf_counter()
        lowered = progs.lowered(name)
        out = res["programs"][name] = {"lower_s": time.perf_counter() - t0, "sets": {}}
        for sname, opts in sets.items():
            t0 = time.perf_counter()
            lowered.compile(compiler_options=opts or None)
            out["sets"][sname] = {"options": opts, "compile_s": time.perf_counter() - t0}
            print(f"{name} [{sname}] compile {out['sets'][sname]['compile_s']:.1f} s", flush=True)
    slug = res["device_kind"].lower().replace(" ", "_")
    os.makedirs(a.out_dir, exist_ok=True)
    path = os.path.join(a.out_dir, f"compile_{a.preset}_{slug}_{dt.datetime.now():%Y%m%d_%H%M%S}.json")
    with open(path, "w") as f:
        json.dump(res, f, indent=1, default=str)
    print(f"written: {path}")
    return res


if __name__ == "__main__":
    main()
