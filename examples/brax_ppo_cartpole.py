"""Brax's PPO trainer on a bulbjax domain from the true state (CartPoleContinuous by default).

The bulbjax env is already batched, time-limited and auto-resetting, so it goes to
`brax.training.agents.ppo.train` with `wrap_env=False` (see `bulbjax/interop/brax.py`).

    .venv/bin/python examples/brax_ppo_cartpole.py --timesteps 20000          # CPU, a few minutes
    .venv/bin/python examples/brax_ppo_cartpole.py --num-envs 1024 --timesteps 2000000  # GPU
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import jax
import jax.numpy as jnp
from brax.training.agents.ppo import train as ppo

from bulbjax.interop.brax import make


def _jax_compat() -> None:
    """Brax 0.14.2 (the newest release) still calls `jax.device_put_replicated`, which jax 0.10
    removed; put back the equivalent (stack one copy per device, place it on those devices)."""
    try:
        jax.device_put_replicated  # noqa: B018
    except AttributeError:
        def device_put_replicated(x, devices):
            stacked = jax.tree.map(lambda a: jnp.stack([jnp.asarray(a)] * len(devices)), x)
            sharding = jax.sharding.PositionalSharding(devices) if hasattr(jax.sharding, "PositionalSharding") \
                else None
            return jax.device_put(stacked, sharding if len(devices) > 1 else devices[0])
        jax.device_put_replicated = device_put_replicated


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="CartPoleContinuous")
    p.add_argument("--num-envs", type=int, default=32)
    p.add_argument("--num-eval-envs", type=int, default=16)
    p.add_argument("--timesteps", type=int, default=20_000)
    p.add_argument("--unroll-length", type=int, default=16)
    p.add_argument("--num-evals", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", default=None, help="write the eval curve here")
    args = p.parse_args()
    _jax_compat()

    env = make(args.env, args.num_envs, obs="state", render=False)
    eval_env = make(args.env, args.num_eval_envs, obs="state", render=False)
    curve: list[dict] = []
    t0 = time.time()

    def progress(step: int, metrics: dict) -> None:
        ret = float(metrics.get("eval/episode_reward", float("nan")))
        curve.append({"step": int(step), "eval_return": ret, "wall_s": time.time() - t0})
        print(f"step {step:>8d}  eval return {ret:8.1f}  ({time.time() - t0:.0f} s)", flush=True)

    # batch_size * num_minibatches must be a multiple of num_envs (Brax's rule)
    train = functools.partial(
        ppo.train, num_timesteps=args.timesteps, num_evals=args.num_evals, episode_length=env.episode_length,
        wrap_env=False, num_envs=args.num_envs, num_eval_envs=args.num_eval_envs, eval_env=eval_env,
        unroll_length=args.unroll_length, batch_size=args.num_envs, num_minibatches=4, num_updates_per_batch=4,
        learning_rate=3e-4, entropy_cost=1e-2, discounting=0.99, normalize_observations=True,
        reward_scaling=0.1, seed=args.seed, progress_fn=progress)
    make_policy, params, _ = train(environment=env)
    print(f"done in {time.time() - t0:.0f} s; final eval return {curve[-1]['eval_return']:.1f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"env": args.env, "args": vars(args), "curve": curve}, f, indent=1)


if __name__ == "__main__":
    main()
