"""Variants of the probe protocol, computed in the same jitted epoch beside the present probe
(`ExperimentConfig.probe_variants`; docs/probes.md, "Variants of the protocol"). They answer
whether a verdict is the latent's or the probe's, and leave the present probe's numbers as they
are: every draw they make comes from keys folded out of the probe's keys (`fold_in`, which
consumes nothing the present probe draws), and they reuse its held-out latents.

- **common**: every learner's probe is fit on the same (frame, state) pairs of a seed, instead of
  pairs from its own replay buffer. The pairs: half from a fixed draw of random-policy steps kept
  from init (`initial_part`, in the run state), half from the epoch's new steps of the current
  policy (`fresh_part`), drawn with the same key for every learner (`common_picks`) and split for
  validation by world, the same split for every learner. Scored on the present probe's held-out
  steps.
- **window**: a sequential learner's probe reads the whole window's latent code, the per-step
  latents of all L steps concatenated (`[L * Z]`), and regresses the state at the window's last
  step, as bulb's code probes it (`unsup_eval_suite/main_learn.py`: `latent_code` of the window,
  target the last step's state). Fit on every window of the learner's window buffer, scored on
  the last step of every held-out window. Frame learners are scored on the same steps with
  their present probe, so every learner's window-variant error is taken on the same steps.
- **raw** is host-side only (`records.raw_summary`): the present probe's MAE averaged over a
  group's entries in the state's units.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from bulbjax.data.sequence import WindowBuffer, Windows
from bulbjax.eval import probe
from bulbjax.learners import is_sequential

# Tags folded into the probe phase's key (`jax.random.fold_in`): the common set's draws and fit
# (one key per seed, the same for every learner) and each learner's whole-window fit.
COMMON_FOLD = 0x59C0
WINDOW_FOLD = 0x59D0


@struct.dataclass
class ProbeSet:
    """Windows of the common probe set, per seed: `windows [..., B, L]` (L the held-out window
    length: the sequential learners' window, or 1 without them) and each window's world
    `[..., B]` (random-policy worlds of init 0..N-1, PPO's worlds N..2N-1: the validation split
    keeps a world's steps together). The first `rand_windows` windows are the random-policy part."""

    windows: Windows
    world: jax.Array  # int32 [..., B]
    rand_windows: int = struct.field(pytree_node=False, default=0)


def frames_as_windows(frames: jax.Array, states: jax.Array, action_dim: int) -> Windows:
    """Frames `[S, B, H, W, 3]` and states `[S, B, D]` as windows of one step (every step valid,
    no action)."""
    s, b = frames.shape[:2]
    return Windows(frames=frames[:, :, None], states=states[:, :, None],
                   actions=jnp.zeros((s, b, 1, action_dim), jnp.float32),
                   valid=jnp.ones((s, b, 1), bool))


def initial_part(windows: Windows, worlds: int, steps: int, key: jax.Array,
                 length: int) -> ProbeSet:
    """The random-policy part kept from init: `ceil(steps / length)` windows (at most all) drawn
    without replacement, the same for every seed's index, from init's random-policy windows
    `[S, C, >= length]` (or frames as one-step windows), cut to `length` steps; window `i` of
    init came from world `i % worlds`."""
    c = windows.valid.shape[1]
    count = min(c, -(-steps // length))
    pick = jax.random.choice(key, c, (count,), replace=False)
    w = jax.tree.map(lambda x: x[:, pick, :length], windows)
    world = jnp.broadcast_to((pick % worlds).astype(jnp.int32), w.valid.shape[:2])
    return ProbeSet(w, world, count)


def fresh_part(windows: Windows, index: jax.Array, worlds: int, length: int) -> ProbeSet:
    """The current policy's part of an epoch: its new windows `[S, B, >= length]` (or frames as
    one-step windows), cut to `length` steps; `index [S, B]`: each one's place in the epoch's
    draw, whose world is `index % worlds` (numbered after init's worlds: `+ worlds`)."""
    w = jax.tree.map(lambda x: x[:, :, :length], windows)
    return ProbeSet(w, (index % worlds + worlds).astype(jnp.int32), 0)


def common_set(rand: ProbeSet, fresh: ProbeSet) -> ProbeSet:
    """The two parts as one set `[S, R0 + R1, L]`, the random-policy part first."""
    cat = lambda a, b: jnp.concatenate([a, b], axis=1)  # noqa: E731
    return ProbeSet(jax.tree.map(cat, rand.windows, fresh.windows), cat(rand.world, fresh.world),
                    rand.rand_windows)


def common_picks(ps: ProbeSet, key: jax.Array, n: int) -> tuple[jax.Array, jax.Array, jax.Array]:
    """One seed's common pairs: `n // 2` valid steps drawn (with replacement) from the
    random-policy part, the rest from the current policy's. Returns the steps' flat indices
    `[n]` into the set's `[B * L]` steps, their states `[n, D]` and worlds `[n]`. The same key
    gives every learner of the seed the same pairs."""
    w = ps.windows
    b, l = w.valid.shape
    r0 = ps.rand_windows * l
    v = w.valid.reshape(-1).astype(jnp.float32)
    k0, k1 = jax.random.split(key)
    first, rest = n // 2, n - n // 2
    i0 = jax.random.choice(k0, r0, (first,), p=v[:r0] / jnp.maximum(v[:r0].sum(), 1.0))
    i1 = r0 + jax.random.choice(k1, b * l - r0, (rest,), p=v[r0:] / jnp.maximum(v[r0:].sum(), 1.0))
    idx = jnp.concatenate([i0, i1])
    return idx, w.states.reshape((b * l, -1))[idx], ps.world[idx // l]


def context_of(learner: Any, config: probe.ProbeConfig) -> int:
    """Steps of context the present probe gives a sequential learner's per-step latent."""
    return getattr(learner, "probe_context", None) or config.sequence_context


def common_latents(learner: Any, params: Any, ps: ProbeSet, idx: jax.Array,
                   config: probe.ProbeConfig) -> jax.Array:
    """One seed's latents of the common pairs `idx` (`common_picks`) as the present probe reads
    them: a frame learner's latent of each picked frame; a sequential learner's per-step
    latents with the present context (`probe.context_latents`) of the set's windows, at the
    picked steps."""
    w = ps.windows
    if is_sequential(learner):
        z = probe.context_latents(learner.encode(params, w), context_of(learner, config))
        return z.reshape((-1, z.shape[-1]))[idx]
    frames = w.frames.reshape((-1,) + w.frames.shape[2:])[idx]
    return learner.encode(params, frames)


def last_steps(x: jax.Array) -> jax.Array:
    """`[B, L, ...]` -> `[B, ...]` at each window's last step (a window cut at its episode's end
    repeats its last valid step there: state and frame)."""
    return x[:, -1]


def whole_windows(z: jax.Array) -> jax.Array:
    """Per-step latents `[B, L, Z]` -> each window's latent code `[B, L * Z]` (steps in order)."""
    return z.reshape(z.shape[:1] + (-1,))


def window_pairs(learner: Any, params: Any, buf: WindowBuffer) -> tuple[jax.Array, jax.Array]:
    """One seed's whole-window training pairs: every window of the learner's window buffer
    (full from init on), its latent code `[C, L * Z]` and the state at its last step `[C, D]`."""
    w = buf.windows
    z = learner.encode(params, w)  # [C, L, Z], the first L = sequence_length steps
    return whole_windows(z), last_steps(w.states[:, : z.shape[1]])


def held_step_latents(ctx: jax.Array, context: int) -> jax.Array:
    """The per-step latents `[B, L, Z]` inside the present probe's held-out context latents
    `[B, L, context * Z]` (`probe.context_latents` puts step t's own latent last)."""
    return ctx[..., ctx.shape[-1] - ctx.shape[-1] // context:]


Tests = dict[str, tuple[jax.Array, jax.Array, jax.Array]]  # stream -> (latents, states, weights)


def fit_scores(key: jax.Array, tz: jax.Array, ts: jax.Array, groups: jax.Array | None,
               tests: Tests, config: probe.ProbeConfig) -> dict[str, dict[str, jax.Array]]:
    """An MLP probe (`probe.fit`) on `tz -> ts`, scored on every test stream's `(latents [M,
    Z'], states [M, D], weights [M])`: `{stream: {"mae", "baseline", "spread"}}`, each `[D]`."""
    return scores(probe.fit(key, tz, ts, config, groups=groups), ts, tests)


def scores(p: probe.ProbeParams, ts: jax.Array, tests: Tests) -> dict[str, dict[str, jax.Array]]:
    """A fitted probe's scores on `tests` (`fit_scores`), its constant predictor the median of
    its training states `ts`."""
    return {st: {"mae": probe.mae(probe.predict(p, z), s, v),
                 "baseline": probe.constant_baseline(ts, s, v), "spread": probe.spread(s, v)}
            for st, (z, s, v) in tests.items()}


def variant_latents(learner: Any, params: Any, buf: Any, common: ProbeSet | None,
                    k_common: jax.Array, config: probe.ProbeConfig, train_frames: int,
                    variants: tuple[str, ...]) -> dict:
    """The learner's half of the variants (one seed; its convolutions): the common pairs'
    latents, states and worlds (`"common"`: `(tz, ts, groups)`) and a sequential learner's
    whole-window pairs (`"window"`: `(tz, ts)`); `buf` is the learner's own buffer."""
    out: dict[str, Any] = {}
    if "common" in variants and common is not None:
        idx, ts, groups = common_picks(common, jax.random.fold_in(k_common, 0), train_frames)
        out["common"] = (common_latents(learner, params, common, idx, config), ts, groups)
    if "window" in variants and is_sequential(learner):
        out["window"] = window_pairs(learner, params, buf)
    return out


def variant_scores(learner: Any, lat: dict, present: probe.ProbeParams, present_ts: jax.Array,
                   held: dict[str, Windows], k_common: jax.Array, k_fit: jax.Array,
                   config: probe.ProbeConfig, targets: Any, variants: tuple[str, ...]) -> dict:
    """The probe's half of the variants (one seed): `{"common": {stream: scores}, "window":
    {stream: scores}}`, `scores` as `fit_scores`. `lat`: `probe_latents`' output with
    `variant_latents`' under `"variants"`; `present`, `present_ts`: the present probe and its
    training targets (a frame learner's window-variant scores are its present probe's on the
    held-out windows' last steps); `targets`: `probing.ProbeTargets`."""
    out: dict[str, Any] = {}
    v = lat["variants"]
    held_z = lat["held"]
    if "common" in v:
        tz, ts, groups = v["common"]
        d = present_ts.shape[-1]
        tests = {st: (held_z[st].reshape((-1, tz.shape[-1])), targets(w.states).reshape((-1, d)),
                      w.valid.reshape(-1)) for st, w in held.items()}
        k = jax.random.fold_in(k_common, 1)
        out["common"] = fit_scores(k, tz, targets(ts), groups, tests, config)
    if "window" in v:
        tz, ts = v["window"]
        ctx = context_of(learner, config)
        tests = {st: (whole_windows(held_step_latents(held_z[st], ctx)),
                      last_steps(targets(w.states)), jnp.ones(w.valid.shape[:1], bool))
                 for st, w in held.items()}
        out["window"] = fit_scores(k_fit, tz, targets(ts), None, tests, config)
    elif "window" in variants:
        tests = {st: (last_steps(held_z[st]), last_steps(targets(w.states)),
                      jnp.ones(w.valid.shape[:1], bool)) for st, w in held.items()}
        out["window"] = scores(present, present_ts, tests)
    return out
