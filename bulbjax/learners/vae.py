"""VAE frame learner: VAE_v0, and with a config change VAE_rpl and beta-VAE.

Likelihood: Bernoulli (sigmoid cross-entropy) on frames scaled to [0, 1], summed over
pixels and channels and averaged over the batch. We pick it over a Gaussian because it
has no output variance to choose: a fixed-variance Gaussian makes the reconstruction
term's scale, and so the effective KL weight (and what beta means), hinge on an
arbitrary sigma, while the Bernoulli term is the common choice for pixel VAEs and
beta-VAE and keeps beta comparable to the literature. Targets in [0, 1] are fine for
it (the loss's minimum is then the targets' entropy, not 0, which does not move the
gradients).

Loss = recon + beta * KL(q(z|x) || N(0, I)), with a single reparameterised sample.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import optax

from bulbjax.learners.base import LearnerConfig, LearnerState, Metrics
from bulbjax.learners.networks import ConvEncoder, DeconvDecoder, check_frame_shape


def _to_unit(frames: jax.Array) -> jax.Array:
    """uint8 frames -> float32 in [0, 1]; other dtypes are refused (they would be mis-scaled)."""
    if frames.dtype != jnp.uint8:
        raise TypeError(f"frames must be uint8 in [0, 255], got dtype {frames.dtype}")
    if frames.ndim != 4:
        raise ValueError(f"frames must be a batch [B, R, R, 3], got shape {frames.shape}")
    return frames.astype(jnp.float32) / 255.0


@dataclasses.dataclass(frozen=True)
class VAE:
    """Conv VAE on single frames. Pure functions of (state/params, frames, key).

    Hashable and immutable, so its bound methods can be passed to jax.jit / vmap / scan.
    """

    latent_dim: int
    config: LearnerConfig = LearnerConfig()
    sequential: ClassVar[bool] = False  # trains on single frames (see SequenceLearner for windows)

    def __post_init__(self) -> None:
        if self.latent_dim < 1:
            raise ValueError(f"latent_dim must be >= 1, got {self.latent_dim!r}")

    @property
    def retain_fraction(self) -> float:
        """Share of the initial replay content to keep for the whole run."""
        return self.config.retain_fraction

    @property
    def batch_size(self) -> int:
        """Frames per batch the caller should sample (config.batch_size; paper: 1,024)."""
        return self.config.batch_size

    @property
    def encoder(self) -> ConvEncoder:
        c = self.config
        return ConvEncoder(self.latent_dim, c.conv_features, c.hidden, c.dtype, **c.conv_forms)

    def decoder(self, resolution: int) -> DeconvDecoder:
        c = self.config
        return DeconvDecoder(resolution, c.conv_features, c.hidden, 3, c.dtype, c.deconv_impl, **c.conv_forms)

    @property
    def optimizer(self) -> optax.GradientTransformation:
        """Adam on the params raveled into one vector: the same maths as per-leaf Adam,
        but one fused update instead of one per leaf, which compiles ~30% faster on CPU."""
        return optax.flatten(optax.adam(self.config.lr))

    def resolution(self, params: Any) -> int:
        """Frame resolution R the params were initialised for (read off a weight shape)."""
        feats = self.config.conv_features
        grid = params["decoder"]["fc_grid"]["kernel"].shape[-1] // feats[-1]
        return math.isqrt(grid) * 2 ** len(feats)

    def _check_matches(self, params: Any, frames: jax.Array) -> None:
        check_frame_shape(frames.shape[1:], len(self.config.conv_features))
        r = self.resolution(params)
        if frames.shape[1] != r:
            raise ValueError(
                f"these params were initialised for {r}x{r}x3 frames; got frames of shape "
                f"{tuple(frames.shape)}"
            )

    def init(self, key: jax.Array, frame_shape: tuple[int, int, int]) -> LearnerState:
        """Fresh float32 params and Adam state for frames of shape (R, R, 3).

        `frame_shape` must be static (a tuple of ints), e.g. bind it with functools.partial
        before jax.vmap-ing over keys.
        """
        r = check_frame_shape(frame_shape, len(self.config.conv_features))
        k_enc, k_dec = jax.random.split(key)
        x = jnp.zeros((1, r, r, 3), jnp.float32)
        z = jnp.zeros((1, self.latent_dim), jnp.float32)
        params = {
            "encoder": self.encoder.init(k_enc, x)["params"],
            "decoder": self.decoder(r).init(k_dec, z)["params"],
        }
        return LearnerState(params, self.optimizer.init(params), jnp.zeros((), jnp.int32))

    @property
    def update_key(self) -> "VAE":
        """This VAE up to what its update takes as an argument (`beta`) or does not use
        (`retain_fraction`, the caller's replay): VAEs with equal keys (vae, vae_rpl, beta_vae)
        can share one compiled update (`update(..., beta=)`; epoch.seeds.update_groups)."""
        return dataclasses.replace(
            self, config=dataclasses.replace(self.config, beta=1.0, retain_fraction=0.0))

    def loss(self, params: Any, frames: jax.Array, key: jax.Array,
             beta: float | jax.Array | None = None) -> tuple[jax.Array, Metrics]:
        """Negative ELBO (beta-weighted KL) on uint8 frames, with its parts as metrics. `beta`
        (a traced scalar allowed) replaces `config.beta`."""
        self._check_matches(params, frames)
        x = _to_unit(frames)
        mean, logvar = self.encoder.apply({"params": params["encoder"]}, x)
        # Flat draw + reshape: same samples' distribution, much faster to compile on XLA:CPU
        # than a multi-dimensional draw (see networks.lecun_normal_flat).
        eps = jax.random.normal(key, (mean.size,), mean.dtype).reshape(mean.shape)
        z = mean + jnp.exp(0.5 * logvar) * eps
        logits = self.decoder(x.shape[1]).apply({"params": params["decoder"]}, z)
        recon = optax.sigmoid_binary_cross_entropy(logits, x).sum(axis=(1, 2, 3)).mean()
        kl = (0.5 * (jnp.exp(logvar) + jnp.square(mean) - 1.0 - logvar)).sum(axis=-1).mean()
        loss = recon + (self.config.beta if beta is None else beta) * kl
        return loss, {"loss": loss, "recon": recon, "kl": kl}

    def update(
        self, state: LearnerState, frames: jax.Array, key: jax.Array,
        beta: float | jax.Array | None = None,
    ) -> tuple[LearnerState, Metrics]:
        """One Adam step on a batch of uint8 frames [B, R, R, 3]; `beta` as in `loss`.

        Metrics (float32 scalars: loss, recon, kl) are those of the batch before the step;
        check them host-side with `check_finite`.
        """
        grads, metrics = jax.grad(self.loss, has_aux=True)(state.params, frames, key, beta)
        updates, opt_state = self.optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return LearnerState(params, opt_state, state.step + 1), metrics

    def encode(self, params: Any, frames: jax.Array) -> jax.Array:
        """Posterior means [B, latent_dim] float32 for uint8 frames [B, R, R, 3]."""
        self._check_matches(params, frames)
        mean, _ = self.encoder.apply({"params": params["encoder"]}, _to_unit(frames))
        return mean

    def decode(self, params: Any, latents: jax.Array) -> jax.Array:
        """Pixel means [B, R, R, 3] float32 in [0, 1] for latents [B, latent_dim]."""
        logits = self.decoder(self.resolution(params)).apply({"params": params["decoder"]}, latents)
        return jax.nn.sigmoid(logits)

    def reconstruct(self, params: Any, frames: jax.Array) -> jax.Array:
        """Decoded posterior means: [B, R, R, 3] float32 in [0, 1] for uint8 frames."""
        return self.decode(params, self.encode(params, frames))
