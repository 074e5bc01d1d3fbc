"""The two sides of the Incline parity (`pybullet_compat.parity_incline`), driven from the same
episode parameters and states: bulbjax's MJX mirror (`InclineMirror`, JAX imported only when one
is built) and the PyBullet original (`BulletSide`), with the comparison's sizes
(`InclineParityConfig`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from pybullet_compat import incline as pbi


@dataclass(frozen=True)
class InclineParityConfig:
    """Sizes of the comparison. `worlds` MJX worlds run every batch (starts, sweep points and
    analytic cases are padded to it), so one compile serves all runs of `steps` steps."""

    name: str = "GeomOnIncline"
    version: int = 0
    worlds: int = 8
    steps: int = 50  # env steps per run (0.04 s each)
    seed: int = 0
    sweep_steps: int = 8  # distance compared after this many steps
    sweep_push: float = -0.5  # action of the mass sweep (a force of -1 N, against the slide)
    checkpoints: tuple[float, ...] = (0.2, 0.4, 0.8, 1.2, 2.0)  # seconds
    analytic_v0: float = 0.5  # m/s down the slope
    ycb_dir: str | None = None
    cache_dir: str | None = None

    def __post_init__(self) -> None:
        pbi.incline_domain(self.name)
        if self.worlds < 1 or self.steps < 2 or not 1 <= self.sweep_steps <= self.steps:
            raise ValueError(f"bad sizes: worlds={self.worlds}, steps={self.steps}, sweep_steps={self.sweep_steps}")


# ---------------------------------------------------------------------------------- MJX side
class InclineMirror:
    """The MJX Incline env of `cfg.worlds` worlds (no frames) driven from fixed draws or states:
    `reset` (bulb's reset with fixed draws), `place` (object put at given poses/velocities after
    a reset with the given draws), `play` (the physics of `steps` env steps, no auto-reset)."""

    def __init__(self, cfg: InclineParityConfig):
        import jax

        import bulbjax

        self.cfg = cfg
        self.env = bulbjax.make(cfg.name, num_envs=cfg.worlds, version=cfg.version, render=False,
                                **({"ycb_dir": cfg.ycb_dir} if cfg.ycb_dir else {}))
        self.n = cfg.worlds
        self._reset = jax.jit(lambda k, fx: self.env.reset_with(k, **fx))
        self._place = jax.jit(self._place_impl)
        self._play = jax.jit(self._play_impl)
        self.qadr = int(self.env._obj_qadr[0])
        self.vadr = int(self.env._obj_vadr[0])

    def _fixed(self, params: list[pbi.InclineParams]) -> dict[str, Any]:
        import jax.numpy as jnp

        params = pad(params, self.n)
        out = {k: jnp.asarray([getattr(p, k) for p in params], jnp.float32) for k in pbi.RESET_FIELDS}
        out["texture"] = out["texture"].astype(jnp.int32)
        return out

    def reset(self, params: list[pbi.InclineParams], seed: int = 0) -> Any:
        """bulb's reset (initial fall included) of every world with the given draws."""
        import jax

        return self._reset(jax.random.PRNGKey(seed), self._fixed(params))

    def _place_impl(self, state: Any, qpos: Any, qvel: Any) -> Any:
        import jax
        import jax.numpy as jnp
        from mujoco import mjx

        d = state.data
        q = d.qpos.at[:, self.qadr:self.qadr + 7].set(qpos)
        v = d.qvel.at[:, self.vadr:self.vadr + 6].set(qvel)
        d = d.replace(qpos=q, qvel=v, qacc_warmstart=jnp.zeros_like(d.qacc_warmstart))
        # the per-world model fields carry a world axis that the Warp kernels index (as in the env)
        d = jax.vmap(mjx.forward, in_axes=(None, 0))(self.env._world_model(state.params), d)
        return state.replace(data=d)

    def place(self, params: list[pbi.InclineParams], qpos: np.ndarray, qvel: np.ndarray) -> Any:
        """A reset with `params`, then every world's object at (qpos [n, 7], qvel [n, 6])."""
        state = self.reset(params)
        return self._place(state, np.asarray(pad_rows(qpos, self.n), np.float32),
                           np.asarray(pad_rows(qvel, self.n), np.float32))

    def _play_impl(self, state: Any, actions: Any) -> Any:
        import jax
        import jax.numpy as jnp

        def body(data, a):
            data = self.env.physics(data, a[:, None], state.params)
            return data, self.env.raw_state(data, state.params)

        raw0 = self.env.raw_state(state.data, state.params)
        raws = jax.lax.scan(body, state.data, actions)[1]
        return jnp.concatenate([raw0[None], raws])

    def play(self, state: Any, actions: np.ndarray) -> np.ndarray:
        """Raw states [T + 1, n, 20] (entry 0 is the start) under actions [T, n] (in [-1, 1])."""
        acts = np.zeros((actions.shape[0], self.n), np.float32)
        acts[:, :actions.shape[1]] = actions
        return np.asarray(self._play(state, acts), np.float64)

    def raw(self, state: Any) -> np.ndarray:
        return np.asarray(state.info["lowdim_raw"], np.float64)


def pad(params: list[Any], n: int) -> list[Any]:
    if not 1 <= len(params) <= n:
        raise ValueError(f"need 1..{n} parameter sets, got {len(params)}")
    return list(params) + [params[-1]] * (n - len(params))


def pad_rows(a: np.ndarray, n: int) -> np.ndarray:
    a = np.asarray(a)
    return np.concatenate([a, np.repeat(a[-1:], n - a.shape[0], 0)]) if a.shape[0] < n else a


# ---------------------------------------------------------------------------------- PyBullet side
class BulletSide:
    """One PyBullet env reused for every start (the object's state and draws are reset each time)."""

    def __init__(self, cfg: InclineParityConfig, bullet_damping: bool = True, inertia: str = "bullet"):
        self.env = pbi.InclineBulletEnv(cfg.name, cfg.version, render=False, ycb_dir=cfg.ycb_dir,
                                        cache_dir=cfg.cache_dir, bullet_damping=bullet_damping, inertia=inertia)

    def play(self, params: list[pbi.InclineParams], actions: np.ndarray,
             starts: np.ndarray | None = None) -> np.ndarray:
        """Raw states [T + 1, n, 20]: from bulb's own reset with each draw, or (starts given:
        [n, 13] = pos, quat wxyz, lin, ang body) from that state on the pitched incline."""
        T, n = actions.shape[0], len(params)
        out = np.zeros((T + 1, n, len(pbi.RAW_NAMES)))
        for i, pr in enumerate(params):
            if starts is None:
                self.env.reset(**asdict(pr))
            else:
                self.env.place(pr)
                s = starts[i]
                self.env.set_pose_velocity(s[:3], s[3:7], s[7:10], s[10:13])
            out[0, i] = self.env.raw_state()
            for t in range(T):
                self.env.physics(float(np.clip(actions[t, i], -1, 1)))
                out[t + 1, i] = self.env.raw_state()
        return out

    def close(self) -> None:
        self.env.close()
