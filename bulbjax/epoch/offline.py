"""The offline fit's programs (`bulbjax fit`): learners trained on one fixed dataset, probed
every M updates, seeds vmapped.

The experiment (`loop.py`) trains learners on a non-stationary replay stream while PPO learns;
this mode isolates the learners: a random-policy dataset (frames, actions, true states, episode
boundaries) is collected once and every learner trains on it with the paper's batches (1,024
frames; 1,024 // L windows of L steps for sequential learners, cut at random starts and at
episode boundaries). Every `probe_every` updates a probe is fit on training data and scored on
held-out random-policy windows (separate worlds), normalised by the held-out states' reference
spread (`bulbjax.eval.probe`). The pieces are the epoch's: its rollout and window cutting collect
the data (`make_source`), `train_learner` / `probe_over_seeds` train and probe (`OfflineFit`).
Driving a fit (the dataset's cache, checkpoints, resume) is `bulbjax.run.offline`; its records
and reports are `bulbjax.report.offline`.

Sources: any registered MJX environment (random policy, as π_rand), or `SyntheticMovers`
(`bulbjax.data.synthetic`: squares at constant velocities, where only sequences can win).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp

from bulbjax.data import sequence, synthetic
from bulbjax.data.sequence import Trajectories, Windows
from bulbjax.epoch.devices import Devices, make_mesh
from bulbjax.epoch.learning import train_learner
from bulbjax.epoch.probing import fit_and_score, probe_latents, probe_over_seeds, probe_targets
from bulbjax.epoch.rollouts.policy import Policy
from bulbjax.epoch.seeds import SeedGroup, Team, learner_loop, over_seeds, resolve_seed_loop, with_seed_loop
from bulbjax.eval import probe
from bulbjax.eval.spec import StateEntry
from bulbjax.learners import is_sequential, make_learner
from bulbjax.offline_config import OfflineConfig


@dataclass(frozen=True)
class Source:
    """Where data comes from: its state spec, frame shape, action width and a collector
    `collect(key, steps) -> Trajectories [steps, data_worlds]` (host-side call, jitted inside)."""

    name: str
    spec: tuple[StateEntry, ...]
    frame_shape: tuple[int, int, int]
    action_dim: int
    collect: Callable[[jax.Array, int], Trajectories]


def make_source(config: OfflineConfig) -> Source:
    """The data source of a config: SyntheticMovers or an MJX env under the random policy."""
    c = config
    if c.synthetic:
        m = c.movers_config()
        gen = jax.jit(lambda k, steps: synthetic.generate(k, m, steps, c.data_worlds), static_argnums=1)
        return Source(synthetic.NAME, m.state_spec, m.frame_shape, m.action_dim, gen)
    b = c.base
    w = c.data_worlds
    # the experiment's env and random-policy rollout (one seed of `data_worlds` worlds); the
    # random policy observes nothing, so no learner is built
    cfg = b.replace(seeds=1, num_envs=w, frames_per_epoch=w, eval_frames=w,
                    replay_capacity=max(b.replay_capacity, w), rl_input="state")
    dev = Devices(cfg)
    policy = Policy(cfg, dev, Team({}, "vmap", SeedGroup(1, w)))

    def _steps(key: jax.Array, steps: int) -> Trajectories:
        k_reset, k_roll = jax.random.split(key)
        _, (ri, low, act, done) = policy.rollout(None, dev.env.reset(k_reset), k_roll, steps, random=True)
        return Trajectories(frames=dev.env.render_sequence(ri), actions=act, states=low, dones=done)

    collect = jax.jit(_steps, static_argnums=1)
    name = b.env + ("Multicolour" if b.multicolour and not b.env.endswith("Multicolour") else "")
    return Source(name, dev.env.state_spec, dev.env.frame_shape, policy.action_dim, collect)


class OfflineFit:
    """Learners (seeds vmapped, or mapped on one GPU) on one dataset; jitted training chunks and probes."""

    def __init__(self, config: OfflineConfig, source: Source | None = None):
        self.config = c = config
        self.source = source or make_source(config)
        b = c.base
        latent = b.latent_factor * len(self.source.spec)
        # learner updates and probe encodings over seeds: lax.map (DSA vmapped, `with_seed_loop`) on
        # one GPU, vmap on the CPU
        self.seed_loop = resolve_seed_loop(b.learner_seed_loop, make_mesh(jax.devices()[:1], b.seeds, 1))
        self.learners = {n: with_seed_loop(make_learner(n, latent, b.learner, self.source.action_dim), self.seed_loop)
                         for n in b.learners}
        # what the probes regress: the state and targets derived from it (`probing.probe_targets`)
        self.targets = probe_targets(self.source.spec)
        self.spec = self.targets.spec
        self.S = b.seeds
        per_call = c.updates_per_call or (1 if jax.default_backend() == "cpu" else c.probe_every)
        self.per_call = min(per_call, c.probe_every)
        self.init = jax.jit(self._init)
        self.train = jax.jit(self._train, static_argnums=3, donate_argnums=0)
        self.probe = jax.jit(self._probe)

    def _init(self, key: jax.Array) -> dict[str, Any]:
        out = {}
        for i, (name, l) in enumerate(self.learners.items()):
            keys = jax.random.split(jax.random.fold_in(key, i), self.S)
            out[name] = jax.vmap(lambda k, l=l: l.init(k, self.source.frame_shape))(keys)
        return out

    def _sampler(self, learner: Any, data: Trajectories) -> Callable[[jax.Array], Any]:
        if is_sequential(learner):
            return lambda k: sequence.sample_windows(data, k, learner.batch_size, learner.window_length)
        return lambda k: sequence.sample_steps(data, k, learner.batch_size)[0]

    def _train(self, states: dict, data: Trajectories, key: jax.Array, updates: int) -> tuple[dict, dict]:
        """`updates` updates of every learner and seed (seeds vmapped, data shared); metrics are
        the means over the updates, per seed."""
        out, metrics = {}, {}
        unroll = True if jax.default_backend() == "cpu" else 1
        for i, (name, l) in enumerate(self.learners.items()):
            keys = jax.random.split(jax.random.fold_in(key, i), self.S)
            run = lambda st, k, l=l: train_learner(l, st, self._sampler(l, data), k, updates, unroll)  # noqa: E731
            out[name], m = over_seeds(learner_loop(self.seed_loop, l), run, states[name], keys)
            metrics[name] = jax.tree.map(lambda x: x.mean(-1), m)
        return out, metrics

    def _probe(self, states: dict, data: Trajectories, held: Windows, key: jax.Array,
               broken: jax.Array | bool = False) -> dict:
        """Probe every learner and seed: fit on training data, score on the held-out windows
        (stream `rand`). `broken=True` (a check of the check) shuffles the per-step latents
        across time steps first (`shuffle_time`); traced, so both share one compile."""
        b = self.config.base
        out = {}
        corrupt = lambda z, k: jnp.where(broken, shuffle_time(z, k), z)  # noqa: E731
        for i, (name, l) in enumerate(self.learners.items()):
            def latents_seed(k_c, k_s, st, l=l):
                if is_sequential(l):
                    train = sequence.sample_windows(data, k_s, -(-b.probe_train_frames // l.sequence_length),
                                                    l.sequence_length)
                else:
                    train = sequence.sample_steps(data, k_s, b.probe_train_frames, with_worlds=True)
                return probe_latents(l, st.params, train, {"rand": held}, k_c, b.probe,
                                     b.probe_train_frames, corrupt)

            def fit_seed(lat, k_f, k_s, st):
                return fit_and_score(lat, {"rand": held}, k_f, b.probe, targets=self.targets)

            keys = jax.random.split(jax.random.fold_in(key, i), self.S)
            k_s, k_p = jax.vmap(jax.random.split)(keys).swapaxes(0, 1)
            out[name] = probe_over_seeds(learner_loop(self.seed_loop, l), latents_seed, fit_seed, k_p, k_s,
                                         states[name])
        return out


def shuffle_time(z: jax.Array, key: jax.Array) -> jax.Array:
    """A deliberately broken latent: per-step latents `[B, L, Z]` permuted across all time steps
    of all windows, so the latent paired with a state belongs to another step."""
    flat = z.reshape((-1, z.shape[-1]))
    return jax.random.permutation(key, flat, axis=0).reshape(z.shape)


def reference_spread(held: Windows, targets: Callable[[jax.Array], jax.Array] = lambda s: s) -> jax.Array:
    """The reference spread: the probe targets of held-out random-policy states, valid steps."""
    t = targets(held.states)
    return probe.spread(t.reshape((-1, t.shape[-1])), held.valid.reshape(-1))
