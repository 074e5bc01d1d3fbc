"""The seed axis: which of a run's seeds an experiment computes, how the learners' work runs over
them, and the run's learners as one team.

Every seed has its own learners, PPO and buffers (a leading seed axis `[S, ...]`). The learners'
work (updates, probe encodings, latents for PPO) runs over that axis with the run's seed loop
(`resolve_seed_loop`: vmapped, mapped one seed at a time, or a hybrid); learners that share one
program (`update_groups`: the VAEs that differ only in beta and replay retention) are stacked
as members after the seed axis (`stack_members`), each reading its own buffer (`switch_buffer`).
`Team` holds a run's learners with its seed loop and the seeds it computes (`SeedGroup`: all of
the run's, or a share of them with the draws they get in the whole run): what the policy, the
data side, learning and probing ask about them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
from jax.sharding import Mesh

from bulbjax.config import SEED_LOOPS
from bulbjax.learners import is_sequential


def resolve_seed_loop(choice: str, mesh: Mesh) -> str:
    """How the learners' work (updates, probe encodings, latents for PPO) runs over the seed axis.

    "vmap" batches the seeds: every convolution over per-seed weights becomes a grouped one,
    which on the H100 runs a VAE update at half the rate of S separate updates (6 seeds, bf16:
    7.97 against 4.19 ms per seed-update, `bench_seed_axis.py`: benchmarks/diagnostics/README.md). "map"
    runs the seeds one after another (`lax.map`), each a plain batch-1,024 update that fills the
    GPU alone. "hybrid" is "map" except for learners whose LSTMs dominate (`hybrid_vmapped`:
    DSA), which are vmapped with their convolutions one seed at a time (`with_seed_loop`,
    `learner_loop`): an LSTM step at ~42 windows leaves the GPU idle, so S seeds' steps cost
    about one seed's when batched.
    "auto" picks "hybrid" on a GPU or TPU with the seeds on one device (fig2-invpend, 6 seeds,
    H100: 1.552 s per epoch against "map"'s 1.593 s, same machine), "vmap" elsewhere: on the
    CPU, XLA runs convolutions inside loops several times slower (tests), and with the seed axis
    sharded over devices a loop over it would gather it."""
    if choice not in SEED_LOOPS:
        raise ValueError(f"learner_seed_loop must be one of {SEED_LOOPS}, got {choice!r}")
    if choice != "auto":
        return choice
    platform = mesh.devices.flat[0].platform
    return "hybrid" if platform != "cpu" and mesh.size == 1 else "vmap"


def with_seed_loop(learner: Any, loop: str) -> Any:
    """The learner as a run with seed loop `loop` uses it: with "hybrid", a learner with LSTMs
    (`hybrid_vmapped`: DSA) runs its frame networks one seed at a time under vmap
    (`per_seed_frames`)."""
    if loop == "hybrid" and getattr(learner, "hybrid_vmapped", False):
        return dataclasses.replace(learner, per_seed_frames="remat")
    return learner


def learner_loop(loop: str, learner: Any) -> str:
    """`over_seeds`' loop for one learner's work in a run with seed loop `loop`: with "hybrid",
    "vmap" for a learner whose frame networks loop over seeds themselves (`with_seed_loop`: its
    LSTMs, heads and Adam batched over seeds, one kernel per step for all of them), "map" for
    the others."""
    if loop == "hybrid":
        return "vmap" if getattr(learner, "per_seed_frames", False) else "map"
    return loop


def over_seeds(loop: str, fn: Callable[..., Any], *args: Any) -> Any:
    """`fn` applied to every seed's slice of `args` (leading axis S): `jax.vmap` for loop
    "vmap", `lax.map` (one seed at a time) for "map" (see `resolve_seed_loop`)."""
    if loop == "map":
        return jax.lax.map(lambda a: fn(*a), args)
    return jax.vmap(fn)(*args)


def buffer_key(fraction: float) -> str:
    """Learners with the same replay retention share one buffer."""
    return f"retain_{fraction:g}"


def update_groups(learners: Mapping[str, Any], share: bool = True) -> list[tuple[str, ...]]:
    """The learners' names in groups that one program serves (`ExperimentConfig.shared_updates`):
    VAEs equal up to beta and replay retention (`VAE.update_key`: vae, vae_rpl, beta_vae) form one
    group, every other learner is alone (and all are alone with `share=False`). Groups come in
    the order of their first member in `learners`, members in `learners`' order."""
    groups: dict[Any, list[str]] = {}
    for name, learner in learners.items():
        k = getattr(learner, "update_key", None) if share else None
        groups.setdefault(("alone", name) if k is None else k, []).append(name)
    return [tuple(g) for g in groups.values()]


def stack_members(trees: Sequence[Any]) -> Any:
    """Per-member pytrees `[S, ...]` stacked into one `[S, G, ...]` (members after seeds)."""
    return jax.tree.map(lambda *xs: jnp.stack(xs, axis=1), *trees)


def unstack_members(tree: Any, names: Sequence[str]) -> dict[str, Any]:
    """`stack_members` undone: `{name: tree[:, j]}` for the j-th member."""
    return {n: jax.tree.map(lambda x, j=j: x[:, j], tree) for j, n in enumerate(names)}


def switch_buffer(which: jax.Array, buffers: Sequence[Any], fn: Callable[[Any, jax.Array], Any],
                  key: jax.Array) -> Any:
    """`fn(buffers[which], key)` for a traced index `which` (a group member's replay buffer):
    one `lax.switch` branch per buffer, so no buffer is copied into a stacked one."""
    if len(buffers) == 1:
        return fn(buffers[0], key)
    return jax.lax.switch(which, [lambda k, b=b: fn(b, k) for b in buffers], key)


@dataclass(frozen=True)
class SeedGroup:
    """The seeds an experiment computes: seeds `offset .. offset + seeds - 1` of a run of `total`
    seeds (default: all of them, `offset` 0), each with `worlds` worlds. A run's seeds spread over
    several experiments (`bulbjax.epoch.groups`: one per device or process) each hold a share;
    every random draw is the one those seeds get in the whole run (`seed_keys`, `world_keys`,
    `seed_columns`), so together they compute what one experiment of all seeds computes."""

    seeds: int
    worlds: int
    offset: int = 0
    total: int = 0  # 0: `seeds` (the whole run)

    def __post_init__(self) -> None:
        if not self.total:
            object.__setattr__(self, "total", self.seeds)
        if not 0 <= self.offset <= self.total - self.seeds:
            raise ValueError(f"seed_group {(self.offset, self.total)} does not hold the config's {self.seeds} seeds")

    @property
    def whole(self) -> bool:
        """Whether this is all of the run's seeds."""
        return self.total == self.seeds

    def seed_keys(self, key: jax.Array) -> jax.Array:
        """`[S]` keys, one per seed of this group: `split(key, total)` of the whole run's seeds,
        this group's slice of them."""
        keys = jax.random.split(key, self.total)
        return keys if self.whole else keys[self.offset:self.offset + self.seeds]

    def world_keys(self, key: jax.Array) -> jax.Array:
        """`[S*N]` keys, one per world of this group's seeds, as `seed_keys` slices them."""
        n = self.worlds
        keys = jax.random.split(key, self.total * n)
        return keys if self.whole else keys[self.offset * n:(self.offset + self.seeds) * n]

    def seed_columns(self, x: jax.Array) -> jax.Array:
        """This group's worlds `[..., S*N]` of a draw made for the whole run's `[..., total*N]`."""
        n = self.worlds
        return x if self.whole else x[..., self.offset * n:(self.offset + self.seeds) * n]


@dataclass(frozen=True, eq=False)
class Team:
    """A run's learners (name -> learner, in the config's order, each as `with_seed_loop` makes
    it) and how their work runs over the seed axis of `group`'s seeds: `seed_loop` as
    `resolve_seed_loop` gives it, `shared_updates` as `ExperimentConfig.shared_updates`. A variant
    (other learners, another seed loop) is `dataclasses.replace(team, ...)`."""

    learners: dict[str, Any]
    seed_loop: str
    group: SeedGroup
    shared_updates: bool = True

    @property
    def seeds(self) -> int:
        return self.group.seeds

    def seed_keys(self, key: jax.Array) -> jax.Array:
        """`[S]` keys, one per seed (`SeedGroup.seed_keys`)."""
        return self.group.seed_keys(key)

    @property
    def retention(self) -> dict[str, float]:
        """Each learner's replay retention (`retain_fraction`): learners with the same one share
        a buffer (`buffer_key`)."""
        return {n: l.retain_fraction for n, l in self.learners.items()}

    @property
    def sequential(self) -> dict[str, bool]:
        """Whether each learner reads windows (svae, pred, dsa) rather than frames."""
        return {n: is_sequential(l) for n, l in self.learners.items()}

    def buffer_of(self, name: str, buffers: dict, windows: dict | None) -> Any:
        """Learner `name`'s buffer: its window buffer (sequential learners) or frame buffer."""
        return (windows if self.sequential[name] else buffers)[buffer_key(self.retention[name])]

    def loop_of(self, learner: str | None) -> str:
        """The seed loop ("map" or "vmap") of `learner`'s work (`learner_loop`)."""
        return learner_loop(self.seed_loop, self.learners.get(learner))

    def over_seeds(self, fn: Callable[..., Any], *args: Any, learner: str | None = None) -> Any:
        """`fn` over every seed's slice of `args` with the run's seed loop (`over_seeds`), as
        `learner`'s work runs over seeds (`learner_loop`; None: a frame learner's)."""
        return over_seeds(self.loop_of(learner), fn, *args)

    def units(self) -> list[tuple[str, ...]]:
        """The learners in the units that one update (and probe) program serves, in order: a
        group of VAEs sharing one program (`update_groups`, `ExperimentConfig.shared_updates`)
        or one learner alone. A unit's work reads only its own members' states (and the
        buffers), so units run in any order, fused in one epoch or as programs of their own
        (`programs.Stages`)."""
        return update_groups(self.learners, self.shared_updates)

    def group_inputs(self, group: Sequence[str], buffers: dict, key: jax.Array
                     ) -> tuple[Any, tuple, jax.Array, jax.Array]:
        """What a group's program takes besides the states: its template learner (the first
        member's `update_key`), the distinct replay buffers of its members, each member's index
        into them `[G]` and each member's keys `[S, G, 2]` (the keys the member would get alone:
        `key` folded with its position among all learners, split over seeds)."""
        index = {n: i for i, n in enumerate(self.learners)}
        bkeys = list(dict.fromkeys(buffer_key(self.retention[n]) for n in group))
        which = jnp.array([bkeys.index(buffer_key(self.retention[n])) for n in group], jnp.int32)
        keys = jnp.stack([self.seed_keys(jax.random.fold_in(key, index[n])) for n in group], 1)
        return self.learners[group[0]].update_key, tuple(buffers[k] for k in bkeys), which, keys
