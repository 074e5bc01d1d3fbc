"""Contrastive learners (beyond the paper): ST-DIM and CURL, registered as `stdim` and `curl`.

Neither reconstructs pixels. Both use the frame VAEs' conv stack (`LearnerConfig.conv_features`,
64-64-128-256, 4x4 stride-2 convolutions with ReLU), an FC layer of `hidden` units and a linear
map to the latent (`latent_dim` = 2 x the state's dimension, as for every learner), and score
pairs with bilinear InfoNCE (van den Oord et al. 2018): for N anchors and their N positives, a
softmax over the N candidates of each anchor, the other anchors' positives being its negatives.

- **ST-DIM** (`stdim`; Anand et al. 2019, the AtariARI learner): spatio-temporal InfoNCE between
  consecutive frames x_t, x_{t+1} of a window. Global-local: the latent of x_t (through `w_gl`)
  against each location of x_{t+1}'s local feature map (the output of the second-to-last conv
  layer: 8x8x128 at 64 px); local-local: each location of x_t's map (through `w_ll`) against the
  same location of x_{t+1}'s. The loss is the mean over locations of both. The scores are
  AtariARI's bilinear products of the raw vectors unless `LearnerConfig.stdim_temperature` > 0,
  which scores L2-normalised vectors over that temperature (bounded; the raw scores diverged in
  4 of 12 long pendulum seeds). It trains on windows
  (a `SequenceLearner`), but its latent is one frame's: the probe reads z_t alone
  (`probe_context = 1`), as AtariARI probes, so that it compares with the frame learners.
- **CURL** (`curl`; Laskin et al. 2020): InfoNCE between two random shifts of the same frame (the
  frame padded by `resolution // 16` px with its edge pixels and cropped back at a random
  offset: RAD's translate, CURL's crop without changing the resolution), the query through the
  online encoder and the key through a momentum encoder (an exponential moving average of the
  online one, `momentum` 0.95 as CURL's encoder tau 0.05) without gradient. Picked over ATC
  (Stooke et al. 2021) because ST-DIM already contrasts time steps: CURL adds the other kind of
  positive (augmentations of one frame) and is a frame learner, trained on the same replay
  frames as VAE_rpl, so the two differ only in their objective.

The equal-compute rule (`bulbjax/learners/base.py`): ST-DIM takes `batch_size //
sequence_length` windows (42 at 1,024 and L = 24), 1,008 frames each encoded once (every frame
is in two pairs), as the sequential learners; CURL takes `batch_size // 2` frames (512), each
encoded twice (query and key), 1,024 encodings. Both encode about the 1,024 frames a VAE does
per update (they decode none, so an update costs less).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from bulbjax.data.augment import random_shift
from bulbjax.learners.base import LearnerConfig, LearnerState, Metrics
from bulbjax.learners.networks import Conv4x4, check_edge_layers, check_frame_shape, lecun_normal_flat
from bulbjax.learners.registry import register_learner


class ContrastiveEncoder(nn.Module):
    """Frames `[B, R, R, 3]` in [0, 1] -> the latent `[B, latent_dim]` and the local feature map
    `[B, h, w, C]` of the second-to-last conv layer (the last one's for a one-layer stack), both
    float32. Conv layers `conv0..` laid out as every learner's (`networks.conv_layers`)."""

    latent_dim: int
    features: tuple[int, ...]
    hidden: int = 512
    dtype: jnp.dtype = jnp.float32
    channel_pad: int = 1
    bias_grad: str = "reduce"
    edge_layers: str = "strided"

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        check_frame_shape(x.shape[1:], len(self.features))
        check_edge_layers(self.edge_layers)
        h, local = x.astype(self.dtype), None
        at = max(len(self.features) - 2, 0)
        for i, f in enumerate(self.features):
            blocked = i == 0 and self.edge_layers == "blocked"
            h = Conv4x4(f, self.dtype, self.channel_pad, self.bias_grad, blocked, relu=True, name=f"conv{i}")(h)
            if i == at:
                local = h
        dense = dict(param_dtype=jnp.float32, kernel_init=lecun_normal_flat)
        g = nn.relu(nn.Dense(self.hidden, dtype=self.dtype, name="fc", **dense)(h.reshape((h.shape[0], -1))))
        z = nn.Dense(self.latent_dim, name="latent", **dense)(g.astype(jnp.float32))
        return z, local.astype(jnp.float32)


def info_nce(logits: jax.Array, valid: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """InfoNCE of `logits [N, N]` whose positives are on the diagonal: the mean over anchors
    (rows) of -log softmax at the positive, and the share of anchors whose positive scores
    highest. `valid [N]` (bool): rows and columns of invalid pairs (padding) are left out, as
    anchors and as negatives."""
    n = logits.shape[0]
    w = jnp.ones((n,), jnp.float32) if valid is None else valid.astype(jnp.float32)
    logits = jnp.where(w[None, :] > 0, logits, -1e9)
    nll = -jnp.diagonal(jax.nn.log_softmax(logits, axis=-1))
    hit = (jnp.argmax(logits, axis=-1) == jnp.arange(n)).astype(jnp.float32)
    total = jnp.maximum(jnp.sum(w), 1.0)
    return jnp.sum(nll * w) / total, jnp.sum(hit * w) / total


def _unit(frames: jax.Array) -> jax.Array:
    if frames.dtype != jnp.uint8:
        raise TypeError(f"frames must be uint8 in [0, 255], got dtype {frames.dtype}")
    return frames.astype(jnp.float32) / 255.0


def _l2_unit(x: jax.Array) -> jax.Array:
    """`x` scaled to unit length along its last axis (zero vectors stay ~zero)."""
    return x * jax.lax.rsqrt(jnp.sum(x * x, axis=-1, keepdims=True) + 1e-12)


def _encoder(latent_dim: int, c: LearnerConfig) -> ContrastiveEncoder:
    return ContrastiveEncoder(latent_dim, c.conv_features, c.hidden, c.dtype, **c.conv_forms)


def _matrix(key: jax.Array, rows: int, cols: int) -> jax.Array:
    return lecun_normal_flat(key, (rows, cols))


@dataclasses.dataclass(frozen=True)
class STDIM:
    """ST-DIM (module docstring): a sequential learner by its data (windows), a frame encoder by
    its latent. Pure functions of (state/params, windows, key); hashable."""

    latent_dim: int
    config: LearnerConfig = LearnerConfig()
    action_dim: int = 1
    sequential: ClassVar[bool] = True
    probe_context: ClassVar[int] = 1  # the probe reads z_t alone: one frame's latent

    def __post_init__(self) -> None:
        if self.latent_dim < 1:
            raise ValueError(f"latent_dim must be >= 1, got {self.latent_dim!r}")

    @property
    def retain_fraction(self) -> float:
        return self.config.retain_fraction

    @property
    def sequence_length(self) -> int:
        return self.config.sequence_length

    @property
    def window_length(self) -> int:
        return self.config.sequence_length

    @property
    def batch_size(self) -> int:
        """Windows per batch: config.batch_size // sequence_length (module docstring)."""
        return max(1, self.config.batch_size // self.sequence_length)

    @property
    def encoder(self) -> ContrastiveEncoder:
        return _encoder(self.latent_dim, self.config)

    @property
    def optimizer(self) -> optax.GradientTransformation:
        return optax.flatten(optax.adam(self.config.lr))

    def _local_channels(self) -> int:
        f = self.config.conv_features
        return f[max(len(f) - 2, 0)]

    def init(self, key: jax.Array, frame_shape: tuple[int, int, int]) -> LearnerState:
        """Encoder and the two bilinear maps `w_gl [Z, C]`, `w_ll [C, C]`; Adam over all."""
        check_frame_shape(frame_shape, len(self.config.conv_features))
        k_e, k_g, k_l = jax.random.split(key, 3)
        c = self._local_channels()
        params = {"encoder": self.encoder.init(k_e, jnp.zeros((1,) + tuple(frame_shape), jnp.float32))["params"],
                  "w_gl": _matrix(k_g, self.latent_dim, c), "w_ll": _matrix(k_l, c, c)}
        return LearnerState(params, self.optimizer.init(params), jnp.zeros((), jnp.int32))

    def _encode_frames(self, params: Any, frames: jax.Array) -> tuple[jax.Array, jax.Array]:
        """uint8 frames `[..., H, W, 3]` -> latents `[..., Z]` and local maps `[..., h, w, C]`."""
        lead = frames.shape[:-3]
        z, local = self.encoder.apply({"params": params["encoder"]},
                                      _unit(frames.reshape((-1,) + frames.shape[-3:])))
        return z.reshape(lead + z.shape[1:]), local.reshape(lead + local.shape[1:])

    def loss(self, params: Any, windows: Any, key: jax.Array) -> tuple[jax.Array, Metrics]:
        """Global-local plus local-local InfoNCE over the valid consecutive pairs of the first
        `sequence_length` steps, each averaged over the local map's locations."""
        l = self.sequence_length
        if windows.frames.shape[1] < l:
            raise ValueError(f"windows of {windows.frames.shape[1]} steps; stdim needs {l}")
        z, local = self._encode_frames(params, windows.frames[:, :l])  # [B, L, Z], [B, L, h, w, C]
        b = z.shape[0]
        n = b * (l - 1)
        valid = (windows.valid[:, : l - 1] & windows.valid[:, 1:l]).reshape(n)
        za = z[:, :-1].reshape(n, -1)
        la = local[:, :-1].reshape(n, -1, local.shape[-1])  # [N, M, C]
        lb = local[:, 1:].reshape(n, -1, local.shape[-1])
        qg, ql, t = za @ params["w_gl"], la @ params["w_ll"], self.config.stdim_temperature
        if t > 0:  # cosine scores over a temperature (LearnerConfig.stdim_temperature): bounded
            qg, ql, lb = _l2_unit(qg), _l2_unit(ql), _l2_unit(lb)
        gl = jnp.einsum("nc,kmc->mnk", qg, lb)  # [M, N, N]
        ll = jnp.einsum("nmc,kmc->mnk", ql, lb)
        if t > 0:
            gl, ll = gl / t, ll / t
        score = jax.vmap(info_nce, in_axes=(0, None))
        gl_loss, gl_acc = score(gl, valid)
        ll_loss, _ = score(ll, valid)
        gl_loss, ll_loss = jnp.mean(gl_loss), jnp.mean(ll_loss)
        loss = gl_loss + ll_loss
        return loss, {"loss": loss, "global_local": gl_loss, "local_local": ll_loss,
                      "accuracy": jnp.mean(gl_acc), "pairs": jnp.sum(valid).astype(jnp.float32)}

    def update(self, state: LearnerState, windows: Any, key: jax.Array) -> tuple[LearnerState, Metrics]:
        """One Adam step on a batch of windows; metrics of the batch before the step."""
        grads, metrics = jax.grad(self.loss, has_aux=True)(state.params, windows, key)
        updates, opt_state = self.optimizer.update(grads, state.opt_state, state.params)
        return LearnerState(optax.apply_updates(state.params, updates), opt_state, state.step + 1), metrics

    def frame_features(self, params: Any, frames: jax.Array) -> jax.Array:
        """Latents `[..., Z]` of uint8 frames `[..., H, W, 3]`, one frame each."""
        return self._encode_frames(params, frames)[0]

    def encode_features(self, params: Any, features: jax.Array, actions: jax.Array) -> jax.Array:
        """Per-step latents of a window from its `frame_features`: the features themselves (the
        latent holds one frame; PPO on `latent:stdim` reads the current frame's)."""
        return features

    def encode(self, params: Any, windows: Any) -> jax.Array:
        """Per-step latents `[B, sequence_length, Z]`, each of its frame alone."""
        return self.frame_features(params, windows.frames[:, : self.sequence_length])


@dataclasses.dataclass(frozen=True)
class CURL:
    """CURL (module docstring): a frame learner. Params `{"online", "w", "target"}`: Adam
    trains the online encoder and the bilinear map `w [Z, Z]`; the target (momentum) encoder
    follows the online one after every step. `encode` is the online encoder's latent."""

    latent_dim: int
    config: LearnerConfig = LearnerConfig()
    momentum: float = 0.95
    shift: int = 0  # px of random shift; 0: resolution // 16 (4 px at 64 px)
    sequential: ClassVar[bool] = False

    def __post_init__(self) -> None:
        if self.latent_dim < 1:
            raise ValueError(f"latent_dim must be >= 1, got {self.latent_dim!r}")
        if not 0.0 <= self.momentum < 1.0:
            raise ValueError(f"momentum must be in [0, 1), got {self.momentum!r}")

    @property
    def retain_fraction(self) -> float:
        return self.config.retain_fraction

    @property
    def batch_size(self) -> int:
        """Frames per batch: config.batch_size // 2, two views each (module docstring)."""
        return max(1, self.config.batch_size // 2)

    @property
    def encoder(self) -> ContrastiveEncoder:
        return _encoder(self.latent_dim, self.config)

    @property
    def optimizer(self) -> optax.GradientTransformation:
        return optax.flatten(optax.adam(self.config.lr))

    def init(self, key: jax.Array, frame_shape: tuple[int, int, int]) -> LearnerState:
        check_frame_shape(frame_shape, len(self.config.conv_features))
        k_e, k_w = jax.random.split(key)
        enc = self.encoder.init(k_e, jnp.zeros((1,) + tuple(frame_shape), jnp.float32))["params"]
        trained = {"online": enc, "w": _matrix(k_w, self.latent_dim, self.latent_dim)}
        params = {**trained, "target": enc}
        return LearnerState(params, self.optimizer.init(trained), jnp.zeros((), jnp.int32))

    def _z(self, enc: Any, x: jax.Array) -> jax.Array:
        return self.encoder.apply({"params": enc}, x)[0]

    def loss(self, trained: Any, target: Any, frames: jax.Array, key: jax.Array) -> tuple[jax.Array, Metrics]:
        """InfoNCE of the online latent of one random shift of each frame (query) against the
        target encoder's latent of another (key), through `w`."""
        x = _unit(frames)
        pad = self.shift or x.shape[1] // 16
        k_q, k_k = jax.random.split(key)
        q = self._z(trained["online"], random_shift(k_q, x, pad))
        k = jax.lax.stop_gradient(self._z(target, random_shift(k_k, x, pad)))
        logits = (q @ trained["w"]) @ k.T
        logits = logits - jax.lax.stop_gradient(jnp.max(logits, axis=-1, keepdims=True))
        loss, acc = info_nce(logits)
        return loss, {"loss": loss, "accuracy": acc}

    def update(self, state: LearnerState, frames: jax.Array, key: jax.Array) -> tuple[LearnerState, Metrics]:
        """One Adam step on uint8 frames `[B, H, W, 3]`, then the momentum update of the target."""
        p = state.params
        trained = {"online": p["online"], "w": p["w"]}
        grads, metrics = jax.grad(self.loss, has_aux=True)(trained, p["target"], frames, key)
        updates, opt_state = self.optimizer.update(grads, state.opt_state, trained)
        trained = optax.apply_updates(trained, updates)
        m = self.momentum
        target = jax.tree.map(lambda t, o: m * t + (1.0 - m) * o, p["target"], trained["online"])
        return LearnerState({**trained, "target": target}, opt_state, state.step + 1), metrics

    def encode(self, params: Any, frames: jax.Array) -> jax.Array:
        """The online encoder's latents `[B, latent_dim]` of uint8 frames `[B, H, W, 3]`."""
        check_frame_shape(frames.shape[1:], len(self.config.conv_features))
        return self._z(params["online"], _unit(frames))


@register_learner("stdim", defaults={"retain_fraction": 0.5}, sequential=True, frame_latent=True)
def make_stdim(latent_dim: int, config: LearnerConfig, action_dim: int) -> STDIM:
    return STDIM(latent_dim=latent_dim, config=config, action_dim=action_dim)


@register_learner("curl", defaults={"retain_fraction": 0.5})
def make_curl(latent_dim: int, config: LearnerConfig, action_dim: int) -> CURL:
    return CURL(latent_dim=latent_dim, config=config)
