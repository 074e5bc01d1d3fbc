"""The training loop of one experiment: every epoch is one jitted function, vmapped over seeds.

Layout of the run state: everything a seed owns (PPO, learners, replay buffers) carries a leading
seed axis `[S, ...]` and is updated with `jax.vmap`; the simulators of all seeds are one batch of
`S * num_envs` worlds (one Warp physics launch and one render context for all seeds, which is
what makes the GPU fast), reshaped to `[S, num_envs]` wherever a per-seed function needs them.

Frame learners (vae, vae_rpl, beta_vae) train on frame replay buffers, sequential learners (svae,
pred, dsa) on window buffers (`bulbjax.data.sequence`) cut from the same rollouts; learners with
the same retention share a buffer. Held-out evaluation streams are windows of L steps (L = 1
without sequential learners), so every learner is probed on the very same (frame, state) pairs:
frame learners encode each frame, sequential learners each window, one latent per step.

PPO observes the true state, the current frame, or a learner's latent of the current frame
(`rl_input`); for a sequential learner, the latent of the current step in the window of the last
L steps ending at it (`PolicyHistory`, kept per world in the run state).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

import bulbjax
from bulbjax.data import replay, sequence
from bulbjax.data.sequence import Windows
from bulbjax.envs.base import EnvState, MjxPixelEnv
from bulbjax.envs.render import warp_devices
from bulbjax.eval import objects, probe
from bulbjax.experiment.config import PROGRAM_FORMS, SEED_LOOPS, ExperimentConfig
from bulbjax.learners import is_sequential, make_learner
from bulbjax.rl.ppo import PPO, PPOState, Transition


@struct.dataclass
class PolicyHistory:
    """What PPO's latent of a sequential learner is read from, per world: the last L steps up to
    and including the current one, cut at the start of the world's current episode, laid out as
    a training window whose episode ends at the current step (`bulbjax.data.sequence`): the
    `count` steps held, oldest first, then padding (the current frame repeated, action 0). The
    latent PPO sees is the learner's per-step latent at step `count - 1` of this window. Part of
    the run state: carried from epoch to epoch and checkpointed with the worlds it follows.

    Cost: memory `S x N x L` frames per set of worlds (train and held-out current-policy: fig2
    with L = 24, 2 x 113 MB). Per step and world, on top of the frame a frame learner would
    encode (rendered once, its conv features computed once and kept, `PolicyWindow`): the
    learner's part after the convs over the L steps (SVAE: an LSTM of L steps; DSA: its two
    sequence encoders; PRED: two FC layers on the L steps' features) and a shift of the window
    (L frames, features and actions copied). Once per rollout (each PPO update's, each held-out
    stream's): L conv passes per world, the features of the history under the new params."""

    frames: jax.Array  # uint8 [S, N, L, H, W, 3]
    actions: jax.Array  # float32 [S, N, L, A]: the action that led into each frame (0 on padding)
    count: jax.Array  # int32 [S, N]: steps of the current episode held, 1..L

    @property
    def valid(self) -> jax.Array:
        """bool [S, N, L]: the steps held (False on padding), as `Windows.valid`."""
        return jnp.arange(self.frames.shape[2]) < self.count[..., None]


@struct.dataclass
class PolicyWindow:
    """A `PolicyHistory` with its frames' `frame_features` under the learner's current params
    (the carry of a rollout: features are computed once per frame, and again for the whole
    history once per rollout, since the params change between epochs)."""

    history: PolicyHistory
    features: jax.Array  # float32 [S, N, L, F]


def push_window(x: jax.Array, new: jax.Array, count: jax.Array, fresh: jax.Array,
                pad_with_new: bool) -> jax.Array:
    """One step of a rolling window in training-window layout (see `PolicyHistory`).

    `x [S, N, L, ...]` holds `count [S, N]` steps then padding; `new [S, N, ...]` is the next
    step; `fresh [S, N]` says it starts a new episode (the window restarts at it). Returns the
    window with `new` appended after the steps held (the oldest step dropped once L are held)
    and the steps after it padded with `new` (`pad_with_new`: frames, features) or zeros
    (actions)."""
    l = x.shape[2]
    full = (count >= l) & ~fresh
    shifted = jnp.concatenate([x[:, :, 1:], new[:, :, None]], axis=2)
    pos = jnp.where(fresh, 0, jnp.minimum(count, l - 1))  # where `new` goes
    expand = lambda a: a.reshape(a.shape + (1,) * (x.ndim - a.ndim))  # noqa: E731  [S, N, L] -> x's rank
    i = jnp.arange(l)[None, None, :]
    base = jnp.where(expand(full[..., None]), shifted, x)
    after = new[:, :, None] if pad_with_new else jnp.zeros_like(new)[:, :, None]
    out = jnp.where(expand(i == pos[..., None]), new[:, :, None], base)
    return jnp.where(expand(i > pos[..., None]), after, out).astype(x.dtype)


@struct.dataclass
class Rendered:
    """Frames of stored steps, uint8 `[..., S*N, H, W, 3]`, kept in place of their render inputs
    where the policy rendered them already (PPO on pixels or a latent): `Experiment._frames_at`
    gathers them instead of rendering the steps again (replay, windows, held-out windows). Costs
    the memory of an epoch's frames (fig2: 128 steps x 384 worlds, ~600 MB); saves about a
    quarter of a probing fig2 epoch's renders (~24k of ~92k frames)."""

    frames: jax.Array


# What a frame-observing policy carries from step to step (`Experiment._policy_view`): every
# world's current frame `[S, N, H, W, 3]` (pixels, a frame learner's latent), its `PolicyWindow`
# (a sequential learner's latent), or None (the true state, the random policy).
PolicyView = jax.Array | PolicyWindow | None


def _history_of(view: PolicyView) -> PolicyHistory | None:
    """The worlds' `PolicyHistory` a rollout hands on: a sequential learner's window, else None."""
    return view.history if isinstance(view, PolicyWindow) else None


@struct.dataclass
class RunState:
    """Carry of the jitted epoch."""

    ppo: PPOState  # [S]
    learners: dict[str, Any]  # name -> LearnerState [S]
    buffers: dict[str, replay.ReplayBuffer]  # retention key -> frame buffer [S]
    windows: dict[str, sequence.WindowBuffer]  # retention key -> window buffer [S] (sequential learners)
    train_env: EnvState  # [S*N] worlds driven by PPO; frames for replay come from here
    curr_env: EnvState  # [S*N] held-out worlds under the current policy (never in replay)
    rand_env: EnvState  # [S*N] held-out worlds under the random policy (never in replay)
    # PPO on a sequential learner's latent: "train" and "curr" worlds' windows; {} otherwise
    policy_history: dict[str, PolicyHistory]
    ref_spread: jax.Array  # [D] reference spread of every state entry (random policy, at init)
    epoch: jax.Array


class EnvStage(NamedTuple):
    """What `Experiment.env_stage` hands on to the rest of an epoch."""

    ppo: PPOState
    train_env: EnvState
    buffers: dict
    windows: dict
    train_hist: PolicyHistory | None
    metrics: dict
    epoch: jax.Array
    k_learn: jax.Array
    k_eval: jax.Array
    k_probe: jax.Array


SEED_AXIS, WORLD_AXIS = "seeds", "worlds"


def make_mesh(devices: Sequence[jax.Device], seeds: int, worlds: int) -> Mesh:
    """A `(seeds, worlds)` mesh over as many of `devices` as the run can use: the seed axis
    takes the largest divisor of `seeds` that fits, the world axis (each seed's worlds split
    further) the largest divisor of `worlds` that fits in the devices left. Seeds come first
    because a seed's PPO and learner updates are not split, only replicated, over the world
    axis. E.g. 6 seeds on 2 or 6 devices: 2 x 1 or 6 x 1; 12 seeds on 8: 6 x 1 (6 devices
    used); 1 seed of 64 worlds on 4: 1 x 4."""
    devices = list(devices)
    n = len(devices)
    ds = max(d for d in range(1, min(seeds, n) + 1) if seeds % d == 0)
    dw = max(d for d in range(1, min(worlds, n // ds) + 1) if worlds % d == 0)
    return Mesh(np.array(devices[: ds * dw], dtype=object).reshape(ds, dw), (SEED_AXIS, WORLD_AXIS))


def parse_compiler_options(items: Sequence[str]) -> dict[str, Any]:
    """`["KEY=VALUE", ...]` -> XLA compile options for `jax.jit(..., compiler_options=...)`: values
    that read as ints, floats or true/false become those, the rest stay strings (e.g.
    `xla_gpu_enable_command_buffer=FUSION,CUBLAS,WHILE`). XLA rejects unknown keys at compile."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"compiler option {item!r} must read KEY=VALUE, e.g. "
                             "xla_gpu_enable_command_buffer=FUSION,CUBLAS,WHILE")
        value: Any = text.strip()
        if value.lower() in ("true", "false"):
            value = value.lower() == "true"
        else:
            for cast in (int, float):
                try:
                    value = cast(value)
                    break
                except ValueError:
                    pass
        out[key.strip()] = value
    return out


def learner_unroll() -> bool | int:
    """How far to unroll the scan over learner updates: fully on CPU, where XLA runs the conv
    net ~8x slower inside a rolled loop (measured: 3.7 s vs 0.45 s per update), not on GPU."""
    return True if jax.default_backend() == "cpu" else 1


def buffer_key(fraction: float) -> str:
    """Learners with the same replay retention share one buffer."""
    return f"retain_{fraction:g}"


def resolve_seed_loop(choice: str, mesh: Mesh) -> str:
    """How the learners' work (updates, probe encodings, latents for PPO) runs over the seed axis.

    "vmap" batches the seeds: every convolution over per-seed weights becomes a grouped one,
    which on the H100 runs a VAE update at half the rate of S separate updates (6 seeds, bf16:
    7.97 against 4.19 ms per seed-update, `benchmarks/bench_seed_axis.py`). "map" runs the seeds
    one after another (`lax.map`), each a plain batch-1,024 update that fills the GPU alone.
    "hybrid" is "map" except for learners whose LSTMs dominate (`hybrid_vmapped`: DSA), which
    are vmapped with their convolutions one seed at a time (`with_seed_loop`, `learner_loop`): an
    LSTM step at ~42 windows leaves the GPU idle, so S seeds' steps cost about one seed's when
    batched.
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


def resolve_programs(choice: str, mesh: Mesh) -> str:
    """How init and the epoch are compiled (`ExperimentConfig.programs`), checked against the
    mesh: split programs run on one device (a sharded run's layouts are set on the fused
    programs' outputs)."""
    if choice not in PROGRAM_FORMS:
        raise ValueError(f"programs must be one of {PROGRAM_FORMS}, got {choice!r}")
    if choice == "split" and mesh.size > 1:
        raise ValueError("programs='split' runs on one device; this run's mesh has "
                         f"{mesh.size} devices: use 'fused'")
    return choice


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


def probe_latents(learner: Any, params: Any, train: Any, held: dict[str, Windows], key: jax.Array,
                  config: probe.ProbeConfig, train_frames: int, corrupt: Any = None) -> dict[str, Any]:
    """The learner's half of a probe (one seed; the convolutions): the training pairs' latents
    `tz [T, Z']`, their states `ts [T, D]` and `groups` (each pair's world, or None), and each
    held-out stream's per-step latents `held [B, L, Z']`. `train` is `(frames, states)` or
    `(frames, states, groups)` for a frame learner and `Windows` for a sequential one, whose
    per-step latents (with `config.sequence_context` steps of context, see
    `probe.context_latents`) are paired with the states of the same step and `train_frames`
    valid steps drawn from them (split by row for validation: windows keep no world ids).
    `corrupt` (tests only) maps per-step latents `[B, L, Z]` to what the probe sees, e.g.
    latents shuffled across time steps."""
    corrupt = corrupt or (lambda z, k: z)
    if is_sequential(learner):
        l = learner.sequence_length
        ctx = lambda z: probe.context_latents(z, config.sequence_context)  # noqa: E731
        z = ctx(corrupt(learner.encode(params, train), key))
        z, s = z.reshape((-1, z.shape[-1])), train.states[:, :l].reshape((-1, train.states.shape[-1]))
        v = train.valid[:, :l].reshape(-1).astype(jnp.float32)
        pick = jax.random.choice(key, v.shape[0], (train_frames,), p=v / v.sum())
        tz, ts, groups = z[pick], s[pick], None
        enc = lambda w: ctx(corrupt(learner.encode(params, w), key))  # noqa: E731
    else:
        tf, ts, *rest = train
        groups = rest[0] if rest else None
        tz = corrupt(learner.encode(params, tf)[:, None], key)[:, 0]

        def enc(w: Windows) -> jax.Array:
            z = learner.encode(params, w.frames.reshape((-1,) + w.frames.shape[2:]))
            return corrupt(z.reshape(w.frames.shape[:2] + z.shape[-1:]), key)
    return {"tz": tz, "ts": ts, "groups": groups, "held": {st: enc(w) for st, w in held.items()}}


def fit_and_score(latents: dict[str, Any], held: dict[str, Windows], key: jax.Array,
                  config: probe.ProbeConfig,
                  score_objects: Callable[[jax.Array, Windows], dict] | None = None,
                  ) -> dict[str, dict[str, jax.Array]]:
    """The probe's half (one seed; small MLPs, best vmapped over seeds): fit latent -> true state
    on `probe_latents`' training pairs and score it on every held-out stream's valid steps.
    `score_objects` (frame learners) maps a stream's per-step latents `[B, L, Z]` and its windows
    to the object-level probe (`Experiment._object_scorer`), kept as `"objects"`.
    Returns `{stream: {"mae", "baseline", "spread"(, "objects")}}`, each `[D]` in the states'
    units."""
    tz, ts = latents["tz"], latents["ts"]
    p = probe.fit(key, tz, ts, config, groups=latents["groups"])
    res = {}
    for stream, w in held.items():
        zw = latents["held"][stream]
        z = zw.reshape((-1, tz.shape[-1]))
        s, v = w.states.reshape((-1, ts.shape[-1])), w.valid.reshape(-1)
        res[stream] = {"mae": probe.mae(probe.predict(p, z), s, v),
                       "baseline": probe.constant_baseline(ts, s, v),
                       "spread": probe.spread(s, v)}
        if score_objects is not None:
            res[stream]["objects"] = score_objects(zw, w)
    return res


def probe_learner(learner: Any, params: Any, train: Any, held: dict[str, Windows], key: jax.Array,
                  config: probe.ProbeConfig, train_frames: int,
                  corrupt: Any = None,
                  score_objects: Callable[[jax.Array, Windows], dict] | None = None,
                  ) -> dict[str, dict[str, jax.Array]]:
    """Fit a probe latent -> true state on `train` and score it on every held-out stream (one
    seed): `probe_latents` then `fit_and_score` (see them)."""
    k_c, k_f = jax.random.split(key)
    lat = probe_latents(learner, params, train, held, k_c, config, train_frames, corrupt)
    return fit_and_score(lat, held, k_f, config, score_objects)


def probe_over_seeds(loop: str, latents_seed: Callable[..., dict], fit_seed: Callable[..., dict],
                     keys: jax.Array, *args: Any) -> dict:
    """A probe of every seed: `latents_seed(k_c, *args)` (the learner's convolutions) with the
    run's seed loop, then `fit_seed(latents, k_f, *args)` (the probe MLP, hundreds of small
    sequential Adam steps) vmapped over seeds whatever the loop: one seed at a time, those steps
    would run S times in a row on a GPU. Same keys as `probe_learner`, so the same numbers."""
    ks = jax.vmap(jax.random.split)(keys)
    lat = over_seeds(loop, latents_seed, ks[:, 0], *args)
    return jax.vmap(fit_seed)(lat, ks[:, 1], *args)


class Experiment:
    """Builds the environment, PPO, learners and the jitted `init` and `epoch` functions.

    `devices` (default: the first device alone) are laid out as a `(seeds, worlds)` mesh
    (`make_mesh`): everything a seed owns is sharded over the seed axis, the worlds of the
    simulators over both axes. The physics and the renderer are Warp kernels that XLA cannot
    partition, so env calls run under `shard_map`, each device stepping and rendering its own
    worlds (the env is built for the worlds of one device, with one render context per device);
    the rest (PPO, learners, replay, probes) is left to XLA's partitioner. On one device nothing
    of this is used and the code is the unsharded one. With fewer seeds than devices the world
    axis takes the other devices: physics and rendering split, PPO and learner updates of a
    seed replicated on its devices."""

    def __init__(self, config: ExperimentConfig, devices: Sequence[jax.Device] | None = None,
                 compiler_options: Mapping[str, Any] | None = None, seed_group: tuple[int, int] | None = None):
        self.config = c = config
        # `seed_group=(offset, total)`: this experiment runs seeds offset..offset+S-1 of a run of
        # `total` seeds (`bulbjax.experiment.groups`): every random draw is the one those seeds get
        # in the whole run (`seed_keys`, `world_keys`), so a run's seeds spread over several
        # experiments (devices, processes) compute what one experiment of all seeds computes.
        self.seed_offset, self.seed_total = seed_group or (0, c.seeds)
        if not 0 <= self.seed_offset <= self.seed_total - c.seeds:
            raise ValueError(f"seed_group {seed_group} does not hold the config's {c.seeds} seeds")
        # XLA options for compiling init and epoch (e.g. xla_gpu_enable_command_buffer): how the
        # program runs, not what it computes (`parse_compiler_options`).
        self.compiler_options = dict(compiler_options or {})
        self.mesh = make_mesh(devices or jax.devices()[:1], c.seeds, c.num_envs)
        self.sharded = self.mesh.size > 1
        self.seed_loop = resolve_seed_loop(c.learner_seed_loop, self.mesh)
        # init and the epoch as one program each, or as several compiled side by side (`Stages`)
        self.split_programs = resolve_programs(c.programs, self.mesh) == "split"
        try:
            self.env: MjxPixelEnv = bulbjax.make(c.env, num_envs=c.seeds * c.num_envs // self.mesh.size,
                                                 resolution=c.resolution, render=True,
                                                 render_steps=False, multicolour=c.multicolour,
                                                 version=c.version)
        except ValueError as err:
            if c.env.startswith(("HalfCheetah", "Ant")):
                raise ValueError(f"{err}. HalfCheetah and Ant come with the locomotion environments "
                                 "(issue 3); the fig2-halfcheetah / fig2-ant presets run once they are "
                                 "registered (check with `bulbjax envs`)") from err
            raise
        self.spec = self.env.state_spec
        latent = c.latent_factor * self.env.state_dim
        # Actions as the sequential learners see them: one-hot for discrete, the clipped vector else.
        self.action_dim = self.env.num_actions if self.env.discrete else self.env.action_size
        self.learners = {n: with_seed_loop(make_learner(n, latent, c.learner, self.action_dim), self.seed_loop)
                         for n in c.learners}
        # PPO observes the true state, the frame (rl_input "pixels") or a learner's latent of it.
        self.rl_learner = c.rl_learner
        self.rl_pixels = c.rl_input == "pixels"
        # A sequential learner's latent is read from a window of the last L steps (PolicyHistory).
        self.rl_sequential = self.rl_learner is not None and is_sequential(self.learners[self.rl_learner])
        num_actions = self.env.num_actions if self.env.discrete else None
        if self.rl_pixels:
            self.ppo = PPO(c.ppo, 0, num_actions, self.env.action_size, frame_shape=self.env.frame_shape)
        elif self.rl_learner is None:
            self.ppo = PPO.for_env(c.ppo, self.env)
        else:
            params = self._abstract_learner_params(self.rl_learner)
            if self.rl_sequential:
                l = self.learners[self.rl_learner].sequence_length
                z = jax.eval_shape(self._window_latents, params,
                                   jax.ShapeDtypeStruct((1, l) + self.env.frame_shape, jnp.uint8),
                                   jax.ShapeDtypeStruct((1, l, self.action_dim), jnp.float32))
            else:
                z = jax.eval_shape(self._encode_frames, params,
                                   jax.ShapeDtypeStruct((1,) + self.env.frame_shape, jnp.uint8))
            self.ppo = PPO(c.ppo, z.shape[-1], num_actions, self.env.action_size)
        self.retention = {n: l.retain_fraction for n, l in self.learners.items()}
        self.sequential = {n: is_sequential(l) for n, l in self.learners.items()}
        self.window_length = c.window_length  # stored windows (0 without sequential learners)
        self.eval_length = c.seq_len if self.window_length else 1  # held-out window length
        # Object-level probe (multi-object domains): names and states -> image positions (px)
        # of the true objects, None for domains without objects in the state (nothing computed).
        self.objects = objects.object_pixels(self.env)
        self.object_radius = objects.default_radius(c.resolution)
        if self.sharded or warp_devices(self.local_mesh_devices()) != warp_devices():
            self._per_device_renderer()  # (also one GPU that is not JAX's default)
        self._rep = NamedSharding(self.mesh, P())
        shapes = jax.eval_shape(self._init, jax.random.PRNGKey(0))
        self._state_sh = self.state_shardings(shapes)
        self._programs: dict[tuple[bool, ...], Any] = {}
        # traced once here: every later use reads this, so that a process's sequence of traces
        # (which numbers MuJoCo Warp's FFI calls, see `Programs`) does not depend on how often
        # it asks for the state's shapes
        self._abstract_state = jax.tree.map(lambda x, sh: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sh),
                                            shapes, self._state_sh)
        opts = self.compiler_options or None
        self.init = jax.jit(self._init, out_shardings=self._state_sh, compiler_options=opts)
        # `epoch(rs, key, probe=False)` skips the held-out rollouts and probes (`--probe-every`).
        # Outputs laid out exactly as the inputs (state as `init` gives it, metrics replicated):
        # an equivalent but differently written sharding (XLA drops size-1 mesh axes) would
        # make the second call compile the epoch again.
        self.epoch = jax.jit(self._epoch, donate_argnums=0, static_argnames="probe",
                             out_shardings=(self._state_sh, self._rep), compiler_options=opts)
        # `epoch_flag(rs, key, flag)`: one program for probing and non-probing epochs, `flag` a
        # boolean array (`abstract_flag`) that switches the held-out rollouts and probes on
        # (`lax.cond`), so a run probing every k epochs compiles and loads one epoch, not two.
        self.epoch_flag = jax.jit(self._epoch, donate_argnums=0,
                                  out_shardings=(self._state_sh, self._rep), compiler_options=opts)

    # ------------------------------------------------------------------ devices
    def _per_device_renderer(self) -> None:
        """One render context per device of the mesh, for the worlds of one device. On GPUs Warp
        looks the context up by the GPU a kernel runs on. Warp has a single CPU device, so
        XLA's host devices (`--xla_force_host_platform_device_count`) would share one context
        and race on its buffers (seen: frames of one device's worlds in the other's); there
        each mesh device gets its own context, picked by its index (`_render_local`)."""
        from bulbjax.envs.render import Renderer

        r, env = self.env.renderer, self.env
        self._renderers: list[Renderer] = []
        devs = warp_devices(self.local_mesh_devices())
        if devs is not None:
            env.renderer = Renderer(env.mj_model, env.num_envs, env.resolution, depth=r.depth, devices=devs)
        else:
            self._renderers = [Renderer(env.mj_model, env.num_envs, env.resolution, depth=r.depth)
                               for _ in range(self.mesh.size)]

    def local_mesh_devices(self) -> list[jax.Device]:
        """The mesh's devices of this process (all of them in a single-process run)."""
        return [d for d in self.mesh.devices.flat if d.process_index == jax.process_index()]

    def _render_local(self, render_inputs: Any) -> jax.Array:
        """`env.render_sequence` of this device's worlds (inside `shard_map`), with this
        device's own render context where the contexts are not per device already (CPU)."""
        if not self._renderers:
            return self.env.render_sequence(render_inputs)

        def with_renderer(r: Any) -> Callable:
            def f(ri: Any) -> jax.Array:
                old, self.env.renderer = self.env.renderer, r  # swapped while tracing only
                try:
                    return self.env.render_sequence(ri)
                finally:
                    self.env.renderer = old
            return f

        index = jax.lax.axis_index((SEED_AXIS, WORLD_AXIS))
        return jax.lax.switch(index, [with_renderer(r) for r in self._renderers], render_inputs)

    def state_shardings(self, rs: RunState) -> RunState:
        """Shardings of a RunState: per-seed parts over the seed axis, simulator worlds (and the
        policy's windows of them) over both axes, the reference spread and the epoch counter
        replicated."""
        seed = NamedSharding(self.mesh, P(SEED_AXIS))
        world = NamedSharding(self.mesh, P((SEED_AXIS, WORLD_AXIS)))

        def each(tree: Any, sh: NamedSharding) -> Any:
            return jax.tree.map(lambda _: sh, tree)

        seed_world = NamedSharding(self.mesh, P(SEED_AXIS, WORLD_AXIS))  # [S, N, ...] per world
        return RunState(ppo=each(rs.ppo, seed), learners=each(rs.learners, seed),
                        buffers=each(rs.buffers, seed), windows=each(rs.windows, seed),
                        train_env=each(rs.train_env, world), curr_env=each(rs.curr_env, world),
                        rand_env=each(rs.rand_env, world),
                        policy_history=each(rs.policy_history, seed_world),
                        ref_spread=self._rep, epoch=self._rep)

    def abstract_state(self) -> RunState:
        """Shapes, dtypes and shardings of the RunState (what a checkpoint is restored into)."""
        return self._abstract_state

    def programs(self, probes: Sequence[bool] = (True, False)) -> Any:
        """The init and epoch executables of a run (`probes`: which epochs it runs), traced in
        one fixed order before anything runs; see `Programs`. Kept per `probes`, so that several
        runs of one experiment in a process (tests) compile once."""
        probes = tuple(bool(p) for p in probes)
        if probes not in self._programs:
            from bulbjax.experiment.programs import Programs  # (it builds on this module)
            self._programs[probes] = Programs(self, probes)
        return self._programs[probes]

    def abstract_key(self) -> jax.ShapeDtypeStruct:
        return jax.ShapeDtypeStruct((2,), jnp.uint32, sharding=self._rep)

    def abstract_flag(self) -> jax.ShapeDtypeStruct:
        """The `flag` argument of `epoch_flag` (a boolean scalar, replicated)."""
        return jax.ShapeDtypeStruct((), jnp.bool_, sharding=self._rep)

    def put_flag(self, probe: bool) -> jax.Array:
        return jax.device_put(np.bool_(probe), self._rep)

    def put_key(self, key: jax.Array) -> jax.Array:
        """A host-side PRNG key placed on the mesh (replicated)."""
        return jax.device_put(key, self._rep)

    def _on_worlds(self, f: Callable, in_specs: Any, out_specs: Any) -> Callable:
        """`f` run per device on its own worlds (`shard_map`) when sharded, else `f` itself."""
        if not self.sharded:
            return f
        return jax.shard_map(f, mesh=self.mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)

    def seed_keys(self, key: jax.Array) -> jax.Array:
        """`[S]` keys, one per seed of this experiment: `split(key, total)` of the whole run's seeds,
        this experiment's slice of them (all of them unless it holds a seed group)."""
        keys = jax.random.split(key, self.seed_total)
        return keys if self.seed_total == self.S else keys[self.seed_offset:self.seed_offset + self.S]

    def world_keys(self, key: jax.Array) -> jax.Array:
        """`[S*N]` keys, one per world of this experiment's seeds, as `seed_keys` slices them."""
        keys = jax.random.split(key, self.seed_total * self.N)
        return keys if self.seed_total == self.S else keys[self.seed_offset * self.N:(self.seed_offset + self.S) * self.N]

    def seed_columns(self, x: jax.Array) -> jax.Array:
        """This experiment's worlds `[..., S*N]` of a draw made for the whole run's `[..., total*N]`."""
        if self.seed_total == self.S:
            return x
        return x[..., self.seed_offset * self.N:(self.seed_offset + self.S) * self.N]

    def _env_reset(self, key: jax.Array) -> EnvState:
        """`env.reset(key)` of all S*N worlds (`env.reset_keys` of `split(key, S*N)`); sharded,
        each device resets its own worlds from the same per-world keys as one device would."""
        keys = self.world_keys(key)
        if not self.sharded:
            return self.env.reset_keys(keys)
        w = P((SEED_AXIS, WORLD_AXIS))
        return self._on_worlds(self.env.reset_keys, (w,), w)(keys)

    def _env_step(self, es: EnvState, action: jax.Array) -> EnvState:
        w = P((SEED_AXIS, WORLD_AXIS))
        return self._on_worlds(self.env.step, (w, w), w)(es, action)

    def _render_sequence(self, render_inputs: Any) -> jax.Array:
        """Frames `[K, S*N, H, W, 3]` of stored steps `[K, S*N]`."""
        if not self.sharded:
            return self.env.render_sequence(render_inputs)
        kw = P(None, (SEED_AXIS, WORLD_AXIS))
        return self._on_worlds(self._render_local, (kw,), kw)(render_inputs)

    # ------------------------------------------------------------------ helpers
    @property
    def S(self) -> int:
        return self.config.seeds

    @property
    def N(self) -> int:
        return self.config.num_envs

    def _per_seed(self, x: jax.Array) -> jax.Array:
        """[S*N, ...] -> [S, N, ...]."""
        return x.reshape((self.S, self.N) + x.shape[1:])

    def _flat(self, x: jax.Array) -> jax.Array:
        """[S, N, ...] -> [S*N, ...]."""
        return x.reshape((self.S * self.N,) + x.shape[2:])

    # ------------------------------------------------------------------ PPO's observation
    def _abstract_learner_params(self, name: str) -> Any:
        """Shapes of one seed's params of learner `name` (to size PPO's input)."""
        l = self.learners[name]
        return jax.eval_shape(lambda k: l.init(k, self.env.frame_shape), jax.random.PRNGKey(0)).params

    def _encode_frames(self, params: Any, frames: jax.Array) -> jax.Array:
        """The RL learner's latent of uint8 frames `[B, H, W, 3]` (one seed), without gradient
        into the learner."""
        return self.learners[self.rl_learner].encode(jax.lax.stop_gradient(params), frames)

    def _window_latents(self, params: Any, frames: jax.Array, actions: jax.Array) -> jax.Array:
        """The sequential RL learner's per-step latents `[B, L, Z]` of windows given as frames
        `[B, L, H, W, 3]` and actions (one seed; sizes PPO's input)."""
        learner = self.learners[self.rl_learner]
        return learner.encode_features(params, learner.frame_features(params, frames), actions)

    def _current_frames(self, es: EnvState) -> jax.Array:
        """Every world's current frame, per seed `[S, N, H, W, 3]` uint8 (rendered here)."""
        ri = jax.tree.map(lambda x: x[None], es.render_input)
        return self._per_seed(self._render_sequence(ri)[0])

    def _history_start(self, es: EnvState) -> PolicyHistory:
        """The `PolicyHistory` of freshly reset worlds: their current frame alone (count 1)."""
        frames = self._current_frames(es)
        l = self.learners[self.rl_learner].sequence_length
        return PolicyHistory(
            frames=jnp.broadcast_to(frames[:, :, None], frames.shape[:2] + (l,) + frames.shape[2:]),
            actions=jnp.zeros((self.S, self.N, l, self.action_dim), jnp.float32),
            count=jnp.ones((self.S, self.N), jnp.int32))

    def _frame_features(self, learners: dict, frames: jax.Array) -> jax.Array:
        """The sequential RL learner's `frame_features` of per-seed frames `[S, N, T, H, W, 3]`
        -> `[S, N, T, F]`, each seed's current params, no gradient into the learner."""
        learner = self.learners[self.rl_learner]
        fn = lambda p, f: learner.frame_features(jax.lax.stop_gradient(p), f)  # noqa: E731
        return self.over_seeds(fn, learners[self.rl_learner].params, frames, learner=self.rl_learner)

    def policy_window(self, learners: dict, history: PolicyHistory) -> PolicyWindow:
        """`history` with the features of its frames under the learners' current params: L conv
        passes per world, once per rollout (the params changed since the history was built)."""
        return PolicyWindow(history, self._frame_features(learners, history.frames))

    def _window_push(self, learners: dict, window: PolicyWindow, es: EnvState, frames: jax.Array,
                     action: jax.Array) -> PolicyWindow:
        """The window after an env step: `es`'s frames `[S, N, H, W, 3]` (one conv pass each)
        appended with the actions that led into them `[S, N(, A)]`; a world whose step ended an
        episode (`es.done`: its frame is the next episode's first) starts its window over."""
        h = window.history
        feats = self._frame_features(learners, frames[:, :, None])[:, :, 0]
        act = self._per_seed(self._action_features(action))
        fresh = self._per_seed(es.done) > 0
        l = h.frames.shape[2]
        hist = PolicyHistory(frames=push_window(h.frames, frames, h.count, fresh, True),
                             actions=push_window(h.actions, act, h.count, fresh, False),
                             count=jnp.where(fresh, 1, jnp.minimum(h.count + 1, l)).astype(jnp.int32))
        return PolicyWindow(hist, push_window(window.features, feats, h.count, fresh, True))

    def _window_obs(self, learners: dict, window: PolicyWindow) -> jax.Array:
        """PPO's latent of every world `[S, N, Z]`: the sequential learner's per-step latent of
        its window at the current step (`count - 1`), each seed's current params."""
        learner = self.learners[self.rl_learner]

        def one_seed(params: Any, feats: jax.Array, actions: jax.Array, count: jax.Array) -> jax.Array:
            z = learner.encode_features(jax.lax.stop_gradient(params), feats, actions)  # [N, L, Z]
            return jnp.take_along_axis(z, (count - 1)[:, None, None], axis=1)[:, 0]

        h = window.history
        return self.over_seeds(one_seed, learners[self.rl_learner].params, window.features, h.actions, h.count,
                               learner=self.rl_learner)

    @property
    def policy_renders(self) -> bool:
        """Whether PPO observes frames (pixels or a learner's latent): its rollouts render every
        step's frame, and keep it for replay, windows and probes (`Rendered`)."""
        return self.rl_pixels or self.rl_learner is not None

    def _policy_view(self, es: EnvState, learners: dict | None, history: PolicyHistory | None,
                     random: bool) -> PolicyView:
        """What a rollout from `es` starts with (`PolicyView`): for a sequential learner the
        worlds' `history` with its features, for pixels or a frame learner the current frames
        (rendered here), None for the true state or the random policy."""
        if random or not self.policy_renders:
            return None
        if self.rl_sequential:
            if history is None:
                raise ValueError("PPO observes a sequential learner's latent: pass the worlds' PolicyHistory")
            return self.policy_window(learners, history)
        return self._current_frames(es)

    def _policy_obs(self, es: EnvState, learners: dict | None, view: PolicyView = None) -> jax.Array:
        """PPO's observation of every world, per seed `[S, N, ...]`: the true state; with
        `rl_input="pixels"` the world's current frame (uint8; `view`, or rendered here); with
        `rl_input="latent:<name>"` that learner's latent of the current frame, encoded with the
        seed's current parameters; for a sequential learner, its latent of the current step of
        the `view`'s window (the last L steps up to the current one, `PolicyHistory`)."""
        if self.rl_learner is None and not self.rl_pixels:
            return self._per_seed(es.obs)
        if self.rl_sequential:
            if learners is None or not isinstance(view, PolicyWindow):
                raise ValueError("PPO observes a sequential learner's latent: pass the learners' "
                                 "states and the worlds' PolicyWindow")
            return self._window_obs(learners, view)
        frames = self._current_frames(es) if view is None else view  # [S, N, H, W, 3]
        if self.rl_pixels:
            return frames
        if learners is None:
            raise ValueError("PPO observes a learner's latent: pass the learners' states")
        return self.over_seeds(self._encode_frames, learners[self.rl_learner].params, frames,
                               learner=self.rl_learner)

    def _policy_step(self, ppo_state: PPOState, es: EnvState, key: jax.Array, random: bool,
                     learners: dict | None = None, view: PolicyView = None):
        """One step of all worlds: PPO's observation, its action (or a random one), the env step.
        Returns `(next env state, obs, action, logp, value, view, stored)`: the `PolicyView`
        moved on to the next env state (its frames rendered here, once per step) and the step
        as rollouts store it (`_stored`)."""
        keys = self.seed_keys(key)
        if random:  # the random policy observes nothing: no frame is rendered for it
            obs = self._per_seed(es.obs)
            action = jax.vmap(lambda k: self.ppo.random_act(k, self.N))(keys)
            logp = value = jnp.zeros((self.S, self.N))
        else:
            obs = self._policy_obs(es, learners, view)
            action, logp, value = jax.vmap(self.ppo.act)(ppo_state, obs, keys)
        nes = self._env_step(es, self._flat(self.ppo.env_action(action)))
        frames = None
        if view is not None:
            frames = self._current_frames(nes)
            view = self._window_push(learners, view, nes, frames, action) if self.rl_sequential else frames
        return nes, obs, action, logp, value, view, self._stored(nes, action, frames)

    def _stored(self, es: EnvState, action: jax.Array, frames: jax.Array | None) -> tuple:
        """A step as rollouts store it: (render input, or the `Rendered` frames where the policy
        rendered them, true state, action features, done), each `[S*N, ...]`."""
        ri = es.render_input if frames is None else Rendered(self._flat(frames))
        return ri, es.lowdim, self._action_features(action), es.done

    def _frames_at(self, render_inputs: Any) -> jax.Array:
        """Frames `[K, S*N, H, W, 3]` of stored steps `[K, S*N]`: rendered from their render
        inputs, or the policy's own frames where it kept them (`Rendered`): the same pixels,
        rendered once."""
        if isinstance(render_inputs, Rendered):
            return render_inputs.frames
        return self._render_sequence(render_inputs)

    def _frames_of_steps(self, render_inputs: Any, lowdim: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Render stored steps `[K, S*N]` -> per-seed frames `[S, K*N, H, W, 3]` and states."""
        frames = self._frames_at(render_inputs)  # [K, S*N, H, W, 3]
        k = frames.shape[0]
        frames = frames.reshape((k, self.S, self.N) + frames.shape[2:]).swapaxes(0, 1)
        lowdim = lowdim.reshape((k, self.S, self.N, -1)).swapaxes(0, 1)
        return (frames.reshape((self.S, k * self.N) + frames.shape[3:]),
                lowdim.reshape((self.S, k * self.N, -1)))

    def _action_features(self, action: jax.Array) -> jax.Array:
        """Per-seed policy actions `[S, N(, A)]` -> float features `[S*N, A]` (one-hot if discrete)."""
        if self.env.discrete:
            return self._flat(jax.nn.one_hot(action, self.action_dim, dtype=jnp.float32))
        return self._flat(self.ppo.env_action(action).astype(jnp.float32))

    def _rollout(self, ppo_state: PPOState, es: EnvState, key: jax.Array, steps: int, random: bool,
                 learners: dict | None = None, history: PolicyHistory | None = None):
        """Run `steps` steps, storing (render inputs, true states, action features, dones), each
        `[steps, S*N, ...]`, unrendered (the random policy, PPO on the state). `learners`: for a policy that observes a latent;
        `history`: the worlds' `PolicyHistory` for one that observes a sequential learner's.
        A policy that observes frames keeps them in place of the render inputs (`Rendered`).
        Returns `((env state, history after the steps or None), stored)`."""
        view = self._policy_view(es, learners, history, random)

        def body(carry, k):
            es, view = carry
            nes, _, _, _, _, view, stored = self._policy_step(ppo_state, es, k, random, learners, view)
            return (nes, view), stored

        (es, view), stored = jax.lax.scan(body, (es, view), jax.random.split(key, steps))
        return (es, _history_of(view)), stored

    def _collect(self, ppo_state: PPOState, es: EnvState, key: jax.Array, steps: int, random: bool):
        """Run `steps` steps and render every one of them (initial replay frames)."""
        (es, _), (ri, low, _, _) = self._rollout(ppo_state, es, key, steps, random)
        frames, states = self._frames_of_steps(ri, low)
        return es, frames, states

    def _windows(self, steps: tuple, starts: jax.Array, length: int) -> Windows:
        """Render windows of `length` steps from stored steps `[T, S*N]` (or gather the policy's
        frames, `Rendered`), one per world and round (`starts [R, S*N]`), cut at episode
        boundaries -> per-seed `Windows [S, R*N, length]`."""
        ri, low, act, done = steps
        r = starts.shape[0]
        src, valid = jax.vmap(lambda st: sequence.window_indices(done, st, length))(starts)
        src, valid = src.reshape((r * length, -1)), valid.reshape((r * length, -1))
        frames = self._frames_at(jax.tree.map(lambda x: sequence.gather_steps(x, src), ri))
        act = sequence.gather_steps(act, src) * valid[..., None]

        def per_seed(x: jax.Array) -> jax.Array:  # [R*L, S*N, ...] -> [S, R*N, L, ...]
            x = x.reshape((r, length, self.S, self.N) + x.shape[2:])
            x = jnp.moveaxis(x, (2, 0, 3, 1), (0, 1, 2, 3))
            return x.reshape((self.S, r * self.N, length) + x.shape[4:])

        return Windows(frames=per_seed(frames), actions=per_seed(act),
                       states=per_seed(sequence.gather_steps(low, src)), valid=per_seed(valid))

    # ------------------------------------------------------------------ init
    def _init(self, key: jax.Array) -> RunState:
        """The run state before the first epoch: `init_env`'s, with every learner's `init_learner`."""
        return self.init_env(key).replace(learners={n: self.init_learner(n, key) for n in self.learners})

    def init_learner(self, name: str, key: jax.Array) -> Any:
        """Learner `name`'s state for every seed `[S]`, from the run's init key."""
        k_learn = jax.random.split(key, 5)[1]
        keys = self.seed_keys(jax.random.fold_in(k_learn, list(self.learners).index(name)))
        learner = self.learners[name]
        # one seed at a time: the same parameters as a vmap, and on the GPU a much cheaper
        # compile for DSA (its init over 6 seeds: 23 s under lax.map, 40 s vmapped; H100)
        return jax.lax.map(lambda k: learner.init(k, self.env.frame_shape), keys)

    def init_env(self, key: jax.Array) -> RunState:
        """The run state before the first epoch without the learners' states (`learners={}`):
        PPO, the worlds, replay and window buffers filled by the random policy, the reference
        spread."""
        c = self.config
        k_ppo, _, k_env, k_fill, k_keep = jax.random.split(key, 5)
        ppo_state = jax.vmap(self.ppo.init)(self.seed_keys(k_ppo))
        learners: dict[str, Any] = {}
        ke = jax.random.split(k_env, 4)
        train_env, curr_env, rand_env = (self._env_reset(k) for k in ke[:3])
        # The reference spread of every state entry, once per run: the random policy's held-out
        # worlds run `reference_steps` steps (pooled over seeds); their π_rand stream goes on from there.
        (rand_env, _), (_, ref_states, _, _) = self._rollout(ppo_state, rand_env, ke[3], c.reference_steps,
                                                             random=True)
        ref_spread = probe.spread(ref_states.reshape((-1, ref_states.shape[-1])))
        # Fill replay with frames of the random policy; retained learners keep a share of them.
        steps = -(-c.replay_capacity // self.N)
        k_fill_reset, k_fill_roll = jax.random.split(k_fill)
        _, frames, states = self._collect(ppo_state, self._env_reset(k_fill_reset), k_fill_roll, steps,
                                          random=True)
        frames, states = frames[:, : c.replay_capacity], states[:, : c.replay_capacity]
        rcfg = replay.ReplayConfig(capacity=c.replay_capacity)
        buffers = {}
        for frac in sorted(set(self.retention.values())):
            def fill(f, s, k, frac=frac):
                buf = replay.init(rcfg, self.env.frame_shape, self.env.state_dim,
                                  extras={"world": jax.ShapeDtypeStruct((), jnp.int32)})
                buf = replay.insert(buf, k, f, s, {"world": self._world_ids(f.shape[0])})
                return replay.retain_initial(buf, k, frac) if frac > 0 else buf
            buffers[buffer_key(frac)] = jax.vmap(fill)(frames, states, self.seed_keys(k_keep))
        # Keys of the window buffers are folded in, so frame-only runs keep their random streams.
        windows = self._init_windows(ppo_state, jax.random.fold_in(key, 1)) if self.window_length else {}
        # PPO on a sequential learner's latent: every policy-driven world's window starts at its first frame.
        history = ({"train": self._history_start(train_env), "curr": self._history_start(curr_env)}
                   if self.rl_sequential else {})
        return RunState(ppo=ppo_state, learners=learners, buffers=buffers, windows=windows,
                        train_env=train_env, curr_env=curr_env, rand_env=rand_env, policy_history=history,
                        ref_spread=ref_spread, epoch=jnp.zeros((), jnp.int32))

    def reference_states(self, key: jax.Array) -> jax.Array:
        """The states `[reference_steps, S*N, D]` that init's reference spread is taken over (the
        random policy's held-out worlds, `init_env`), recomputed from the init key: a run of seed
        groups pools them over all its groups (`bulbjax.experiment.groups`)."""
        k_ppo, _, k_env, _, _ = jax.random.split(key, 5)
        ppo_state = jax.vmap(self.ppo.init)(self.seed_keys(k_ppo))
        ke = jax.random.split(k_env, 4)
        _, (_, ref_states, _, _) = self._rollout(ppo_state, self._env_reset(ke[2]), ke[3],
                                                 self.config.reference_steps, random=True)
        return ref_states

    def _init_windows(self, ppo_state: PPOState, key: jax.Array) -> dict[str, sequence.WindowBuffer]:
        """Fill the window buffers with windows of a random-policy rollout (consecutive,
        non-overlapping windows per world), then retain a share of them for the sequential
        learners that ask for it (all of them by default: the paper's fix applied to all)."""
        c, lw = self.config, self.window_length
        cap = sequence.capacity_in_windows(c.replay_capacity, lw)
        rounds = -(-cap // self.N)
        k_reset, k_roll, k_keep = jax.random.split(key, 3)
        _, st = self._rollout(ppo_state, self._env_reset(k_reset), k_roll, rounds * lw, random=True)
        starts = jnp.broadcast_to((jnp.arange(rounds) * lw)[:, None], (rounds, self.S * self.N))
        w = jax.tree.map(lambda x: x[:, :cap], self._windows(st, starts, lw))
        out = {}
        fracs = {self.retention[n] for n, seq in self.sequential.items() if seq}
        for frac in sorted(fracs):
            def fill(w, k, frac=frac):
                buf = sequence.init(cap, lw, self.env.frame_shape, self.env.state_dim, self.action_dim)
                buf = sequence.insert(buf, k, w)
                return sequence.retain_initial(buf, k, frac) if frac > 0 else buf
            out[buffer_key(frac)] = jax.vmap(fill)(w, self.seed_keys(k_keep))
        return out

    # ------------------------------------------------------------------ epoch phases
    def rl_phase(self, ppo_state: PPOState, env_state: EnvState, key: jax.Array,
                 learners: dict | None = None, history: PolicyHistory | None = None):
        """PPO on the true state (or on a learner's latent, `learners` given; a sequential
        learner's also needs the worlds' `history`): rollouts of all seeds' worlds at once,
        per-seed updates.
        Returns the new PPO state, env state, update metrics, per-seed finished-episode return
        sum and count, the stored steps (render inputs, or the policy's frames: `_stored`; true
        states, action features, dones) `[U*T, S*N, ...]`, and the worlds' new `PolicyHistory`
        (None without one)."""
        c = self.config
        view = self._policy_view(env_state, learners, history, False)

        def rl_update(carry, k):
            ppo_state, es, view = carry
            k_roll, k_upd = jax.random.split(k)

            def step(carry, kk):
                es, view = carry
                nes, obs, action, logp, value, view, stored = self._policy_step(ppo_state, es, kk, False,
                                                                                learners, view)
                tr = Transition(obs, action, self._per_seed(nes.reward), self._per_seed(nes.done),
                                self._per_seed(nes.truncated), logp, value)
                ep = (self._per_seed(nes.info["episode_return"] * nes.done).sum(1),
                      self._per_seed(nes.done).sum(1))
                return (nes, view), (tr, ep, stored)

            (es, view), (traj, ep, stored) = jax.lax.scan(step, (es, view),
                                                          jax.random.split(k_roll, c.ppo.num_steps))
            traj = jax.tree.map(lambda x: x.swapaxes(0, 1), traj)  # [S, T, N, ...]
            ppo_state, m = jax.vmap(self.ppo.update)(ppo_state, traj, self._policy_obs(es, learners, view),
                                                    self.seed_keys(k_upd))
            return (ppo_state, es, view), (m, ep, stored)

        (ppo_state, env_state, view), (m, ep, stored) = jax.lax.scan(
            rl_update, (ppo_state, env_state, view), jax.random.split(key, c.ppo_updates_per_epoch))
        total = c.ppo_updates_per_epoch * c.ppo.num_steps
        steps = jax.tree.map(lambda x: x.reshape((total,) + x.shape[2:]), stored)
        return (ppo_state, env_state, jax.tree.map(lambda x: x.mean(0), m), ep[0].sum((0, 1)),
                ep[1].sum((0, 1)), steps, _history_of(view))

    def replay_phase(self, buffers: dict, steps: tuple, key: jax.Array) -> dict:
        """Render a random subset of the epoch's stored steps (all worlds of each chosen step;
        the policy's own frames where it kept them, `Rendered`) and write those frames of the
        current policy into every replay buffer."""
        c = self.config
        ri, low = steps[:2]
        k_pick, k_ins = jax.random.split(key)
        pick = jax.random.choice(k_pick, low.shape[0], (c.frames_per_epoch // self.N,), replace=False)
        frames, states = self._frames_of_steps(jax.tree.map(lambda x: x[pick], ri), low[pick])
        keys = self.seed_keys(k_ins)
        world = {"world": jnp.broadcast_to(self._world_ids(frames.shape[1]), frames.shape[:2])}
        return {k: jax.vmap(replay.insert)(b, keys, frames, states, world) for k, b in buffers.items()}

    def _world_ids(self, n: int) -> jax.Array:
        """`[n]` world index (0..N-1) of each of a seed's `n` frames as `_frames_of_steps` lays
        them out (step-major). Kept in replay so that the probe's validation split keeps one
        world's frames together (`probe.fit`'s `groups`)."""
        return (jnp.arange(n) % self.N).astype(jnp.int32)

    def window_phase(self, windows: dict, steps: tuple, key: jax.Array) -> dict:
        """Cut windows of the epoch's stored steps at random starts (one per world and round, cut
        at episode boundaries), render them, and write `frames_per_epoch // window_length` of them
        per seed (a random subset) into every window buffer: the frame buffers' frame budget."""
        if not windows:
            return windows
        c, lw = self.config, self.window_length
        per_epoch = max(1, c.frames_per_epoch // lw)
        rounds = -(-per_epoch // self.N)
        k_start, k_pick, k_ins = jax.random.split(key, 3)
        total = steps[1].shape[0]
        starts = self.seed_columns(jax.random.randint(k_start, (rounds, self.seed_total * self.N), 0, total - lw + 1))
        w = self._windows(steps, starts, lw)
        picks = jax.vmap(lambda k: jax.random.permutation(k, rounds * self.N)[:per_epoch])(
            self.seed_keys(k_pick))
        w = jax.vmap(lambda ws, p: jax.tree.map(lambda x: x[p], ws))(w, picks)
        keys = self.seed_keys(k_ins)
        return {k: jax.vmap(sequence.insert)(b, keys, w) for k, b in windows.items()}

    def over_seeds(self, fn: Callable[..., Any], *args: Any, learner: str | None = None) -> Any:
        """`fn` over every seed's slice of `args` with the run's seed loop (`over_seeds`), as
        `learner`'s work runs over seeds (`learner_loop`; None: a frame learner's)."""
        return over_seeds(self.loop_of(learner), fn, *args)

    def loop_of(self, learner: str | None) -> str:
        """The seed loop ("map" or "vmap") of `learner`'s work (`learner_loop`)."""
        return learner_loop(self.seed_loop, self.learners.get(learner))

    def units(self) -> list[tuple[str, ...]]:
        """The learners in the units that one update (and probe) program serves, in order: a
        group of VAEs sharing one program (`update_groups`, `ExperimentConfig.shared_updates`)
        or one learner alone. A unit's work reads only its own members' states (and the
        buffers), so units run in any order, fused in one epoch or as programs of their own
        (`Stages`)."""
        return update_groups(self.learners, self.config.shared_updates)

    def learn_phase(self, learners: dict, buffers: dict, key: jax.Array,
                    windows: dict | None = None) -> tuple[dict, dict]:
        """`learner_batches` updates of every learner on batches sampled from its replay buffer:
        `learner.batch_size` frames (frame learners) or windows (sequential learners: the frame
        batch divided by the sequence length, the paper's equalised compute). One `learn_unit`
        per unit (`units`)."""
        out, metrics = {}, {}
        for unit in self.units():
            states, m = self.learn_unit(unit, learners, buffers, key, windows)
            out.update(states)
            metrics.update(m)
        return {n: out[n] for n in self.learners}, {n: metrics[n] for n in self.learners}

    def learn_unit(self, unit: Sequence[str], learners: dict, buffers: dict, key: jax.Array,
                   windows: dict | None = None) -> tuple[dict, dict]:
        """`learn_phase` for one unit (`units`): its members' new states and per-seed mean
        metrics. `key` is the epoch's learning key; each member's keys are folded in with its
        position among all learners, so a unit gets the same keys alone as in the whole phase.
        Its ops carry the scope `bj.learn.<members>` (benchmarks/trace_summary.py)."""
        with jax.named_scope(f"bj.learn.{'+'.join(unit)}"):
            return self._learn_unit(unit, learners, buffers, key, windows)

    def _learn_unit(self, unit: Sequence[str], learners: dict, buffers: dict, key: jax.Array,
                    windows: dict | None) -> tuple[dict, dict]:
        c = self.config
        if len(unit) > 1:
            states, m = self._learn_group(unit, learners, buffers, key)
            return states, {n: jax.tree.map(lambda x: x.mean(-1), mm) for n, mm in m.items()}
        (name,) = unit
        learner, seq, i = self.learners[name], self.sequential[name], list(self.learners).index(name)

        def train_seed(state, b, k):
            if seq:
                sample = lambda kk: sequence.sample(b, kk, learner.batch_size)  # noqa: E731
            else:
                sample = lambda kk: replay.sample(b, kk, learner.batch_size)[0]  # noqa: E731
            return train_learner(learner, state, sample, k, c.learner_batches)

        keys = self.seed_keys(jax.random.fold_in(key, i))
        buf = (windows if seq else buffers)[buffer_key(self.retention[name])]
        state, m = self.over_seeds(train_seed, learners[name], buf, keys, learner=name)
        return {name: state}, {name: jax.tree.map(lambda x: x.mean(-1), m)}

    def _group_inputs(self, group: Sequence[str], buffers: dict, key: jax.Array
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

    def _learn_group(self, group: Sequence[str], learners: dict, buffers: dict, key: jax.Array
                     ) -> tuple[dict, dict]:
        """`learn_phase` for a group of VAEs (`update_groups`): one update program, run over
        seeds and, within a seed, over members (each with its beta and its replay buffer), with
        the run's seed loop. Same keys and batches as each member's own `learn_phase` step."""
        c = self.config
        template, bufs, which, keys = self._group_inputs(group, buffers, key)
        betas = jnp.array([self.learners[n].config.beta for n in group], jnp.float32)
        draw = lambda b, k: replay.sample(b, k, template.batch_size)[0]  # noqa: E731

        def train_seed(states, bs, ks):
            def member(state, k, beta, w):
                sample = lambda kk: switch_buffer(w, bs, draw, kk)  # noqa: E731
                return train_learner(template, state, sample, k, c.learner_batches, beta=beta)
            return self.over_seeds(member, states, ks, betas, which)

        states = stack_members([learners[n] for n in group])
        states, m = self.over_seeds(train_seed, states, bufs, keys)
        return unstack_members(states, group), unstack_members(m, group)

    def eval_phase(self, ppo_state: PPOState, curr_env: EnvState, rand_env: EnvState, key: jax.Array,
                   learners: dict | None = None, history: PolicyHistory | None = None):
        """Held-out windows (never in replay) from the current and from a random policy: each
        world's rollout of `ceil(eval_frames / N)` steps, rounded up to whole windows of
        `eval_length` steps, cut into consecutive windows (and at episode boundaries).
        `history`: the current-policy worlds' `PolicyHistory` (PPO on a sequential learner's
        latent). Returns both env states, the windows and the new history (None without one)."""
        le = self.eval_length
        rounds = -(-self.config.eval_frames // (self.N * le))
        starts = jnp.broadcast_to((jnp.arange(rounds) * le)[:, None], (rounds, self.S * self.N))
        k_curr, k_rand = jax.random.split(key)
        (curr_env, history), cst = self._rollout(ppo_state, curr_env, k_curr, rounds * le, random=False,
                                                 learners=learners, history=history)
        (rand_env, _), rst = self._rollout(ppo_state, rand_env, k_rand, rounds * le, random=True)
        return curr_env, rand_env, {"curr": self._windows(cst, starts, le),
                                    "rand": self._windows(rst, starts, le)}, history

    def _object_scorer(self, learner: Any) -> Callable[[jax.Array, Windows], dict] | None:
        """The object-level probe of one seed's held-out stream for a learner with boxes (SPAIR,
        `boxes_of_latents`) in a domain with objects; None otherwise. It maps the stream's
        per-step latents `[B, L, Z]` and windows to `objects.reduce_scores` of its valid steps
        (per object: distance from the true object's image position to the nearest present box
        centre, share within `object_radius` px) plus the `radius`."""
        if self.objects is None or is_sequential(learner) or not hasattr(learner, "boxes_of_latents"):
            return None
        _, pixels = self.objects
        res, radius = self.config.resolution, self.object_radius

        def score(z: jax.Array, w: Windows) -> dict:
            centres, pres = learner.boxes_of_latents(z.reshape((-1, z.shape[-1])), res)
            pos = pixels(w.states.reshape((-1, w.states.shape[-1])))
            out = objects.reduce_scores(objects.object_scores(centres, pres, pos, radius), w.valid)
            return {**out, "radius": jnp.float32(radius)}

        return score

    def probe_phase(self, learners: dict, buffers: dict, held_out: dict, key: jax.Array,
                    windows: dict | None = None) -> dict:
        """Alignment probes: fit latents -> true state on replay data, evaluate on the held-out
        windows' valid steps. Frame learners: one latent per frame. Sequential learners: the
        per-step latents of replay windows (probe_train_frames valid steps drawn from them) and
        of the held-out windows; the latent at step t is matched with the state at step t.
        Learners with boxes (SPAIR) in domains with objects also get the object-level probe
        on the same held-out steps, per stream under `"objects"` (`_object_scorer`). One
        `probe_unit` per unit (`units`)."""
        out = {}
        for unit in self.units():
            out.update(self.probe_unit(unit, learners, buffers, held_out, key, windows))
        return {n: out[n] for n in self.learners}

    def probe_unit(self, unit: Sequence[str], learners: dict, buffers: dict, held_out: dict,
                   key: jax.Array, windows: dict | None = None) -> dict:
        """`probe_phase` for one unit (`units`), with the keys its members get in the whole phase;
        its ops carry the scope `bj.probe.<members>`."""
        with jax.named_scope(f"bj.probe.{'+'.join(unit)}"):
            return self._probe_unit(unit, learners, buffers, held_out, key, windows)

    def _probe_unit(self, unit: Sequence[str], learners: dict, buffers: dict, held_out: dict,
                    key: jax.Array, windows: dict | None) -> dict:
        c = self.config
        if len(unit) > 1:
            return self._probe_group(unit, learners, buffers, held_out, key)
        (name,) = unit
        learner, seq, i = self.learners[name], self.sequential[name], list(self.learners).index(name)

        def latents_seed(k_c, k_s, lstate, b, held):
            if seq:
                train = sequence.sample(b, k_s, -(-c.probe_train_frames // learner.sequence_length))
            else:
                frames, states, extras = replay.sample_with_extras(b, k_s, c.probe_train_frames)
                train = (frames, states, extras["world"])
            return probe_latents(learner, lstate.params, train, held, k_c, c.probe, c.probe_train_frames)

        def fit_seed(lat, k_f, k_s, lstate, b, held):
            return fit_and_score(lat, held, k_f, c.probe, self._object_scorer(learner))

        keys = self.seed_keys(jax.random.fold_in(key, i))
        k_s, k_p = jax.vmap(jax.random.split)(keys).swapaxes(0, 1)
        buf = (windows if seq else buffers)[buffer_key(self.retention[name])]
        return {name: probe_over_seeds(self.loop_of(name), latents_seed, fit_seed, k_p,
                                       k_s, learners[name], buf, held_out)}

    def _probe_group(self, group: Sequence[str], learners: dict, buffers: dict, held_out: dict,
                     key: jax.Array) -> dict:
        """`probe_phase` for a group of VAEs (`update_groups`): the encodings with the run's seed
        loop over seeds and members, the probe MLPs of all seeds and members vmapped side by
        side. Same keys as each member's own probe (`probe_over_seeds`), so the same numbers."""
        c = self.config
        template, bufs, which, keys = self._group_inputs(group, buffers, key)
        split = jax.vmap(jax.vmap(jax.random.split))
        k_s, k_p = jnp.moveaxis(split(keys), 2, 0)  # each [S, G, 2]
        k_c, k_f = jnp.moveaxis(split(k_p), 2, 0)
        score = self._object_scorer(template)

        def draw(b, k):
            frames, states, extras = replay.sample_with_extras(b, k, c.probe_train_frames)
            return frames, states, extras["world"]

        def latents_seed(kc, ks, states, bs, held):
            def member(kcm, ksm, state, w):
                train = switch_buffer(w, bs, draw, ksm)
                return probe_latents(template, state.params, train, held, kcm, c.probe, c.probe_train_frames)
            return self.over_seeds(member, kc, ks, states, which)

        def fit_seed(lat, kf, held):
            return jax.vmap(lambda l, k: fit_and_score(l, held, k, c.probe, score))(lat, kf)

        states = stack_members([learners[n] for n in group])
        lat = self.over_seeds(latents_seed, k_c, k_s, states, bufs, held_out)
        return unstack_members(jax.vmap(fit_seed)(lat, k_f, held_out), group)

    def _rl_learners(self, learners: dict) -> dict | None:
        """The learner states PPO's policy reads (its `rl_input` learner's), None when it reads none."""
        return None if self.rl_learner is None else {self.rl_learner: learners[self.rl_learner]}

    def env_stage(self, ppo_state: PPOState, train_env: EnvState, buffers: dict, windows: dict,
                  train_hist: PolicyHistory | None, learners: dict | None, ref_spread: jax.Array,
                  epoch: jax.Array, key: jax.Array) -> "EnvStage":
        """An epoch's environment work, before any learner updates: PPO (rollouts and updates),
        frames of its rollouts into replay, windows into the window buffers; the epoch's
        metrics of it, its counter moved on, and the keys of the later phases. `learners`: the
        states PPO's policy reads (`_rl_learners`)."""
        k_rl, k_rep, k_learn, k_eval, k_probe = jax.random.split(key, 5)
        # named scopes label each phase's ops in a profiler trace (benchmarks/trace_summary.py)
        with jax.named_scope("bj.rl"):
            ppo_state, train_env, ppo_m, ret_sum, count, steps, train_hist = self.rl_phase(
                ppo_state, train_env, k_rl, learners, train_hist)
        with jax.named_scope("bj.replay"):
            buffers = self.replay_phase(buffers, steps, k_rep)
        with jax.named_scope("bj.windows"):
            windows = self.window_phase(windows, steps, jax.random.fold_in(k_rep, 1))
        metrics = {
            "rl_return": jnp.where(count > 0, ret_sum / jnp.maximum(count, 1), jnp.nan),
            "rl_episodes": count,
            "ppo": ppo_m,
            "ref_spread": jnp.broadcast_to(ref_spread, (self.S,) + ref_spread.shape),
            "replay_dropped": {**{k: b.num_dropped for k, b in buffers.items()},
                               **{f"windows_{k}": b.num_dropped for k, b in windows.items()}},
        }
        return EnvStage(ppo_state, train_env, buffers, windows, train_hist, metrics, epoch + 1,
                        k_learn, k_eval, k_probe)

    def eval_stage(self, ppo_state: PPOState, curr_env: EnvState, rand_env: EnvState,
                   rl_learners: dict | None, curr_hist: PolicyHistory | None, key: jax.Array) -> tuple:
        """A probing epoch's held-out rollouts (`eval_phase`); `rl_learners`: the updated states
        PPO's policy reads (`_rl_learners`)."""
        with jax.named_scope("bj.eval"):
            return self.eval_phase(ppo_state, curr_env, rand_env, key, rl_learners, curr_hist)

    def _epoch(self, rs: RunState, key: jax.Array, probe: bool | jax.Array = True
               ) -> tuple[RunState, dict[str, Any]]:
        """One epoch; with `probe=False` no held-out rollout or probe (metrics without `probes`).
        A traced boolean `probe` (`epoch_flag`) puts both in one program: the held-out rollouts
        and probes run under `lax.cond`, and the metrics always have `probes` (NaN or 0 where the
        epoch did not probe; `Programs.epoch` drops them). `Stages` runs the same steps
        (`env_stage`, `learn_unit`, `eval_stage`, `probe_unit`) as programs of their own."""
        hist = dict(rs.policy_history)
        env = self.env_stage(rs.ppo, rs.train_env, rs.buffers, rs.windows, hist.get("train"),
                             self._rl_learners(rs.learners), rs.ref_spread, rs.epoch, key)
        if env.train_hist is not None:
            hist["train"] = env.train_hist
        ppo_state, train_env, buffers, windows = env.ppo, env.train_env, env.buffers, env.windows
        k_eval, k_probe = env.k_eval, env.k_probe
        learners, learn_m = self.learn_phase(rs.learners, buffers, env.k_learn, windows)
        metrics = {**env.metrics, "learners": learn_m}
        curr_env, rand_env = rs.curr_env, rs.rand_env

        def evaluate(ops: tuple) -> tuple:
            curr_env, rand_env, curr_hist, ppo_state, learners, buffers, windows = ops
            curr_env, rand_env, held_out, curr_hist = self.eval_stage(ppo_state, curr_env, rand_env,
                                                                      self._rl_learners(learners), curr_hist, k_eval)
            return curr_env, rand_env, curr_hist, self.probe_phase(learners, buffers, held_out, k_probe, windows)

        ops = (curr_env, rand_env, hist.get("curr"), ppo_state, learners, buffers, windows)
        if isinstance(probe, (bool, np.bool_)):
            if probe:
                curr_env, rand_env, curr_hist, metrics["probes"] = evaluate(ops)
                if curr_hist is not None:
                    hist["curr"] = curr_hist
        else:
            # `skip` returns placeholders shaped like `evaluate`'s probes. `lax.switch` traces its
            # branches in order, so `evaluate`'s own trace gives those shapes: the eval and probe
            # phases are traced once, not twice (an `eval_shape` first; ~1/7 of the epoch's
            # tracing on the CPU). Were the order ever different, `skip` falls back to `eval_shape`.
            shapes: list[Any] = []

            def evaluate_once(ops: tuple) -> tuple:
                out = evaluate(ops)
                shapes.append(jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), out[3]))
                return out

            def skip(ops: tuple) -> tuple:
                probes_shape = shapes[0] if shapes else jax.eval_shape(evaluate, ops)[3]
                return ops[0], ops[1], ops[2], jax.tree.map(_blank, probes_shape)

            curr_env, rand_env, curr_hist, metrics["probes"] = jax.lax.switch(
                jnp.where(probe, 0, 1), [evaluate_once, skip], ops)
            if curr_hist is not None:
                hist["curr"] = curr_hist
        new = RunState(ppo=ppo_state, learners=learners, buffers=buffers, windows=windows,
                       train_env=train_env, curr_env=curr_env, rand_env=rand_env, policy_history=hist,
                       ref_spread=rs.ref_spread, epoch=env.epoch)
        if self.sharded:  # the next epoch gets the layout this one got
            new = jax.lax.with_sharding_constraint(new, self._state_sh)
        return new, metrics


def _blank(s: jax.ShapeDtypeStruct) -> jax.Array:
    """NaN (floats) or 0 of a shape: the probes of an epoch that did not probe."""
    return jnp.full(s.shape, jnp.nan if jnp.issubdtype(s.dtype, jnp.inexact) else 0, s.dtype)
