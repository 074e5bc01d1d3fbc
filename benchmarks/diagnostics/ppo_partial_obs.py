"""Can PPO balance the InvertedPendulum from what one frame shows? (issue 41: why PPO from a
frame learner's latent or from pixels stays near the random policy's return)

A frame holds positions, not velocities: a VAE's latent of one frame, or a CNN on one frame,
can at best give PPO the cart's position and the pole's angle. This runs the repository's PPO
(`bulbjax.rl.ppo.train`, the `fig2-invpend` preset's PPO settings, 64 worlds, no rendering) on
the true state seen three ways, the synthetic case where the answer is known:

* `state`: the whole state (x, x velocity, cos and sin of the angle, angular velocity), what
  PPO from the state observes in the experiment;
* `positions`: the position entries only (x, cos, sin): the most a one-frame latent can hold;
* `positions_stack2`: the position entries of the current and the previous step (the previous
  one repeated at an episode's first step): what a policy reading the latents of the last two
  frames could hold (frame stacking, as pixel RL does).

Per variant and seed it prints the first PPO update whose rollout's finished episodes reach 950
on average, the share of later updates at or above 950, and the mean return of the last 50
updates, and writes `benchmarks/results/ppo_partial_obs_<device>_<stamp>.json`.

    python benchmarks/diagnostics/ppo_partial_obs.py --updates 300 --seeds 3     # CPU, minutes
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import bulbjax
from bulbjax.experiment.config import preset
from bulbjax.rl.ppo import train

RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "results")
POSITIONS = (0, 2, 3)  # InvertedPendulum's state: x, x velocity, cos, sin, angular velocity
VARIANTS = ("state", "positions", "positions_stack2")
SOLVED = 950.0


class ObservedAs:
    """`env` with PPO's observation replaced by a view of its true state (`variant`): the whole
    state, its position entries, or the position entries of this step and the previous one
    (kept in `info["previous"]`; an episode's first step repeats its own)."""

    def __init__(self, env: Any, variant: str):
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        self.env, self.variant = env, variant
        self.discrete, self.num_actions, self.action_size = env.discrete, env.num_actions, env.action_size
        self.obs_size = {"state": env.obs_size, "positions": len(POSITIONS),
                         "positions_stack2": 2 * len(POSITIONS)}[variant]

    def _view(self, es: Any, previous: jax.Array) -> Any:
        pos = es.lowdim[:, POSITIONS]
        obs = {"state": es.obs, "positions": pos,
               "positions_stack2": jnp.concatenate([pos, previous], axis=1)}[self.variant]
        return es.replace(obs=obs, info={**es.info, "previous": pos})

    def reset(self, key: jax.Array) -> Any:
        es = self.env.reset(key)
        return self._view(es, es.lowdim[:, POSITIONS])

    def step(self, es: Any, action: jax.Array) -> Any:
        previous = es.info["previous"]
        info = {k: v for k, v in es.info.items() if k != "previous"}
        nes = self.env.step(es.replace(info=info), action)
        # a world whose step ended an episode shows the next episode's first state: no previous
        fresh = nes.done[:, None] > 0
        return self._view(nes, jnp.where(fresh, nes.lowdim[:, POSITIONS], previous))


def summarise(returns: np.ndarray) -> dict[str, Any]:
    """First update at `SOLVED`, the share of later updates at or above it, last-50 mean."""
    ok = np.nan_to_num(returns, nan=0.0) >= SOLVED
    first = int(np.argmax(ok)) if ok.any() else None
    later = float(ok[first:].mean()) if first is not None else 0.0
    return {"first_update_at_950": first, "share_at_950_after": later,
            "mean_last_50": float(np.nanmean(returns[-50:]))}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--updates", type=int, default=300, help="PPO updates per seed (the experiment runs 2 per epoch)")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--out", default=RESULTS)
    a = p.parse_args(argv)
    cfg = preset("fig2-invpend").ppo
    env = bulbjax.make("InvertedPendulum", num_envs=cfg.num_envs, render=False)
    out: dict[str, Any] = {"device": jax.devices()[0].device_kind, "updates": a.updates, "seeds": a.seeds,
                           "ppo": {k: v for k, v in vars(cfg).items() if not k.startswith("_")}, "variants": {}}
    keys = jax.random.split(jax.random.PRNGKey(0), a.seeds)
    for variant in a.variants.split(","):
        wrapped = ObservedAs(env, variant)
        t0 = time.time()
        # one seed after another: the env's Warp calls do not batch under jax.vmap
        ret = np.stack([np.asarray(train(wrapped, cfg, k, a.updates)[1]["mean_episode_return"], np.float64)
                        for k in keys])  # [S, U]
        seeds = [summarise(r) for r in ret]
        out["variants"][variant] = {"seconds": time.time() - t0, "per_seed": seeds,
                                    "returns": [[None if np.isnan(x) else round(float(x), 1) for x in r] for r in ret]}
        print(f"{variant:17s} ({time.time() - t0:.0f} s): " + "; ".join(
            f"first at 950 {s['first_update_at_950']}, share after {s['share_at_950_after']:.2f}, "
            f"last 50 {s['mean_last_50']:.0f}" for s in seeds), flush=True)
    os.makedirs(a.out, exist_ok=True)
    kind = out["device"].lower().replace(" ", "_")
    path = os.path.join(a.out, f"ppo_partial_obs_{kind}_{time.strftime('%Y%m%d_%H%M%S')}.json")
    with open(path, "w") as fh:
        json.dump(out, fh, indent=1, default=str)
    print(f"wrote {path}")
    return out


if __name__ == "__main__":
    main()
