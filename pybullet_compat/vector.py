"""N PyBullet envs stepped together, with auto-reset, as bulb trained with many parallel envs.

The envs are bulb's pybullet_envs domains (`BulletPixelEnv`), the Incline originals
(`pybullet_compat.incline.InclineBulletEnv`) or the Rearrange originals
(`pybullet_compat.rearrange_env.RearrangeBulletEnv`), picked by name; `env_kwargs` go to the
Incline/Rearrange constructor, e.g. `version`, or `shape` / `objects` prepared in the parent so
that workers never import JAX.
`ProcessVecEnv` runs one env per process (multiprocessing, one pipe each; 'spawn' by default so
it is safe after JAX started threads), `SerialVecEnv` runs the same in this process. Both return
batched arrays with bulbjax's conventions: frames [N, H, W, 3] uint8, states [N, D] float32,
rewards, terminated/truncated flags, and on a finished episode the first frame/state of the next
one, with `info['episode_return'/'episode_length']` valid where done.
"""

from __future__ import annotations

import multiprocessing as mp
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from pybullet_compat.envs import DOMAINS, BulletPixelEnv, domain
from pybullet_compat.incline import INCLINE_DOMAINS, InclineBulletEnv, incline_domain
from pybullet_compat.rearrange_env import RearrangeBulletEnv
from pybullet_compat.rearrange_scene import REARRANGE_DOMAINS, rearrange_domain


def any_domain(name: str) -> Any:
    """The spec of a pybullet_envs domain (`DomainSpec`), an Incline domain (`InclineSpec`) or a
    Rearrange domain (`RearrangeSpec`); an unknown name lists them all."""
    if name in INCLINE_DOMAINS:
        return incline_domain(name)
    if name in REARRANGE_DOMAINS:
        return rearrange_domain(name)
    try:
        return domain(name)
    except ValueError:
        raise ValueError(f"unknown PyBullet domain {name!r}; available: "
                         f"{', '.join([*DOMAINS, *INCLINE_DOMAINS, *REARRANGE_DOMAINS])}") from None


@dataclass(frozen=True)
class VecConfig:
    """What every env of a vector is made with."""

    name: str
    resolution: int = 64
    render: bool = True
    env_kwargs: tuple[tuple[str, Any], ...] = ()  # constructor options of Incline / Rearrange envs

    def make(self) -> Any:
        if self.name in INCLINE_DOMAINS:
            return InclineBulletEnv(self.name, resolution=self.resolution, render=self.render, **dict(self.env_kwargs))
        if self.name in REARRANGE_DOMAINS:
            return RearrangeBulletEnv(self.name, resolution=self.resolution, render=self.render, **dict(self.env_kwargs))
        if self.env_kwargs:
            raise ValueError(f"{self.name} takes no env_kwargs, got {dict(self.env_kwargs)}")
        return BulletPixelEnv(self.name, self.resolution, self.render)


class _AutoResetEnv:
    """One env plus auto-reset: what a worker process (or the serial vector) holds."""

    def __init__(self, cfg: VecConfig):
        self.env = cfg.make()

    def reset(self, seed: int | None) -> tuple[np.ndarray, np.ndarray]:
        return self.env.reset(seed)

    def step(self, action: Any) -> tuple:
        r = self.env.step(action)
        frame, state = r.frame, r.state
        if r.terminated or r.truncated:
            frame, state = self.env.reset()
        return frame, state, r.reward, r.terminated, r.truncated, r.info["episode_return"], r.info["episode_length"]

    def set_state(self, qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.env.set_qpos_qvel(qpos, qvel)

    def get_state(self) -> tuple[np.ndarray, np.ndarray]:
        return self.env.get_qpos_qvel()


def _worker(remote: Any, cfg: VecConfig) -> None:
    """Process main loop: build the env, then serve (command, payload) messages until 'close'."""
    try:
        env = _AutoResetEnv(cfg)
        remote.send(("ok", None))
    except Exception as err:  # report construction errors (e.g. pybullet missing) to the parent
        remote.send(("error", repr(err)))
        remote.close()
        return
    while True:
        cmd, payload = remote.recv()
        try:
            if cmd == "close":
                env.env.close()
                remote.close()
                return
            out = getattr(env, cmd)(*payload)
            remote.send(("ok", out))
        except Exception as err:
            remote.send(("error", repr(err)))


def _stack(outs: Sequence[tuple]) -> tuple[np.ndarray, ...]:
    return tuple(np.stack([o[i] for o in outs]) for i in range(len(outs[0])))


class _VecBase:
    """Shared batching logic; subclasses implement `_call(cmd, payloads) -> list of results`."""

    num_envs: int
    cfg: VecConfig

    def __init__(self, name: str, num_envs: int, resolution: int, render: bool,
                 env_kwargs: Mapping[str, Any] | Sequence[Mapping[str, Any]] | None = None):
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.spec = any_domain(name)
        self.num_envs = num_envs
        per_env = env_kwargs if isinstance(env_kwargs, (list, tuple)) else [env_kwargs or {}] * num_envs
        if len(per_env) != num_envs:
            raise ValueError(f"need one env_kwargs per env ({num_envs}), got {len(per_env)}")
        self.cfgs = [VecConfig(name, resolution, render, tuple(sorted(kw.items()))) for kw in per_env]
        self.cfg = self.cfgs[0]

    def _call(self, cmd: str, payloads: Sequence[tuple]) -> list[Any]:
        raise NotImplementedError

    def reset(self, seeds: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Reset all envs (env i seeded with `seeds[i]`) -> frames [N, H, W, 3], states [N, D]."""
        seeds = [None] * self.num_envs if seeds is None else [int(s) for s in seeds]
        if len(seeds) != self.num_envs:
            raise ValueError(f"need {self.num_envs} seeds, got {len(seeds)}")
        frames, states = _stack(self._call("reset", [(s,) for s in seeds]))
        return frames, states.astype(np.float32)

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        """Step every env -> (frames, states, rewards [N], terminated [N], truncated [N], info).

        Where an episode ended, frames/states are the next episode's first ones and
        `info['episode_return'/'episode_length']` describe the finished episode."""
        actions = np.asarray(actions)
        if actions.shape[0] != self.num_envs:
            raise ValueError(f"need actions for {self.num_envs} envs, got shape {actions.shape}")
        frames, states, rew, term, trunc, ep_ret, ep_len = _stack(self._call("step", [(a,) for a in actions]))
        done = term | trunc
        info = {"episode_return": np.where(done, ep_ret, 0.0), "episode_length": np.where(done, ep_len, 0)}
        return frames, states.astype(np.float32), rew.astype(np.float32), term, trunc, info

    def set_qpos_qvel(self, qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Put env i in the physical state (qpos[i], qvel[i]) -> frames, states."""
        frames, states = _stack(self._call("set_state", list(zip(np.asarray(qpos), np.asarray(qvel)))))
        return frames, states.astype(np.float32)

    def get_qpos_qvel(self) -> tuple[np.ndarray, np.ndarray]:
        """Physical states of all envs (qpos [N, nq], qvel [N, nv])."""
        return _stack(self._call("get_state", [()] * self.num_envs))

    def close(self) -> None:
        pass

    def __enter__(self) -> "_VecBase":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class SerialVecEnv(_VecBase):
    """N envs in this process (the reference the process version must reproduce)."""

    def __init__(self, name: str, num_envs: int, resolution: int = 64, render: bool = True,
                 env_kwargs: Mapping[str, Any] | Sequence[Mapping[str, Any]] | None = None):
        super().__init__(name, num_envs, resolution, render, env_kwargs)
        self.envs = [_AutoResetEnv(cfg) for cfg in self.cfgs]

    def _call(self, cmd: str, payloads: Sequence[tuple]) -> list[Any]:
        return [getattr(e, cmd)(*p) for e, p in zip(self.envs, payloads)]

    def close(self) -> None:
        for e in self.envs:
            e.env.close()
        self.envs = []


class ProcessVecEnv(_VecBase):
    """N envs, one per process, talking over pipes: all commands are sent, then all replies read."""

    def __init__(self, name: str, num_envs: int, resolution: int = 64, render: bool = True,
                 start_method: str = "spawn",
                 env_kwargs: Mapping[str, Any] | Sequence[Mapping[str, Any]] | None = None):
        super().__init__(name, num_envs, resolution, render, env_kwargs)
        ctx = mp.get_context(start_method)
        self._remotes, self._procs = [], []
        for cfg in self.cfgs:
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(child, cfg), daemon=True)
            proc.start()
            child.close()
            self._remotes.append(parent)
            self._procs.append(proc)
        for status, msg in (r.recv() for r in self._remotes):
            if status != "ok":
                self.close()
                raise RuntimeError(f"a PyBullet worker failed to start: {msg}")

    def _call(self, cmd: str, payloads: Sequence[tuple]) -> list[Any]:
        for r, p in zip(self._remotes, payloads):
            r.send((cmd, p))
        out = []
        for r in self._remotes:
            status, val = r.recv()
            if status != "ok":
                raise RuntimeError(f"PyBullet worker error in {cmd!r}: {val}")
            out.append(val)
        return out

    def close(self) -> None:
        for r in self._remotes:
            try:
                r.send(("close", ()))
            except (BrokenPipeError, OSError):
                pass
        for p in self._procs:
            p.join(timeout=5)
            if p.is_alive():
                p.terminate()
        self._remotes, self._procs = [], []

    def __del__(self) -> None:
        if getattr(self, "_procs", None):
            self.close()
