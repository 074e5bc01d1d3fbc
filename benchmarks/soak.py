"""Soak every registered environment: many worlds, random actions, millions of steps, counting
what went non-finite.

For each environment (default: all registered names, the multicolour variants included;
`--envs` picks some), `--worlds` worlds (default 4,096) step with uniform random actions
(continuous: U[-1, 1]; discrete: uniform over the actions) for at least `--steps` env steps in
all (default 1 M; `--long-steps`, default 10 M, for CartPole, InvertedPendulum, HalfCheetah and
Ant and their multicolour variants). Physics only (`render=False`) unless `--render`; domains
with object versions draw one per world and episode (`version="random"`), so every block and
object configuration is stepped. The steps run in jitted `lax.scan` chunks of `--chunk` steps.

Per environment it reports (from `EnvState.counts`, see `MjxPixelEnv.step`): worlds reset because
their physics went non-finite, the non-finite entries seen in them (qpos, qvel, state, reward),
and the chunks in which that happened; episodes ended (terminated / truncated); non-finite
entries that *leaked* into a returned state (obs, qpos, qvel: must be 0, it is the guarantee
`step` gives); action entries repaired (must be 0: the actions are in range); steps, compile time,
wall time and steps per second. One line per chunk at most every `--print-every` seconds and one
per environment: never silent for minutes.

Results go to `<out-dir>/soak_<device>[_gpu<I>]_<timestamp>.json`, rewritten after every
environment (a run cut short keeps what it had). An environment that cannot be built (e.g. the
YCB models are not installed) is recorded as skipped with the reason, and the soak goes on.

Each environment runs in a child process of its own (its console lines pass through): a Warp
error in one (a failed build, or the "Warp error: unknown stream" that FrankaRearrangeYcb met
after FrankaRearrangeOneGeom had run in the same process) cannot break the next, and is recorded
as that environment's failure (exit status and the child's last lines). `--in-process` runs them
all in this process instead.

Two GPUs, two processes (the 24 names split between them):
  python benchmarks/soak.py --device-index 0 --envs CartPole,...  &
  python benchmarks/soak.py --device-index 1 --envs Ant,...
`--device-index I` makes this process see only GPU I (CUDA_VISIBLE_DEVICES, set before JAX and
Warp start). `--list` prints the names and the steps each gets.

CPU smoke run (what tests/test_soak.py runs): python benchmarks/soak.py --small
(`--small`: 8 worlds, 400 steps in all, CartPole and InvertedPendulum unless --envs is given.)
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import re
import sys
import time
from typing import Any, Sequence

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
sys.path.insert(0, REPO)  # this working tree's bulbjax, not an installed copy

LONG = ("CartPole", "InvertedPendulum", "HalfCheetah", "Ant")  # 10 M steps each (and their variants)
SMALL = dict(worlds=8, steps=400, long_steps=400, chunk=25, envs=("CartPole", "InvertedPendulum"))


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--envs", default=None, help="comma-separated names (default: every registered name)")
    ap.add_argument("--worlds", type=int, default=None, help="worlds per environment (default 4096)")
    ap.add_argument("--steps", type=int, default=None, help="env steps per environment, all worlds (default 1e6)")
    ap.add_argument("--long-steps", type=int, default=None,
                    help=f"env steps for {', '.join(LONG)} and their variants (default 1e7)")
    ap.add_argument("--chunk", type=int, default=None, help="steps per world in one jitted call (default 250)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--render", action="store_true", help="render 64x64 frames every step too (slower)")
    ap.add_argument("--device-index", type=int, default=None, metavar="I",
                    help="use GPU I only (sets CUDA_VISIBLE_DEVICES before JAX starts)")
    ap.add_argument("--small", action="store_true",
                    help="CPU smoke sizes: 8 worlds, 400 steps, CartPole and InvertedPendulum (flags given win)")
    ap.add_argument("--print-every", type=float, default=20.0, help="seconds between progress lines (default 20)")
    ap.add_argument("--out-dir", default=os.path.join(HERE, "results"))
    ap.add_argument("--tag", default="", help="added to the file name")
    ap.add_argument("--list", action="store_true", help="print the environments and their step counts, then exit")
    ap.add_argument("--in-process", action="store_true",
                    help="every environment in this process (default: one child process per environment)")
    ap.add_argument("--child-json", default=None, help=argparse.SUPPRESS)  # a child: soak --envs, write its record
    a = ap.parse_args(argv)
    base = SMALL if a.small else dict(worlds=4096, steps=1_000_000, long_steps=10_000_000, chunk=250, envs=None)
    for k in ("worlds", "steps", "long_steps", "chunk"):
        if getattr(a, k) is None:
            setattr(a, k, base[k])
    if a.envs is None and base["envs"] is not None:
        a.envs = ",".join(base["envs"])
    for flag, v, least in (("--worlds", a.worlds, 1), ("--steps", a.steps, 1), ("--long-steps", a.long_steps, 1),
                           ("--chunk", a.chunk, 1), ("--seed", a.seed, 0), ("--device-index", a.device_index, 0)):
        if v is not None and v < least:
            ap.error(f"{flag} must be >= {least}, got {v}")
    return a


def steps_for(name: str, a: argparse.Namespace) -> int:
    base = name[: -len("Multicolour")] if name.endswith("Multicolour") else name
    return a.long_steps if base in LONG else a.steps


def device_slug(kind: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", kind.lower()).strip("_") or "unknown"


def make_chunk(env: Any, chunk: int):
    """A jitted `(state, key) -> (state, stats)`: `chunk` steps of every world under uniform random
    actions, with the episodes ended and the non-finite entries that leaked into returned states."""
    import jax
    import jax.numpy as jnp

    def act(k):
        if env.discrete:
            return jax.random.randint(k, (env.num_envs,), 0, env.num_actions, jnp.int32)
        return jax.random.uniform(k, (env.num_envs, env.action_size), minval=-1.0, maxval=1.0)

    def leaked(s) -> jax.Array:
        bad = lambda x: (~jnp.isfinite(x)).sum(dtype=jnp.int32)  # noqa: E731
        return bad(s.obs) + bad(s.data.qpos) + bad(s.data.qvel)

    versions = max(int(env.num_versions), 1)

    def body(carry, k):
        s, done, trunc, leak, by_version = carry
        version = s.params.get("version", jnp.zeros(env.num_envs, jnp.int32))  # of the episode stepped
        before = s.counts["nonfinite_resets"]
        s = env.step(s, act(k))
        new = s.counts["nonfinite_resets"] - before
        by_version = by_version + jax.ops.segment_sum(new, version, num_segments=versions)
        return (s, done + s.done.sum().astype(jnp.int32), trunc + s.truncated.sum().astype(jnp.int32),
                leak + leaked(s), by_version), None

    def run(state, key):
        z = jnp.zeros((), jnp.int32)
        carry = (state, z, z, z, jnp.zeros(versions, jnp.int32))
        (state, done, trunc, leak, by_version), _ = jax.lax.scan(body, carry, jax.random.split(key, chunk))
        return state, {"episodes": done, "truncated": trunc, "leaked": leak, "by_version": by_version,
                       **{k: v.sum() for k, v in state.counts.items()}}

    return jax.jit(run, donate_argnums=0)


def soak_one(name: str, a: argparse.Namespace, log) -> dict[str, Any]:
    """Soak one environment; its record (or the reason it was skipped)."""
    import jax
    import numpy as np

    import bulbjax
    from bulbjax.envs.registry import env_class

    target = steps_for(name, a)
    per_world = max(1, math.ceil(target / a.worlds))
    chunk = min(a.chunk, per_world)
    chunks = math.ceil(per_world / chunk)
    rec: dict[str, Any] = {"env": name, "worlds": a.worlds, "steps_per_world": chunks * chunk,
                           "steps": chunks * chunk * a.worlds, "chunk": chunk, "target_steps": target}
    t0 = time.perf_counter()
    try:
        version = "random" if env_class(name).num_versions else 0
        env = bulbjax.make(name, num_envs=a.worlds, render=a.render, version=version)
    except Exception as err:  # noqa: BLE001  e.g. YCB models missing: recorded, the soak goes on
        rec.update(skipped=f"{type(err).__name__}: {err}".splitlines()[0][:300])
        log(f"{name:<28} skipped: {rec['skipped']}")
        return rec
    rec["version"] = version
    key = jax.random.PRNGKey(a.seed)
    k_reset, key = jax.random.split(key)
    reset = jax.jit(env.reset)
    run = make_chunk(env, chunk)
    state = reset(k_reset)
    compiled = run.lower(state, key).compile()
    jax.block_until_ready(state)
    # non-finite entries in the first reset's state (the resets inside `step` are in `leaked`)
    rec["reset_nonfinite"] = int(sum((~np.isfinite(np.asarray(x))).sum()
                                     for x in (state.obs, state.data.qpos, state.data.qvel)))
    rec["build_compile_s"] = round(time.perf_counter() - t0, 2)
    totals = {"episodes": 0, "truncated": 0, "leaked": 0}
    by_version = np.zeros(max(int(env.num_versions), 1), np.int64)  # non-finite resets per object version
    events: list[list[int]] = []  # [chunk, worlds reset for non-finite physics in it]
    prev_resets, t_run, t_print = 0, time.perf_counter(), time.perf_counter()
    for c in range(chunks):
        key, k = jax.random.split(key)
        state, stats = compiled(state, k)
        stats = jax.device_get(stats)
        by_version += np.asarray(stats.pop("by_version"), np.int64)
        stats = {k: int(v) for k, v in stats.items()}
        for k in totals:
            totals[k] += stats[k]
        if stats["nonfinite_resets"] > prev_resets and len(events) < 200:
            events.append([c, stats["nonfinite_resets"] - prev_resets])
        prev_resets = stats["nonfinite_resets"]
        now = time.perf_counter()
        if now - t_print >= a.print_every and c + 1 < chunks:
            done = (c + 1) * chunk * a.worlds
            log(f"  {name}: {done:,} / {rec['steps']:,} steps, {done / (now - t_run):,.1f} "
                f"steps/s, non-finite resets so far {prev_resets}")
            t_print = now
    run_s = time.perf_counter() - t_run
    per_world_counts = {k: jax.device_get(v) for k, v in state.counts.items()}
    rec.update(
        nonfinite_resets=int(per_world_counts["nonfinite_resets"].sum()),
        nonfinite_entries=int(per_world_counts["nonfinite_entries"].sum()),
        nonfinite_worlds=int((per_world_counts["nonfinite_resets"] > 0).sum()),
        nonfinite_max_per_world=int(per_world_counts["nonfinite_resets"].max()),
        nonfinite_events=events,
        **({"nonfinite_by_version": by_version.tolist()} if env.num_versions else {}),
        actions_fixed=int(per_world_counts["actions_fixed"].sum()),
        episodes=totals["episodes"], truncated=totals["truncated"],
        terminated=totals["episodes"] - totals["truncated"], leaked_nonfinite=totals["leaked"],
        run_s=round(run_s, 3), wall_s=round(time.perf_counter() - t0, 2),
        steps_per_s=round(rec["steps"] / run_s, 1) if run_s > 0 else None)
    log(f"{name:<28} {rec['steps']:>12,} steps  {rec['steps_per_s'] or 0:>12,.1f} steps/s  episodes "
        f"{rec['episodes']:>9,}  non-finite resets {rec['nonfinite_resets']:>6} ({rec['nonfinite_entries']} "
        f"entries, {rec['nonfinite_worlds']} worlds)  leaked {rec['leaked_nonfinite']}  "
        f"compile {rec['build_compile_s']:.1f} s  wall {rec['wall_s']:.1f} s")
    return rec


def child_argv(name: str, a: argparse.Namespace, record: str) -> list[str]:
    """This script's command line for one environment in a child (sizes as given here; the
    child inherits CUDA_VISIBLE_DEVICES, so no --device-index)."""
    argv = [sys.executable, os.path.abspath(__file__), "--envs", name, "--worlds", str(a.worlds),
            "--steps", str(a.steps), "--long-steps", str(a.long_steps), "--chunk", str(a.chunk),
            "--seed", str(a.seed), "--print-every", str(a.print_every), "--child-json", record]
    return argv + (["--render"] if a.render else [])


def soak_in_child(name: str, a: argparse.Namespace, path: str, log) -> dict[str, Any]:
    """`soak_one` of `name` in a child process, its console lines passed through; a child that
    dies without its record is this environment's failure (exit status, last lines)."""
    import collections
    import subprocess

    record = f"{path}.{name}.child.json"
    tail: collections.deque[str] = collections.deque(maxlen=20)
    t0 = time.perf_counter()
    with subprocess.Popen(child_argv(name, a, record), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, bufsize=1) as p:
        for line in p.stdout:
            line = line.rstrip("\n")
            tail.append(line)
            if not line.startswith(("Warning: EPA horizon", "To disable the print warning")):
                log(line)
        rc = p.wait()
    if rc == 0 and os.path.exists(record):
        with open(record) as f:
            rec = json.load(f)
        os.remove(record)
        return rec
    log(f"{name:<28} FAILED in its child process (exit {rc}); the soak goes on")
    return {"env": name, "failed": f"exit {rc}", "last_lines": list(tail), "wall_s": round(time.perf_counter() - t0, 2)}


def device_kind_in_child() -> tuple[str, str]:
    """The first JAX device's kind and platform, asked in a short child process, so that this
    process never starts a GPU client (it would take the memory the soak's children need)."""
    import subprocess

    code = "import jax; d = jax.devices()[0]; print(getattr(d, 'device_kind', d.platform)); print(d.platform)"
    env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    lines = r.stdout.strip().splitlines()
    return (lines[-2], lines[-1]) if r.returncode == 0 and len(lines) >= 2 else ("unknown", "unknown")


def write_json(path: str, obj: Any) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=1)
    os.replace(tmp, path)


def main(argv: Sequence[str] | None = None) -> int:
    a = parse_args(argv)
    if a.device_index is not None:  # before JAX or Warp look at the GPUs
        if "jax" in sys.modules and os.environ.get("CUDA_VISIBLE_DEVICES") != str(a.device_index):
            print("soak: --device-index must be given before JAX starts (run the script, don't import it)",
                  file=sys.stderr)
            return 2
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        ids = [x for x in visible.split(",") if x.strip()] if visible else None
        if ids is not None and a.device_index >= len(ids):
            print(f"soak: --device-index {a.device_index}, but CUDA_VISIBLE_DEVICES={visible}", file=sys.stderr)
            return 2
        os.environ["CUDA_VISIBLE_DEVICES"] = ids[a.device_index] if ids is not None else str(a.device_index)

    import jax

    from bulbjax.envs.registry import env_names

    known = env_names()
    names = [x.strip() for x in a.envs.split(",") if x.strip()] if a.envs else known
    unknown = [n for n in names if n not in known]
    if unknown:
        print(f"soak: unknown environments {unknown}; registered: {', '.join(known)}", file=sys.stderr)
        return 2
    if a.list:
        for n in names:
            print(f"{n:<28} {steps_for(n, a):>12,} steps")
        return 0
    if a.child_json:  # one environment, its record to the parent
        write_json(a.child_json, soak_one(names[0], a, lambda msg: print(msg, flush=True)))
        return 0
    isolate = not a.in_process
    if isolate:  # the parent leaves the GPU to its children: a short child names the device
        kind, platform = device_kind_in_child()
    else:
        dev = jax.devices()[0]
        kind, platform = getattr(dev, "device_kind", dev.platform), dev.platform
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%d_%H%M%S")
    gpu = f"_gpu{a.device_index}" if a.device_index is not None else ""
    tag = f"_{a.tag}" if a.tag else ""
    os.makedirs(a.out_dir, exist_ok=True)
    path = os.path.join(a.out_dir, f"soak_{device_slug(kind)}{gpu}{tag}_{stamp}.json")
    log = lambda msg: print(msg, flush=True)  # noqa: E731
    out: dict[str, Any] = {
        "what": "benchmarks/soak.py: random actions, counts of non-finite physics (EnvState.counts)",
        "argv": sys.argv[1:] if argv is None else list(argv), "device": {"kind": kind, "platform": platform,
                                                                          "index": a.device_index},
        "jax": jax.__version__, "worlds": a.worlds, "render": a.render, "seed": a.seed,
        "started": stamp, "isolated": isolate, "envs": []}
    log(f"soak: {len(names)} environments, {a.worlds} worlds, {a.steps:,} steps ({a.long_steps:,} for "
        f"{', '.join(LONG)}), {'rendered' if a.render else 'physics only'}, on {kind}; results: {path}")
    for n in names:
        out["envs"].append(soak_in_child(n, a, path, log) if isolate else soak_one(n, a, log))
        write_json(path, out)
    ran = [r for r in out["envs"] if "skipped" not in r and "failed" not in r]
    out["summary"] = {"envs": len(ran), "skipped": [r["env"] for r in out["envs"] if "skipped" in r],
                      "failed": [r["env"] for r in out["envs"] if "failed" in r],
                      "steps": sum(r["steps"] for r in ran),
                      "nonfinite_resets": sum(r["nonfinite_resets"] for r in ran),
                      "with_nonfinite": [r["env"] for r in ran if r["nonfinite_resets"]],
                      "leaked_nonfinite": sum(r["leaked_nonfinite"] + r["reset_nonfinite"] for r in ran)}
    write_json(path, out)
    s = out["summary"]
    log(f"soak done: {s['envs']} environments, {s['steps']:,} steps, {s['nonfinite_resets']} non-finite resets "
        f"({', '.join(s['with_nonfinite']) or 'none'}), leaked {s['leaked_nonfinite']}, skipped "
        f"{', '.join(s['skipped']) or 'none'}, failed {', '.join(s['failed']) or 'none'}; {path}")
    return 1 if s["leaked_nonfinite"] or s["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
