"""PPO from the true low-dimensional state on HalfCheetah / Ant (no pixels), within a time budget.

Prints the mean return of finished episodes against environment steps and writes
`benchmarks/results/ppo_<env>_<device>_<timestamp>.json` (curve, settings, timings). PPO
settings are the domain's (`bulbjax.envs.registry.ppo_config_for`), with command-line overrides.

    python benchmarks/train_ppo_locomotion.py --env HalfCheetah --minutes 10
    python benchmarks/train_ppo_locomotion.py --env Ant --num-envs 64 --minutes 10
    python benchmarks/train_ppo_locomotion.py --env HalfCheetah --minutes 0.5 --updates-per-call 1 --num-steps 16  # CPU smoke

Updates run in jitted chunks of `--updates-per-call` (a scan over rollout + update), so the
host only syncs between chunks to print and check the budget.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import bulbjax
from bulbjax.envs.registry import ppo_config_for
from bulbjax.rl.ppo import PPO, rollout

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def make_chunk(ppo: PPO, env, num_steps: int, updates: int):
    """Jitted `chunk(ppo_state, env_state, key)`: `updates` PPO updates; per-update metrics."""

    def one(carry, k):
        ps, es = carry
        k_roll, k_upd = jax.random.split(k)
        es, traj, ex = rollout(ppo, ps, env, es, k_roll, num_steps)
        ps, m = ppo.update(ps, traj, ex["last_obs"], k_upd)
        out = dict(return_sum=ex["episode_return_sum"], length_sum=ex["episode_length_sum"],
                   episodes=ex["episode_count"], reward_per_step=traj.reward.mean(),
                   approx_kl=m["approx_kl"], value_loss=m["value_loss"], entropy=m["entropy"])
        return (ps, es), out

    @jax.jit
    def chunk(ps, es, key):
        return jax.lax.scan(one, (ps, es), jax.random.split(key, updates))

    return chunk


def train(env_name: str, args: argparse.Namespace) -> dict:
    overrides = {k: v for k, v in dict(lr=args.lr, num_steps=args.num_steps, update_epochs=args.epochs,
                                       num_minibatches=args.minibatches).items() if v is not None}
    cfg = dataclasses.replace(ppo_config_for(env_name), num_envs=args.num_envs, **overrides)
    env = bulbjax.make(env_name, num_envs=args.num_envs, render=False)
    ppo = PPO.for_env(cfg, env)
    chunk = make_chunk(ppo, env, cfg.num_steps, args.updates_per_call)
    key = jax.random.PRNGKey(args.seed)
    k_init, k_env, key = jax.random.split(key, 3)
    ps, es = jax.jit(ppo.init)(k_init), jax.jit(env.reset)(k_env)
    steps_per_update = cfg.num_steps * args.num_envs
    curve, env_steps, t_compile = [], 0, None
    t0 = time.time()
    print(f"{env_name}: {args.num_envs} envs x {cfg.num_steps} steps per update, "
          f"{args.updates_per_call} updates per call, budget {args.minutes} min on {jax.devices()[0].device_kind}")
    window: list[tuple[float, float]] = []  # (return sum, episodes) of recent updates
    while time.time() - t0 < 60 * args.minutes:
        key, k = jax.random.split(key)
        t_call = time.time()
        (ps, es), m = chunk(ps, es, k)
        m = jax.device_get(m)
        if t_compile is None:
            t_compile = time.time() - t_call
            t_train0 = time.time()
        for u in range(args.updates_per_call):
            env_steps += steps_per_update
            window = (window + [(float(m["return_sum"][u]), float(m["episodes"][u]))])[-args.window:]
            n = sum(e for _, e in window)
            ret = sum(r for r, _ in window) / n if n else math.nan
            length = float(m["length_sum"][u] / m["episodes"][u]) if m["episodes"][u] else math.nan
            curve.append(dict(env_steps=env_steps, mean_return=ret, episodes=float(m["episodes"][u]),
                              mean_length=length, reward_per_step=float(m["reward_per_step"][u]),
                              approx_kl=float(m["approx_kl"][u]), wall_s=time.time() - t0))
        c = curve[-1]
        print(f"  steps {env_steps:>10,d}  return {c['mean_return']:8.1f}  (last {args.window} updates, "
              f"ep len {c['mean_length']:6.1f})  reward/step {c['reward_per_step']:6.3f}  "
              f"kl {c['approx_kl']:.4f}  {time.time() - t0:6.0f} s", flush=True)
    wall = time.time() - t0
    train_steps = env_steps - steps_per_update * args.updates_per_call
    train_time = time.time() - t_train0 if t_compile is not None else math.nan
    finite = [c["mean_return"] for c in curve if not math.isnan(c["mean_return"])]
    return dict(env=env_name, device=jax.devices()[0].device_kind, num_envs=args.num_envs, seed=args.seed,
                ppo=dataclasses.asdict(cfg), updates_per_call=args.updates_per_call, env_steps=env_steps,
                wall_s=wall, first_call_s=t_compile,
                env_steps_per_s=train_steps / train_time if train_steps > 0 and train_time > 0 else math.nan,
                final_return=finite[-1] if finite else math.nan,
                best_return=max(finite) if finite else math.nan,
                solved_return=env.solved_return, curve=curve)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="HalfCheetah", help="HalfCheetah, Ant, or both (comma-separated)")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--minutes", type=float, default=10.0, help="wall-time budget per env (incl. compile)")
    p.add_argument("--updates-per-call", type=int, default=10)
    p.add_argument("--window", type=int, default=10, help="updates averaged in the printed return")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--num-steps", type=int, default=None)
    p.add_argument("--epochs", type=int, default=None)
    p.add_argument("--minibatches", type=int, default=None)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args(argv)
    if args.minutes <= 0 or args.num_envs < 1 or args.updates_per_call < 1:
        p.error("--minutes, --num-envs and --updates-per-call must be positive")
    os.makedirs(args.out, exist_ok=True)
    for name in [n.strip() for n in args.env.split(",") if n.strip()]:
        res = train(name, args)
        dev = re.sub(r"[^a-z0-9]+", "_", res["device"].lower()).strip("_")
        path = os.path.join(args.out, f"ppo_{name.lower()}_{dev}_{time.strftime('%Y%m%d_%H%M%S')}.json")
        with open(path, "w") as f:
            json.dump(res, f, indent=1)
        print(f"{name}: return {res['final_return']:.1f} (best {res['best_return']:.1f}, PyBullet solved "
              f"{res['solved_return']:g}) after {res['env_steps']:,d} steps, "
              f"{res['env_steps_per_s']:.0f} env steps/s; {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
