"""Rendered frames per second of the Incline domains (YcbOnIncline, GeomOnIncline): bulbjax on its
accelerator against the PyBullet originals (`pybullet_compat.incline`) in N processes on this
machine's CPU cores, in one run; plus the YCB mesh cache build time from an empty cache.

1. Cache: bulb's six YCB objects at the env's scale processed by `bulbjax.assets.load_ycb_object`
   into a fresh, empty cache folder (`--build-cache-dir`, default a new temporary folder), timed
   per object; then loaded again (cache hits, timed). The rest of the run uses that cache
   (`$BULBJAX_CACHE_DIR` is set to it), so both simulators load the same processed meshes.
2. PyBullet: `pybullet_compat.vector.ProcessVecEnv` of `--procs` envs (default 16), random pushes,
   auto-reset, every step renders bulb's 64x64 frame (ER_TINY_RENDERER) and returns the state;
   frames/s = procs x vector steps / wall time over `--seconds` after a warm-up. With
   `--version random` process i simulates version i % 6 (bulb's envs have one version each).
3. bulbjax: `bulbjax.make(name, num_envs=W, version=..., render=True)`, `--steps` random-push
   steps in one jitted scan (physics + forward + Warp render + state), median of `--repeats`
   calls after compiling; frames/s = W x steps / call time.

    python benchmarks/bench_incline.py --ycb-dir /path/to/ycb              # GPU: 1,024 and 4,096 worlds
    python benchmarks/bench_incline.py --small --ycb-dir ../shared/ycb     # CPU smoke test (~3 min)

Writes benchmarks/results/incline_<device>_<stamp>.json (and incline_latest.json) and prints its path.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # run from a checkout without installing
sys.path.insert(0, HERE)

import frames_bench  # noqa: E402
from frames_bench import device_info, log, parse_reset_chunks, time_bulbjax, time_pybullet  # noqa: E402


@dataclass(frozen=True)
class Settings:
    """What to measure (`--small` shrinks every size for a CPU smoke test)."""

    envs: tuple[str, ...]
    version: str  # "0".."5" or "random"
    procs: int
    worlds: tuple[int, ...]
    seconds: float
    steps: int
    repeats: int
    resolution: int
    out: str
    ycb_dir: str | None
    build_cache_dir: str | None
    keep_cache: bool
    skip_pybullet: bool
    skip_bulbjax: bool
    skip_cache: bool
    seed: int = 0
    # worlds per reset chunk in `step` (None: the domain's default, 0: the full-batch reset)
    reset_chunks: tuple[int | None, ...] = (None,)
    # reset pool sizes in `step`, multiples of the worlds (None: the domain's default, 0: no pool)
    reset_pools: tuple[int | None, ...] = (None,)
    raw_warp: bool = True  # the raw MuJoCo Warp probe of each env's scene at each world count (raw_warp.py)

    @property
    def mjx_version(self) -> int | str:
        return "random" if self.version == "random" else int(self.version)

    def pybullet_versions(self) -> list[int]:
        return [i % 6 for i in range(self.procs)] if self.version == "random" else [int(self.version)] * self.procs


def bench_cache(s: Settings, cache: str) -> dict[str, Any]:
    """Build bulb's six YCB objects (default scale 2.5) into the empty folder `cache`, then load them again."""
    from bulbjax.assets import load_ycb_object
    from pybullet_compat.incline import SCALES, YCB_OBJECTS

    if os.path.isdir(cache) and os.listdir(cache):
        raise ValueError(f"--build-cache-dir {cache} is not empty: the build must start from an empty cache")
    scale = SCALES[""]
    rows, t_all = [], time.perf_counter()
    for name in YCB_OBJECTS:
        t0 = time.perf_counter()
        a = load_ycb_object(name, scale=scale, ycb_dir=s.ycb_dir, cache_dir=cache)
        build = time.perf_counter() - t0
        t0 = time.perf_counter()
        b = load_ycb_object(name, scale=scale, ycb_dir=s.ycb_dir, cache_dir=cache)
        hit = time.perf_counter() - t0
        if a.from_cache or not b.from_cache:
            raise RuntimeError(f"{name}: expected a build then a cache hit")
        rows.append({"object": name, "build_s": build, "cache_hit_s": hit, "visual_faces": int(len(a.visual_faces)),
                     "collision_faces": int(len(a.collision_faces)), "textured": a.texture_path is not None})
    total = time.perf_counter() - t_all
    return {"scale": scale, "objects": rows, "build_total_s": sum(r["build_s"] for r in rows),
            "cache_hit_total_s": sum(r["cache_hit_s"] for r in rows), "wall_s": total}


def bench_pybullet(name: str, s: Settings) -> dict[str, Any]:
    """Frames/s of `s.procs` PyBullet Incline processes stepping and rendering together."""
    from pybullet_compat.incline import incline_domain, object_shape

    spec = incline_domain(name)
    versions = s.pybullet_versions()
    shapes = {v: object_shape(spec, v, s.ycb_dir) for v in sorted(set(versions))}  # no JAX in the workers
    return time_pybullet(name, s.procs, [{"version": v, "shape": shapes[v]} for v in versions], 1, s.seconds,
                         s.resolution, s.seed, meta={"versions": versions})


def bench_bulbjax(name: str, worlds: int, s: Settings, reset_chunk: int | None = None,
                  reset_pool: int | None = None) -> dict[str, Any]:
    """Frames/s of one bulbjax Incline env of `worlds` worlds, `s.steps` rendered steps per jitted scan."""
    return time_bulbjax(name, worlds, 1, s.steps, s.repeats, s.resolution, s.seed,
                        meta={"version": s.mjx_version, "reset_chunk": reset_chunk, "reset_pool": reset_pool},
                        version=s.mjx_version, ycb_dir=s.ycb_dir, reset_chunk=reset_chunk, reset_pool=reset_pool)


def parse_args(argv: list[str] | None = None) -> Settings:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--envs", default="YcbOnIncline,GeomOnIncline")
    p.add_argument("--version", default="0", help="object version 0..5, or 'random' (MJX: per world; PyBullet: i %% 6)")
    p.add_argument("--procs", type=int, default=None, help="PyBullet processes (default 16; --small: 2)")
    p.add_argument("--worlds", default=None, help="bulbjax batch sizes (default 1024,4096; --small: 8)")
    p.add_argument("--seconds", type=float, default=None, help="PyBullet measurement time per env (default 20)")
    p.add_argument("--steps", type=int, default=None, help="bulbjax steps per jitted scan (default 50)")
    p.add_argument("--repeats", type=int, default=None, help="timed bulbjax scans (default 5)")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--out", default=os.path.join(HERE, "results"))
    p.add_argument("--ycb-dir", default=None, help="YCB models (default $BULBJAX_YCB_DIR)")
    p.add_argument("--build-cache-dir", default=None,
                   help="empty folder to build the YCB cache in (default: a new temporary folder, removed at the end)")
    p.add_argument("--keep-cache", action="store_true", help="keep the temporary cache folder")
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
    p.add_argument("--skip-cache", action="store_true", help="no cache build timing (use the existing cache)")
    a = p.parse_args(argv)
    small = a.small
    pick = lambda v, big, little: v if v is not None else (little if small else big)  # noqa: E731
    if a.version != "random" and a.version not in tuple("012345"):
        p.error(f"--version must be 0..5 or 'random', got {a.version!r}")
    worlds = tuple(int(w) for w in pick(a.worlds, "1024,4096", "8").split(","))
    return Settings(envs=tuple(a.envs.split(",")), version=a.version, procs=pick(a.procs, 16, 2), worlds=worlds,
                    seconds=pick(a.seconds, 20.0, 3.0), steps=pick(a.steps, 50, 5), repeats=pick(a.repeats, 5, 2),
                    resolution=a.resolution, out=a.out, ycb_dir=a.ycb_dir or os.environ.get("BULBJAX_YCB_DIR"),
                    build_cache_dir=a.build_cache_dir, keep_cache=a.keep_cache, skip_pybullet=a.skip_pybullet,
                    skip_bulbjax=a.skip_bulbjax, skip_cache=a.skip_cache,
                    reset_chunks=parse_reset_chunks(a.reset_chunk),
                    reset_pools=parse_reset_chunks(a.reset_pool, "--reset-pool"),
                    raw_warp=not a.skip_raw_warp)


def main(argv: list[str] | None = None) -> str:
    s = parse_args(argv)

    from pybullet_compat.incline import incline_domain

    for name in s.envs:
        incline_domain(name)
    if any(n.startswith("Ycb") for n in s.envs) and not s.ycb_dir:
        raise SystemExit("YcbOnIncline needs the YCB models: pass --ycb-dir or set BULBJAX_YCB_DIR")
    info = device_info()
    log(f"device: {info.get('device')} ({info.get('platform')}), {info['cpu_count']} CPU cores")
    results: dict[str, Any] = {"settings": asdict(s), "device": info, "rows": []}
    made_tmp = None
    if not s.skip_cache and s.ycb_dir:
        cache = s.build_cache_dir or (made_tmp := tempfile.mkdtemp(prefix="bulbjax_cache_bench_"))
        results["ycb_cache"] = bench_cache(s, cache)
        results["ycb_cache"]["dir"] = cache
        os.environ["BULBJAX_CACHE_DIR"] = cache  # both simulators load the meshes just built
        c = results["ycb_cache"]
        log(f"YCB cache: 6 objects built in {c['build_total_s']:.1f} s from an empty cache, "
            f"cache hits {c['cache_hit_total_s']:.2f} s")
    try:
        frames_bench.measure_rows(results, s, "incline", bench_pybullet, bench_bulbjax)
    finally:
        if made_tmp and not s.keep_cache:
            shutil.rmtree(made_tmp, ignore_errors=True)
    print_table(results)
    path = write(results, s.out)
    print(path)
    return path


def print_table(results: dict[str, Any]) -> None:
    frames_bench.print_table(results)
    if "ycb_cache" in results:
        c = results["ycb_cache"]
        print(f"\nYCB cache from empty: {c['build_total_s']:.1f} s for 6 objects; hits {c['cache_hit_total_s']:.2f} s")


def write(results: dict[str, Any], out: str) -> str:
    return frames_bench.write(results, out, "incline")


if __name__ == "__main__":
    main()
