"""Stable-Baselines3 PPO on a bulbjax gymnasium vector env (CartPole from the true state by default).

SB3 has its own `VecEnv` API (auto-reset in the same step, the ended episode's last observation in
`infos[i]["terminal_observation"]`), which is bulbjax's `autoreset_mode="same_step"`: the small
`SB3VecEnv` below maps one onto the other. Stable-Baselines3 pulls PyTorch, so it is not a bulbjax
dependency; install it yourself (`pip install stable-baselines3`).

    python examples/sb3_ppo_cartpole.py --timesteps 4096
    python examples/sb3_ppo_cartpole.py --obs pixels --timesteps 4096   # CnnPolicy on 64x64 frames
"""

from __future__ import annotations

import argparse
import time
from typing import Any, Sequence

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv

from bulbjax.gym import BulbjaxVectorEnv, make_vec


class SB3VecEnv(VecEnv):
    """SB3's `VecEnv` over a `BulbjaxVectorEnv` in "same_step" autoreset mode."""

    def __init__(self, venv: BulbjaxVectorEnv):
        if venv.config.autoreset_mode != "same_step":
            raise ValueError('SB3 auto-resets in the same step: make the env with autoreset_mode="same_step"')
        self.venv = venv
        self._actions: np.ndarray | None = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    def reset(self) -> np.ndarray:
        seed = self._seeds[0]  # one key for all worlds: SB3's per-env seeds are seed + i
        obs, _ = self.venv.reset(seed=seed)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        obs, reward, terminated, truncated, info = self.venv.step(self._actions)
        done = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(done):
            infos[i] = {"terminal_observation": info["final_obs"][i],
                        "TimeLimit.truncated": bool(truncated[i] and not terminated[i]),
                        "episode": {"r": float(info["episode_return"][i]), "l": int(info["episode_length"][i])}}
        return obs, reward, done, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self.venv, attr_name)] * len(self._get_indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *args: Any, indices: Any = None, **kwargs: Any) -> list[Any]:
        return [getattr(self.venv, method_name)(*args, **kwargs)] * len(self._get_indices(indices))

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(self._get_indices(indices))

    def _get_indices(self, indices: Any) -> Sequence[int]:
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else indices


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="CartPole")
    p.add_argument("--obs", default="state", choices=["state", "pixels"])
    p.add_argument("--num-envs", type=int, default=8)
    p.add_argument("--resolution", type=int, default=64, help="frames (obs=pixels; SB3's CnnPolicy needs >= 36)")
    p.add_argument("--timesteps", type=int, default=4096)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    venv = make_vec(args.env, args.num_envs, obs=args.obs, autoreset_mode="same_step",
                    render=args.obs == "pixels", resolution=args.resolution)
    env = SB3VecEnv(venv)
    policy = "CnnPolicy" if args.obs == "pixels" else "MlpPolicy"
    model = PPO(policy, env, n_steps=128, batch_size=256, n_epochs=4, learning_rate=3e-4, seed=args.seed,
                verbose=0, device="cpu")
    t0 = time.time()
    model.learn(total_timesteps=args.timesteps)
    train_s = time.time() - t0
    returns = [ep["r"] for ep in model.ep_info_buffer]
    print(f"{args.timesteps} steps in {train_s:.0f} s ({args.timesteps / train_s:.0f} steps/s); "
          f"mean return of the last {len(returns)} training episodes: {np.mean(returns):.1f}")

    # greedy evaluation: one episode per world
    obs = env.reset()
    ret, alive = np.zeros(args.num_envs), np.ones(args.num_envs, bool)
    while alive.any():
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, done, _ = env.step(action)
        ret += reward * alive
        alive &= ~done
    print(f"greedy return per world: {ret.round(1).tolist()} (mean {ret.mean():.1f})")


if __name__ == "__main__":
    main()
