"""SPAIR frame learner (Crawford & Pineau, "Spatially Invariant Unsupervised Object Detection
with Convolutional Neural Networks", AAAI 2019) with a learned background, in Flax.

Model. A conv backbone maps the frame to a G x G grid of cell features. Each cell k has
- `z_where`: Gaussian logits of the box; the centre is an offset in [-0.5, 1.5] cells from the
  cell's corner (sigmoid of the logit, scaled), the size a fraction in [0, 1] of the frame;
- `z_what`: Gaussian appearance code from an object encoder that sees only a glimpse of
  `spair_glimpse`^2 pixels cut from the frame at the box by a spatial transformer;
- `z_depth`: Gaussian logit, depth = 4 * sigmoid(logit) (larger is nearer the camera);
- `z_pres`: Concrete (relaxed Bernoulli) presence with temperature `spair_temperature`.
Inside a cell the heads run in the original's order where -> what -> depth -> pres, each seeing
the cell features and the samples before it. The object decoder turns z_what into a glimpse of
RGB + alpha; the inverse transform puts it back into the frame, and the objects are composited
by depth over the background.

Parallel, not autoregressive. The original visits the cells one by one and feeds each cell the
samples of its already-visited neighbours (the "lateral context"), so the graph is G*G steps
deep, each with a glimpse encoder. Here all cells are inferred at once, as SPACE (Lin et al.
2020) does: a 3x3 conv on the grid gives every cell its neighbours' features in place of their
samples. Why: under jit the parallel version is one batched op per stage instead of 16-36
dependent ones (much faster to compile and run, and it vmaps over seeds); the backbone's
receptive field already spans the neighbours, which is what the context is for (to stop two
cells explaining one object), and SPACE shows the parallel posterior detects as well. The
posterior is mean-field over cells; the prior on the number of objects is the original's and
stays autoregressive (a cheap lax.scan over cells on [B, K+1] count vectors, below).

Priors and KL (the original's values): where-logits N(0, 1) for the centre offsets and
N(logit(0.1), 0.5) for the sizes; what N(0, I); depth logit N(0, 1); posterior stds are
2 * sigmoid(.). The where/what/depth KLs are weighted by the cell's presence sample. z_pres
has the original's count prior: the number of objects C ~ p(C = n) proportional to
(1 - q) q^n on 0..K, and cell i is present with the prior probability
p(z_i = 1 | z_<i) = E[(C - n_<i) / (K - i) | z_<i]; the KL is the Bernoulli KL between the
cell's posterior probability and that conditional, given the earlier cells' hard samples.

Annealing (the original's schedules). The prior odds q / (1 - q) fall from
`spair_count_odds_start` (1e6: the count prior is then nearly uniform on 0..K, so objects are
cheap while the decoders learn) to `spair_count_odds_end` (0.0125: few objects) as
odds(t) = (start - end) * 0.1^(t / spair_count_decay_steps) + end. "Training wheels": for the
first `spair_training_wheels` updates the where, depth and pres heads get no gradient (their
outputs are used, but stopped), so boxes stay put while the object encoder/decoder learn.

Background: a small VAE of its own (conv encoder, `spair_bg_dim` latents with a N(0, I) prior,
a decoder to a 4x4 grid of RGB logits resized bilinearly to the frame), so it can only draw a
smooth backdrop and the objects are left to the object layer. Its KL joins the ELBO.

Compositing: each present object's alpha (alpha * z_pres) weighs it against the others with
softmax(log alpha + 3 * depth) per pixel, so a nearer opaque object hides a farther one (the
original's render weighs objects by alpha * depth; this is a sharper, smooth version); the
objects' joint alpha blends them over the background.

Likelihood: Gaussian with a fixed std (`spair_pixel_std`, 0.15 as SPACE's) by default; 0 gives
the original's Bernoulli cross-entropy (as the repo's VAEs). On the test scenes (squares on a
backdrop, a few hundred updates) the Bernoulli term was too weak against the KLs: colour errors
of a square cost ~1 nat per pixel, objects were switched off before their decoders learned, and
no square was found; with std 0.15 every square was. Loss = recon + beta * (sum of KLs).

Glimpse sampling and rendering are bilinear, written as separable interpolation matrices
(a glimpse is Wy @ frame @ Wx^T): batched matmuls, no gathers or loops, exact inverses of each
other for axis-aligned boxes. Params are float32 and independent of the frame size.

Latent for the probes, per cell: [y, x, h, w, pres, depth, what] with y, x the box centre and
h, w its size as fractions of the frame (from the posterior means), pres the presence
probability, depth in [0, 4], what the posterior mean; `encode` returns the cells flattened in
row-major order, so latent_dim = G*G * (6 + spair_what_dim) whatever latent_dim is asked for.

The parts (constants, glimpse geometry, networks, priors and KLs) are in `parts.py`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from bulbjax.learners.base import LearnerConfig, LearnerState, Metrics
from bulbjax.learners.networks import check_frame_shape
from bulbjax.learners.spair.parts import (
    ALPHA_LOGIT_BIAS, ALPHA_LOGIT_SCALE, CELL_FEATURES, CELL_LATENT, HW_PRIOR, HW_RANGE, LATERAL,
    LOGIT_CLIP, MAX_DEPTH, MLP, OBJ_DECODER, OBJ_ENCODER, OBJ_LOGIT_SCALE, WHERE_BIAS, YX_PRIOR,
    YX_RANGE, Backbone, BackgroundDecoder, BackgroundEncoder, Cells, composite, count_prior_kl,
    count_prior_log_odds, extract_glimpses, normal_kl, pixel_nll, posterior_std, render_glimpses,
)


# ============================================================================ learner
@dataclasses.dataclass(frozen=True)
class SPAIR:
    """SPAIR on single frames; pure functions of (state/params, frames, key), hashable, so the
    bound methods go through jax.jit / vmap / scan like the VAEs'. `latent_dim` is fixed by the
    config (see the module docstring); the registry's request is ignored."""

    config: LearnerConfig = LearnerConfig(batch_size=64, retain_fraction=0.5)
    sequential: ClassVar[bool] = False

    @property
    def grid(self) -> int:
        return self.config.spair_grid

    @property
    def num_cells(self) -> int:
        return self.grid * self.grid

    @property
    def cell_dim(self) -> int:
        """Latent size per cell: y, x, h, w, pres, depth and z_what."""
        return CELL_LATENT + self.config.spair_what_dim

    @property
    def latent_dim(self) -> int:
        return self.num_cells * self.cell_dim

    @property
    def retain_fraction(self) -> float:
        return self.config.retain_fraction

    @property
    def batch_size(self) -> int:
        """Frames per batch (config.batch_size; the registry's preset is the paper's 64)."""
        return self.config.batch_size

    @property
    def optimizer(self) -> optax.GradientTransformation:
        """Adam after clipping the global gradient norm to 1 (the original's max_grad_norm), on
        the raveled params (one fused update, as the VAE)."""
        return optax.flatten(optax.chain(optax.clip_by_global_norm(1.0), optax.adam(self.config.lr)))

    # ------------------------------------------------------------------ modules
    def _modules(self, resolution: int) -> dict[str, nn.Module]:
        c = self.config
        g2 = c.spair_glimpse * c.spair_glimpse
        return {
            "backbone": Backbone(self.grid),
            "where": MLP(LATERAL, 8, WHERE_BIAS),
            "what_encoder": MLP(OBJ_ENCODER, 2 * c.spair_what_dim),
            "depth": MLP(LATERAL, 2),
            "pres": MLP(LATERAL, 1),
            "what_decoder": MLP(OBJ_DECODER, 4 * g2),
            "bg_encoder": BackgroundEncoder(c.spair_bg_dim),
            "bg_decoder": BackgroundDecoder(resolution),
        }

    def init(self, key: jax.Array, frame_shape: tuple[int, int, int]) -> LearnerState:
        """Fresh float32 params and optimiser state for frames (R, R, 3), R a multiple of 8.
        `frame_shape` must be static (bind it with functools.partial before vmap)."""
        r = check_frame_shape(frame_shape, 3)
        c, k = self.config, self.num_cells
        mods = self._modules(r)
        x = jnp.zeros((1, r, r, 3), jnp.float32)
        cell = jnp.zeros((1, k, CELL_FEATURES), jnp.float32)
        what = jnp.zeros((1, k, c.spair_what_dim), jnp.float32)
        inputs = {
            "backbone": x,
            "where": cell,
            "what_encoder": jnp.zeros((1, k, c.spair_glimpse**2 * 3), jnp.float32),
            "depth": jnp.zeros((1, k, CELL_FEATURES + 4 + c.spair_what_dim), jnp.float32),
            "pres": jnp.zeros((1, k, CELL_FEATURES + 5 + c.spair_what_dim), jnp.float32),
            "what_decoder": what,
            "bg_encoder": x,
            "bg_decoder": jnp.zeros((1, c.spair_bg_dim), jnp.float32),
        }
        keys = dict(zip(mods, jax.random.split(key, len(mods))))
        params = {n: m.init(keys[n], inputs[n])["params"] for n, m in mods.items()}
        return LearnerState(params, self.optimizer.init(params), jnp.zeros((), jnp.int32))

    def _apply(self, params: Any, name: str, x: jax.Array, resolution: int = 0) -> Any:
        return self._modules(resolution)[name].apply({"params": params[name]}, x)

    # ------------------------------------------------------------------ inference
    def _box(self, logits: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Box logits [B, K, 4] (y, x offsets; h, w sizes) -> centres, sizes [B, K, 2] as
        fractions of the frame."""
        s = jax.nn.sigmoid(jnp.clip(logits, -LOGIT_CLIP, LOGIT_CLIP))
        offset = YX_RANGE[0] + (YX_RANGE[1] - YX_RANGE[0]) * s[..., :2]
        g = self.grid
        rows, cols = jnp.meshgrid(jnp.arange(g), jnp.arange(g), indexing="ij")
        corner = jnp.stack([rows.ravel(), cols.ravel()], axis=-1).astype(jnp.float32)  # [K, 2]
        centres = (corner + offset) / g
        sizes = HW_RANGE[0] + (HW_RANGE[1] - HW_RANGE[0]) * s[..., 2:]
        return centres, sizes

    def _cells(self, params: Any, x: jax.Array, key: jax.Array | None, wheels: jax.Array) -> Cells:
        """Infer every cell's latents from frames x [B, R, R, 3] in [0, 1]. With key=None the
        posterior means (and presence probabilities) are returned instead of samples.
        `wheels` = 1 stops the gradient into the where/depth/pres heads (training wheels)."""
        c = self.config
        b, k = x.shape[0], self.num_cells
        keys = jax.random.split(key, 4) if key is not None else [None] * 4

        def stop(v: jax.Array) -> jax.Array:
            return wheels * jax.lax.stop_gradient(v) + (1.0 - wheels) * v

        def sample(mean: jax.Array, std: jax.Array, k_: jax.Array | None) -> jax.Array:
            if k_ is None:
                return mean
            return mean + std * jax.random.normal(k_, (mean.size,)).reshape(mean.shape)

        feats = self._apply(params, "backbone", x).reshape((b, k, CELL_FEATURES))

        out = self._apply(params, "where", feats)
        w_mean, w_std = stop(out[..., :4]), stop(posterior_std(out[..., 4:]))
        where = sample(w_mean, w_std, keys[0])
        prior_mean = jnp.array([YX_PRIOR[0]] * 2 + [HW_PRIOR[0]] * 2)
        prior_std = jnp.array([YX_PRIOR[1]] * 2 + [HW_PRIOR[1]] * 2)
        kl_where = normal_kl(w_mean, w_std, prior_mean, prior_std).sum(-1)
        centres, sizes = self._box(where)

        glimpses = extract_glimpses(x, centres, sizes, c.spair_glimpse)
        out = self._apply(params, "what_encoder", glimpses.reshape((b, k, -1)))
        a_mean, a_std = out[..., : c.spair_what_dim], posterior_std(out[..., c.spair_what_dim :])
        what = sample(a_mean, a_std, keys[1])
        kl_what = normal_kl(a_mean, a_std, 0.0, 1.0).sum(-1)

        out = self._apply(params, "depth", jnp.concatenate([feats, where, what], axis=-1))
        d_mean, d_std = stop(out[..., 0]), stop(posterior_std(out[..., 1]))
        d_logit = sample(d_mean, d_std, keys[2])
        depth = MAX_DEPTH * jax.nn.sigmoid(jnp.clip(d_logit, -LOGIT_CLIP, LOGIT_CLIP))
        kl_depth = normal_kl(d_mean, d_std, 0.0, 1.0)

        pres_in = jnp.concatenate([feats, where, what, depth[..., None]], axis=-1)
        log_odds = jnp.clip(stop(self._apply(params, "pres", pres_in)[..., 0]), -LOGIT_CLIP, LOGIT_CLIP)
        if keys[3] is None:
            pres = jax.nn.sigmoid(log_odds)
        else:  # Concrete sample: sigmoid((log-odds + logistic noise) / temperature)
            u = jax.random.uniform(keys[3], (log_odds.size,), minval=1e-6, maxval=1.0 - 1e-6)
            noise = (jnp.log(u) - jnp.log1p(-u)).reshape(log_odds.shape)
            pres = jax.nn.sigmoid((log_odds + noise) / c.spair_temperature)
        return Cells(centres, sizes, what, depth, pres, log_odds, kl_where, kl_what, kl_depth)

    def _background(self, params: Any, x: jax.Array, key: jax.Array | None) -> tuple[jax.Array, jax.Array]:
        """Background [B, R, R, 3] in [0, 1] (from a sample, or the mean with key=None) and
        its KL [B]."""
        mean, logvar = self._apply(params, "bg_encoder", x)
        z = mean
        if key is not None:
            z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, (mean.size,)).reshape(mean.shape)
        kl = (0.5 * (jnp.exp(logvar) + jnp.square(mean) - 1.0 - logvar)).sum(-1)
        return jax.nn.sigmoid(self._apply(params, "bg_decoder", z, x.shape[1])), kl

    def _render(self, params: Any, cells: Cells, background: jax.Array) -> jax.Array:
        """Decode every cell's glimpse, draw it at its box and composite over the background."""
        b, k = cells.what.shape[:2]
        g = self.config.spair_glimpse
        logits = self._apply(params, "what_decoder", cells.what).reshape((b, k, g, g, 4))
        logits = logits * jnp.array([OBJ_LOGIT_SCALE] * 3 + [ALPHA_LOGIT_SCALE])
        logits = logits + jnp.array([0.0] * 3 + [ALPHA_LOGIT_BIAS])
        rgba = jax.nn.sigmoid(jnp.clip(logits, -LOGIT_CLIP, LOGIT_CLIP))
        premult = jnp.concatenate([rgba[..., :3] * rgba[..., 3:], rgba[..., 3:]], axis=-1)
        drawn = render_glimpses(premult, cells.centres, cells.sizes, background.shape[1:3])
        pres = cells.pres[:, :, None, None]
        return composite(drawn[..., :3] * pres[..., None], drawn[..., 3] * pres, cells.depth, background)

    # ------------------------------------------------------------------ training
    def loss(self, params: Any, frames: jax.Array, key: jax.Array, step: jax.Array) -> tuple[jax.Array, Metrics]:
        """Negative ELBO (beta-weighted KLs) on uint8 frames at update `step` (the annealing and
        training-wheel schedules read it), with its parts as metrics."""
        c = self.config
        x = _to_unit(frames)
        check_frame_shape(x.shape[1:], 3)
        k_cells, k_bg = jax.random.split(key)
        wheels = (step < c.spair_training_wheels).astype(jnp.float32)
        cells = self._cells(params, x, k_cells, wheels)
        background, kl_bg = self._background(params, x, k_bg)
        recon = pixel_nll(self._render(params, cells, background), x, c.spair_pixel_std)
        prior = count_prior_log_odds(c, step)
        present = jax.lax.stop_gradient(cells.pres) > 0.5
        kl_pres = count_prior_kl(cells.pres_log_odds, present, prior).sum(-1).mean()
        kl_where = (cells.pres * cells.kl_where).sum(-1).mean()
        kl_what = (cells.pres * cells.kl_what).sum(-1).mean()
        kl_depth = (cells.pres * cells.kl_depth).sum(-1).mean()
        kl = kl_pres + kl_where + kl_what + kl_depth + kl_bg.mean()
        loss = recon + c.beta * kl
        metrics = {
            "loss": loss, "recon": recon, "kl": kl, "kl_pres": kl_pres, "kl_where": kl_where,
            "kl_what": kl_what, "kl_depth": kl_depth, "kl_bg": kl_bg.mean(),
            "num_objects": present.sum(-1).astype(jnp.float32).mean(), "prior_log_odds": prior,
        }
        return loss, metrics

    def update(self, state: LearnerState, frames: jax.Array, key: jax.Array) -> tuple[LearnerState, Metrics]:
        """One step on uint8 frames [B, R, R, 3]; metrics are those of the batch before the
        step (check them host-side with `check_finite`)."""
        grads, metrics = jax.grad(self.loss, has_aux=True)(state.params, frames, key, state.step)
        updates, opt_state = self.optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return LearnerState(params, opt_state, state.step + 1), metrics

    # ------------------------------------------------------------------ evaluation
    def _posterior(self, params: Any, frames: jax.Array) -> tuple[jax.Array, Cells]:
        x = _to_unit(frames)
        check_frame_shape(x.shape[1:], 3)
        return x, self._cells(params, x, None, jnp.zeros((), jnp.float32))

    def encode(self, params: Any, frames: jax.Array) -> jax.Array:
        """Latents [B, G*G * (6 + spair_what_dim)] float32: per cell (row-major) the box centre
        (y, x) and size (h, w) as fractions of the frame, presence probability, depth and the
        z_what mean, all from the posterior means."""
        _, cells = self._posterior(params, frames)
        per_cell = jnp.concatenate(
            [cells.centres, cells.sizes, cells.pres[..., None], cells.depth[..., None], cells.what], axis=-1)
        return per_cell.reshape((per_cell.shape[0], -1))

    def reconstruct(self, params: Any, frames: jax.Array) -> jax.Array:
        """Reconstructions [B, R, R, 3] float32 in [0, 1] from the posterior means (presence
        probabilities as soft presences)."""
        x, cells = self._posterior(params, frames)
        background, _ = self._background(params, x, None)
        return self._render(params, cells, background)

    def background(self, params: Any, frames: jax.Array) -> jax.Array:
        """The background model's mean [B, R, R, 3] in [0, 1] for uint8 frames."""
        x = _to_unit(frames)
        return self._background(params, x, None)[0]

    def boxes(self, params: Any, frames: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(centres_px [B, G*G, 2], sizes_px [B, G*G, 2], pres [B, G*G]) for uint8 frames:
        box centres and sizes in pixels, (x, y) = (column, row) from the frame's top-left
        corner (a pixel's centre is at +0.5), and presence probabilities (a box is usually
        called present above 0.5)."""
        x, cells = self._posterior(params, frames)
        r = x.shape[1]
        return cells.centres[..., ::-1] * r, cells.sizes[..., ::-1] * r, cells.pres

    def boxes_of_latents(self, z: jax.Array, resolution: int) -> tuple[jax.Array, jax.Array]:
        """(centres_px [..., G*G, 2], pres [..., G*G]) of latents [..., latent_dim] from `encode`
        of frames of `resolution` pixels: the same centres and presences as `boxes`, without
        encoding the frames again (the experiment's object probe reuses the probe's latents)."""
        cells = z.reshape(z.shape[:-1] + (self.num_cells, self.cell_dim))
        return cells[..., 1::-1] * resolution, cells[..., 4]


def _to_unit(frames: jax.Array) -> jax.Array:
    """uint8 frames [B, R, R, 3] -> float32 in [0, 1]; other dtypes are refused."""
    if frames.dtype != jnp.uint8:
        raise TypeError(f"frames must be uint8 in [0, 255], got dtype {frames.dtype}")
    if frames.ndim != 4:
        raise ValueError(f"frames must be a batch [B, R, R, 3], got shape {frames.shape}")
    return frames.astype(jnp.float32) / 255.0


# ============================================================================ synthetic scenes
def synthetic_scene(
    key: jax.Array, batch: int, resolution: int = 32, num_objects: int = 3, size: int = 6
) -> tuple[jax.Array, jax.Array]:
    """Frames of `num_objects` coloured squares of `size` px on a smooth two-colour backdrop,
    and the squares' centres: (uint8 [B, R, R, 3], float32 [B, M, 2] (x, y) pixels).

    The squares sit in distinct slots of a coarse layout (slots of ~size+4 px, so they do not
    overlap) at a random place inside the slot, so they straddle SPAIR cells freely. For tests
    and examples of object discovery."""
    slots = max(1, resolution // (size + 4))
    if num_objects > slots * slots:
        raise ValueError(f"{num_objects} squares of {size} px do not fit a {resolution}px frame")
    slot = resolution // slots
    k_slot, k_jit, k_col, k_bg = jax.random.split(key, 4)
    order = jax.vmap(lambda k: jax.random.permutation(k, slots * slots))(jax.random.split(k_slot, batch))
    cell = order[:, :num_objects]
    jitter = jax.random.randint(k_jit, (batch, num_objects, 2), 0, slot - size + 1)
    corner = jnp.stack([cell % slots, cell // slots], axis=-1) * slot + jitter  # (x, y) top-left
    colour = jax.random.uniform(k_col, (batch, num_objects, 3), minval=0.0, maxval=1.0)
    colour = colour.at[jnp.arange(batch)[:, None], jnp.arange(num_objects)[None], jnp.arange(num_objects)[None] % 3].set(1.0)
    tops = jax.random.uniform(k_bg, (batch, 2, 3), minval=0.05, maxval=0.4)
    ramp = (jnp.arange(resolution, dtype=jnp.float32) / (resolution - 1))[None, :, None, None]
    frame = tops[:, None, None, 0] * (1 - ramp) + tops[:, None, None, 1] * ramp  # [B, R, 1, 3]
    frame = jnp.broadcast_to(frame, (batch, resolution, resolution, 3))
    pix = jnp.arange(resolution)
    inside_x = (pix[None, None, :] >= corner[..., 0:1]) & (pix[None, None, :] < corner[..., 0:1] + size)
    inside_y = (pix[None, None, :] >= corner[..., 1:2]) & (pix[None, None, :] < corner[..., 1:2] + size)
    mask = inside_y[:, :, :, None] & inside_x[:, :, None, :]  # [B, M, R(y), R(x)]
    for m in range(num_objects):
        frame = jnp.where(mask[:, m, :, :, None], colour[:, m, None, None, :], frame)
    frames = jnp.round(frame * 255.0).astype(jnp.uint8)
    return frames, corner.astype(jnp.float32) + size / 2.0
