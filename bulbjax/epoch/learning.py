"""The learners' side of an epoch: their init and `learner_batches` updates on batches from
their replay (frame learners) or window buffers (sequential learners), one unit at a time
(`Team.units`: the VAEs that share one program, each other learner alone)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import jax
import jax.numpy as jnp

from bulbjax.data import replay, sequence
from bulbjax.epoch.keys import init_keys
from bulbjax.epoch.seeds import Team, stack_members, switch_buffer, unstack_members


def learner_unroll() -> bool | int:
    """How far to unroll the scan over learner updates: fully on CPU, where XLA runs the conv
    net ~8x slower inside a rolled loop (measured: 3.7 s vs 0.45 s per update), not on GPU."""
    return True if jax.default_backend() == "cpu" else 1


def train_learner(learner: Any, state: Any, sample: Any, key: jax.Array, updates: int,
                  unroll: bool | int | None = None, **update_args: Any) -> tuple[Any, dict]:
    """`updates` updates of one learner (one seed) on batches `sample(key)` gives (uint8 frames
    for frame learners, `Windows` for sequential ones), as one `lax.scan`; per-update metrics.
    `update_args` go to every `learner.update` (e.g. a VAE's traced `beta`, `update_groups`)."""
    def one(state, k):
        k_s, k_u = jax.random.split(k)
        return learner.update(state, sample(k_s), k_u, **update_args)
    keys = jax.random.split(key, updates)
    if updates == 1:  # no loop: XLA:CPU runs even a one-step scan ~4x slower than the bare update
        state, m = one(state, keys[0])
        return state, jax.tree.map(lambda x: x[None], m)
    return jax.lax.scan(one, state, keys, unroll=learner_unroll() if unroll is None else unroll)


@dataclass(frozen=True, eq=False)
class Learning:
    """Init and updates of a run's learners (`team`), every seed's: `batches` updates per epoch
    (`ExperimentConfig.learner_batches`) on frames of `frame_shape`."""

    team: Team
    batches: int
    frame_shape: tuple[int, int, int]

    def init_learner(self, name: str, key: jax.Array) -> Any:
        """Learner `name`'s state for every seed `[S]`, from the run's init key."""
        k_learn = init_keys(key).learners
        keys = self.team.seed_keys(jax.random.fold_in(k_learn, list(self.team.learners).index(name)))
        learner = self.team.learners[name]
        # one seed at a time: the same parameters as a vmap, and on the GPU a much cheaper
        # compile for DSA (its init over 6 seeds: 23 s under lax.map, 40 s vmapped; H100)
        return jax.lax.map(lambda k: learner.init(k, self.frame_shape), keys)

    def learn_phase(self, learners: dict, buffers: dict, key: jax.Array,
                    windows: dict | None = None) -> tuple[dict, dict]:
        """`batches` updates of every learner on batches sampled from its replay buffer:
        `learner.batch_size` frames (frame learners) or windows (sequential learners: the frame
        batch divided by the sequence length, the paper's equalised compute). One `learn_unit`
        per unit (`Team.units`)."""
        out, metrics = {}, {}
        for unit in self.team.units():
            states, m = self.learn_unit(unit, learners, buffers, key, windows)
            out.update(states)
            metrics.update(m)
        names = self.team.learners
        return {n: out[n] for n in names}, {n: metrics[n] for n in names}

    def learn_unit(self, unit: Sequence[str], learners: dict, buffers: dict, key: jax.Array,
                   windows: dict | None = None) -> tuple[dict, dict]:
        """`learn_phase` for one unit (`Team.units`): its members' new states and per-seed mean
        metrics. `key` is the epoch's learning key; each member's keys are folded in with its
        position among all learners, so a unit gets the same keys alone as in the whole phase.
        Its ops carry the scope `bj.learn.<members>` (benchmarks/trace_summary.py)."""
        with jax.named_scope(f"bj.learn.{'+'.join(unit)}"):
            return self._learn_unit(unit, learners, buffers, key, windows)

    def _learn_unit(self, unit: Sequence[str], learners: dict, buffers: dict, key: jax.Array,
                    windows: dict | None) -> tuple[dict, dict]:
        t = self.team
        if len(unit) > 1:
            states, m = self._learn_group(unit, learners, buffers, key)
            return states, {n: jax.tree.map(lambda x: x.mean(-1), mm) for n, mm in m.items()}
        (name,) = unit
        learner, seq, i = t.learners[name], t.sequential[name], list(t.learners).index(name)

        def train_seed(state, b, k):
            if seq:
                sample = lambda kk: sequence.sample(b, kk, learner.batch_size)  # noqa: E731
            else:
                sample = lambda kk: replay.sample(b, kk, learner.batch_size)[0]  # noqa: E731
            return train_learner(learner, state, sample, k, self.batches)

        keys = t.seed_keys(jax.random.fold_in(key, i))
        buf = t.buffer_of(name, buffers, windows)
        state, m = t.over_seeds(train_seed, learners[name], buf, keys, learner=name)
        return {name: state}, {name: jax.tree.map(lambda x: x.mean(-1), m)}

    def _learn_group(self, group: Sequence[str], learners: dict, buffers: dict, key: jax.Array
                     ) -> tuple[dict, dict]:
        """`learn_phase` for a group of VAEs (`update_groups`): one update program, run over
        seeds and, within a seed, over members (each with its beta and its replay buffer), with
        the run's seed loop. Same keys and batches as each member's own `learn_phase` step."""
        t = self.team
        template, bufs, which, keys = t.group_inputs(group, buffers, key)
        betas = jnp.array([t.learners[n].config.beta for n in group], jnp.float32)
        draw = lambda b, k: replay.sample(b, k, template.batch_size)[0]  # noqa: E731

        def train_seed(states, bs, ks):
            def member(state, k, beta, w):
                sample = lambda kk: switch_buffer(w, bs, draw, kk)  # noqa: E731
                return train_learner(template, state, sample, k, self.batches, beta=beta)
            return t.over_seeds(member, states, ks, betas, which)

        states = stack_members([learners[n] for n in group])
        states, m = t.over_seeds(train_seed, states, bufs, keys)
        return unstack_members(states, group), unstack_members(m, group)
