"""Which multi-GPU forms of MJX-Warp physics and the Warp renderer compile and run (diagnostic,
issue 36): each case in its own subprocess, so a segfault names its case; with `--gdb CASE`
the case runs under cuda-gdb and prints the native backtrace of the crash.

Cases (all on an InvertedPendulum of 8 worlds per device, 2 devices unless said):
  plain        a shard_map program without Warp
  reset_sm     env reset under shard_map over 2 GPUs (the form `Experiment` uses when sharded);
               reset_sm@NONE, reset_sm@WARP_STAGED_EX: the same in another Warp graph mode
  reset_sm1    the same over a 1-device mesh of the second GPU
  reset_pmap   env reset under jax.pmap
  reset_gspmd  env reset under jit with the worlds sharded over 2 GPUs, no shard_map
  reset_each   one jitted reset per GPU, each on its own device, dispatched together
  render_each  reset + render per GPU (a render context per GPU), dispatched together
  epoch_each   a small six-learner Experiment per GPU (init + 2 epochs), dispatched together
  reset_mp     2 processes (jax.distributed on localhost, one GPU each), shard_map reset over
               the global 2-device mesh
  epoch_mp     2 processes as reset_mp, a small six-learner Experiment over the global mesh
               (init + 2 epochs)

    python benchmarks/diagnostics/diag_multigpu.py [CASE ...] [--gdb CASE] [--out results.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
CASES = ("plain", "reset_sm1", "reset_each", "render_each", "reset_pmap", "reset_gspmd", "reset_sm",
         "reset_sm@NONE", "reset_sm@WARP_STAGED_EX", "reset_mp", "epoch_mp", "epoch_each")


def _env(n: int = 8, render: bool = False):
    import bulbjax

    return bulbjax.make("InvertedPendulum", num_envs=n, render=render, render_steps=False)


def case(name: str, rank: int | None = None) -> None:
    sys.path.insert(0, ROOT)
    import jax

    name, _, graph_mode = name.partition("@")
    if graph_mode:  # e.g. reset_sm@NONE: MJX-Warp's calls in another Warp graph mode
        import functools

        from mujoco import mjx
        from warp._src.jax.ffi import JaxCallableGraphMode

        mjx.put_model = functools.partial(mjx.put_model, graph_mode=JaxCallableGraphMode[graph_mode])

    if name in ("reset_mp", "epoch_mp"):
        gpu = os.environ.get("JAX_PLATFORMS", "") != "cpu"
        if not gpu:
            jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(coordinator_address="127.0.0.1:29517", num_processes=2,
                                   process_id=rank, local_device_ids=[rank] if gpu else None)
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

    print("jax", jax.__version__, "devices", jax.devices(), "local", jax.local_devices(), flush=True)
    try:
        print("pmap_shmap_merge", jax.config.jax_pmap_shmap_merge, flush=True)
    except AttributeError:
        pass
    devs = jax.devices()[:2]
    w = P("w")

    def sm(f, mesh, i, o):
        return jax.shard_map(f, mesh=mesh, in_specs=i, out_specs=o, check_vma=False)

    if name == "plain":
        mesh = Mesh(devs, ("w",))
        x = jax.device_put(jnp.ones((8, 4)), NamedSharding(mesh, w))
        print(jax.jit(sm(lambda a: a * 2, mesh, (w,), w))(x).sum())
    elif name in ("reset_sm", "reset_sm1", "reset_mp"):
        env = _env()
        mesh = Mesh(devs[1:] if name == "reset_sm1" else devs, ("w",))
        keys = jax.random.split(jax.random.PRNGKey(0), 8 * mesh.size)
        keys = jax.make_array_from_callback(keys.shape, NamedSharding(mesh, w), lambda i: np.asarray(keys)[i])
        t = time.time()
        f = jax.jit(sm(env.reset_keys, mesh, (w,), w)).lower(keys).compile()
        print(f"compiled in {time.time() - t:.1f} s", flush=True)
        es = f(keys)
        jax.block_until_ready(es)
        print("qpos sum (addressable)", [float(s.data.sum()) for s in es.data.qpos.addressable_shards])
    elif name == "reset_pmap":
        env = _env()
        keys = jax.random.split(jax.random.PRNGKey(0), 16).reshape(2, 8, -1)
        es = jax.pmap(env.reset_keys, devices=devs)(keys)
        jax.block_until_ready(es)
        print("qpos sum", float(es.data.qpos.sum()))
    elif name == "reset_gspmd":
        env = _env(16)
        mesh = Mesh(devs, ("w",))
        keys = jax.device_put(jax.random.split(jax.random.PRNGKey(0), 16), NamedSharding(mesh, w))
        es = jax.jit(env.reset_keys)(keys)
        jax.block_until_ready(es)
        print("qpos sum", float(es.data.qpos.sum()))
    elif name in ("reset_each", "render_each"):
        from bulbjax.envs.render import Renderer, warp_devices

        outs = []
        envs = []
        for d in devs:
            env = _env(render=name == "render_each")
            if name == "render_each":
                env.renderer = Renderer(env.mj_model, 8, env.resolution, devices=warp_devices([d]))
            envs.append(env)
            keys = jax.device_put(jax.random.split(jax.random.PRNGKey(0), 8), d)

            def f(k, env=env):
                es = env.reset_keys(k)
                if name == "render_each":
                    ri = jax.tree.map(lambda x: x[None], es.render_input)
                    return es.data.qpos.sum(), env.render_sequence(ri).astype(jnp.float32).mean()
                return es.data.qpos.sum()
            outs.append(jax.jit(f)(keys))
        jax.block_until_ready(outs)
        print("per device", jax.device_get(outs))
    elif name == "epoch_mp":
        from bulbjax.config import preset
        from bulbjax.epoch import Experiment, small_config

        cfg = small_config(preset("fig2-invpend")).replace(seeds=2)
        exp = Experiment(cfg, devices=jax.devices())
        print("mesh", dict(exp.mesh.shape), "local worlds", exp.env.num_envs, flush=True)
        t = time.time()
        rs = exp.init(exp.put_key(jax.random.PRNGKey(0)))
        jax.block_until_ready(rs)
        print(f"init in {time.time() - t:.1f} s", flush=True)
        for i in range(2):
            t = time.time()
            rs, m = exp.epoch(rs, exp.put_key(jax.random.PRNGKey(1 + i)), probe=True)
            m = jax.device_get(m)
            print(f"epoch {i} in {time.time() - t:.1f} s; returns", np.asarray(m["rl_return"]).tolist(), flush=True)
    elif name == "epoch_each":
        from bulbjax.config import preset
        from bulbjax.epoch import Experiment, small_config

        cfg = small_config(preset("fig2-invpend")).replace(seeds=2)
        exps = [Experiment(cfg, devices=[d]) for d in devs]
        t = time.time()
        rss = [e.init(e.put_key(jax.random.PRNGKey(0))) for e in exps]
        jax.block_until_ready(rss)
        print(f"init on both in {time.time() - t:.1f} s", flush=True)
        for i in range(2):
            t = time.time()
            outs = [e.epoch(rs, e.put_key(jax.random.PRNGKey(1 + i)), probe=True) for e, rs in zip(exps, rss)]
            jax.block_until_ready(outs)
            rss = [o[0] for o in outs]
            ms = [jax.device_get(o[1]) for o in outs]
            print(f"epoch {i} in {time.time() - t:.1f} s; returns per device",
                  [float(np.mean(m["rl_return"])) for m in ms], flush=True)
    else:
        raise SystemExit(f"unknown case {name}")
    print("ok", flush=True)


def run_case(name: str, gdb: bool = False, timeout: int = 300) -> dict:
    cmd = [sys.executable, "-X", "faulthandler", __file__, "--case", name]
    if gdb and shutil.which("cuda-gdb"):
        cmd = ["cuda-gdb", "-q", "-batch", "-ex", "set pagination off", "-ex", "set cuda api_failures ignore",
               "-ex", "run", "-ex", "bt 40", "-ex", "info threads", "--args"] + cmd
    t = time.time()
    if name in ("reset_mp", "epoch_mp"):
        procs = [subprocess.Popen(cmd + ["--rank", str(r)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                 for r in range(2)]
        outs = []
        for p in procs:
            try:
                outs.append(p.communicate(timeout=timeout)[0])
            except subprocess.TimeoutExpired:
                p.kill()
                outs.append(p.communicate()[0] + "\n(timeout)")
        rc = max(p.returncode for p in procs)
        text = "\n---- rank 1\n".join(outs)
    else:
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
            rc, text = r.returncode, r.stdout + r.stderr
        except subprocess.TimeoutExpired as e:
            rc, text = -999, (e.stdout or b"").decode() if isinstance(e.stdout, bytes) else str(e.stdout)
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith(("Module", "[New Thread", "[Thread"))]
    return {"case": name, "rc": rc, "seconds": round(time.time() - t, 1), "ok": rc == 0 and "ok" in lines[-3:],
            "tail": lines[-60:] if gdb or rc != 0 else lines[-6:]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="*", default=list(CASES))
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--rank", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--gdb", action="append", default=[], help="run this case under cuda-gdb (native backtrace)")
    ap.add_argument("--timeout", type=int, default=300)
    ap.add_argument("--out", help="write the outcomes as JSON here")
    a = ap.parse_args()
    if a.case:
        case(a.case, a.rank)
        return
    results = []
    for name in a.cases:
        r = run_case(name, timeout=a.timeout)
        results.append(r)
        print(f"== {name}: rc {r['rc']} ok {r['ok']} ({r['seconds']} s)\n" + "\n".join(r["tail"]), flush=True)
    for name in a.gdb:
        r = run_case(name, gdb=True, timeout=a.timeout)
        r["case"] = f"{name} (cuda-gdb)"
        results.append(r)
        print(f"== {name} under cuda-gdb: rc {r['rc']}\n" + "\n".join(r["tail"]), flush=True)
    if a.out:
        with open(a.out, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
