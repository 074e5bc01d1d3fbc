"""Rendered frames per second (64x64 RGB + true state): the PyBullet originals with N parallel
processes on this machine's CPU cores, against bulbjax on its accelerator (or CPU), in one run.

PyBullet: `pybullet_compat.ProcessVecEnv`, one env per process (N = CPU cores by default), random
actions, auto-reset; every step renders bulb's frame with `getCameraImage` (ER_TINY_RENDERER) and
returns the state; frames/s = N x steps / wall time over `--seconds` after a warm-up.
bulbjax: `bulbjax.make(name, num_envs=W, render=True)`, `--steps` random-action steps in one
jitted scan (physics + forward + 64x64 Warp render + state), median of `--repeats` calls after
compiling; frames/s = W x steps / call time. Ratio = bulbjax's best batch size / PyBullet.

    python benchmarks/bench_pybullet_vs_bulbjax.py --envs CartPole,InvertedPendulum,HalfCheetah,Ant \\
        --worlds 1024,4096 --seconds 20

Needs no network; gym is imported only by pybullet_envs' modules (never `gym.make`). Writes
benchmarks/results/pybullet_vs_bulbjax_<device>_<stamp>.json (and ..._latest.json).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # run from a checkout without installing
sys.path.insert(0, HERE)

from frames_bench import device_info, log, measure_env, print_table, write  # noqa: E402


@dataclass(frozen=True)
class Settings:
    """What to measure."""

    envs: tuple[str, ...]
    procs: int
    worlds: tuple[int, ...]
    seconds: float
    steps: int
    repeats: int
    resolution: int
    out: str
    skip_pybullet: bool
    skip_bulbjax: bool
    seed: int = 0


def bench_pybullet(name: str, s: Settings) -> dict[str, Any]:
    """Frames/s of `s.procs` PyBullet processes stepping and rendering together."""
    from pybullet_compat.envs import domain
    from pybullet_compat.vector import ProcessVecEnv

    spec = domain(name)
    rng = np.random.default_rng(s.seed)

    def actions() -> np.ndarray:
        if spec.discrete:
            return rng.integers(0, spec.num_actions, s.procs)
        return rng.uniform(-1, 1, (s.procs, spec.action_size)).astype(np.float32)

    t0 = time.perf_counter()
    venv = ProcessVecEnv(name, s.procs, resolution=s.resolution, render=True)
    start_s = time.perf_counter() - t0
    try:
        venv.reset(seeds=list(range(s.procs)))
        for _ in range(20):  # warm-up
            venv.step(actions())
        steps, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < s.seconds:
            frames, states, *_ = venv.step(actions())
            steps += 1
        wall = time.perf_counter() - t0
    finally:
        venv.close()
    assert frames.shape == (s.procs, s.resolution, s.resolution, 3) and frames.dtype == np.uint8
    return {"env": name, "processes": s.procs, "vector_steps": steps, "wall_s": wall, "start_s": start_s,
            "frames_per_s": s.procs * steps / wall, "frames_per_s_per_process": steps / wall,
            "state_dim": int(states.shape[1]), "pixels_mean": float(frames.mean())}


def bench_bulbjax(name: str, worlds: int, s: Settings) -> dict[str, Any]:
    """Frames/s of one bulbjax env of `worlds` worlds, `s.steps` rendered steps per jitted scan."""
    import jax
    import jax.numpy as jnp

    import bulbjax

    env = bulbjax.make(name, num_envs=worlds, resolution=s.resolution, render=True)

    def act(key: jax.Array) -> jax.Array:
        if env.discrete:
            return jax.random.randint(key, (worlds,), 0, env.num_actions, dtype=jnp.int32)
        return jax.random.uniform(key, (worlds * env.action_size,), minval=-1.0, maxval=1.0).reshape(
            worlds, env.action_size)

    @jax.jit
    def rollout(state: Any, key: jax.Array) -> tuple[Any, jax.Array]:
        def body(carry, _):
            st, k = carry
            k, ka = jax.random.split(k)
            return (env.step(st, act(ka)), k), None
        return jax.lax.scan(body, (state, key), None, length=s.steps)[0]

    key = jax.random.PRNGKey(s.seed)
    state = jax.jit(env.reset)(key)
    t0 = time.perf_counter()
    compiled = rollout.lower(state, key).compile()
    compile_s = time.perf_counter() - t0
    state, key = jax.block_until_ready(compiled(state, key))
    calls = []
    for _ in range(s.repeats):
        t0 = time.perf_counter()
        state, key = jax.block_until_ready(compiled(state, key))
        calls.append(time.perf_counter() - t0)
    med = statistics.median(calls)
    px = np.asarray(state.pixels)
    return {"env": name, "worlds": worlds, "steps": s.steps, "repeats": s.repeats, "compile_s": compile_s,
            "call_s": calls, "median_call_s": med, "frames_per_s": worlds * s.steps / med,
            "frames_per_s_best": worlds * s.steps / min(calls), "state_dim": int(state.lowdim.shape[1]),
            "pixels_mean": float(px.mean())}


def parse_args(argv: list[str] | None = None) -> Settings:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--envs", default="CartPole,InvertedPendulum,HalfCheetah,Ant")
    p.add_argument("--procs", type=int, default=os.cpu_count() or 1, help="PyBullet processes (default: CPU cores)")
    p.add_argument("--worlds", default="1024,4096", help="bulbjax batch sizes, comma-separated")
    p.add_argument("--seconds", type=float, default=20.0, help="PyBullet measurement time per env")
    p.add_argument("--steps", type=int, default=100, help="bulbjax steps per jitted scan")
    p.add_argument("--repeats", type=int, default=5, help="timed bulbjax scans")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--out", default=os.path.join(HERE, "results"))
    p.add_argument("--skip-pybullet", action="store_true")
    p.add_argument("--skip-bulbjax", action="store_true")
    a = p.parse_args(argv)
    return Settings(envs=tuple(a.envs.split(",")), procs=a.procs, worlds=tuple(int(w) for w in a.worlds.split(",")),
                    seconds=a.seconds, steps=a.steps, repeats=a.repeats, resolution=a.resolution, out=a.out,
                    skip_pybullet=a.skip_pybullet, skip_bulbjax=a.skip_bulbjax)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    s = parse_args(argv)
    info = device_info()
    log(f"device: {info.get('device')} ({info.get('platform')}), {info['cpu_count']} CPU cores, python {info['python']}")
    results: dict[str, Any] = {"settings": asdict(s), "device": info, "rows": []}
    try:
        import bulbjax
        available = set(bulbjax.env_names(with_variants=False))
    except Exception as err:
        available, results["bulbjax_error"] = set(), repr(err)
    for name in s.envs:
        missing = not s.skip_bulbjax and name not in available
        row = measure_env(name, s.procs, s.worlds, None if s.skip_pybullet else (lambda: bench_pybullet(name, s)),
                          None if s.skip_bulbjax or missing else (lambda w: bench_bulbjax(name, w, s)))
        if missing:
            row["bulbjax_error"] = f"{name} is not registered in this bulbjax"
        results["rows"].append(row)
    print_table(results)
    write(results, s.out, "pybullet_vs_bulbjax")
    return results


if __name__ == "__main__":
    main()
