"""How long a checkpoint holds up the run loop (issue 56): seconds per checkpoint that the loop
waits, per way of writing, on one small run.

A run of `--epochs` epochs (CartPole, one learner, `--small`; `--replay-mult` scales the replay
buffer, the bulk of a run's state as on a GPU preset) is made once per way of writing, each with
a checkpoint after every epoch, in this process (one compile for all: `run(experiment=...)`). The
loop's stall per checkpoint is the time `run._save` blocks it (`Checkpointer.save`: the host copy,
and for a synchronous write the whole write); the wait for the last background write at the end is
reported apart. Ways: `orbax` (one process's checkpoints, synchronous: before issue 56),
`orbax-background` (orbax's asynchronous save of host copies: a one-process run now), `files` (a
multi-process run's `ProcessFiles`, synchronous: before) and `files-background` (the same written
in a thread while the loop goes on: a multi-process run now).

    PYTHONPATH=. python benchmarks/bench_checkpoint_stall.py --epochs 6 --replay-mult 8
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--epochs", type=int, default=6)
    p.add_argument("--replay-mult", type=int, default=8, help="replay capacity x this (state size)")
    p.add_argument("--ways", default="orbax,orbax-background,files,files-background")
    p.add_argument("--json", default=None, help="write the numbers here too")
    a = p.parse_args(argv)

    import jax
    import numpy as np

    from bulbjax.config import RunOptions
    from bulbjax.epoch.loop import Experiment
    from bulbjax.run import checkpoint
    from bulbjax.run import loop as run_mod
    from bulbjax.run.settings import resolve

    cfg = resolve(None, overrides=dict(env="CartPole", learners="vae", seeds=1, epochs=a.epochs,
                                       ppo_updates_per_epoch=1), small=True, ppo_options=("num_steps=16",))
    cfg = dataclasses.replace(cfg, replay_capacity=cfg.replay_capacity * a.replay_mult)
    exp = Experiment(cfg)
    state_bytes = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(exp.abstract_state()))
    out: dict = {"epochs": a.epochs, "state_mb": round(state_bytes / 2**20, 1), "backend": jax.default_backend(),
                 "ways": {}}
    real_save, real_ckpt = run_mod._save, run_mod.Checkpointer
    for way in a.ways.split(","):
        stalls: list[float] = []
        final: list[float] = []

        def timed_save(ckpt, run_dir, epoch, rs, key):
            t = time.perf_counter()
            real_save(ckpt, run_dir, epoch, rs, key)
            (final if rs is None else stalls).append(time.perf_counter() - t)

        def make(run_dir, keep=2, process=None, cleanup_tmp=False, background=False, way=way):
            if way.startswith("orbax"):
                return real_ckpt(run_dir, keep=keep, cleanup_tmp=cleanup_tmp, background=way == "orbax-background")
            return real_ckpt(run_dir, keep=keep, process=0, cleanup_tmp=cleanup_tmp,
                             background=way == "files-background")

        run_mod._save, run_mod.Checkpointer = timed_save, make
        try:
            with tempfile.TemporaryDirectory() as d:
                t = time.perf_counter()
                run_mod.run(cfg, RunOptions(checkpoint_every=1), os.path.join(d, "r"), experiment=exp,
                            log=lambda s: None, progress=False)
                wall = time.perf_counter() - t
        finally:
            run_mod._save, run_mod.Checkpointer = real_save, real_ckpt
        # the first checkpoint's own start-up (orbax's manager, the folder) apart from the rest
        out["ways"][way] = {"stall_s_mean": round(float(np.mean(stalls[1:] or stalls)), 4),
                            "stall_s_max": round(float(np.max(stalls)), 4), "stall_s_first": round(stalls[0], 4),
                            "final_wait_s": round(sum(final), 4), "run_wall_s": round(wall, 2)}
        print(f"{way:>17}: loop waits {out['ways'][way]['stall_s_mean']:.3f} s per checkpoint "
              f"(max {out['ways'][way]['stall_s_max']:.3f}, first {stalls[0]:.3f}); end wait "
              f"{sum(final):.3f} s; run {wall:.1f} s; state {out['state_mb']} MB", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    main()
