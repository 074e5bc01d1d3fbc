"""Alignment probes of an epoch: fit latents -> true state on replay data, score on held-out
windows (`bulbjax.eval.probe` does the fitting; this module feeds it every learner's latents,
every seed's, with the run's seed loop), plus the object-level probe of learners with boxes
(SPAIR) in domains with objects (`bulbjax.eval.objects`).

A probe has two halves: the learner's (`probe_latents`: its convolutions, run with the seed
loop) and the probe's (`fit_and_score`: small MLPs, hundreds of sequential Adam steps, best
vmapped over seeds whatever the loop): `probe_over_seeds` runs both, `probe_learner` one seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from bulbjax.data import replay, sequence
from bulbjax.data.sequence import Windows
from bulbjax.envs.objects import rearrange
from bulbjax.epoch import probe_variants as pv
from bulbjax.epoch.probe_variants import ProbeSet
from bulbjax.epoch.seeds import Team, over_seeds, stack_members, switch_buffer, unstack_members
from bulbjax.eval import angles, linear, objects, probe
from bulbjax.eval.spec import StateEntry
from bulbjax.learners import is_sequential


def probe_latents(learner: Any, params: Any, train: Any, held: dict[str, Windows], key: jax.Array,
                  config: probe.ProbeConfig, train_frames: int, corrupt: Any = None) -> dict[str, Any]:
    """The learner's half of a probe (one seed; the convolutions): the training pairs' latents
    `tz [T, Z']`, their states `ts [T, D]` and `groups` (each pair's world, or None), and each
    held-out stream's per-step latents `held [B, L, Z']`. A sequential learner's own
    `probe_context` (steps of context) replaces `config.sequence_context` when it has one. `train` is `(frames, states)` or
    `(frames, states, groups)` for a frame learner and `Windows` for a sequential one, whose
    per-step latents (with `config.sequence_context` steps of context, see
    `probe.context_latents`) are paired with the states of the same step and `train_frames`
    valid steps drawn from them (split by row for validation: windows keep no world ids).
    `corrupt` (tests only) maps per-step latents `[B, L, Z]` to what the probe sees, e.g.
    latents shuffled across time steps."""
    corrupt = corrupt or (lambda z, k: z)
    if is_sequential(learner):
        l = learner.sequence_length
        # a learner whose per-step latent holds one frame (stdim) may ask for fewer steps
        context = getattr(learner, "probe_context", None) or config.sequence_context
        ctx = lambda z: probe.context_latents(z, context)  # noqa: E731
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


@dataclass(frozen=True, eq=False)
class ProbeTargets:
    """What the probes regress: the env's state (`state_spec`, D entries) followed by targets
    derived from it (`derive`: states `[..., D] -> [..., D']`, entries `derived`), e.g. the
    Rearrange objects' major-axis angles (`rearrange_scene.angle_targets`). Derived here, in
    the probing layer, and not in the env: the env's state keeps bulb's layout (its parity with
    bulb's state is tested), replay and windows keep the env's states, and every probe, the
    reference spread and the reports use `spec` (= state_spec + derived). `angle_pairs`: per
    object with an angle target, its name and the indices (in `spec`) of its (cos 2θ, sin 2θ)
    pair, scored as an angle error (`angles.mean_angle_error`)."""

    state_spec: tuple[StateEntry, ...]
    derived: tuple[StateEntry, ...] = ()
    derive: Callable[[jax.Array], jax.Array] | None = None

    @property
    def spec(self) -> tuple[StateEntry, ...]:
        return tuple(self.state_spec) + tuple(self.derived)

    def __call__(self, states: jax.Array) -> jax.Array:
        """`[..., D] -> [..., D + D']`; the states themselves without derived targets."""
        if self.derive is None:
            return states
        return jnp.concatenate([states, self.derive(states).astype(states.dtype)], axis=-1)

    @property
    def angle_pairs(self) -> tuple[tuple[str, int, int], ...]:
        names = [e.name for e in self.spec]
        return tuple((n[: -len("_axis_cos2")], i, names.index(n[: -len("cos2")] + "sin2"))
                     for i, n in enumerate(names) if n.endswith("_axis_cos2"))


def probe_targets(spec: Sequence[StateEntry]) -> ProbeTargets:
    """The probe targets of a state spec: a Rearrange state (objects with rotation matrices and
    shape properties) gets its objects' major-axis angles (`rearrange.angle_targets`); other
    states are probed as they are."""
    spec = tuple(spec)
    derived = rearrange.angle_target_spec(spec)
    if not derived:
        return ProbeTargets(spec)
    return ProbeTargets(spec, derived, rearrange.angle_targets(spec))


def fit_and_score(latents: dict[str, Any], held: dict[str, Windows], key: jax.Array,
                  config: probe.ProbeConfig,
                  score_objects: Callable[[jax.Array, Windows], dict] | None = None,
                  targets: ProbeTargets | None = None,
                  ) -> dict[str, dict[str, jax.Array]]:
    """The probe's half (one seed; small MLPs, best vmapped over seeds): fit latent -> true state
    on `probe_latents`' training pairs and score it on every held-out stream's valid steps.
    `score_objects` (frame learners) maps a stream's per-step latents `[B, L, Z]` and its windows
    to the object-level probe (`Probing.object_scorer`), kept as `"objects"`. `targets`: what is
    regressed (`ProbeTargets`; default the states as they are); with angle targets, each
    stream also gets `"angle": {"mae", "baseline"}`, `[A]` mean angle errors (rad) of the probe
    and of the constant predictor per object with an angle (`ProbeTargets.angle_pairs`).
    Beside the MLP, the linear (ridge) probe (`bulbjax.eval.linear`) on the same training pairs
    and the MLP's own validation split (`probe.validation_rows`, recomputed from the same key:
    no key drawn beyond the MLP's), scored on the same steps: `"linear_mae"` `[D]` and the
    regulariser it chose per entry, `"linear_log10_lambda"` `[D]`. `"inputs_clamped"` (scalar):
    the share of the stream's valid steps whose latent the MLP probe clamped to its fit range
    (`probe.standardise`).
    Returns `{stream: {"mae", "baseline", "spread", "inputs_clamped", "linear_mae", "linear_log10_lambda"
    (, "objects", "angle")}}`, each `[D]` in the targets' units."""
    return fit_present(latents, held, key, config, score_objects, targets)[0]


def fit_present(latents: dict[str, Any], held: dict[str, Windows], key: jax.Array,
                config: probe.ProbeConfig,
                score_objects: Callable[[jax.Array, Windows], dict] | None = None,
                targets: ProbeTargets | None = None) -> tuple[dict, probe.ProbeParams, jax.Array]:
    """`fit_and_score`'s scores, with the fitted MLP probe and its training targets (what the
    probe-protocol variants score beside it, `probe_variants.variant_scores`)."""
    targets = targets or ProbeTargets(())
    tz, ts = latents["tz"], targets(latents["ts"])
    p = probe.fit(key, tz, ts, config, groups=latents["groups"])
    lin = linear.fit(tz, ts, probe.validation_rows(key, tz.shape[0], config, latents["groups"]))
    pairs = np.array([(c, s) for _, c, s in targets.angle_pairs], int).reshape((-1, 2))
    res = {}
    for stream, w in held.items():
        zw = latents["held"][stream]
        z = zw.reshape((-1, tz.shape[-1]))
        s, v = targets(w.states).reshape((-1, ts.shape[-1])), w.valid.reshape(-1)
        pred = probe.predict(p, z)
        vf = jnp.asarray(v, jnp.float32)
        clamped = probe.clamped_rows(p, z).astype(jnp.float32)
        res[stream] = {"mae": probe.mae(pred, s, v),
                       "inputs_clamped": jnp.sum(clamped * vf) / jnp.maximum(jnp.sum(vf), 1.0),
                       "baseline": probe.constant_baseline(ts, s, v),
                       "spread": probe.spread(s, v),
                       "linear_mae": probe.mae(linear.predict(lin, z), s, v),
                       "linear_log10_lambda": lin.log10_lambda}
        if len(pairs):
            const = jnp.broadcast_to(jnp.median(ts, axis=0), s.shape)
            res[stream]["angle"] = {"mae": angles.mean_angle_error(pred[:, pairs], s[:, pairs], v),
                                    "baseline": angles.mean_angle_error(const[:, pairs], s[:, pairs], v)}
        if score_objects is not None:
            res[stream]["objects"] = score_objects(zw, w)
    return res, p, ts


def probe_learner(learner: Any, params: Any, train: Any, held: dict[str, Windows], key: jax.Array,
                  config: probe.ProbeConfig, train_frames: int,
                  corrupt: Any = None,
                  score_objects: Callable[[jax.Array, Windows], dict] | None = None,
                  targets: ProbeTargets | None = None,
                  ) -> dict[str, dict[str, jax.Array]]:
    """Fit a probe latent -> true state on `train` and score it on every held-out stream (one
    seed): `probe_latents` then `fit_and_score` (see them)."""
    k_c, k_f = jax.random.split(key)
    lat = probe_latents(learner, params, train, held, k_c, config, train_frames, corrupt)
    return fit_and_score(lat, held, k_f, config, score_objects, targets)


def probe_over_seeds(loop: str, latents_seed: Callable[..., dict], fit_seed: Callable[..., dict],
                     keys: jax.Array, *args: Any) -> dict:
    """A probe of every seed: `latents_seed(k_c, *args)` (the learner's convolutions) with the
    run's seed loop, then `fit_seed(latents, k_f, *args)` (the probe MLP, hundreds of small
    sequential Adam steps) vmapped over seeds whatever the loop: one seed at a time, those steps
    would run S times in a row on a GPU. Same keys as `probe_learner`, so the same numbers."""
    ks = jax.vmap(jax.random.split)(keys)
    lat = over_seeds(loop, latents_seed, ks[:, 0], *args)
    return jax.vmap(fit_seed)(lat, ks[:, 1], *args)


def object_pixels(env) -> tuple[list[str], Callable[[jax.Array], jax.Array]] | None:
    """For domains whose true state holds object positions (the Rearrange domains: entries
    `obj<i>_x/y/z` of group `object_position`, each in [-1, 1] of the tray's box): the object
    names and a jittable map states [..., D] -> image positions [..., M, 2] (px, (x, y)) through
    the domain's world-fixed camera (`objects.world_camera`, `objects.project_points`). None for
    other domains (no objects in the state)."""
    spec = list(env.state_spec)
    names = [e.name for e in spec]
    objs = objects.object_names(spec)
    if not objs:
        return None
    if not isinstance(env, rearrange.Rearrange):
        return None  # other scalings of object positions are not known here
    idx = np.array([[names.index(f"{o}_{a}") for a in "xyz"] for o in objs])  # [M, 3]
    lo, hi = np.asarray(rearrange.OBJ_XYZ_MIN, np.float32), np.asarray(rearrange.OBJ_XYZ_MAX, np.float32)
    pos, mat, fovy = objects.world_camera(env.mj_model)
    res = env.resolution

    def pixels(states: jax.Array) -> jax.Array:
        world = (states[..., idx] + 1.0) / 2.0 * (hi - lo) + lo  # [..., M, 3] metres
        return objects.project_points(world, pos, mat, fovy, res)

    return objs, pixels


@dataclass(frozen=True, eq=False)
class Probing:
    """The probes of a run's learners (`team`) under `config` (the run's `ProbeConfig`), fitted
    on `train_frames` replay frames (or valid window steps) per seed. `objects`: the domain's
    `object_pixels` (None without objects), `object_radius` (px) within which a box finds one;
    `targets`: what the probes regress (`probe_targets`: the state and targets derived from it)."""

    team: Team
    config: probe.ProbeConfig
    train_frames: int
    resolution: int
    objects: tuple[list[str], Callable] | None = None
    object_radius: float = 0.0
    targets: ProbeTargets | None = None  # what is regressed (default: the states as they are)
    # probe-protocol variants computed beside the present probe (`ExperimentConfig.probe_variants`)
    variants: tuple[str, ...] = ()

    def object_scorer(self, learner: Any) -> Callable[[jax.Array, Windows], dict] | None:
        """The object-level probe of one seed's held-out stream for a learner with boxes (SPAIR,
        `boxes_of_latents`) in a domain with objects; None otherwise. It maps the stream's
        per-step latents `[B, L, Z]` and windows to `objects.reduce_scores` of its valid steps
        (per object: distance from the true object's image position to the nearest present box
        centre, share within `object_radius` px) plus the `radius`."""
        if self.objects is None or is_sequential(learner) or not hasattr(learner, "boxes_of_latents"):
            return None
        _, pixels = self.objects
        res, radius = self.resolution, self.object_radius

        def score(z: jax.Array, w: Windows) -> dict:
            centres, pres = learner.boxes_of_latents(z.reshape((-1, z.shape[-1])), res)
            pos = pixels(w.states.reshape((-1, w.states.shape[-1])))
            out = objects.reduce_scores(objects.object_scores(centres, pres, pos, radius), w.valid)
            return {**out, "radius": jnp.float32(radius)}

        return score

    def probe_phase(self, learners: dict, buffers: dict, held_out: dict, key: jax.Array,
                    windows: dict | None = None, common: ProbeSet | None = None) -> dict:
        """Alignment probes: fit latents -> true state on replay data, evaluate on the held-out
        windows' valid steps. Frame learners: one latent per frame. Sequential learners: the
        per-step latents of replay windows (probe_train_frames valid steps drawn from them) and
        of the held-out windows; the latent at step t is matched with the state at step t.
        Learners with boxes (SPAIR) in domains with objects also get the object-level probe
        on the same held-out steps, per stream under `"objects"` (`object_scorer`). One
        `probe_unit` per unit (`Team.units`). With probe-protocol variants (`variants`), each
        learner's output also has `"variants"` (`probe_variants.variant_scores`); `common`: the
        common probe set `[S, ...]` (`probe_variants.common_set`) the "common" variant needs."""
        out = {}
        for unit in self.team.units():
            out.update(self.probe_unit(unit, learners, buffers, held_out, key, windows, common))
        return {n: out[n] for n in self.team.learners}

    def probe_unit(self, unit: Sequence[str], learners: dict, buffers: dict, held_out: dict,
                   key: jax.Array, windows: dict | None = None,
                   common: ProbeSet | None = None) -> dict:
        """`probe_phase` for one unit (`Team.units`), with the keys its members get in the whole
        phase; its ops carry the scope `bj.probe.<members>`."""
        if "common" in self.variants and common is None:
            raise ValueError("the 'common' probe variant needs the common probe set "
                             "(probe_variants.common_set)")
        with jax.named_scope(f"bj.probe.{'+'.join(unit)}"):
            return self._probe_unit(unit, learners, buffers, held_out, key, windows, common)

    def _variant_keys(self, key: jax.Array) -> jax.Array:
        """`[S, 2]`: each seed's key of the common set's draws and fit, the same for every learner
        (folded out of the phase's key: nothing the present probes draw is consumed)."""
        return self.team.seed_keys(jax.random.fold_in(key, pv.COMMON_FOLD))

    def _probe_unit(self, unit: Sequence[str], learners: dict, buffers: dict, held_out: dict,
                    key: jax.Array, windows: dict | None, common: ProbeSet | None) -> dict:
        t, cfg, frames, variants = self.team, self.config, self.train_frames, self.variants
        if len(unit) > 1:
            return self._probe_group(unit, learners, buffers, held_out, key, common)
        (name,) = unit
        learner, seq, i = t.learners[name], t.sequential[name], list(t.learners).index(name)

        def latents_seed(k_c, k_s, lstate, b, held, com, k_com):
            if seq:
                train = sequence.sample(b, k_s, -(-frames // learner.sequence_length))
            else:
                f, states, extras = replay.sample_with_extras(b, k_s, frames)
                train = (f, states, extras["world"])
            lat = probe_latents(learner, lstate.params, train, held, k_c, cfg, frames)
            if variants:
                lat["variants"] = pv.variant_latents(learner, lstate.params, b, com, k_com, cfg,
                                                     frames, variants)
            return lat

        def fit_seed(lat, k_f, k_s, lstate, b, held, com, k_com):
            present = {k: v for k, v in lat.items() if k != "variants"}
            score = self.object_scorer(learner)
            res, p, ts = fit_present(present, held, k_f, cfg, score, self.targets)
            if variants:
                res["variants"] = pv.variant_scores(learner, lat, p, ts, held, k_com,
                                                    jax.random.fold_in(k_f, pv.WINDOW_FOLD), cfg,
                                                    self.targets or ProbeTargets(()), variants)
            return res

        keys = t.seed_keys(jax.random.fold_in(key, i))
        k_s, k_p = jax.vmap(jax.random.split)(keys).swapaxes(0, 1)
        buf = t.buffer_of(name, buffers, windows)
        k_com = self._variant_keys(key)
        return {name: probe_over_seeds(t.loop_of(name), latents_seed, fit_seed, k_p, k_s,
                                       learners[name], buf, held_out, common, k_com)}

    def _probe_group(self, group: Sequence[str], learners: dict, buffers: dict, held_out: dict,
                     key: jax.Array, common: ProbeSet | None) -> dict:
        """`probe_phase` for a group of VAEs (`update_groups`): the encodings with the run's seed
        loop over seeds and members, the probe MLPs of all seeds and members vmapped side by
        side. Same keys as each member's own probe (`probe_over_seeds`), so the same numbers."""
        t, cfg, frames, variants = self.team, self.config, self.train_frames, self.variants
        template, bufs, which, keys = t.group_inputs(group, buffers, key)
        split = jax.vmap(jax.vmap(jax.random.split))
        k_s, k_p = jnp.moveaxis(split(keys), 2, 0)  # each [S, G, 2]
        k_c, k_f = jnp.moveaxis(split(k_p), 2, 0)
        score = self.object_scorer(template)
        targets = self.targets or ProbeTargets(())

        def draw(b, k):
            f, states, extras = replay.sample_with_extras(b, k, frames)
            return f, states, extras["world"]

        def latents_seed(kc, ks, states, bs, held, com, k_com):
            def member(kcm, ksm, state, w):
                train = switch_buffer(w, bs, draw, ksm)
                lat = probe_latents(template, state.params, train, held, kcm, cfg, frames)
                if variants:  # a frame learner's: the common pairs only
                    lat["variants"] = pv.variant_latents(template, state.params, None, com, k_com,
                                                         cfg, frames, variants)
                return lat
            return t.over_seeds(member, kc, ks, states, which)

        def fit_seed(lat, kf, held, k_com):
            def member(l, k):
                present = {n: v for n, v in l.items() if n != "variants"}
                res, p, ts = fit_present(present, held, k, cfg, score, self.targets)
                if variants:
                    k_w = jax.random.fold_in(k, pv.WINDOW_FOLD)
                    res["variants"] = pv.variant_scores(template, l, p, ts, held, k_com, k_w, cfg,
                                                        targets, variants)
                return res
            return jax.vmap(member)(lat, kf)

        states = stack_members([learners[n] for n in group])
        k_com = self._variant_keys(key)
        lat = t.over_seeds(latents_seed, k_c, k_s, states, bufs, held_out, common, k_com)
        return unstack_members(jax.vmap(fit_seed)(lat, k_f, held_out, k_com), group)
