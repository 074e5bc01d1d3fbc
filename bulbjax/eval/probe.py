"""Alignment probes: regress true low-dimensional state from learned latents (paper Sec. 2/Fig. 2).

A small MLP is fit on (latent, state) pairs and judged by mean absolute error on held-out pairs,
in each state entry's own unit, next to the best constant predictor (training median). Per
entry, a validation split of the training pairs picks the MLP snapshot (or the training median)
that predicts it best, so that a latent without information about an entry scores about the
constant predictor on it instead of an overfit MLP's worse error (`fit`).

Errors on a fixed scale: the normalised error of an entry divides its MAE by a *reference
spread* of that entry which does not depend on the policy being scored: the mean absolute
deviation around the median of the entry under the random policy, measured once per run on
held-out data (``spread`` below). Every stream (pi_curr, pi_rand) and every epoch is divided by
the same number, so a normalised error of 1.0 is what predicting the random-policy median
achieves on random-policy frames, errors of different streams and epochs compare directly, and
a solved policy whose states hardly move no longer inflates them (dividing by the scored
stream's own spread did: pi_curr errors up to ~90 on solved pendulums).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from bulbjax.eval.spec import StateEntry

_EPS = 1e-6
# An entry whose reference spread is below this share of the median spread of the entries with
# its unit barely moves under the random policy (a resting sphere's height: 8e-5 against 0.25
# for the objects' x, y): its normalised error would be noise divided by ~0, so it is excluded.
_REL_FLOOR = 1e-2


def normalisable(ref_spread_D: Any, spec: Sequence[StateEntry]) -> np.ndarray:
    """`[D]` bool: the entries whose reference spread can normalise errors: above `_EPS` and
    above `_REL_FLOOR` times the median spread of the entries of its unit that are above `_EPS`."""
    r = np.asarray(ref_spread_D, np.float64)
    good = r > _EPS
    for unit in {e.unit for e in spec}:
        idx = np.array([i for i, e in enumerate(spec) if e.unit == unit and good[i]], int)
        if idx.size:
            good[idx] &= r[idx] > _REL_FLOOR * np.median(r[idx])
    return good


@dataclasses.dataclass(frozen=True)
class ProbeConfig:
    """Probe MLP and its training schedule (hashable: pass it as a static argument)."""

    hidden: tuple[int, ...] = (256, 256)
    lr: float = 1e-3
    steps: int = 500
    batch_size: int = 256
    # Sequential learners: the probe at step t reads the per-step latents of steps t-c+1..t of
    # the window (`context_latents`), a part of the window's latent code as the original bulb
    # probes read it (all steps of a window); 1 = z_t alone. Frame learners: one frame, always.
    sequence_context: int = 2
    # Model selection against overfitting (see `fit`): this share of the training pairs is held
    # out, and per state entry the prediction of the snapshot (of `snapshots` taken during
    # training) or the training median with the lowest validation MAE is used. 0: no selection,
    # the MLP after `steps` for every entry.
    validation: float = 0.2
    snapshots: int = 10

    def __post_init__(self) -> None:
        if self.sequence_context < 1:
            raise ValueError(f"sequence_context must be >= 1, got {self.sequence_context}")
        if not 0.0 <= self.validation < 1.0:
            raise ValueError(f"validation must be in [0, 1), got {self.validation}")
        if self.snapshots < 1 or self.steps < 1:
            raise ValueError(f"steps and snapshots must be >= 1, got {self.steps}, {self.snapshots}")


def context_latents(z: jax.Array, context: int) -> jax.Array:
    """Per-step latents `[B, L, Z]` -> `[B, L, context * Z]`: at step t the latents of steps
    t-context+1..t (oldest first); before a window's first step its first latent is repeated."""
    parts = []
    for lag in range(context - 1, -1, -1):
        shifted = jnp.concatenate([jnp.repeat(z[:, :1], lag, axis=1), z[:, : z.shape[1] - lag]], axis=1)
        parts.append(shifted)
    return jnp.concatenate(parts, axis=-1)


@struct.dataclass
class ProbeParams:
    """Trained probe: `K` snapshots of the MLP's weights (leading axis K), the training-set
    standardisation of inputs and targets, and per state entry which snapshot predicts it
    (`choice` in 0..K-1) or, `choice == K`, the training median `y_const`."""

    mlp: Any  # [K, ...] per leaf
    choice: jax.Array  # [D] int32
    y_const: jax.Array  # [D]
    x_mean: jax.Array  # [L]
    x_std: jax.Array  # [L], 0 for constant columns
    y_mean: jax.Array  # [D]
    y_std: jax.Array  # [D], 0 for constant columns
    x_lo: jax.Array  # [L], the least standardised input `standardise` lets through per column
    x_hi: jax.Array  # [L], and the greatest (`clamp_bounds`)
    hidden: tuple[int, ...] = struct.field(pytree_node=False, default=(256, 256))


class _MLP(nn.Module):
    hidden: tuple[int, ...]
    out: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.relu(nn.Dense(width)(x))
        return nn.Dense(self.out)(x)


def _moments(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Mean and std over the batch; constant columns get std 0."""
    std = jnp.std(x, axis=0)
    return jnp.mean(x, axis=0), jnp.where(std > _EPS, std, 0.0)


def _safe(std: jax.Array) -> jax.Array:
    """Divisor for standardising: constant columns are only centred, never divided by ~0."""
    return jnp.where(std > 0, std, 1.0)


def _n_validation(rows: int, share: float) -> int:
    """Rows held out for selection: round(rows * share), at least 1 when share > 0, and at
    least one row left to train on."""
    if share <= 0 or rows < 2:
        return 0
    return int(min(rows - 1, max(1, round(rows * share))))


def _validation_mask(key: jax.Array, rows: int, share: float, groups: jax.Array | None) -> jax.Array:
    """`[B]` bool, the rows held out for selection. Without `groups`: `_n_validation` rows drawn
    at random. With `groups` (`[B]` int, e.g. each frame's world): every group is held out whole
    with probability `share`, so that no group has rows on both sides (frames of one scene are
    near copies of each other: a row split would let the probe's memorisation pass validation).
    Never all rows: if every group came out held out, none is."""
    if share <= 0 or rows < 2:
        return jnp.zeros((rows,), bool)
    if groups is None:
        n_val = _n_validation(rows, share)
        return jnp.zeros((rows,), bool).at[jax.random.permutation(key, rows)[:n_val]].set(True)
    u = jax.vmap(lambda g: jax.random.uniform(jax.random.fold_in(key, g)))(groups.astype(jnp.uint32))
    mask = u < share
    return jnp.where(mask.all(), False, mask)


def _snapshot_predictions(model: nn.Module, mlps: Any, x: jax.Array, y_mean: jax.Array,
                          y_std: jax.Array) -> jax.Array:
    """Predictions `[K, B, D]` of every snapshot (leading axis of `mlps`) for standardised
    inputs `x`, in the states' units. y_std is 0 for targets constant in training, so those are
    predicted exactly as that constant."""
    return jax.vmap(lambda p: model.apply(p, x))(mlps) * y_std + y_mean


def validation_rows(key: jax.Array, rows: int, config: ProbeConfig = ProbeConfig(),
                    groups: jax.Array | None = None) -> jax.Array:
    """`[rows]` bool: the rows `fit(key, ...)` holds out for validation (recomputed from the
    same key, nothing drawn beyond it), so that the linear probe (`bulbjax.eval.linear`) is
    chosen on exactly the MLP's validation split and fitted on its training rows."""
    return _validation_mask(jax.random.split(key, 3)[0], rows, config.validation, groups)


@functools.partial(jax.jit, static_argnames=("config",))
def fit(
    key: jax.Array, latents: jax.Array, states: jax.Array, config: ProbeConfig = ProbeConfig(),
    groups: jax.Array | None = None,
) -> ProbeParams:
    """Fit an MLP ``latents [B, L] -> states [B, D]`` with Adam on standardised MSE, using
    ``config.steps`` minibatches (rounded up to a multiple of the snapshots) drawn with
    replacement. Jitted; vmap over ``key`` for seeds.

    Why the selection: with a wide latent and many targets (a Rearrange state has 100 entries,
    its latent 200 dimensions, 2,048 training pairs) the MLP memorises the training pairs for
    the entries the latent does not hold, and its held-out error ends *above* the constant
    predictor's (measured: 1.16x on pure-noise latents). So a random `validation` share of the
    pairs is held out, `snapshots` copies of the weights are kept at even intervals of training,
    and each state entry is predicted by the snapshot with the lowest validation MAE on it, or
    by the training median (the constant baseline) when that is lower still. A latent that holds
    nothing about an entry then scores about the constant predictor on it, not worse.
    `groups` (`[B]` int, optional): rows of one group (e.g. one world's frames, which in a scene
    of resting objects are near copies) go to the same side of the split (`_validation_mask`).
    Inputs and targets are standardised with the moments of all `B` rows."""
    latents = latents.astype(jnp.float32)
    states = states.astype(jnp.float32)
    k_split, init_key, train_key = jax.random.split(key, 3)
    rows = latents.shape[0]
    val = _validation_mask(k_split, rows, config.validation, groups)
    n_train = rows - jnp.sum(val, dtype=jnp.int32)
    train_rows = jnp.argsort(val, stable=True)  # training rows first
    x_mean, x_std = _moments(latents)
    y_mean, y_std = _moments(states)
    x = (latents - x_mean) / _safe(x_std)
    y = (states - y_mean) / _safe(y_std)

    model = _MLP(config.hidden, states.shape[-1])
    mlp = model.init(init_key, x[:1])
    opt = optax.adam(config.lr)

    def loss_fn(p: Any, xb: jax.Array, yb: jax.Array) -> jax.Array:
        return jnp.mean((model.apply(p, xb) - yb) ** 2)

    def step(carry: tuple[Any, Any], k: jax.Array) -> tuple[tuple[Any, Any], None]:
        p, opt_state = carry
        idx = train_rows[jax.random.randint(k, (config.batch_size,), 0, n_train)]
        grads = jax.grad(loss_fn)(p, x[idx], y[idx])
        updates, opt_state = opt.update(grads, opt_state, p)
        return (optax.apply_updates(p, updates), opt_state), None

    # K snapshots: the weights after each of K equal chunks of training (the last at `steps`).
    selecting = config.validation > 0 and rows >= 2
    k_snap = min(config.snapshots, config.steps) if selecting else 1
    chunk = -(-config.steps // k_snap)

    def train_chunk(carry: tuple[Any, Any], keys: jax.Array) -> tuple[tuple[Any, Any], Any]:
        carry = jax.lax.scan(step, carry, keys)[0]
        return carry, carry[0]

    keys = jax.random.split(train_key, k_snap * chunk).reshape((k_snap, chunk, -1))
    _, mlps = jax.lax.scan(train_chunk, (mlp, opt.init(mlp)), keys)
    y_const = jnp.median(states, axis=0)
    if selecting:
        w = val.astype(jnp.float32)[:, None]
        n_val = jnp.sum(w)
        pred = _snapshot_predictions(model, mlps, x, y_mean, y_std)  # [K, B, D]
        val_mae = jnp.concatenate([jnp.sum(jnp.abs(pred - states) * w, axis=1),
                                   jnp.sum(jnp.abs(y_const - states) * w, axis=0)[None]]) / jnp.maximum(n_val, 1.0)
        # No validation rows (one group only): the last snapshot for every entry.
        choice = jnp.where(n_val > 0, jnp.argmin(val_mae, axis=0), k_snap - 1).astype(jnp.int32)
    else:
        choice = jnp.zeros(states.shape[-1], jnp.int32)
    return ProbeParams(mlps, choice, y_const, x_mean, x_std, y_mean, y_std, *clamp_bounds(x), hidden=config.hidden)


def clamp_bounds(x: jax.Array, rows: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """`([L], [L])`: the range the probes clamp standardised inputs to, from the fit rows `x
    [B, L]` (those with `rows [B]` True, default all): each column's range widened by half its
    width on each side. Room for the extrapolation an ordinary held-out frame needs (a linear
    probe stays exact on a linear target); none for a column constant over the fit rows."""
    rows = jnp.ones(x.shape[:1], bool) if rows is None else rows
    lo = jnp.min(x, axis=0, where=rows[:, None], initial=jnp.inf)
    hi = jnp.max(x, axis=0, where=rows[:, None], initial=-jnp.inf)
    half = 0.5 * (hi - lo)
    return lo - half, hi + half


def standardise(params: ProbeParams, latents: jax.Array) -> jax.Array:
    """Latents `[B, L]` as the probe's MLP reads them: standardised with the fit rows' moments,
    each column clamped to the range the fit rows spanned, widened by half its width on each side
    (`clamp_bounds`). Why the clamp: a held-out frame whose
    latent lies far outside the fit rows (in a column nearly constant over the fit pairs, one
    divides by a std of ~0) reaches the MLP as an extreme input and comes out as an extreme
    prediction. Measured on `fig3-rearrange-geom` (3 seeds, 1,000 epochs): in 5 of SPAIR's 600
    probed seed-epochs every entry's error jumped, up to ~320x the reference spread for the MLP
    and ~450x for the linear probe on the same frames, and fell back the next probe. Clamped,
    such a frame is predicted from the nearest point of what the probe was fitted on. How often
    it happens is recorded (`clamped_rows`; `probing.fit_and_score`'s `"inputs_clamped"`).
    """
    return jnp.clip(_standardised(params, latents), params.x_lo, params.x_hi)


def _standardised(params: ProbeParams, latents: jax.Array) -> jax.Array:
    return (latents.astype(jnp.float32) - params.x_mean) / _safe(params.x_std)


def clamped_rows(params: ProbeParams, latents: jax.Array, tol: float = 1e-3) -> jax.Array:
    """`[B]` bool: the rows of `latents [B, L]` that `standardise` clamps, i.e. with a column
    outside its bounds (`clamp_bounds`) by more than `tol` (in std units)."""
    x = _standardised(params, latents)
    return jnp.any((x < params.x_lo - tol) | (x > params.x_hi + tol), axis=-1)


@jax.jit
def predict(params: ProbeParams, latents: jax.Array) -> jax.Array:
    """Predicted states ``[B, D]`` in the states' own units: per entry, its chosen snapshot's
    prediction or the training median (`fit`), from latents clamped to the fit rows' range
    (`standardise`)."""
    model = _MLP(params.hidden, params.y_mean.shape[-1])
    x = standardise(params, latents)
    pred = _snapshot_predictions(model, params.mlp, x, params.y_mean, params.y_std)  # [K, B, D]
    k = pred.shape[0]
    picked = jnp.take_along_axis(pred, jnp.minimum(params.choice, k - 1)[None, None, :], axis=0)[0]
    return jnp.where(params.choice >= k, params.y_const, picked)


def chose_constant(params: ProbeParams) -> jax.Array:
    """`[D]` bool: the entries the probe predicts by the training median (`fit`)."""
    return params.choice >= jax.tree.leaves(params.mlp)[0].shape[0]


def mae(pred: jax.Array, states: jax.Array, weights: jax.Array | None = None) -> jax.Array:
    """Per-entry mean absolute error ``[D]``. ``weights [B]`` (e.g. the valid mask of sequence
    windows, padded steps 0) makes it a weighted mean over the batch."""
    err = jnp.abs(pred - states)
    if weights is None:
        return jnp.mean(err, axis=0)
    w = weights.astype(jnp.float32)[:, None]
    return jnp.sum(err * w, axis=0) / jnp.maximum(jnp.sum(w), 1e-12)


def _median(states: jax.Array, weights: jax.Array | None) -> jax.Array:
    """Per-entry median over the batch, over the rows with nonzero weight when given."""
    if weights is None:
        return jnp.median(states, axis=0)
    return jnp.nanmedian(jnp.where(weights[:, None] > 0, states, jnp.nan), axis=0)


def constant_baseline(
    train_states: jax.Array, test_states: jax.Array, weights: jax.Array | None = None
) -> jax.Array:
    """Per-entry test MAE ``[D]`` of always predicting the training median (the MAE-optimal
    constant): the bar a probe has to clear for a latent to carry any information. ``weights``
    weigh the test rows (see `mae`)."""
    return mae(jnp.median(train_states, axis=0), test_states, weights)


def spread(states: jax.Array, weights: jax.Array | None = None) -> jax.Array:
    """Per-entry mean absolute deviation around the median ``[D]``. On random-policy held-out
    states it is the reference spread that normalises errors (see module docstring); on a scored
    stream it is reported beside the errors. ``weights`` select/weigh rows (see `mae`)."""
    return mae(_median(states, weights), states, weights)


def _aggregate(
    idx: list[int], spec: Sequence[StateEntry], m: np.ndarray, b: np.ndarray, mn: np.ndarray, bn: np.ndarray
) -> dict[str, Any]:
    """Mean over entries ``idx``; raw means only when all entries share a unit."""
    units = {spec[i].unit for i in idx}
    unit = units.pop() if len(units) == 1 else None
    ok = [i for i in idx if np.isfinite(mn[i])]
    return {
        "n": len(idx),
        "unit": unit,
        "mae": float(np.mean(m[idx])) if unit is not None and idx else None,
        "baseline": float(np.mean(b[idx])) if unit is not None and idx else None,
        "mae_norm": float(np.mean(mn[ok])) if ok else float("nan"),
        "baseline_norm": float(np.mean(bn[ok])) if ok else float("nan"),
    }


def summarise(
    mae_D: Any, baseline_D: Any, ref_spread_D: Any, spec: Sequence[StateEntry],
    spread_D: Any | None = None,
) -> dict[str, Any]:
    """Host-side report of one probe evaluation.

    ``mae_D`` and ``baseline_D`` are the probe's and the constant predictor's MAE per entry in
    the entry's unit; ``ref_spread_D`` is the run's reference spread (random policy, see the
    module docstring), the divisor of every normalised value; ``spread_D`` (optional) is the
    scored stream's own spread, reported only.

    Returns ``{"entries": {name: {...}}, "groups": {group: {...}}, "overall": {...},
    "excluded": [names], "normalised_by": "ref_spread"}``. Each entry has ``group, unit, mae,
    baseline, ref_spread, spread, mae_norm = mae / ref_spread, baseline_norm = baseline /
    ref_spread``; groups and overall have ``n, unit, mae, baseline, mae_norm, baseline_norm``,
    where normalised values are the equal-weight mean over entries and raw values are given only
    if every entry has the same unit (else None). Entries whose reference spread is ~0 (e.g. a
    contact the random policy never makes), or below 1% of the median spread of the entries
    with its unit (`normalisable`; e.g. a resting sphere's height), cannot be normalised: their
    normalised values are NaN and they are listed in ``excluded`` and left out of normalised
    averages.
    """
    m, b, r = (np.asarray(a, np.float64) for a in (mae_D, baseline_D, ref_spread_D))
    d = len(spec)
    if not (m.shape == b.shape == r.shape == (d,)):
        raise ValueError(f"expected [D={d}] arrays, got {m.shape}, {b.shape}, {r.shape}")
    own = np.full(d, np.nan) if spread_D is None else np.asarray(spread_D, np.float64)
    if own.shape != (d,):
        raise ValueError(f"expected a [D={d}] spread, got {own.shape}")
    names = [e.name for e in spec]
    if len(set(names)) != d:
        raise ValueError(f"duplicate state entry names in spec: {names}")
    good = normalisable(r, spec)
    safe = np.where(good, r, 1.0)
    mn = np.where(good, m / safe, np.nan)
    bn = np.where(good, b / safe, np.nan)

    entries = {
        e.name: {
            "group": e.group,
            "unit": e.unit,
            "mae": float(m[i]),
            "baseline": float(b[i]),
            "ref_spread": float(r[i]),
            "spread": float(own[i]),
            "mae_norm": float(mn[i]),
            "baseline_norm": float(bn[i]),
        }
        for i, e in enumerate(spec)
    }
    groups: dict[str, list[int]] = {}
    for i, e in enumerate(spec):
        groups.setdefault(e.group, []).append(i)
    return {
        "entries": entries,
        "groups": {g: _aggregate(idx, spec, m, b, mn, bn) for g, idx in groups.items()},
        "overall": _aggregate(list(range(d)), spec, m, b, mn, bn),
        "excluded": [names[i] for i in range(d) if not good[i]],
        "normalised_by": "ref_spread",
    }
