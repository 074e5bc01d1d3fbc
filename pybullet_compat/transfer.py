"""PPO policies across simulators: train in bulbjax (MJX) or in the PyBullet original with the
same PPO code (`bulbjax.rl.ppo`), save/load them, and measure returns in either simulator.

PyBullet training drives a vector of PyBullet envs from a host loop: the jitted `ppo.act` picks
actions, the envs step (auto-reset), and the collected `Transition` [T, N] goes to the jitted
`ppo.update`, exactly as `bulbjax.rl.ppo.rollout` does inside MJX.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from bulbjax.rl.ppo import PPO, PPOConfig, PPOState, Transition, train
from pybullet_compat.vector import SerialVecEnv, VecConfig, any_domain

POLICY_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs", "parity", "policies")


@dataclass(frozen=True)
class TransferConfig:
    """Training budget per domain (PPO updates of num_envs x num_steps steps) and evaluation size."""

    updates: int = 30
    num_envs: int = 64
    num_steps: int = 64
    eval_episodes: int = 16
    seed: int = 0


def make_ppo(name: str, num_envs: int = 64, num_steps: int = 64) -> PPO:
    """The PPO (default bulbjax hyperparameters) for domain `name`'s observation and actions."""
    spec = any_domain(name)
    cfg = PPOConfig(num_envs=num_envs, num_steps=num_steps)
    return PPO(cfg, spec.state_dim, spec.num_actions if spec.discrete else None, spec.action_size)


def train_in_bulbjax(name: str, cfg: TransferConfig) -> tuple[PPOState, np.ndarray]:
    """PPO trained on the MJX mirror (`bulbjax.rl.ppo.train`); returns state and per-update returns."""
    import bulbjax

    env = bulbjax.make(name, num_envs=cfg.num_envs, render=False)
    ppo_cfg = PPOConfig(num_envs=cfg.num_envs, num_steps=cfg.num_steps)
    state, metrics = train(env, ppo_cfg, jax.random.PRNGKey(cfg.seed), cfg.updates)
    return state, np.asarray(metrics["mean_episode_return"])


def train_in_pybullet(name: str, cfg: TransferConfig, log: Callable[[str], None] | None = None
                      ) -> tuple[PPOState, np.ndarray]:
    """The same PPO trained on the PyBullet original (serial vector of `num_envs`, no frames)."""
    ppo = make_ppo(name, cfg.num_envs, cfg.num_steps)
    key = jax.random.PRNGKey(cfg.seed)
    key, k_init = jax.random.split(key)
    state = ppo.init(k_init)
    act = jax.jit(ppo.act)
    update = jax.jit(ppo.update)
    env_action = jax.jit(ppo.env_action)
    returns, last = [], float("nan")
    with SerialVecEnv(name, cfg.num_envs, render=False) as venv:
        _, obs = venv.reset(seeds=[cfg.seed * 100_003 + i for i in range(cfg.num_envs)])
        for u in range(cfg.updates):
            buf: dict[str, list] = {k: [] for k in ("obs", "action", "reward", "done", "truncated", "log_prob", "value")}
            finished = []
            for _ in range(cfg.num_steps):
                key, k = jax.random.split(key)
                action, logp, value = act(state, jnp.asarray(obs), k)
                _, nobs, rew, term, trunc, info = venv.step(np.asarray(env_action(action)))
                done = term | trunc
                for k_, v in (("obs", obs), ("action", np.asarray(action)), ("reward", rew),
                              ("done", done.astype(np.float32)), ("truncated", trunc.astype(np.float32)),
                              ("log_prob", np.asarray(logp)), ("value", np.asarray(value))):
                    buf[k_].append(v)
                finished += list(info["episode_return"][done])
                obs = nobs
            traj = Transition(**{k_: jnp.asarray(np.stack(v)) for k_, v in buf.items()})
            key, k = jax.random.split(key)
            state, _ = update(state, traj, jnp.asarray(obs), k)
            last = float(np.mean(finished)) if finished else last
            returns.append(last)
            if log is not None:
                log(f"  pybullet PPO {name} update {u + 1}/{cfg.updates}: mean return {last:.1f}")
    return state, np.asarray(returns)


def policy_fn(ppo: PPO, state: PPOState) -> Callable[[jax.Array, jax.Array], jax.Array]:
    """Deterministic (mode) policy `(states [N, D], key) -> env actions`, jittable."""
    def pi(obs: jax.Array, key: jax.Array) -> jax.Array:
        return ppo.env_action(ppo.act(state, obs, key, deterministic=True)[0])
    return pi


def evaluate_in_bulbjax(name: str, ppo: PPO, state: PPOState, episodes: int, seed: int = 1) -> np.ndarray:
    """Returns of the first episode of each of `episodes` MJX worlds under the deterministic policy."""
    import bulbjax

    env = bulbjax.make(name, num_envs=episodes, render=False)
    pi = policy_fn(ppo, state)
    steps = env.episode_length

    @jax.jit
    def run(key: jax.Array) -> tuple[jax.Array, jax.Array]:
        def body(es, k):
            es = env.step(es, pi(es.obs, k))
            return es, (es.done, es.info["episode_return"])
        k0, k1 = jax.random.split(key)
        return jax.lax.scan(body, env.reset(k0), jax.random.split(k1, steps))[1]

    done, ret = (np.asarray(x) for x in run(jax.random.PRNGKey(seed)))
    first = np.argmax(done > 0, axis=0)  # every world ends by the time limit at the latest
    return ret[first, np.arange(episodes)]


def evaluate_in_pybullet(name: str, ppo: PPO, state: PPOState, episodes: int, seed: int = 1) -> np.ndarray:
    """Returns of `episodes` PyBullet episodes (env i seeded `seed * 1000 + i`), deterministic policy."""
    pi = jax.jit(policy_fn(ppo, state))
    key = jax.random.PRNGKey(0)
    out = []
    for i in range(episodes):
        env = VecConfig(name, render=False).make()  # pybullet_envs domain or Incline original
        _, s = env.reset(seed=seed * 1000 + i)
        while True:
            a = np.asarray(pi(jnp.asarray(s[None]), key))[0]
            r = env.step(a)
            s = r.state
            if r.terminated or r.truncated:
                out.append(r.info["episode_return"])
                break
        env.close()
    return np.asarray(out)


def save_policy(path: str, state: PPOState) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(serialization.to_bytes(state))


def load_policy(path: str, ppo: PPO) -> PPOState:
    template = ppo.init(jax.random.PRNGKey(0))
    with open(path, "rb") as f:
        return serialization.from_bytes(template, f.read())


def policy_path(name: str, trained_in: str) -> str:
    return os.path.join(POLICY_DIR, f"{name}_{trained_in}.msgpack")


def get_policy(name: str, trained_in: str, cfg: TransferConfig, retrain: bool = False,
               log: Callable[[str], None] = print) -> tuple[PPO, PPOState, dict]:
    """Load the cached policy (docs/parity/policies/) or train and cache it."""
    ppo = make_ppo(name, cfg.num_envs, cfg.num_steps)
    path = policy_path(name, trained_in)
    if os.path.exists(path) and not retrain:
        return ppo, load_policy(path, ppo), {"cached": _rel(path)}
    t0 = time.time()
    log(f"training PPO on {name} in {trained_in} ({cfg.updates} updates of {cfg.num_envs}x{cfg.num_steps} steps)")
    if trained_in == "bulbjax":
        state, curve = train_in_bulbjax(name, cfg)
    else:
        state, curve = train_in_pybullet(name, cfg, log)
    save_policy(path, state)
    return ppo, state, {"trained_seconds": round(time.time() - t0, 1), "updates": cfg.updates,
                        "final_training_return": float(curve[-1]), "path": _rel(path)}


def _rel(path: str) -> str:
    """Path relative to the repository root (for reports)."""
    return os.path.relpath(path, os.path.dirname(os.path.dirname(os.path.dirname(POLICY_DIR))))


TRANSFER_UPDATES = {"InvertedPendulum": 30, "CartPole": 100, "GeomOnIncline": 40}


def transfer_report(domains: tuple[str, ...] = ("InvertedPendulum", "CartPole"), episodes: int = 16,
                    log: Callable[[str], None] = print,
                    sources: tuple[str, ...] = ("bulbjax", "pybullet")) -> dict[str, Any]:
    """For each domain: a policy trained in each of `sources` (bulbjax, pybullet), each evaluated
    (deterministic, `episodes` episodes) in both simulators. For the Incline domains, training in
    PyBullet is the cheap one on a CPU (~2 min for 40 updates of GeomOnIncline)."""
    out: dict[str, Any] = {}
    for name in domains:
        cfg = TransferConfig(updates=TRANSFER_UPDATES.get(name, 30), eval_episodes=episodes)
        out[name] = {}
        for src in sources:
            ppo, state, meta = get_policy(name, src, cfg, log=log)
            rb = evaluate_in_bulbjax(name, ppo, state, episodes)
            rp = evaluate_in_pybullet(name, ppo, state, episodes)
            out[name][f"trained_in_{src}"] = {
                **meta, "return_in_bulbjax": {"mean": float(rb.mean()), "std": float(rb.std()), "min": float(rb.min())},
                "return_in_pybullet": {"mean": float(rp.mean()), "std": float(rp.std()), "min": float(rp.min())}}
            log(f"  {name} trained in {src}: return in bulbjax {rb.mean():.1f} +- {rb.std():.1f}, "
                f"in PyBullet {rp.mean():.1f} +- {rp.std():.1f}")
    return out
