"""Does PPO's pixel torso see the pendulum at init? Feature spread over frames, per init seed.

PPO from two frames' pixels on InvertedPendulumMulticolour learns in one seed of three; the other
two never leave the random policy's return, with or without an entropy bonus, their approximate
KL per update 10-100x below the learning seed's (docs/results/rl_inputs_frames_h200). A policy
whose features do not vary with the frame cannot move its action with the state. This renders
frames of the random policy, stacks the last two as `--rl-frames 2` does, initialises PPO's
pixel actor-critic (`PixelTorso` + Gaussian head) under `--inits` keys, and reports for each:
the share of the torso's 256 features that are constant over the frames (dead ReLUs), the
median feature spread, and the spread of the policy mean and of the value over the frames,
relative to their magnitude. CPU, ~2 min:

    python benchmarks/diagnostics/pixel_torso_init.py --inits 16
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(os.path.dirname(HERE)))


def frames_of_random_policy(worlds: int, steps: int, seed: int):
    """uint8 `[worlds * steps, 64, 64, 6]`: each step's frame with the previous one, oldest first
    (an episode's first frame repeated), under uniform random actions."""
    import jax
    import jax.numpy as jnp

    import bulbjax

    env = bulbjax.make("InvertedPendulum", num_envs=worlds, multicolour=True)
    step = jax.jit(env.step)
    key = jax.random.PRNGKey(seed)
    state = jax.jit(env.reset)(key)
    prev, out = state.pixels, []
    for _ in range(steps):
        key, k = jax.random.split(key)
        state = step(state, jax.random.uniform(k, (worlds, env.action_size), minval=-1.0, maxval=1.0))
        first = state.done[:, None, None, None] if state.done.ndim == 1 else False
        last = jnp.where(first, state.pixels, prev)
        out.append(jnp.concatenate([last, state.pixels], axis=-1))
        prev = state.pixels
    return jnp.concatenate(out, axis=0)


def spread_at_init(frames, inits: int) -> list[dict]:
    """Per init key: dead-feature share, median feature std, policy-mean and value spreads."""
    import jax
    import jax.numpy as jnp

    from bulbjax.rl.networks import PixelTorso
    from bulbjax.rl.ppo import PPO
    from bulbjax.rl.ppo_config import PPOConfig

    ppo = PPO(PPOConfig(), obs_size=0, action_size=1, frame_shape=tuple(frames.shape[1:]))
    rows = []
    for i in range(inits):
        params = ppo.init(jax.random.PRNGKey(i)).params
        feats = PixelTorso().apply({"params": params["params"]["PixelTorso_0"]}, frames)
        mean, _, value = ppo.network.apply(params, frames)
        std = jnp.std(feats, axis=0)
        rows.append({"init": i, "dead_share": float(jnp.mean(std < 1e-6)),
                     "feature_std_median": float(jnp.median(std)),
                     "feature_mean": float(jnp.mean(feats)),
                     "policy_mean_std": float(jnp.std(mean)), "policy_mean_abs": float(jnp.mean(jnp.abs(mean))),
                     "value_std": float(jnp.std(value)), "value_abs": float(jnp.mean(jnp.abs(value)))})
    return rows


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--inits", type=int, default=16)
    p.add_argument("--worlds", type=int, default=32)
    p.add_argument("--steps", type=int, default=24)
    p.add_argument("--out", default=os.path.join(os.path.dirname(HERE), "results"))
    a = p.parse_args(argv)
    import jax

    frames = frames_of_random_policy(a.worlds, a.steps, 0)
    rows = spread_at_init(frames, a.inits)
    for r in rows:
        print("init {init:2d}: dead features {dead_share:.2f}, median feature std {feature_std_median:.4f}, "
              "policy mean std {policy_mean_std:.2e} (|mean| {policy_mean_abs:.2e}), value std {value_std:.3f} "
              "(|value| {value_abs:.3f})".format(**r), flush=True)
    out = {"frames": list(frames.shape), "device": jax.devices()[0].device_kind, "rows": rows}
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, f"pixel_torso_init_{jax.devices()[0].platform}_{time.strftime('%Y%m%d_%H%M%S')}.json")
    with open(path, "w") as fh:
        json.dump(out, fh, indent=1)
    print(f"wrote {path}")
    return out


if __name__ == "__main__":
    main()
