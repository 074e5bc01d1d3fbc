"""bulbjax's MJX mirror driven from a given physical state, for side-by-side comparison.

`MjxMirror` puts every world of `bulbjax.make(name, render=False)` into given (qpos, qvel) and
plays actions along two paths in one `lax.scan` (per-step jit calls cost ~4x more on the CPU):
- the env path: the public `env.step` (its control mapping, frame skip, state, reward and
  termination), which gives rewards and where each episode ends;
- the physics path: the same physics without termination or auto-reset (`mjx.step` x
  `frame_skip` on the env's control, then its state), so trajectories can be compared past the
  point where an episode would end, as the PyBullet env keeps stepping when asked to.
Both are identical until an episode ends. The physics path uses the env's `_ctrl` and `_lowdim`
hooks (the mirror's own definitions of control and state). The MJX model is an argument of the
compiled rollouts, so an edited model (`pybullet_compat.parity.patch_mirror`) reuses them.
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

Policy = Callable[[jax.Array, jax.Array], jax.Array]  # (states [N, D], key) -> actions


class MjxMirror:
    """Batched MJX mirror of domain `name` with `num_envs` worlds, started from given states."""

    def __init__(self, name: str, num_envs: int, env: Any | None = None):
        import bulbjax

        self.name = name
        self.env = env if env is not None else bulbjax.make(name, num_envs=num_envs, render=False)
        self.num_envs = self.env.num_envs
        self.frame_skip = int(getattr(self.env, "frame_skip", 1))
        self.dt = float(self.env.mj_model.opt.timestep) * self.frame_skip
        self._state0 = self.env.reset(jax.random.PRNGKey(0))
        self._start = jax.jit(self._start_impl)
        self._runs: dict[Any, Callable] = {}

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(e.name for e in self.env.state_spec)

    @contextlib.contextmanager
    def _model(self, mx: Any):
        """Let the env's own methods read `mx` (a traced argument) as its model while tracing."""
        saved = self.env.mx
        self.env.mx = mx
        try:
            yield
        finally:
            self.env.mx = saved

    def _start_impl(self, mx: Any, state0: Any, qpos: jax.Array, qvel: jax.Array) -> Any:
        d0 = state0.data
        data = d0.replace(qpos=qpos, qvel=qvel, qacc_warmstart=jnp.zeros_like(d0.qacc_warmstart))
        data = jax.vmap(mjx.forward, in_axes=(None, 0))(mx, data)
        lowdim = jax.vmap(self.env._lowdim)(data)
        zeros = jnp.zeros(self.num_envs)
        return state0.replace(data=data, obs=lowdim, lowdim=lowdim, reward=zeros, done=zeros, truncated=zeros,
                              step_count=jnp.zeros(self.num_envs, jnp.int32), episode_return=zeros)

    def start(self, qpos: Any, qvel: Any) -> Any:
        """An `EnvState` with every world at (qpos[i], qvel[i]) after a forward pass."""
        qpos = jnp.asarray(np.asarray(qpos), jnp.float32).reshape(self.num_envs, -1)
        qvel = jnp.asarray(np.asarray(qvel), jnp.float32).reshape(self.num_envs, -1)
        nq, nv = self.env.mj_model.nq, self.env.mj_model.nv
        if qpos.shape[1] != nq or qvel.shape[1] != nv:
            raise ValueError(f"{self.name}: the mirror has nq={nq}, nv={nv}; got {qpos.shape[1]}, {qvel.shape[1]}")
        return self._start(self.env.mx, self._state0, qpos, qvel)

    def _physics(self, data: Any, action: jax.Array) -> tuple[Any, jax.Array]:
        data = self.env.physics(data, action)
        return data, jax.vmap(self.env._lowdim)(data)

    def _run(self, mx: Any, state: Any, xs: Any, steps: int, policy: Policy | None) -> dict[str, jax.Array]:
        def body(carry, x):
            es, data, obs = carry
            action = x if policy is None else policy(obs, x)
            action = action.astype(jnp.int32 if self.env.discrete else jnp.float32)
            es = self.env.step(es, action)
            data, lowdim = self._physics(data, action)
            out = dict(state=lowdim, reward=es.reward, done=es.done, truncated=es.truncated,
                       qpos=data.qpos, qvel=data.qvel, action=action)
            return (es, data, lowdim), out

        with self._model(mx):
            return jax.lax.scan(body, (state, state.data, state.obs), xs, length=steps)[1]

    def play(self, qpos: Any, qvel: Any, actions: Any) -> dict[str, np.ndarray]:
        """Open loop: actions [T, N, ...] from (qpos, qvel). Returns [T, N, ...] arrays (entry t
        is after action t): state, qpos, qvel (physics path); reward, done, truncated (env path,
        valid up to and including each world's first done); action."""
        actions = jnp.asarray(np.asarray(actions), jnp.int32 if self.env.discrete else jnp.float32)
        steps = int(actions.shape[0])
        key = ("play", steps)
        if key not in self._runs:
            self._runs[key] = jax.jit(lambda mx, s, xs: self._run(mx, s, xs, steps, None))
        return _to_numpy(self._runs[key](self.env.mx, self.start(qpos, qvel), actions))

    def play_policy(self, qpos: Any, qvel: Any, policy: Policy, steps: int, key: jax.Array,
                    policy_id: Any = None) -> dict[str, np.ndarray]:
        """Closed loop: `policy(states, key)` on the physics path's own states for `steps` steps;
        returns what `play` returns. `policy_id` caches the compiled rollout per policy."""
        ck = ("policy", steps, policy_id if policy_id is not None else id(policy))
        if ck not in self._runs:
            self._runs[ck] = jax.jit(lambda mx, s, xs: self._run(mx, s, xs, steps, policy))
        return _to_numpy(self._runs[ck](self.env.mx, self.start(qpos, qvel), jax.random.split(key, steps)))


def _to_numpy(d: dict[str, Any]) -> dict[str, np.ndarray]:
    return {k: np.asarray(v) for k, v in d.items()}
