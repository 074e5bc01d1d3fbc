"""Shared timing of rendered frames/s for the "bulbjax against the PyBullet originals" benchmarks
(`bench_incline.py`, `bench_rearrange.py`, `bench_pybullet_vs_bulbjax.py`): N PyBullet processes (`pybullet_compat.vector`)
stepping with random actions, one bulbjax env of W worlds stepping in one jitted scan, the
per-env loop that records errors and the ratio, the table and the JSON file.

Actions are uniform in [-1, 1] on both sides (bulbjax's convention, which the originals share).
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np


def log(msg: str) -> None:
    print(msg, flush=True)


def device_info() -> dict[str, Any]:
    """The machine: CPU cores, Python, JAX device and versions of the simulators."""
    info: dict[str, Any] = {"cpu_count": os.cpu_count(), "python": platform.python_version(),
                            "machine": platform.machine()}
    try:
        import jax
        d = jax.devices()[0]
        info.update(platform=d.platform, device=getattr(d, "device_kind", str(d)), jax=jax.__version__)
    except Exception as err:  # pragma: no cover
        info["jax_error"] = repr(err)
    for pkg in ("pybullet", "gym", "mujoco", "mujoco-warp"):
        try:
            from importlib import metadata
            info[pkg] = metadata.version(pkg)
        except Exception:
            info[pkg] = None
    return info



def time_pybullet(name: str, procs: int, env_kwargs: Sequence[Mapping[str, Any]], action_size: int,
                  seconds: float, resolution: int, seed: int = 0, warmup: int = 10,
                  meta: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Frames/s of `procs` PyBullet processes (`ProcessVecEnv`, auto-reset) stepping with random
    actions and rendering every step, over `seconds` after `warmup` steps. `meta` goes into the
    result after the process count (e.g. the versions the processes simulate)."""
    from pybullet_compat.vector import ProcessVecEnv

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    venv = ProcessVecEnv(name, procs, resolution=resolution, render=True, env_kwargs=list(env_kwargs))
    start_s = time.perf_counter() - t0
    try:
        venv.reset(seeds=list(range(procs)))
        for _ in range(warmup):
            venv.step(rng.uniform(-1, 1, (procs, action_size)))
        steps, episodes, t0 = 0, 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            frames, states, _, term, trunc, _ = venv.step(rng.uniform(-1, 1, (procs, action_size)))
            steps += 1
            episodes += int((term | trunc).sum())
        wall = time.perf_counter() - t0
    finally:
        venv.close()
    assert frames.shape == (procs, resolution, resolution, 3) and frames.dtype == np.uint8
    return {"env": name, "processes": procs, **(meta or {}), "vector_steps": steps, "wall_s": wall,
            "start_s": start_s, "episodes_ended": episodes, "frames_per_s": procs * steps / wall,
            "frames_per_s_per_process": steps / wall, "state_dim": int(states.shape[1]),
            "pixels_mean": float(frames.mean())}


def time_bulbjax(name: str, worlds: int, action_size: int, steps: int, repeats: int, resolution: int,
                 seed: int = 0, meta: Mapping[str, Any] | None = None, **make_kwargs: Any) -> dict[str, Any]:
    """Frames/s of one bulbjax env of `worlds` worlds (`bulbjax.make(name, ..., **make_kwargs)`,
    rendering on): `steps` random-action steps in one jitted scan, median of `repeats` calls
    after compiling and one untimed call. `meta` goes into the result after the world count."""
    import jax

    import bulbjax

    t0 = time.perf_counter()
    env = bulbjax.make(name, num_envs=worlds, resolution=resolution, render=True, **make_kwargs)
    make_s = time.perf_counter() - t0

    @jax.jit
    def rollout(state: Any, key: jax.Array) -> tuple[Any, jax.Array]:
        def body(carry, _):
            st, k = carry
            k, ka = jax.random.split(k)
            return (env.step(st, jax.random.uniform(ka, (worlds, action_size), minval=-1.0, maxval=1.0)), k), None
        return jax.lax.scan(body, (state, key), None, length=steps)[0]

    key = jax.random.PRNGKey(seed)
    t0 = time.perf_counter()
    state = jax.block_until_ready(jax.jit(env.reset)(key))
    reset_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    compiled = rollout.lower(state, key).compile()
    compile_s = time.perf_counter() - t0
    state, key = jax.block_until_ready(compiled(state, key))
    calls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        state, key = jax.block_until_ready(compiled(state, key))
        calls.append(time.perf_counter() - t0)
    med = statistics.median(calls)
    px = np.asarray(state.pixels)
    return {"env": name, "worlds": worlds, **(meta or {}), "steps": steps, "repeats": repeats, "make_s": make_s,
            "first_reset_s": reset_s, "compile_s": compile_s, "call_s": calls, "median_call_s": med,
            "frames_per_s": worlds * steps / med, "frames_per_s_best": worlds * steps / min(calls),
            "state_dim": int(state.lowdim.shape[1]), "pixels_mean": float(px.mean()),
            "finite_worlds": int(np.isfinite(np.asarray(state.lowdim)).all(1).sum())}


def parse_reset_chunks(text: str, flag: str = "--reset-chunk") -> tuple[int | None, ...]:
    """`--reset-chunk` values: comma-separated worlds per reset chunk in `step`, "default" for the
    domain's default, 0 for the full-batch reset (the path before chunks): "default,0" times
    both in one run. Also `--reset-pool`'s values (`flag`): the pool's size as a multiple of the
    worlds, "default" the domain's, 0 no pool (the chunked resets)."""
    out = []
    for part in text.split(","):
        part = part.strip()
        if part == "default":
            out.append(None)
        elif part.isdigit():
            out.append(int(part))
        else:
            raise ValueError(f"{flag} takes 'default' or integers >= 0 (comma-separated), got {part!r}")
    return tuple(out)


def measure_env(name: str, procs: int, worlds: Sequence[int], pybullet: Callable[[], dict[str, Any]] | None,
                bulbjax: Callable[[int], dict[str, Any]] | None) -> dict[str, Any]:
    """One table row: PyBullet (`pybullet()`, unless None), bulbjax at each world count
    (`bulbjax(w)`, unless None), a failing case recorded with its error; the ratio of the best
    bulbjax batch to PyBullet."""
    row: dict[str, Any] = {"env": name}
    if pybullet is not None:
        try:
            row["pybullet"] = pybullet()
            log(f"{name}: PyBullet {procs} processes: {row['pybullet']['frames_per_s']:,.0f} frames/s")
        except Exception as err:
            row["pybullet_error"] = repr(err)
            log(f"{name}: PyBullet failed: {err!r}")
    if bulbjax is not None:
        row["bulbjax"] = []
        for w in worlds:
            try:
                r = bulbjax(w)
                row["bulbjax"].append(r)
                # which reset path the row timed (None: the domain's default)
                chunk, pool = r.get("reset_chunk"), r.get("reset_pool")
                log(f"{name}: bulbjax {w} worlds, reset_chunk {'default' if chunk is None else chunk}, "
                    f"reset_pool {'default' if pool is None else pool}: {r['frames_per_s']:,.0f} frames/s "
                    f"(compile {r['compile_s']:.0f} s)")
            except Exception as err:
                row["bulbjax"].append({"worlds": w, "error": repr(err)})
                log(f"{name}: bulbjax {w} worlds failed: {err!r}")
    ok = [r for r in row.get("bulbjax", []) if "frames_per_s" in r]
    if ok and "pybullet" in row:
        best = max(ok, key=lambda r: r["frames_per_s"])
        row["ratio_best_bulbjax_to_pybullet"] = best["frames_per_s"] / row["pybullet"]["frames_per_s"]
        row["best_worlds"] = best["worlds"]
        log(f"{name}: ratio bulbjax/PyBullet = {row['ratio_best_bulbjax_to_pybullet']:.3g}x")
    return row


def print_table(results: dict[str, Any]) -> None:
    """Markdown table of `results['rows']` (from `measure_env`)."""
    procs = results["settings"]["procs"]
    print(f"\n| env | PyBullet, {procs} processes (frames/s) | bulbjax (worlds: frames/s) | ratio |")
    print("|---|---|---|---|")
    for row in results["rows"]:
        pb = f"{row['pybullet']['frames_per_s']:,.0f}" if "pybullet" in row else row.get("pybullet_error", "-")
        bj = ", ".join(f"{r['worlds']}: {r['frames_per_s']:,.0f}" for r in row.get("bulbjax", []) if "frames_per_s" in r)
        ratio = row.get("ratio_best_bulbjax_to_pybullet")
        rc, rp = row.get("reset_chunk"), row.get("reset_pool")
        env = row["env"] + (f" (reset chunk {rc})" if rc is not None else "") + (
            f" (reset pool {rp})" if rp is not None else "")
        print(f"| {env} | {pb} | {bj or row.get('bulbjax_error', '-')} | {f'{ratio:.3g}x' if ratio else '-'} |")


def measure_rows(results: dict[str, Any], s: Any, prefix: str,
                 pybullet: Callable[[str, Any], dict[str, Any]],
                 bulbjax: Callable[[str, int, Any, int | None, int | None], dict[str, Any]]) -> None:
    """One `measure_env` row per environment of `s.envs` and reset path (each of `s.reset_chunks`
    with each of `s.reset_pools`; PyBullet only with the first: it has one reset), appended to
    `results["rows"]` and saved after each (`save_progress`). `s`: a family bench's settings
    (envs, procs, worlds, reset_chunks, reset_pools, skip_pybullet, skip_bulbjax, out)."""
    paths = [(rc, rp) for rc in s.reset_chunks for rp in s.reset_pools]
    for name in s.envs:
        for i, (rc, rp) in enumerate(paths):
            row = measure_env(name, s.procs, s.worlds,
                              None if s.skip_pybullet or i else (lambda: pybullet(name, s)),
                              None if s.skip_bulbjax else (lambda w: bulbjax(name, w, s, rc, rp)))
            results["rows"].append({**row, "reset_chunk": rc, "reset_pool": rp})
            save_progress(results, s.out, prefix)
        if getattr(s, "raw_warp", False) and not s.skip_bulbjax:
            raw_rows(results, s, name)
            save_progress(results, s.out, prefix)


def raw_rows(results: dict[str, Any], s: Any, name: str) -> None:
    """The raw MuJoCo Warp probe (`raw_warp.probe`: step + render of env `name`'s scene, no JAX,
    no resets) at each of `s.worlds`, in `results["raw_warp"]`, with each bulbjax row's rate as
    a share of it (`share_of_raw`)."""
    from raw_warp import probe

    for w in s.worlds:
        try:
            r = probe(name, w, steps=s.steps, repeats=s.repeats, resolution=s.resolution,
                      version=s.mjx_version, ycb_dir=s.ycb_dir)
        except Exception as err:
            results.setdefault("raw_warp", []).append({"env": name, "worlds": w, "error": repr(err)})
            log(f"{name}: raw Warp probe at {w} worlds failed: {err!r}")
            continue
        results.setdefault("raw_warp", []).append(r)
        log(f"{name}: raw MuJoCo Warp step + render, {w} worlds: {r['frames_per_s']:,.0f} frames/s")
        for row in results["rows"]:
            for b in row.get("bulbjax", []) if row["env"] == name else []:
                if b.get("worlds") == w and "frames_per_s" in b:
                    b["share_of_raw"] = b["frames_per_s"] / r["frames_per_s"]
                    log(f"{name}: bulbjax {w} worlds (reset chunk {row.get('reset_chunk')}, pool "
                        f"{row.get('reset_pool')}) = {b['share_of_raw']:.2f}x the raw probe")


def save_progress(results: dict[str, Any], out: str, prefix: str) -> None:
    """`<out>/<prefix>_latest.json` after each row, so a call cut short (a device time limit)
    keeps the rows it measured; `write` gives the final, timestamped file."""
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, f"{prefix}_latest.json"), "w") as f:
        json.dump(results, f, indent=1, default=str)


def write(results: dict[str, Any], out: str, prefix: str) -> str:
    """`<out>/<prefix>_<device>_<stamp>.json` and `<out>/<prefix>_latest.json`; returns the first."""
    os.makedirs(out, exist_ok=True)
    dev = str(results["device"].get("device", "cpu")).lower()
    slug = "".join(c if c.isalnum() else "_" for c in dev).strip("_") or "cpu"
    path = os.path.join(out, f"{prefix}_{slug}_{time.strftime('%Y%m%d_%H%M%S')}.json")
    for p in (path, os.path.join(out, f"{prefix}_latest.json")):
        with open(p, "w") as f:
            json.dump(results, f, indent=1, default=str)
    log(f"wrote {path}")
    return path
