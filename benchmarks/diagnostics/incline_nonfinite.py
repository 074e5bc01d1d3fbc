"""Non-finite resets of an Incline domain under random actions, with the fix of issue 40 and
without it (`--stale-subtreemass`: the model's compiled subtree masses, as before the fix).

The Incline domains set each world's object mass (and inertia) as model fields; MuJoCo's subtree
centre of mass divides the mass-weighted body positions by `body_subtreemass`, a compile-time
constant. Left at the compiled masses, each object's subtree COM sits at mass/mass0 times its
position, and the float32 mass matrix built about that point (hundreds of metres away for an
object parked at 50 m) loses the object's rotational inertia: its Cholesky goes NaN. The script
also checks the mass matrix of the first step directly: the worlds whose `qLD` is non-finite.

    python benchmarks/diagnostics/incline_nonfinite.py --env GeomOnInclineSm --worlds 32 --steps 100
    python benchmarks/diagnostics/incline_nonfinite.py --env GeomOnInclineSm --worlds 32 --steps 100 --stale-subtreemass
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)  # this working tree's bulbjax


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--env", default="GeomOnInclineSm")
    ap.add_argument("--worlds", type=int, default=32)
    ap.add_argument("--steps", type=int, default=100, help="env steps per world")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ycb-dir", default=None)
    ap.add_argument("--stale-subtreemass", action="store_true",
                    help="keep the compiled body_subtreemass in every world's model (the code before the fix)")
    a = ap.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import numpy as np
    from mujoco import mjx

    import bulbjax
    from bulbjax.envs import incline

    t0 = time.time()
    env = bulbjax.make(a.env, num_envs=a.worlds, render=False, version="random", ycb_dir=a.ycb_dir)
    if a.stale_subtreemass:
        fixed = env._world_model
        env._world_model = lambda p: (fixed(p).tree_replace({"body_subtreemass": env.mx.body_subtreemass})
                                      if p else fixed(p))
    key = jax.random.PRNGKey(a.seed)
    state = jax.jit(env.reset)(key)

    # the first step's mass matrix of fresh draws, before any fall: which worlds factor to NaN
    draws = env._draws_fixed(jax.random.split(jax.random.fold_in(key, 1), a.worlds))
    data, params, _ = jax.vmap(env._place)(draws)
    fwd = jax.jit(lambda d, p: jax.vmap(mjx.forward, in_axes=(None, 0))(env._world_model(p), d))(data, params)
    bad_m = ~np.isfinite(np.asarray(fwd._impl.qLD)).all(axis=1)

    step = jax.jit(env.step)
    episodes = np.zeros(a.worlds, np.int64)
    actions = jax.random.uniform(jax.random.fold_in(key, 2), (a.steps, a.worlds, 1), minval=-1.0, maxval=1.0)
    for i in range(a.steps):
        state = step(state, actions[i])
        episodes += np.asarray(state.done, bool)
    counts = {k: np.asarray(v) for k, v in state.counts.items()}
    leaked = int((~np.isfinite(np.asarray(state.obs))).sum() + (~np.isfinite(np.asarray(state.data.qpos))).sum())
    mass = np.asarray(draws["mass"])
    out = {
        "env": a.env, "worlds": a.worlds, "steps": a.steps, "seed": a.seed,
        "stale_subtreemass": a.stale_subtreemass,
        "episodes": int(episodes.sum()), "nonfinite_resets": int(counts["nonfinite_resets"].sum()),
        "nonfinite_worlds": int((counts["nonfinite_resets"] > 0).sum()), "leaked": leaked,
        "first_step_nan_mass_matrix": f"{int(bad_m.sum())} of {a.worlds}",
        "first_step_nan_mass_matrix_mass_range": ([float(mass[bad_m].min()), float(mass[bad_m].max())]
                                                  if bad_m.any() else None),
        "mass_range_drawn": list(incline.MASS), "wall_s": round(time.time() - t0, 1),
    }
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
