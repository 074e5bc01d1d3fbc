"""Where an Incline env step's time goes, against raw MuJoCo Warp on the same scene (issue 39).

The Incline with the reset pool renders at about a third of `benchmarks/raw_warp.py`'s probe (step
+ BVH refit + render, no resets, no JAX). This splits one env step of `--worlds` worlds, each part
timed in the same process on the same device, every one as a jitted `lax.scan` of `--steps` steps
(median of `--repeats` calls after a compiling one), in this order:

* `full`: `env.step` with random pushes and rendering, as `bench_incline.py` times it;
* `raw`: the raw Warp probe of the same scene and world count (`raw_warp.probe`);
* `raw_pushed`: the raw probe under the env's workload (`probe(..., pushed=True)`: each world's
  slope, its object pushed by a held force in bulb's range, every launch of 16 steps from the
  reset state), the ceiling of the episodes' physics and render without JAX and without falls;
* `physics`: `env.physics` alone in a scan (the Warp steps and kinematics; no reward, resets,
  selects or frames);
* `refill`: one pool refill alone (`resets.make_pool` for the pool's f x N keys: bulb's settle of
  f x N fresh worlds), and how many refills the `full` scan made (episodes ended per step);
* `no_render`: `full` with `render=False` (physics, the pose pass, auto-reset, the pool);
* `full_forward`: `full` with MJX's full forward pass after resets instead of the kinematics pass
  (`env._poses`: what `step` ran before; the same episodes and frames), for the change's effect;
* with `--graph-modes`: `physics` and `full` again under each of those `EnvConfig.graph_mode`
  values (MJX's default is "warp": a Warp-captured CUDA graph per call and buffer addresses).

With `--trace DIR`, one more call of `full` and of `physics` is traced (JAX profiler) and each
trace's summary (`trace_summary.summarise`: kernels and copies, GPU busy time and launches per
step) goes into the JSON.

It prints the per-step milliseconds of each and what they imply (render share, refill share,
physics as JAX runs it, the rest: the wrapper's selects, state and reward), and writes
`benchmarks/results/incline_gap_<env>_<device>_<stamp>.json` after every part, so that a run
stopped by a time limit keeps what it measured (the whole takes ~6 min on an H100 at 4,096 worlds).

    python benchmarks/diagnostics/incline_gap.py --env GeomOnIncline --worlds 4096      # GPU
    python benchmarks/diagnostics/incline_gap.py --env GeomOnIncline --worlds 4096 --parts full,physics \
        --graph-modes jax,warp_staged                                                     # graph modes alone
    python benchmarks/diagnostics/incline_gap.py --env GeomOnIncline --parts full,physics --trace /tmp/t  # profile
    python benchmarks/diagnostics/incline_gap.py --small                                # CPU smoke test
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(os.path.dirname(HERE)))
sys.path.insert(0, os.path.dirname(HERE))

from timing import time_fn  # noqa: E402  (first call, then median of repeats)


PARTS = ("full", "raw", "raw_pushed", "physics", "refill", "no_render", "full_forward")
PUSHED_STEPS = 16  # raw_pushed: about an Incline episode under random pushes (13-21 steps)


def scan_random_pushes(fn: Any, carry: Any, worlds: int, size: int, steps: int, repeats: int,
                       trace: str = "") -> tuple[dict[str, float], list[int]]:
    """Time a jitted scan of `steps` applications of `fn(carry, action) -> (carry, ended)` under
    uniform random pushes `[worlds, size]`, continued from call to call (`time_fn`: a compiling
    call, then the median of `repeats`); also the summed `ended` of each timed call. `trace`: a
    folder to write a JAX profiler trace of one more call to (its kernels and copies)."""
    import jax
    import jax.numpy as jnp

    @jax.jit
    def rollout(carry, key):
        def body(c, _):
            x, k = c
            k, ka = jax.random.split(k)
            x, ended = fn(x, jax.random.uniform(ka, (worlds, size), minval=-1.0, maxval=1.0))
            return (x, k), ended
        (carry, key), ended = jax.lax.scan(body, (carry, key), None, length=steps)
        return carry, key, jnp.sum(ended)

    box = {"carry": carry, "key": jax.random.PRNGKey(1), "ended": []}

    def call():
        box["carry"], box["key"], ended = rollout(box["carry"], box["key"])
        box["ended"].append(ended)
        return box["carry"]

    timing = time_fn(call, repeats)
    if trace:
        with jax.profiler.trace(trace):
            jax.block_until_ready(call())
    return timing, [int(e) for e in box["ended"][1:1 + repeats]]


def trace_summary_of(folder: str, steps: int) -> dict[str, Any]:
    """`trace_summary.summarise_dir` of the trace written under `folder`, with each device's busy
    time, launches and copies per env step (the copies: kernels named Memcpy/Memset)."""
    import trace_summary

    try:
        res = trace_summary.summarise_dir(folder, top=25)
    except FileNotFoundError as err:
        return {"error": str(err)}
    for dev in res["devices"].values():
        streams = dev["lines"].get("streams", {"top": []})["top"]
        copies = [t for t in streams if "Memcpy" in t["name"] or "Memset" in t["name"]]
        dev["per_step"] = {"busy_ms": dev["busy_ms"] / steps, "span_ms": dev["span_ms"] / steps,
                           "launches": dev["kernel_launches"] / steps,
                           "copies_ms": sum(t["ms"] for t in copies) / steps,
                           "copies": sum(t["count"] for t in copies) / steps}
    return res


def step_scan(name: str, worlds: int, steps: int, repeats: int, render: bool, resolution: int,
              forward: bool = False, graph_mode: str | None = None, trace: str = "") -> dict[str, Any]:
    """Median seconds of `steps` random-push env steps in one jitted scan, and the episodes that
    ended in them; `forward`: with MJX's full forward pass after resets (as for a moving camera)."""
    import jax

    import bulbjax

    env = bulbjax.make(name, num_envs=worlds, resolution=resolution, render=render, graph_mode=graph_mode)
    if forward:
        env._pose_pass = "forward"
    state = jax.block_until_ready(jax.jit(env.reset)(jax.random.PRNGKey(0)))

    def step(st, action):
        st = env.step(st, action)
        return st, st.done.sum()

    t, ended = scan_random_pushes(step, state, worlds, env.action_size, steps, repeats, trace)
    first, med = t["first_s"], t["median_s"]
    extra = {"trace": trace_summary_of(trace, steps)} if trace else {}
    return {**extra, "render": render, "pose_pass": env._pose_pass, "graph_mode": graph_mode, "first_call_s": first,
            "call_s": med, "ms_per_step": 1e3 * med / steps,
            "frames_per_s": worlds * steps / med, "ended_per_step": statistics.median(ended) / steps,
            "reset_pool": int(env.reset_pool), "frame_skip": int(getattr(env, "frame_skip", 1))}


def physics_scan(name: str, worlds: int, steps: int, repeats: int, resolution: int,
                 graph_mode: str | None = None, trace: str = "") -> dict[str, Any]:
    """Median seconds of `steps` env steps of physics alone (`env.physics`: `frame_skip` Warp
    steps with the action applied, and the kinematics pass where the domain has one) in one jitted
    scan from a reset, no reward, resets or frames: the Warp calls' share of the step, as JAX
    runs them."""
    import jax

    import bulbjax

    env = bulbjax.make(name, num_envs=worlds, resolution=resolution, render=False, graph_mode=graph_mode)
    state0 = jax.block_until_ready(jax.jit(env.reset)(jax.random.PRNGKey(0)))
    params = state0.params  # the worlds' physical parameters (the Incline's slope)
    t, _ = scan_random_pushes(lambda d, a: (env.physics(d, a, params), 0), state0.data, worlds,
                              env.action_size, steps, repeats, trace)
    extra = {"trace": trace_summary_of(trace, steps)} if trace else {}
    return {**extra, "graph_mode": graph_mode, "first_call_s": t["first_s"], "call_s": t["median_s"],
            "ms_per_step": 1e3 * t["median_s"] / steps}


def refill(name: str, worlds: int, repeats: int, resolution: int) -> dict[str, Any]:
    """Median seconds of one full pool refill (`make_pool` of f x N fresh, settled worlds)."""
    import jax

    import bulbjax
    from bulbjax.envs import resets

    env = bulbjax.make(name, num_envs=worlds, resolution=resolution, render=False)
    jax.block_until_ready(env.reset(jax.random.PRNGKey(0)))
    keys = jax.random.split(jax.random.PRNGKey(2), env.reset_pool * worlds)
    fn = jax.jit(lambda k: resets.make_pool(env, k))
    t = time_fn(lambda: fn(keys), repeats)
    first, med = t["first_s"], t["median_s"]
    return {"entries": int(env.reset_pool * worlds), "first_call_s": first, "call_s": med}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="GeomOnIncline")
    p.add_argument("--worlds", type=int, default=4096)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--skip-raw", action="store_true")
    p.add_argument("--parts", default=",".join(PARTS),
                   help="which of the default graph mode's parts to time, in this order (default all; "
                        "e.g. full,physics before --graph-modes for the modes' comparison alone)")
    p.add_argument("--graph-modes", default="",
                   help="comma-separated EnvConfig.graph_mode values (e.g. jax,warp_staged) to time `physics` "
                        "and `full` under as well, after the parts above (GPU: how MJX-Warp's calls use CUDA graphs)")
    p.add_argument("--trace", default="",
                   help="a folder: also trace one call of `full` and `physics` (JAX profiler) and keep each trace's "
                        "summary (busy time, launches, copies per step; benchmarks/trace_summary.py) in the JSON")
    p.add_argument("--small", action="store_true", help="CPU smoke test: 8 worlds, 3 steps, 2 repeats")
    p.add_argument("--out", default=os.path.join(os.path.dirname(HERE), "results"))
    a = p.parse_args(argv)
    if a.small:
        a.worlds, a.steps, a.repeats = 8, 3, 2
    import jax

    import raw_warp

    out: dict[str, Any] = {"env": a.env, "worlds": a.worlds, "steps": a.steps, "device": str(jax.devices()[0]),
                           "device_kind": jax.devices()[0].device_kind, "jax": jax.__version__}
    os.makedirs(a.out, exist_ok=True)
    kind = out["device_kind"].lower().replace(" ", "_")
    path = os.path.join(a.out, f"incline_gap_{a.env.lower()}_{kind}_{time.strftime('%Y%m%d_%H%M%S')}.json")

    def save() -> None:
        """Write what is measured so far (each part is minutes on a GPU: a run stopped by a time
        limit keeps the parts it finished)."""
        with open(path, "w") as fh:
            json.dump(out, fh, indent=1)

    parts = [x for x in a.parts.split(",") if x]
    bad = sorted(set(parts) - set(PARTS))
    if bad:
        p.error(f"--parts: unknown {bad}; choose from {','.join(PARTS)}")
    if "full" in parts:
        out["full"] = step_scan(a.env, a.worlds, a.steps, a.repeats, True, a.resolution,
                                trace=os.path.join(a.trace, "full") if a.trace else "")
        save()
        print(f"full step + render: {out['full']['ms_per_step']:.3f} ms/step, {out['full']['frames_per_s']:,.0f} frames/s, "
              f"{out['full']['ended_per_step']:.1f} episodes ended per step", flush=True)
    if "raw" in parts and not a.skip_raw:
        raw = raw_warp.probe(a.env, a.worlds, steps=a.steps, repeats=a.repeats, resolution=a.resolution)
        out["raw"] = {**raw, "ms_per_step": 1e3 * raw["call_s"] / a.steps}
        save()
        print(f"raw Warp step + render: {out['raw']['ms_per_step']:.3f} ms/step, {raw['frames_per_s']:,.0f} frames/s",
              flush=True)
    if "raw_pushed" in parts and not a.skip_raw:
        raw = raw_warp.probe(a.env, a.worlds, steps=PUSHED_STEPS, repeats=a.repeats, resolution=a.resolution,
                             pushed=True)
        out["raw_pushed"] = {**raw, "ms_per_step": 1e3 * raw["call_s"] / PUSHED_STEPS}
        save()
        print(f"raw Warp step + render, pushed: {out['raw_pushed']['ms_per_step']:.3f} ms/step, "
              f"{raw['frames_per_s']:,.0f} frames/s", flush=True)
    if "physics" in parts:
        out["physics"] = physics_scan(a.env, a.worlds, a.steps, a.repeats, a.resolution,
                                      trace=os.path.join(a.trace, "physics") if a.trace else "")
        save()
        print(f"physics alone (env.physics): {out['physics']['ms_per_step']:.3f} ms/step", flush=True)
    if "refill" in parts and "full" in out:
        out["refill"] = refill(a.env, a.worlds, a.repeats, a.resolution)
        per_step = out["full"]["ended_per_step"] / max(out["refill"]["entries"], 1)  # refills per step, on average
        out["refill"]["per_step"] = per_step
        out["refill"]["ms_per_step"] = 1e3 * out["refill"]["call_s"] * per_step
        save()
        print(f"one refill of {out['refill']['entries']} entries: {1e3 * out['refill']['call_s']:.1f} ms; "
              f"{per_step:.3f} refills per step -> {out['refill']['ms_per_step']:.3f} ms/step", flush=True)
    if "no_render" in parts:
        out["no_render"] = step_scan(a.env, a.worlds, a.steps, a.repeats, False, a.resolution)
        save()
        print(f"step without render: {out['no_render']['ms_per_step']:.3f} ms/step", flush=True)
    if "full_forward" in parts:
        out["full_forward"] = step_scan(a.env, a.worlds, a.steps, a.repeats, True, a.resolution, forward=True)
        print(f"full, forward pass after resets: {out['full_forward']['ms_per_step']:.3f} ms/step, "
              f"{out['full_forward']['frames_per_s']:,.0f} frames/s", flush=True)
    if all(k in out for k in ("full", "no_render", "refill", "physics", "full_forward")):
        f, n, r = out["full"]["ms_per_step"], out["no_render"]["ms_per_step"], out["refill"]["ms_per_step"]
        out["split_ms_per_step"] = {"render (full - no_render)": f - n, "refills": r,
                                    "rest of the step (no_render - refills)": n - r,
                                    "of which physics (env.physics alone)": out["physics"]["ms_per_step"],
                                    "of which the wrapper (no_render - refills - physics)":
                                        n - r - out["physics"]["ms_per_step"],
                                    "kinematics pass's saving (full_forward - full)":
                                        out["full_forward"]["ms_per_step"] - f}
        if "raw" in out:
            out["split_ms_per_step"]["raw step + render"] = out["raw"]["ms_per_step"]
        save()
        for k, v in out["split_ms_per_step"].items():
            print(f"  {k}: {v:.3f} ms/step", flush=True)
    for mode in [m for m in a.graph_modes.split(",") if m]:
        phys = physics_scan(a.env, a.worlds, a.steps, a.repeats, a.resolution, graph_mode=mode)
        full = step_scan(a.env, a.worlds, a.steps, a.repeats, True, a.resolution, graph_mode=mode)
        out.setdefault("by_graph_mode", {})[mode] = {"physics": phys, "full": full}
        save()
        print(f"graph_mode {mode}: physics {phys['ms_per_step']:.3f} ms/step, full {full['ms_per_step']:.3f} ms/step, "
              f"{full['frames_per_s']:,.0f} frames/s", flush=True)
    print(f"wrote {path}")
    return out


if __name__ == "__main__":
    main()
