"""How long bulb's initial fall lasts on the Incline: `stepSimulation`s per world until the
object's x passes its drawn start_x (at most 50; `Incline._fall`), over `--worlds` fresh draws.

Why: every episode starts with this fall, so it sets what a reset costs at best; the pool's
refills run each batch until its slowest world is done (docs/performance.md, "The reset pool").

    python benchmarks/diagnostics/incline_fall.py --worlds 256      # CPU, ~1 min
"""

from __future__ import annotations

import argparse
import json


def fall_lengths(name: str, worlds: int, seed: int) -> list[int]:
    """Each world's number of fall iterations (one bulb `stepSimulation` each) from `seed`'s draws."""
    import jax
    import jax.numpy as jnp

    import bulbjax
    from bulbjax.envs.base import where_tree
    from bulbjax.envs.incline import BULLET_SUBSTEPS, FALL_STEPS

    env = bulbjax.make(name, num_envs=worlds, render=False, reset_pool=0)
    draws = jax.vmap(env._draws)(jax.random.split(jax.random.PRNGKey(seed), worlds))
    data, params, start_x = jax.vmap(env._place)(draws)
    slot, zero = env._slot(params), jnp.zeros(worlds)

    @jax.jit
    def run(data):
        def body(carry, _):
            d, active, n = carry
            d = where_tree(active, env._substeps(d, params, zero, BULLET_SUBSTEPS), d)
            x = jax.vmap(lambda dd, s: env._object_qpos(dd, s)[0])(d, slot)
            return (d, active & (x <= start_x), n + active), None
        init = (data, jnp.ones(worlds, bool), jnp.zeros(worlds, jnp.int32))
        return jax.lax.scan(body, init, None, length=FALL_STEPS)[0][2]

    return [int(v) for v in run(data)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="GeomOnIncline")
    p.add_argument("--worlds", type=int, default=256)
    p.add_argument("--seed", type=int, default=3)
    a = p.parse_args()
    import numpy as np

    from bulbjax.envs.incline import FALL_STEPS

    n = np.asarray(fall_lengths(a.env, a.worlds, a.seed))
    print(json.dumps({"env": a.env, "worlds": a.worlds, "mean": float(n.mean()), "median": float(np.median(n)),
                      "p90": float(np.percentile(n, 90)), "max": int(n.max()),
                      "share_at_cap": float((n >= FALL_STEPS).mean())}))


if __name__ == "__main__":
    main()
