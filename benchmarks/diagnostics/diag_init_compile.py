"""What init's compile time is made of (issue 13, cold start): each learner's parameter init
over the seeds (`vmap`, and `lax.map` as `Learning.init_learner` does it) compiled alone, then the
env's rollouts that fill the buffers. Prints seconds per part; `--out FILE` writes them as JSON.

    python benchmarks/diagnostics/diag_init_compile.py --preset fig2-invpend --bf16
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

BENCH = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(BENCH))
sys.path.insert(0, BENCH)

import jax  # noqa: E402

from profile_epoch import add_config_args, build_config  # noqa: E402

from bulbjax.experiment.loop import Experiment  # noqa: E402


def timed_compile(f, *args) -> float:
    t0 = time.perf_counter()
    jax.jit(f).lower(*args).compile()
    return time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_config_args(p)
    p.add_argument("--out", default="")
    a = p.parse_args()
    cfg = build_config(a)
    exp = Experiment(cfg)
    keys = jax.random.split(jax.random.PRNGKey(0), cfg.seeds)
    out: dict = {"device_kind": jax.devices()[0].device_kind, "preset": a.preset, "parts": {}}
    for name, learner in exp.learners.items():
        one = lambda k, l=learner: l.init(k, exp.env.frame_shape)  # noqa: E731
        out["parts"][f"{name} init (vmap)"] = timed_compile(jax.vmap(one), keys)
        out["parts"][f"{name} init (lax.map)"] = timed_compile(lambda ks, one=one: jax.lax.map(one, ks), keys)
        print({k: round(v, 1) for k, v in out["parts"].items() if k.startswith(name)}, flush=True)
    ppo = jax.vmap(exp.ppo.init)(keys)
    k = jax.random.PRNGKey(1)
    steps = -(-cfg.replay_capacity // exp.N)
    reset = exp.devices.env_reset
    out["parts"]["env reset"] = timed_compile(reset, k)
    out["parts"]["replay fill rollout (render every step)"] = timed_compile(
        lambda pp, kk: exp.streams.collect(pp, reset(kk), kk, steps, random=True), ppo, k)
    out["parts"]["reference rollout"] = timed_compile(
        lambda pp, kk: exp.policy.rollout(pp, reset(kk), kk, cfg.reference_steps, random=True), ppo, k)
    if exp.window_length:
        out["parts"]["window buffers fill"] = timed_compile(exp.streams.init_windows, ppo, k)
    for n, v in out["parts"].items():
        print(f"{n:45} {v:7.1f} s")
    if a.out:
        with open(a.out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
