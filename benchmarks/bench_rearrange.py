"""Rendered frames per second of the Rearrange domains (default ReacherRearrangeYcb and
FrankaRearrangeYcb): bulbjax on its accelerator against the PyBullet originals
(`pybullet_compat.rearrange_env`) in N processes on this machine's CPU cores, in one run.

1. PyBullet: `pybullet_compat.vector.ProcessVecEnv` of `--procs` envs (default 16), random torques
   a ~ U[-1, 1], auto-reset (bulb's reset: 20 settle steps and 10 random-torque steps, not
   counted as frames), every step renders bulb's 64x64 frame (ER_TINY_RENDERER) and returns the
   state; frames/s = procs x vector steps / wall time over `--seconds` after a warm-up. Objects
   are prepared here (YCB meshes from bulbjax's cache, the same files the MJX mirror loads) and
   passed to the workers, which never import JAX. With `--version random` process i simulates
   version i % 12 (bulb's envs have one version each).
2. bulbjax: `bulbjax.make(name, num_envs=W, version=..., render=True)`, `--steps` random-torque
   steps in one jitted scan (physics + kinematics + Warp render + state, auto-reset inside),
   median of `--repeats` calls after compiling; frames/s = W x steps / call time.

    python benchmarks/bench_rearrange.py --ycb-dir /path/to/ycb --out "$OUT"        # GPU: 1,024 and 4,096 worlds
    python benchmarks/bench_rearrange.py --small --ycb-dir ../shared/ycb --out /tmp/b  # CPU smoke test

Writes <out>/rearrange_<device>_<stamp>.json (and rearrange_latest.json) and prints its path last.
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import asdict, dataclass
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # run from a checkout without installing
sys.path.insert(0, HERE)

import frames_bench  # noqa: E402
from frames_bench import device_info, log, parse_reset_chunks, time_bulbjax, time_pybullet  # noqa: E402

NUM_VERSIONS = 12


@dataclass(frozen=True)
class Settings:
    """What to measure (`--small` shrinks every size for a CPU smoke test)."""

    envs: tuple[str, ...]
    version: str  # "0".."11" or "random"
    procs: int
    worlds: tuple[int, ...]
    seconds: float
    steps: int
    repeats: int
    resolution: int
    out: str
    ycb_dir: str | None
    skip_pybullet: bool
    skip_bulbjax: bool
    # worlds per reset chunk in `step` (None: the domain's default, 0: the full-batch reset)
    reset_chunks: tuple[int | None, ...] = (None,)
    # reset pool sizes in `step`, multiples of the worlds (None: the domain's default, 0: no pool)
    reset_pools: tuple[int | None, ...] = (None,)
    raw_warp: bool = True  # the raw MuJoCo Warp probe of each env's scene at each world count (raw_warp.py)
    seed: int = 0

    @property
    def mjx_version(self) -> int | str:
        return "random" if self.version == "random" else int(self.version)

    def pybullet_versions(self) -> list[int]:
        if self.version == "random":
            return [i % NUM_VERSIONS for i in range(self.procs)]
        return [int(self.version)] * self.procs


def bench_pybullet(name: str, s: Settings) -> dict[str, Any]:
    """Frames/s of `s.procs` PyBullet Rearrange processes stepping and rendering together."""
    from pybullet_compat.rearrange_scene import rearrange_domain, rearrange_objects

    spec = rearrange_domain(name)
    versions = s.pybullet_versions()
    objects = {v: rearrange_objects(name, v, s.ycb_dir) for v in sorted(set(versions))}  # no JAX in the workers
    return time_pybullet(name, s.procs, [{"version": v, "objects": objects[v]} for v in versions], spec.action_size,
                         s.seconds, s.resolution, s.seed, meta={"versions": versions})


def bench_bulbjax(name: str, worlds: int, s: Settings, reset_chunk: int | None = None,
                  reset_pool: int | None = None) -> dict[str, Any]:
    """Frames/s of one bulbjax Rearrange env of `worlds` worlds, `s.steps` rendered steps per jitted scan."""
    from pybullet_compat.rearrange_scene import rearrange_domain

    return time_bulbjax(name, worlds, rearrange_domain(name).action_size, s.steps, s.repeats, s.resolution, s.seed,
                        meta={"version": s.mjx_version, "reset_chunk": reset_chunk, "reset_pool": reset_pool},
                        version=s.mjx_version, ycb_dir=s.ycb_dir, reset_chunk=reset_chunk, reset_pool=reset_pool)


def parse_args(argv: list[str] | None = None) -> Settings:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--envs", default="ReacherRearrangeYcb,FrankaRearrangeYcb",
                   help="comma-separated [Reacher|Franka]Rearrange[Geom|OneGeom|Ycb|OneYcb]")
    p.add_argument("--version", default="0", help="0..11, or 'random' (MJX: per world; PyBullet: i %% 12)")
    p.add_argument("--procs", type=int, default=None, help="PyBullet processes (default 16; --small: 2)")
    p.add_argument("--worlds", default=None, help="bulbjax batch sizes (default 1024,4096; --small: 2)")
    p.add_argument("--seconds", type=float, default=None, help="PyBullet measurement time per env (default 20)")
    p.add_argument("--steps", type=int, default=None, help="bulbjax steps per jitted scan (default 50; --small: 3)")
    p.add_argument("--repeats", type=int, default=None, help="timed bulbjax scans (default 5; --small: 2)")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--out", default=os.path.join(HERE, "results"))
    p.add_argument("--ycb-dir", default=None, help="YCB models (default $BULBJAX_YCB_DIR)")
    p.add_argument("--small", action="store_true", help="CPU smoke test sizes")
    p.add_argument("--reset-chunk", default="default",
                   help="worlds per reset chunk in step, comma-separated: 'default' (the domain's), 0 (the "
                        "full-batch reset, the path before chunks); 'default,0' times both")
    p.add_argument("--reset-pool", default="default",
                   help="reset pool size in step as a multiple of the worlds, comma-separated: 'default' (the "
                        "domain's), 0 (no pool: the chunked resets); '0,default' times both")
    p.add_argument("--skip-pybullet", action="store_true")
    p.add_argument("--skip-bulbjax", action="store_true")
    p.add_argument("--skip-raw-warp", action="store_true",
                   help="no raw MuJoCo Warp probe (step + render of the same scene, no JAX, no resets)")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    pick = lambda v, big, little: v if v is not None else (little if a.small else big)  # noqa: E731
    if a.version != "random" and a.version not in tuple(str(v) for v in range(NUM_VERSIONS)):
        p.error(f"--version must be 0..{NUM_VERSIONS - 1} or 'random', got {a.version!r}")
    worlds = tuple(int(w) for w in pick(a.worlds, "1024,4096", "2").split(","))
    return Settings(envs=tuple(e.strip() for e in a.envs.split(",") if e.strip()), version=a.version,
                    procs=pick(a.procs, 16, 2), worlds=worlds, seconds=pick(a.seconds, 20.0, 3.0),
                    steps=pick(a.steps, 50, 3), repeats=pick(a.repeats, 5, 2), resolution=a.resolution, out=a.out,
                    ycb_dir=a.ycb_dir or os.environ.get("BULBJAX_YCB_DIR"), skip_pybullet=a.skip_pybullet,
                    skip_bulbjax=a.skip_bulbjax, seed=a.seed, reset_chunks=parse_reset_chunks(a.reset_chunk),
                    reset_pools=parse_reset_chunks(a.reset_pool, "--reset-pool"),
                    raw_warp=not a.skip_raw_warp)


def main(argv: list[str] | None = None) -> str:
    s = parse_args(argv)

    from pybullet_compat.rearrange_scene import rearrange_domain

    for name in s.envs:
        rearrange_domain(name)  # an unknown name lists the valid ones
    if any("Ycb" in n for n in s.envs) and not s.ycb_dir:
        raise SystemExit("the Ycb variants need the YCB models: pass --ycb-dir or set BULBJAX_YCB_DIR")
    info = device_info()
    log(f"device: {info.get('device')} ({info.get('platform')}), {info['cpu_count']} CPU cores")
    results: dict[str, Any] = {"settings": asdict(s), "device": info, "rows": []}
    frames_bench.measure_rows(results, s, "rearrange", bench_pybullet, bench_bulbjax)
    frames_bench.print_table(results)
    path = frames_bench.write(results, s.out, "rearrange")
    print(path)
    return path


if __name__ == "__main__":
    main()
