"""Linear probe: closed-form ridge regression latents -> true state, beside the MLP probe.

The standard linear-evaluation protocol of representation learning (AtariARI, Anand et al.
2019, scores its representations with linear probes), and a check on the MLP probe's choices: an
MLP that overfits, or whose snapshot selection misfires, shows as an MLP error above the linear
one on the same pairs.

Protocol. The probe sees exactly the MLP probe's pairs and split (`probe.validation_rows`: the
same held-out validation rows, whole worlds where the pairs carry world ids). Inputs and targets
are standardised with the moments of the *training* rows; for every regulariser `lam` of
`LAMBDAS` the ridge solution of the standardised problem

    W_lam = (X'X / n + lam I)^-1 X'Y / n      (X, Y: the n training rows, centred and scaled)

is one Cholesky solve on the `Z x Z` Gram matrix (Z = latent width), and per state entry the
`lam` with the lowest validation MAE is kept. `lam` is on the scale of the standardised Gram
matrix, whose eigenvalues average 1: 1e-4 barely regularises, 1e3 shrinks every coefficient to
~0, i.e. predicts the training mean, the constant a latent without information about the entry
should give. Without validation rows (`ProbeConfig.validation == 0`) every entry takes
`DEFAULT_LAMBDA`. Pure jnp, jittable and vmappable: it runs inside the jitted epoch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from flax import struct

from bulbjax.eval.probe import clamp_bounds

# Regulariser grid (standardised Gram scale, see the module docstring): 1e-4 .. 1e3.
LAMBDAS: tuple[float, ...] = tuple(10.0 ** k for k in range(-4, 4))
DEFAULT_LAMBDA = 1.0  # no validation rows to choose by
_EPS = 1e-6
_HI = jax.lax.Precision.HIGHEST  # full float32 products (GPUs default to TF32 for f32 matmuls)


@struct.dataclass
class RidgeParams:
    """A fitted linear probe: `w [Z, D]` on standardised inputs and targets, the training rows'
    moments, and per entry the log10 of the regulariser chosen (`log10_lambda [D]`)."""

    w: jax.Array
    x_mean: jax.Array  # [Z]
    x_std: jax.Array  # [Z], 1 for constant columns (they are only centred)
    y_mean: jax.Array  # [D]
    y_std: jax.Array  # [D], 1 for constant targets (predicted as their mean)
    log10_lambda: jax.Array  # [D]
    x_lo: jax.Array  # [Z], the least standardised input `predict` lets through per column
    x_hi: jax.Array  # [Z], and the greatest (the training rows' `probe.clamp_bounds`)


def _weighted_moments(x: jax.Array, w: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Mean and std of the rows with weight 1 (`w [B]` in {0, 1}); std 1 where ~constant."""
    n = jnp.maximum(jnp.sum(w), 1.0)
    mean = jnp.sum(x * w[:, None], axis=0) / n
    std = jnp.sqrt(jnp.sum(((x - mean) ** 2) * w[:, None], axis=0) / n)
    return mean, jnp.where(std > _EPS, std, 1.0)


def fit(latents: jax.Array, states: jax.Array, val: jax.Array,
        lambdas: tuple[float, ...] = LAMBDAS) -> RidgeParams:
    """Ridge regression `latents [B, Z] -> states [B, D]` on the rows with `val [B]` False,
    the regulariser chosen per entry on the rows with `val` True (module docstring)."""
    x = latents.astype(jnp.float32)
    y = states.astype(jnp.float32)
    train = (~val).astype(jnp.float32)
    x_mean, x_std = _weighted_moments(x, train)
    y_mean, y_std = _weighted_moments(y, train)
    xs = (x - x_mean) / x_std
    x_lo, x_hi = clamp_bounds(xs, train > 0)
    ys = (y - y_mean) / y_std
    xt = xs * train[:, None]  # validation rows out of the sums
    n = jnp.maximum(jnp.sum(train), 1.0)
    gram = jnp.matmul(xt.T, xt, precision=_HI) / n  # [Z, Z]
    cross = jnp.matmul(xt.T, ys, precision=_HI) / n  # [Z, D]
    lam = jnp.asarray(lambdas, jnp.float32)
    eye = jnp.eye(gram.shape[0], dtype=jnp.float32)

    def solve(l: jax.Array) -> jax.Array:
        return jsl.cho_solve(jsl.cho_factor(gram + l * eye, lower=True), cross)

    # one regulariser after another, not vmapped: a batched Cholesky solve runs jaxlib's LAPACK
    # `trsm` with a parallel batch map on XLA:CPU's thread pool, and two of those side by side
    # (several learners' probes in one program) wait on each other for ever on 2 cores
    # (`fig5-rearrange-ycb --small` hung in 3 of 3 tries; with this it runs). Same numbers.
    ws = jax.lax.map(solve, lam)  # [K, Z, D]
    wv = val.astype(jnp.float32)[:, None]
    n_val = jnp.sum(val)
    xc = jnp.clip(xs, x_lo, x_hi)  # validation rows as `predict` will see them
    pred = jnp.einsum("bz,kzd->kbd", xc, ws, precision=_HI) * y_std + y_mean  # [K, B, D]
    val_mae = jnp.sum(jnp.abs(pred - y) * wv, axis=1) / jnp.maximum(n_val, 1)  # [K, D]
    val_mae = jnp.where(jnp.isfinite(val_mae), val_mae, jnp.inf)
    default = jnp.argmin(jnp.abs(jnp.log10(lam) - jnp.log10(DEFAULT_LAMBDA)))
    choice = jnp.where(n_val > 0, jnp.argmin(val_mae, axis=0), default)  # [D]
    w = jnp.take_along_axis(ws, choice[None, None, :], axis=0)[0]  # [Z, D]
    return RidgeParams(w, x_mean, x_std, y_mean, y_std, jnp.log10(lam)[choice], x_lo, x_hi)


def predict(params: RidgeParams, latents: jax.Array) -> jax.Array:
    """Predicted states `[B, D]` in the states' own units, from latents clamped as the MLP probe
    clamps its inputs (`bulbjax.eval.probe.standardise` says why)."""
    xs = jnp.clip((latents.astype(jnp.float32) - params.x_mean) / params.x_std, params.x_lo, params.x_hi)
    return jnp.matmul(xs, params.w, precision=_HI) * params.y_std + params.y_mean
