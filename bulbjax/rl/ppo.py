"""Proximal Policy Optimisation (clipped objective, GAE), PureJaxRL style.

Everything here is per seed and pure: the caller vmaps `PPO.init`, `rollout` and
`PPO.update` over seeds and jits the whole training epoch.  The `train` helper
shows (and tests) the canonical loop: one `jax.jit` around a `lax.scan` over updates.

Truncation vs termination in GAE.  The environments auto-reset, so the observation
that ended a truncated (time-limit) episode is lost.  With `bootstrap_truncated`
(default) a truncated step gets the reward `r_t + gamma * V(s_t)`, i.e. the value of
the missing final observation `s_{t+1}` is approximated by the value of the last
observation we did see (one physics step earlier), and the GAE trace is then cut as
for a termination.  Terminated steps bootstrap with 0.  Without it, truncation is
treated as termination (the common, slightly biased, choice).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Optional

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
from flax import struct

from bulbjax.data.augment import random_shift
from bulbjax.rl.networks import DiscreteActorCritic, GaussianActorCritic, PixelActorCritic
from bulbjax.rl.ppo_config import PPOConfig, lr_factor

_LOG_2PI = math.log(2.0 * math.pi)


def _is_log_std(path: tuple) -> bool:
    return bool(path) and getattr(path[-1], "key", None) == "log_std"


def floor_log_std(params: Any, floor: float) -> Any:
    """`params` with every `log_std` parameter (Gaussian heads) raised to at least `floor`."""
    return jax.tree_util.tree_map_with_path(
        lambda path, x: jnp.maximum(x, floor) if _is_log_std(path) else x, params)


def mean_log_std(params: Any) -> jax.Array:
    """Mean of the Gaussian head's `log_std` parameter (NaN when the policy has none)."""
    leaves = [x for path, x in jax.tree_util.tree_flatten_with_path(params)[0] if _is_log_std(path)]
    return jnp.mean(jnp.concatenate([x.ravel() for x in leaves])) if leaves else jnp.asarray(jnp.nan)


@struct.dataclass
class RunningStats:
    """Running mean/variance (parallel Welford), used to normalise observations."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @classmethod
    def create(cls, size: int) -> "RunningStats":
        return cls(jnp.zeros(size), jnp.ones(size), jnp.asarray(1e-4, jnp.float32))

    def update(self, x: jax.Array) -> "RunningStats":
        x = x.reshape(-1, x.shape[-1])
        n = x.shape[0]
        b_mean, b_var = x.mean(0), x.var(0)
        delta = b_mean - self.mean
        tot = self.count + n
        mean = self.mean + delta * n / tot
        m2 = self.var * self.count + b_var * n + delta**2 * self.count * n / tot
        return RunningStats(mean, m2 / tot, tot)


@struct.dataclass
class PPOState:
    """Per-seed learner state."""

    params: Any
    opt_state: Any
    obs_stats: RunningStats
    step: jax.Array  # number of updates done (int32)


@struct.dataclass
class Transition:
    """One rollout, leading axes [T, N]. `obs` is the raw observation the action was taken in."""

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    done: jax.Array
    truncated: jax.Array
    log_prob: jax.Array
    value: jax.Array


def _sequential_under_vmap(fn: Callable[[jax.Array], Any]) -> Callable[[jax.Array], Any]:
    """`fn(key)` whose vmap over keys runs as `jax.lax.map` (one key at a time)."""

    @jax.custom_batching.custom_vmap
    def wrapped(key: jax.Array) -> Any:
        return fn(key)

    @wrapped.def_vmap
    def _rule(axis_size: int, in_batched: Any, key: jax.Array) -> tuple[Any, Any]:
        out = jax.lax.map(fn, key)
        return out, jax.tree.map(lambda _: True, out)

    return wrapped


def compute_gae(
    reward: jax.Array,
    value: jax.Array,
    done: jax.Array,
    truncated: jax.Array,
    last_value: jax.Array,
    gamma: float,
    gae_lambda: float,
    bootstrap_truncated: bool = True,
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimation over [T, ...] arrays; returns (advantages, value targets).

    `done` cuts the trace (terminated or truncated); with `bootstrap_truncated` a truncated
    step's reward is augmented by `gamma * value_t` as a stand-in for the lost final state's value.
    """
    if bootstrap_truncated:
        reward = reward + gamma * truncated * value

    def body(carry, x):
        gae, next_value = carry
        r, v, d = x
        delta = r + gamma * next_value * (1.0 - d) - v
        gae = delta + gamma * gae_lambda * (1.0 - d) * gae
        return (gae, v), gae

    _, adv = jax.lax.scan(body, (jnp.zeros_like(last_value), last_value), (reward, value, done), reverse=True)
    return adv, adv + value


class PPO:
    """PPO for one seed. `num_actions` set -> categorical policy; else Gaussian over `action_size` dims.

    `frame_shape` set (e.g. `(64, 64, 3)`): observations are uint8 frames of that shape, seen
    through a conv torso trained end to end with the policy (`PixelActorCritic`); no running
    observation statistics then (the torso scales pixels itself) and `obs_size` is ignored.
    """

    def __init__(
        self,
        config: PPOConfig,
        obs_size: int,
        num_actions: Optional[int] = None,
        action_size: int = 1,
        frame_shape: Optional[tuple[int, int, int]] = None,
    ):
        self.config = config
        self.frame_shape = tuple(frame_shape) if frame_shape is not None else None
        self.pixels = self.frame_shape is not None
        if self.pixels and len(self.frame_shape) != 3:
            raise ValueError(f"frame_shape must be (H, W, C), got {frame_shape}")
        self.obs_size = 0 if self.pixels else obs_size
        self.num_actions = num_actions
        self.action_size = action_size
        self.discrete = num_actions is not None
        if self.discrete:
            self.network: nn.Module = DiscreteActorCritic(num_actions, tuple(config.hidden))
        else:
            self.network = GaussianActorCritic(action_size, tuple(config.hidden), config.init_log_std)
        if self.pixels:
            self.network = PixelActorCritic(self.network)
        # The anneal (`lr_factor`) scales Adam's step in `update`: the optimiser state is the
        # constant-lr one either way, and the schedule follows PPO's update count.
        self.tx = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.lr, eps=1e-5))

    @classmethod
    def for_env(cls, config: PPOConfig, env: Any) -> "PPO":
        """Build from an environment's `obs_size`, `discrete`, `num_actions`, `action_size`."""
        return cls(config, env.obs_size, env.num_actions if env.discrete else None, getattr(env, "action_size", 1))

    # ------------------------------------------------------------------ state / acting
    def init(self, key: jax.Array) -> PPOState:
        """Fresh per-seed state. Under `jax.vmap` over keys the seeds are initialised one after
        another (`lax.map`): the vmapped orthogonal (QR) initialiser hung XLA:CPU (jax 0.10.2)."""
        return _sequential_under_vmap(self._init_one)(key)

    def _init_one(self, key: jax.Array) -> PPOState:
        dummy = (jnp.zeros((1,) + self.frame_shape, jnp.uint8) if self.pixels
                 else jnp.zeros((1, self.obs_size)))
        params = self.network.init(key, dummy)
        stats = RunningStats.create(max(self.obs_size, 1))  # unused (size 1) for frames
        return PPOState(params, self.tx.init(params), stats, jnp.zeros((), jnp.int32))

    def normalize(self, state: PPOState, obs: jax.Array) -> jax.Array:
        """Normalise raw observations with the state's running statistics (identity if disabled,
        and for frames, which the pixel torso scales)."""
        if not self.config.normalize_obs or self.pixels:
            return obs
        s = state.obs_stats
        z = (obs - s.mean) / jnp.sqrt(s.var + 1e-8)
        return jnp.clip(z, -self.config.obs_clip, self.config.obs_clip)

    def _evaluate(self, params: Any, nobs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(log_prob, entropy, value) of `action` under the policy at normalised obs."""
        if self.discrete:
            logits, value = self.network.apply(params, nobs)
            logp_all = jax.nn.log_softmax(logits)
            logp = jnp.take_along_axis(logp_all, action[..., None].astype(jnp.int32), -1)[..., 0]
            entropy = -(jnp.exp(logp_all) * logp_all).sum(-1)
        else:
            mean, log_std, value = self.network.apply(params, nobs)
            z = (action - mean) * jnp.exp(-log_std)
            logp = (-0.5 * z**2 - log_std - 0.5 * _LOG_2PI).sum(-1)
            entropy = (log_std + 0.5 * (1.0 + _LOG_2PI)).sum(-1)
        return logp, entropy, value

    def act(
        self, state: PPOState, obs: jax.Array, key: jax.Array, deterministic: bool = False
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Sample actions for raw obs [N, obs_size] -> (action, log_prob [N], value [N]).

        Discrete: int32 [N]. Continuous: float32 [N, action_size], the *unclipped* Gaussian
        sample (log_prob refers to it); pass it through `env_action` before `env.step`.
        `deterministic` returns the mode (argmax / mean) instead of a sample.
        """
        nobs = self.normalize(state, obs)
        if self.discrete:
            logits, value = self.network.apply(state.params, nobs)
            if deterministic:
                action = jnp.argmax(logits, -1)
            else:
                action = jax.random.categorical(key, logits)
            action = action.astype(jnp.int32)
            logp = jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], -1)[..., 0]
        else:
            mean, log_std, value = self.network.apply(state.params, nobs)
            if deterministic:
                action = mean
            else:
                action = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
            z = (action - mean) * jnp.exp(-log_std)
            logp = (-0.5 * z**2 - log_std - 0.5 * _LOG_2PI).sum(-1)
        return action, logp, value

    def env_action(self, action: jax.Array) -> jax.Array:
        """Map a policy action to what `env.step` takes (clip continuous actions to [-1, 1])."""
        return action if self.discrete else jnp.clip(action, -1.0, 1.0)

    def random_act(self, key: jax.Array, n: int) -> jax.Array:
        """Random policy pi_rand: uniform over actions (int32 [n]) or uniform in [-1, 1] ([n, action_size])."""
        if self.discrete:
            return jax.random.randint(key, (n,), 0, self.num_actions, jnp.int32)
        return jax.random.uniform(key, (n, self.action_size), minval=-1.0, maxval=1.0)

    # ------------------------------------------------------------------ learning
    def _loss(self, params: Any, mb: dict, key: jax.Array | None = None) -> tuple[jax.Array, dict]:
        cfg = self.config
        obs = mb["obs"]
        if self.pixels and cfg.pixel_shift > 0 and key is not None:  # frames [B, H, W, C]
            obs = random_shift(key, obs, cfg.pixel_shift)
        logp, entropy, value = self._evaluate(params, obs, mb["action"])
        log_ratio = logp - mb["log_prob"]
        ratio = jnp.exp(log_ratio)
        adv = mb["adv"]
        if cfg.normalize_advantages:
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        pg_loss = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - cfg.clip_eps, 1.0 + cfg.clip_eps) * adv).mean()
        v_err = (value - mb["target"]) ** 2
        if cfg.value_clip_eps is not None:
            v_clip = mb["value"] + jnp.clip(value - mb["value"], -cfg.value_clip_eps, cfg.value_clip_eps)
            v_err = jnp.maximum(v_err, (v_clip - mb["target"]) ** 2)
        v_loss = 0.5 * v_err.mean()
        ent = entropy.mean()
        total = pg_loss + cfg.vf_coef * v_loss - cfg.ent_coef * ent
        metrics = dict(
            total_loss=total,
            policy_loss=pg_loss,
            value_loss=v_loss,
            entropy=ent,
            approx_kl=((ratio - 1.0) - log_ratio).mean(),
            clip_frac=(jnp.abs(ratio - 1.0) > cfg.clip_eps).mean(),
        )
        return total, metrics

    def update(
        self, state: PPOState, traj: Transition, last_obs: jax.Array, key: jax.Array
    ) -> tuple[PPOState, dict]:
        """GAE + `update_epochs` epochs of shuffled minibatch steps on the clipped objective.

        Metrics (means over the minibatch steps): the losses, entropy, approx KL, clip fraction,
        `lr` (the annealed rate), `update_frac` (share of steps applied; < 1 after a KL stop),
        `obs_mean_shift` / `obs_std_shift` (how far the observation statistics moved, in old
        standard deviations / |log std ratio|), and for Gaussian policies `log_std_mean`.
        Observations are normalised with the statistics the rollout was collected with (so the
        first ratio is exactly 1); the statistics are then updated with this rollout's obs.
        """
        cfg = self.config
        nobs = self.normalize(state, traj.obs)
        last_value = self.network.apply(state.params, self.normalize(state, last_obs))[-1]
        adv, target = compute_gae(
            traj.reward * cfg.reward_scale,
            traj.value,
            traj.done,
            traj.truncated,
            last_value,
            cfg.gamma,
            cfg.gae_lambda,
            cfg.bootstrap_truncated,
        )
        batch = dict(obs=nobs, action=traj.action, log_prob=traj.log_prob, value=traj.value, adv=adv, target=target)
        batch_size = traj.reward.size
        assert batch_size % cfg.num_minibatches == 0, "T * N must be divisible by num_minibatches"
        batch = jax.tree.map(lambda x: x.reshape((batch_size,) + x.shape[2:]), batch)

        steps_per_update = cfg.update_epochs * cfg.num_minibatches
        aug_key = jax.random.fold_in(key, 0x5EED)  # leaves `key`'s permutations as they were

        def minibatch_step(carry, xs):
            params, opt_state, stopped = carry
            mb, j = xs  # j: the minibatch step's index within this update
            # the frames' shifts (cfg.pixel_shift), drawn apart from the minibatches' order
            grads, metrics = jax.grad(self._loss, has_aux=True)(params, mb, jax.random.fold_in(aug_key, j))
            updates, new_opt = self.tx.update(grads, opt_state, params)
            factor = lr_factor(cfg, state.step + j / steps_per_update)
            if cfg.anneal_updates > 0:
                updates = jax.tree.map(lambda u: u * factor, updates)
            new_params = optax.apply_updates(params, updates)
            if cfg.min_log_std is not None:
                new_params = floor_log_std(new_params, cfg.min_log_std)
            if cfg.target_kl is not None:  # this step and all later ones of the update are skipped
                stopped = stopped | (metrics["approx_kl"] > 1.5 * cfg.target_kl)
                keep_old = lambda old, new: jnp.where(stopped, old, new)  # noqa: E731
                new_params = jax.tree.map(keep_old, params, new_params)
                new_opt = jax.tree.map(keep_old, opt_state, new_opt)
            metrics = dict(metrics, lr=cfg.lr * factor, update_frac=1.0 - stopped.astype(jnp.float32))
            return (new_params, new_opt, stopped), metrics

        def epoch(carry, xs):
            k, e = xs
            perm = jax.random.permutation(k, batch_size)
            mbs = jax.tree.map(
                lambda x: x[perm].reshape((cfg.num_minibatches, -1) + x.shape[1:]), batch
            )
            return jax.lax.scan(minibatch_step, carry, (mbs, e * cfg.num_minibatches + jnp.arange(cfg.num_minibatches)))

        (params, opt_state, _), metrics = jax.lax.scan(
            epoch, (state.params, state.opt_state, jnp.zeros((), bool)),
            (jax.random.split(key, cfg.update_epochs), jnp.arange(cfg.update_epochs)),
        )
        metrics = jax.tree.map(jnp.mean, metrics)
        obs_stats = self._next_obs_stats(state, traj.obs)
        old, new = state.obs_stats, obs_stats
        metrics["obs_mean_shift"] = jnp.mean(jnp.abs(new.mean - old.mean) / jnp.sqrt(old.var + 1e-8))
        metrics["obs_std_shift"] = jnp.mean(jnp.abs(0.5 * jnp.log((new.var + 1e-8) / (old.var + 1e-8))))
        if not self.discrete:
            metrics["log_std_mean"] = mean_log_std(params)
        new_state = PPOState(params, opt_state, obs_stats, state.step + 1)
        return new_state, metrics

    def _next_obs_stats(self, state: PPOState, obs: jax.Array) -> RunningStats:
        """The observation statistics after an update on rollout `obs`: unchanged without
        normalisation (or for frames), and once `obs_norm_updates` updates are done."""
        cfg = self.config
        if not cfg.normalize_obs or self.pixels:
            return state.obs_stats
        new = state.obs_stats.update(obs)
        if cfg.obs_norm_updates > 0:
            frozen = state.step >= cfg.obs_norm_updates
            new = jax.tree.map(lambda a, b: jnp.where(frozen, a, b), state.obs_stats, new)
        return new


def rollout(
    ppo: PPO,
    ppo_state: PPOState,
    env: Any,
    env_state: Any,
    key: jax.Array,
    num_steps: int,
    extract: Optional[Callable[[Any], Any]] = None,
) -> tuple[Any, Transition, dict]:
    """Run the current policy for `num_steps` in one seed's batched env (lax.scan).

    Returns (env_state, traj [T, N], extras) with extras: `last_obs` [N, obs_size] (for
    `ppo.update`), `episode_return_sum`, `episode_length_sum`, `episode_count` over episodes that
    finished in this rollout, `mean_episode_return` (NaN when none finished), and, if `extract`
    is given, `extracted`: `extract(env_state_after_step)` stacked over [T] (e.g. pixels and
    lowdim for the replay buffer).
    """

    def step(carry, k):
        es = carry
        action, log_prob, value = ppo.act(ppo_state, es.obs, k)
        nes = env.step(es, ppo.env_action(action))
        tr = Transition(es.obs, action, nes.reward, nes.done, nes.truncated, log_prob, value)
        ep = (
            (nes.info["episode_return"] * nes.done).sum(),
            (nes.info["episode_length"] * nes.done).sum(),
            nes.done.sum(),
        )
        out = (tr, ep, extract(nes) if extract is not None else None)
        return nes, out

    env_state, (traj, ep, extracted) = jax.lax.scan(step, env_state, jax.random.split(key, num_steps))
    ret_sum, len_sum, count = (x.sum() for x in ep)
    extras = dict(
        last_obs=env_state.obs,
        episode_return_sum=ret_sum,
        episode_length_sum=len_sum,
        episode_count=count,
        mean_episode_return=jnp.where(count > 0, ret_sum / jnp.maximum(count, 1.0), jnp.nan),
    )
    if extract is not None:
        extras["extracted"] = extracted
    return env_state, traj, extras


def train(env: Any, config: PPOConfig, key: jax.Array, num_updates: int) -> tuple[PPOState, dict]:
    """Standalone PPO training for one seed; the whole loop is a single jit (scan over updates).

    `env` must already be batched (its own num_envs is used). Returns the final PPOState and
    per-update metrics [num_updates]: losses, `episode_count`, and `mean_episode_return` (mean
    return of episodes finished during that update's rollout, carried forward from the previous
    update when none finished; NaN before the first finished episode).
    """
    ppo = PPO.for_env(config, env)

    @jax.jit
    def run(key: jax.Array):
        k_init, k_env, k_loop = jax.random.split(key, 3)
        carry0 = (ppo.init(k_init), env.reset(k_env), jnp.asarray(jnp.nan, jnp.float32))

        def one_update(carry, k):
            ps, es, last_ret = carry
            k_roll, k_upd = jax.random.split(k)
            es, traj, extras = rollout(ppo, ps, env, es, k_roll, config.num_steps)
            ps, metrics = ppo.update(ps, traj, extras["last_obs"], k_upd)
            ret = jnp.where(extras["episode_count"] > 0, extras["mean_episode_return"], last_ret)
            metrics = dict(metrics, mean_episode_return=ret, episode_count=extras["episode_count"])
            return (ps, es, ret), metrics

        (ps, _, _), metrics = jax.lax.scan(one_update, carry0, jax.random.split(k_loop, num_updates))
        return ps, metrics

    return run(key)
