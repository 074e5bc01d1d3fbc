"""SPAIR's parts (`learner.py` assembles them into the learner): the original's constants and
network sizes; the glimpse geometry (bilinear sampling of boxes out of frames and back in,
separable interpolation matrices) and depth compositing; the networks (backbone, per-cell MLP
heads, object encoder/decoder, background VAE); and the distributions (posterior stds, normal
KLs, the original's annealed prior on the number of objects, the pixel likelihood)."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from bulbjax.learners.base import LearnerConfig
from bulbjax.learners.networks import GaussianHead, lecun_normal_flat

# --- the original's constants (auto_yolo's yolo_air config) -------------------------------
YX_RANGE = (-0.5, 1.5)  # box centre offset within its cell, in cells
HW_RANGE = (0.0, 1.0)  # box side as a fraction of the frame (the original's anchor = image)
YX_PRIOR = (0.0, 1.0)  # Normal prior (mean, std) of the centre-offset logits
HW_PRIOR = (math.log(0.1 / 0.9), 0.5)  # ... of the size logits: boxes of ~10% of the frame
MAX_DEPTH = 4.0  # depth = MAX_DEPTH * sigmoid(depth logit); prior N(0, 1) on the logit
OBJ_LOGIT_SCALE, ALPHA_LOGIT_SCALE, ALPHA_LOGIT_BIAS = 2.0, 0.1, 5.0  # decoder output scaling
LOGIT_CLIP = 10.0
# --- network sizes (the original's where they apply) ---------------------------------------
BACKBONE_FILTERS = 128
CELL_FEATURES = 100
LATERAL = (100, 100)  # hidden units of the where/depth/pres heads
OBJ_ENCODER = (256, 128)
OBJ_DECODER = (128, 256)
BG_FILTERS, BG_HIDDEN, BG_GRID = 32, 64, 4
DEPTH_SHARPNESS = 3.0  # compositing weight exp(3 * depth): a depth gap of 1 is ~20:1
CELL_LATENT = 6  # y, x, h, w, pres, depth per cell before z_what
# The where head starts at its prior (means and stds; std = 2 sigmoid(logit)), so boxes start
# at ~10% of the frame with a near-zero KL instead of half the frame with ~20 nats per cell,
# which made the first updates switch every object off before the decoders learned anything.
WHERE_BIAS = (YX_PRIOR[0],) * 2 + (HW_PRIOR[0],) * 2 + (
    math.log(YX_PRIOR[1] / (2 - YX_PRIOR[1])),) * 2 + (math.log(HW_PRIOR[1] / (2 - HW_PRIOR[1])),) * 2

_DENSE = dict(param_dtype=jnp.float32, kernel_init=lecun_normal_flat)


# ============================================================================ geometry
def _tent(src: jax.Array, n: int) -> jax.Array:
    """Bilinear weights [..., m, n] of source positions `src` [..., m] (pixel units, pixel
    centres at 0..n-1) on n pixels; zero beyond one pixel outside the range."""
    return jnp.maximum(0.0, 1.0 - jnp.abs(src[..., None] - jnp.arange(n, dtype=src.dtype)))


def _glimpse_src(centre: jax.Array, size: jax.Array, glimpse: int, res: int) -> jax.Array:
    """Frame pixel coordinates [..., glimpse] of a glimpse's pixels along one axis, for boxes
    with `centre` and `size` [...] as fractions of the frame."""
    u = (jnp.arange(glimpse, dtype=jnp.float32) + 0.5) / glimpse - 0.5
    return (centre[..., None] + size[..., None] * u) * res - 0.5


def extract_glimpses(frames: jax.Array, centres: jax.Array, sizes: jax.Array, glimpse: int) -> jax.Array:
    """Glimpses [B, K, g, g, C] cut from frames [B, H, W, C] at K boxes per frame.

    `centres`, `sizes` [B, K, 2] are (y, x) and (h, w) as fractions of the frame. Bilinear,
    with the frame's edge pixels repeated outside it (as the original's resampler_edge)."""
    _, h, w, _ = frames.shape
    ys = jnp.clip(_glimpse_src(centres[..., 0], sizes[..., 0], glimpse, h), 0.0, h - 1.0)
    xs = jnp.clip(_glimpse_src(centres[..., 1], sizes[..., 1], glimpse, w), 0.0, w - 1.0)
    rows = jnp.einsum("bkih,bhwc->bkiwc", _tent(ys, h), frames)
    return jnp.einsum("bkiwc,bkjw->bkijc", rows, _tent(xs, w))


def render_glimpses(glimpses: jax.Array, centres: jax.Array, sizes: jax.Array, res: tuple[int, int]) -> jax.Array:
    """The inverse of `extract_glimpses`: glimpses [B, K, g, g, C] drawn into frames
    [B, K, H, W, C] at their boxes, zero outside them (bilinear, soft one-pixel edges)."""
    g = glimpses.shape[2]
    h, w = res

    def src(centre: jax.Array, size: jax.Array, n: int) -> jax.Array:
        p = (jnp.arange(n, dtype=jnp.float32) + 0.5) / n  # frame pixel centres, as fractions
        return ((p - centre[..., None]) / size[..., None] + 0.5) * g - 0.5

    wy = _tent(src(centres[..., 0], sizes[..., 0], h), g)  # [B, K, H, g]
    wx = _tent(src(centres[..., 1], sizes[..., 1], w), g)  # [B, K, W, g]
    cols = jnp.einsum("bkhi,bkijc->bkhjc", wy, glimpses)
    return jnp.einsum("bkhjc,bkwj->bkhwc", cols, wx)


def composite(colour: jax.Array, alpha: jax.Array, depth: jax.Array, background: jax.Array) -> jax.Array:
    """Objects over a background: [B, H, W, C] from premultiplied colours [B, K, H, W, C],
    alphas [B, K, H, W] (presence included), depths [B, K] (larger is nearer) and backgrounds
    [B, H, W, C]. Per pixel the objects are weighted by softmax(log alpha + 3 depth), so the
    nearest opaque one shows; their weighted alpha blends them over the background."""
    logits = jnp.log(alpha + 1e-12) + DEPTH_SHARPNESS * depth[:, :, None, None]
    weight = jax.nn.softmax(logits, axis=1)
    front = jnp.sum(weight[..., None] * colour, axis=1)
    cover = jnp.sum(weight * alpha, axis=1)
    return front + (1.0 - cover)[..., None] * background


# ============================================================================ networks
class MLP(nn.Module):
    """ReLU MLP [..., F] -> [..., out]; the per-cell heads and the object encoder/decoder.
    `out_bias` (length out) sets the output layer's initial bias (default zeros)."""

    hidden: tuple[int, ...]
    out: int
    out_bias: tuple[float, ...] | None = None

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for i, h in enumerate(self.hidden):
            x = nn.relu(nn.Dense(h, name=f"fc{i}", **_DENSE)(x))
        bias = self.out_bias
        init = nn.initializers.zeros if bias is None else (lambda *_: jnp.asarray(bias, jnp.float32))
        return nn.Dense(self.out, name="out", bias_init=init, **_DENSE)(x)


def _conv(features: int, kernel: int, stride: int, name: str) -> nn.Conv:
    return nn.Conv(features, (kernel, kernel), strides=(stride, stride), padding="SAME",
                   param_dtype=jnp.float32, kernel_init=lecun_normal_flat, name=name)


def _resize(h: jax.Array, side: int) -> jax.Array:
    """[B, r, r, C] -> [B, side, side, C] (bilinear, antialiased); identity if r == side."""
    if h.shape[1] == side:
        return h
    return jax.image.resize(h, (h.shape[0], side, side, h.shape[-1]), "linear", antialias=True)


class Backbone(nn.Module):
    """Frames [B, R, R, 3] -> cell features [B, G, G, CELL_FEATURES].

    Three 4x4 stride-2 convs (R/8 per side), resized to G x G when R/8 != G, then a 3x3 conv
    that hands each cell its neighbours' features (the parallel stand-in for the original's
    lateral context) and 1x1 convs, as the original's final layers."""

    grid: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        h = x
        for i in range(3):
            h = nn.relu(_conv(BACKBONE_FILTERS, 4, 2, f"conv{i}")(h))
        h = _resize(h, self.grid)
        h = nn.relu(_conv(BACKBONE_FILTERS, 3, 1, "context")(h))
        h = nn.relu(_conv(BACKBONE_FILTERS, 1, 1, "cell")(h))
        return _conv(CELL_FEATURES, 1, 1, "out")(h)


class BackgroundEncoder(nn.Module):
    """Frames [B, R, R, 3] -> (mean, logvar) [B, latent_dim] of the background VAE."""

    latent_dim: int

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        h = x
        for i in range(3):
            h = nn.relu(_conv(BG_FILTERS, 4, 2, f"conv{i}")(h))
        h = _resize(h, BG_GRID).reshape((x.shape[0], -1))
        h = nn.relu(nn.Dense(BG_HIDDEN, name="fc", **_DENSE)(h))
        return GaussianHead(self.latent_dim, name="head")(h)


class BackgroundDecoder(nn.Module):
    """Latents [B, latent_dim] -> background logits [B, R, R, 3]: a BG_GRID x BG_GRID grid of
    logits resized bilinearly to R, so the background can only be smooth."""

    resolution: int

    @nn.compact
    def __call__(self, z: jax.Array) -> jax.Array:
        h = nn.relu(nn.Dense(BG_HIDDEN, name="fc", **_DENSE)(z))
        h = nn.Dense(BG_GRID * BG_GRID * 3, name="grid", **_DENSE)(h)
        h = h.reshape((z.shape[0], BG_GRID, BG_GRID, 3))
        r = self.resolution
        return jax.image.resize(h, (z.shape[0], r, r, 3), "linear")


# ============================================================================ distributions
def posterior_std(logit: jax.Array) -> jax.Array:
    """The original's posterior std: 2 * sigmoid(clipped logit)."""
    return 2.0 * jax.nn.sigmoid(jnp.clip(logit, -LOGIT_CLIP, LOGIT_CLIP))


def normal_kl(mean: jax.Array, std: jax.Array, prior_mean: Any, prior_std: Any) -> jax.Array:
    """KL(N(mean, std^2) || N(prior_mean, prior_std^2)), elementwise."""
    var_ratio = jnp.square(std / prior_std)
    return 0.5 * (var_ratio + jnp.square((mean - prior_mean) / prior_std) - 1.0 - jnp.log(var_ratio))


def count_prior_log_odds(config: LearnerConfig, step: jax.Array) -> jax.Array:
    """The original's annealed prior log-odds of a cell holding an object at update `step`:
    log((start - end) * 0.1^(step / decay_steps) + end)."""
    c = config
    t = jnp.asarray(step, jnp.float32) / c.spair_count_decay_steps
    start, end = c.spair_count_odds_start, c.spair_count_odds_end
    return jnp.log((start - end) * jnp.power(0.1, t) + end)


def count_prior_kl(log_odds: jax.Array, present: jax.Array, prior_log_odds: jax.Array) -> jax.Array:
    """The original's z_pres KL [B, K] under its prior on the number of objects.

    `log_odds` [B, K]: the cells' posterior log-odds; `present` [B, K] bool: their hard samples
    (which condition the prior of the later cells); `prior_log_odds`: log(q / (1 - q)) of the
    count prior p(C = n) ~ (1 - q) q^n, n = 0..K. Cells are taken in row-major order."""
    b, k = log_odds.shape
    support = jnp.arange(k + 1, dtype=jnp.float32)
    log_count = jax.nn.log_sigmoid(-prior_log_odds) + support * jax.nn.log_sigmoid(prior_log_odds)
    log_count = jnp.broadcast_to(log_count - jax.nn.logsumexp(log_count), (b, k + 1))

    def step(carry, inp):
        log_count, so_far = carry
        i, on = inp
        p_given = jnp.clip((support - so_far[:, None]) / (k - i), 0.0, 1.0)  # P(z_i=1 | C, z_<i)
        p_on = jnp.sum(jnp.exp(log_count) * p_given, axis=-1)
        mult = jnp.where(on[:, None], p_given, 1.0 - p_given)
        log_count = log_count + jnp.log(jnp.maximum(mult, 1e-30))
        log_count = log_count - jax.nn.logsumexp(log_count, axis=-1, keepdims=True)
        return (log_count, so_far + on), p_on

    steps = (jnp.arange(k, dtype=jnp.float32), present.T)
    _, p_on = jax.lax.scan(step, (log_count, jnp.zeros((b,), jnp.float32)), steps)
    p_on = jax.lax.stop_gradient(jnp.clip(p_on.T, 1e-6, 1.0 - 1e-6))
    prob = jax.nn.sigmoid(log_odds)
    return (prob * (jax.nn.log_sigmoid(log_odds) - jnp.log(p_on))
            + (1.0 - prob) * (jax.nn.log_sigmoid(-log_odds) - jnp.log1p(-p_on)))


def pixel_nll(out: jax.Array, x: jax.Array, std: float) -> jax.Array:
    """Negative log-likelihood of frames x under reconstructions `out` (both [B, R, R, 3] in
    [0, 1]), summed over pixels and averaged over the batch: Bernoulli for std = 0, else
    Gaussian with that std."""
    if std == 0.0:
        out = jnp.clip(out, 1e-6, 1.0 - 1e-6)
        nll = -(x * jnp.log(out) + (1.0 - x) * jnp.log1p(-out))
    else:
        nll = 0.5 * jnp.square((x - out) / std) + math.log(std) + 0.5 * math.log(2 * math.pi)
    return nll.sum(axis=(1, 2, 3)).mean()


class Cells(NamedTuple):
    """Per-cell inference results, each [B, K, ...] (K = G*G, row-major)."""

    centres: jax.Array  # [B, K, 2] (y, x), fractions of the frame
    sizes: jax.Array  # [B, K, 2] (h, w), fractions of the frame
    what: jax.Array  # [B, K, A] sample (or mean)
    depth: jax.Array  # [B, K] in [0, MAX_DEPTH]
    pres: jax.Array  # [B, K] relaxed sample (or probability)
    pres_log_odds: jax.Array  # [B, K]
    kl_where: jax.Array  # [B, K] summed over the 4 box logits
    kl_what: jax.Array  # [B, K]
    kl_depth: jax.Array  # [B, K]
