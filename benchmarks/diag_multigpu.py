"""Where a sharded (2-GPU) program with MJX-Warp physics and the Warp renderer fails: each case
compiled and run in its own subprocess, so a segfault names its case (diagnostic, issue 14)."""

from __future__ import annotations

import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
CASES = ("plain", "physics", "physics_cond", "render", "reset", "init_small")


def case(name: str) -> None:
    sys.path.insert(0, os.path.dirname(HERE))
    import jax
    import jax.numpy as jnp
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

    import bulbjax
    from bulbjax.envs.render import Renderer, warp_devices

    devs = jax.devices()[:2]
    mesh = Mesh(devs, ("w",))
    w = P("w")
    sm = lambda f, i, o: jax.shard_map(f, mesh=mesh, in_specs=i, out_specs=o, check_vma=False)  # noqa: E731
    if name == "plain":
        x = jax.device_put(jnp.ones((8, 4)), NamedSharding(mesh, w))
        print(jax.jit(sm(lambda a: a * 2, (w,), w))(x).sum())
        return
    if name == "init_small":
        from bulbjax.experiment import Experiment, small_config
        from bulbjax.experiment.config import preset
        cfg = small_config(preset("fig2-invpend")).replace(seeds=2, learners=("vae",))
        exp = Experiment(cfg, devices=devs)
        rs = exp.init(exp.put_key(jax.random.PRNGKey(0)))
        jax.block_until_ready(rs)
        rs, m = exp.epoch(rs, exp.put_key(jax.random.PRNGKey(1)), probe=False)
        jax.block_until_ready(rs)
        print("epoch ok")
        return
    env = bulbjax.make("InvertedPendulum", num_envs=8, render=(name == "render"), render_steps=False)
    keys = jax.device_put(jax.random.split(jax.random.PRNGKey(0), 16), NamedSharding(mesh, w))
    es = jax.jit(sm(env.reset_keys, (w,), w))(keys)
    jax.block_until_ready(es)
    print("reset ok")
    if name == "reset":
        return
    act = jax.device_put(jnp.zeros((16, env.action_size)), NamedSharding(mesh, w))
    if name == "physics":
        out = jax.jit(sm(lambda e, a: env.physics(e.data, a), (w, w), w))(es, act)
    elif name == "physics_cond":
        out = jax.jit(sm(env.step, (w, w), w))(es, act)
    else:
        env.renderer = Renderer(env.mj_model, 8, env.resolution, devices=warp_devices(devs))
        ri = jax.tree.map(lambda x: x[None], es.render_input)
        out = jax.jit(sm(env.render_sequence, (P(None, "w"),), P(None, "w")))(ri)
    jax.block_until_ready(out)
    print("ok")


def main() -> None:
    if len(sys.argv) > 1:
        case(sys.argv[1])
        return
    for name in CASES:
        r = subprocess.run([sys.executable, "-X", "faulthandler", __file__, name], capture_output=True, text=True,
                           timeout=300)
        tail = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip() and not ln.startswith("Module")]
        print(f"== {name}: rc {r.returncode}")
        print("\n".join(tail[-12:]))


if __name__ == "__main__":
    main()
