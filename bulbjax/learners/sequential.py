"""Sequential learners SVAE, PRED and DSA (paper Sec. IV.A), trained on windows of frames.

All three reuse the frame VAEs' conv stack and deconv decoder (networks.py), temporal models
(temporal.py: SVAE's LSTM, DSA's encoders), the Bernoulli likelihood and Adam, and take
`Windows` (bulbjax.data.sequence): frames `[B, T, R, R, 3]` uint8, actions `[B, T, A]`, and a
`valid` mask that is False on padding after an episode boundary.
Losses are per valid frame: (sum over valid steps of reconstruction + beta * KL) / (number of
valid steps), so beta=1 weighs reconstruction and KL per frame exactly as the frame VAE does.

Actions: `windows.actions[:, t]` is the action that led into frame t. The learners condition on
`a_prev[:, t] = actions[:, t]` for t >= 1 and zeros at t = 0 (the action before a window is
context the window does not have), so whatever frame t is decoded from depends on actions
a_1..a_{t-1} of the window, never on the true state.

Per-step latents, `encode(params, windows) -> [B, sequence_length, latent_dim]`; the probe maps
the latents at steps t-1 and t (`ProbeConfig.sequence_context`) to the true state at step t:
- svae: posterior mean of z_t, the output of an LSTM over frames 1..t and the actions into them
  (causal: the latent at step t has seen no later frame).
- pred: chunk t of the predictive latent's mean, the part the decoder turns into frame t. It is a
  function of the whole input window (frames 1..L), as PRED is defined; chunks L..L+k-1 are the
  forecast, trained but not probed (their frames are not in the input).
- dsa: [mean of the static latent f, mean of the dynamic z_t]; f is shared by every step of a
  window. The latent budget is split: static `max(1, latent_dim // 4)`, dynamic the rest, so the
  probe sees as many numbers per step as for the other learners.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from bulbjax.data.sequence import Windows
from bulbjax.learners.base import LearnerConfig, LearnerState, Metrics
from bulbjax.learners.networks import DeconvDecoder, FrameFeatures, GaussianHead, check_frame_shape, lecun_normal_flat
from bulbjax.learners.per_seed import per_seed, per_seed_loss
from bulbjax.learners.temporal import SequenceModel

# `SequentialVAE.per_seed_frames`: off, conv stack recomputed in its backward loop, or saved.
PER_SEED_FRAMES = ("", "remat", "saved")


def _normal(key: jax.Array, like: jax.Array) -> jax.Array:
    """Standard normal noise shaped like `like` (flat draw: fast to compile on XLA:CPU)."""
    return jax.random.normal(key, (like.size,), like.dtype).reshape(like.shape)


def _unit_frames(frames: jax.Array) -> jax.Array:
    """uint8 frames -> float32 in [0, 1], what the conv stacks and the likelihood see."""
    return frames.astype(jnp.float32) / 255.0


def _prev_actions(actions: jax.Array) -> jax.Array:
    """Actions into each frame `[B, T, A]` -> what step t is conditioned on: the action into
    frame t, zero at t = 0 (the action before a window is context it does not have)."""
    return actions.astype(jnp.float32).at[:, 0].set(0.0)


def _kl_std_normal(mean: jax.Array, logvar: jax.Array) -> jax.Array:
    """KL(N(mean, exp(logvar)) || N(0, I)), summed over the last axis."""
    return (0.5 * (jnp.exp(logvar) + jnp.square(mean) - 1.0 - logvar)).sum(-1)


def _kl_normal(m_q: jax.Array, lv_q: jax.Array, m_p: jax.Array, lv_p: jax.Array) -> jax.Array:
    """KL(N(m_q, exp(lv_q)) || N(m_p, exp(lv_p))), summed over the last axis."""
    return (0.5 * (lv_p - lv_q + (jnp.exp(lv_q) + jnp.square(m_q - m_p)) * jnp.exp(-lv_p) - 1.0)).sum(-1)


@dataclasses.dataclass(frozen=True)
class SequentialVAE:
    """Shared plumbing of the sequential learners: config, input checks, Adam, decoding.

    Subclasses define `_init_parts`, `_conv` (the per-frame feature network) and either
    `_posterior_of_features` (SVAE, PRED) or `_loss_parts` and `_means_of_features` (DSA): every
    latent is a function of the per-frame features and the previous actions, which is what lets
    `frame_features` be computed once per frame and reused by `encode_features`.
    Hashable and immutable, so bound methods can go through jax.jit / vmap / scan.
    """

    latent_dim: int
    config: LearnerConfig = LearnerConfig()
    action_dim: int = 1  # one-hot size for discrete actions, action_size for continuous
    # Frame networks one seed at a time when vmapped over seeds, the rest batched: how the
    # "hybrid" seed loop runs learners with LSTMs on one GPU (`seeds.resolve_seed_loop`). ""
    # (off), "remat" (the conv stack's forward recomputed in its backward loop) or "saved" (its
    # activations saved); the decoder and likelihood compute value and gradient in one loop
    # (`per_seed_loss`). Same numbers, another schedule.
    per_seed_frames: str = ""
    sequential: ClassVar[bool] = True
    # Whether the "hybrid" seed loop vmaps this learner (`epoch.seeds.with_seed_loop`): worth
    # it where LSTMs are a large share of an update (DSA: three; H100, 6 seeds, 5.74 -> 5.03 ms
    # per seed-update), not for SVAE's one (4.25 -> 4.28 ms; the diagnostic bench_seed_axis.py,
    # benchmarks/diagnostics/README.md).
    hybrid_vmapped: ClassVar[bool] = False

    def __post_init__(self) -> None:
        if self.per_seed_frames not in PER_SEED_FRAMES:
            raise ValueError(f"per_seed_frames must be one of {PER_SEED_FRAMES}, got {self.per_seed_frames!r}")
        if self.latent_dim < 1:
            raise ValueError(f"latent_dim must be >= 1, got {self.latent_dim!r}")
        if self.action_dim < 1:
            raise ValueError(f"action_dim must be >= 1, got {self.action_dim!r}")

    # ------------------------------------------------------------------ sizes
    @property
    def retain_fraction(self) -> float:
        """Share of the initial replay windows to keep for the whole run."""
        return self.config.retain_fraction

    @property
    def sequence_length(self) -> int:
        """Input steps per window, L; `encode` gives one latent per step of these."""
        return self.config.sequence_length

    @property
    def window_length(self) -> int:
        """Steps a training window needs."""
        return self.sequence_length

    @property
    def batch_size(self) -> int:
        """Windows per batch: the frame learners' batch divided by L (equalised compute)."""
        return max(1, self.config.batch_size // self.sequence_length)

    @property
    def optimizer(self) -> optax.GradientTransformation:
        """Adam on the raveled params (one fused update; see VAE.optimizer)."""
        return optax.flatten(optax.adam(self.config.lr))

    def decoder(self, resolution: int) -> DeconvDecoder:
        c = self.config
        return DeconvDecoder(resolution, c.conv_features, c.hidden, 3, c.dtype, c.deconv_impl, **c.conv_forms)

    def resolution(self, params: Any) -> int:
        """Frame resolution R the params were initialised for (read off a weight shape)."""
        feats = self.config.conv_features
        grid = params["decoder"]["fc_grid"]["kernel"].shape[-1] // feats[-1]
        return math.isqrt(grid) * 2 ** len(feats)

    # ------------------------------------------------------------------ inputs
    def _inputs(self, params: Any, windows: Windows, length: int
                ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Checked, cut to `length` steps: uint8 frames [B, T, R, R, 3], a_prev [B, T, A]
        (zero at step 0), valid as float32 [B, T]."""
        if not isinstance(windows, Windows):
            raise TypeError(f"{type(self).__name__} trains on Windows (bulbjax.data.sequence), "
                            f"got {type(windows).__name__}")
        f = windows.frames
        if f.dtype != jnp.uint8:
            raise TypeError(f"frames must be uint8 in [0, 255], got dtype {f.dtype}")
        if f.ndim != 5:
            raise ValueError(f"windows' frames must be [B, T, R, R, 3], got shape {f.shape}")
        if f.shape[1] < length:
            raise ValueError(
                f"wrong sequence length: {type(self).__name__.lower()} needs windows of at least "
                f"{length} steps (sequence_length={self.sequence_length}"
                f"{f', pred_horizon={self.config.pred_horizon}' if length > self.sequence_length else ''}), "
                f"got {f.shape[1]}")
        if windows.actions.shape[:2] != f.shape[:2] or windows.actions.shape[-1] != self.action_dim:
            raise ValueError(f"actions must be [B, T, action_dim={self.action_dim}] (one-hot for "
                             f"discrete actions), got {windows.actions.shape}")
        check_frame_shape(f.shape[2:], len(self.config.conv_features))
        r = self.resolution(params)
        if f.shape[2] != r:
            raise ValueError(f"these params were initialised for {r}x{r}x3 frames; got frames "
                             f"of shape {tuple(f.shape[2:])}")
        w = windows.head(length)
        return w.frames, _prev_actions(w.actions), w.valid.astype(jnp.float32)

    def _features(self, module: nn.Module, params: Any, frames: jax.Array) -> jax.Array:
        """Per-frame module over uint8 frames [B, T, R, R, 3] -> [B, T, F] (one seed at a time
        under vmap with `per_seed_frames`)."""
        def run(p: Any, f: jax.Array) -> jax.Array:
            x = _unit_frames(f.reshape((-1,) + f.shape[2:]))
            return module.apply({"params": p}, x).reshape(f.shape[:2] + (-1,))
        if self.per_seed_frames:
            run = per_seed(run, remat=self.per_seed_frames == "remat")
        return run(params, frames)

    def _decode_logits(self, params: Any, z: jax.Array) -> jax.Array:
        """Decoder-input latents [B, T, Z] -> pixel logits [B, T, R, R, 3]."""
        b, t = z.shape[:2]
        dec = self.decoder(self.resolution(params))
        logits = dec.apply({"params": params["decoder"]}, z.reshape((b * t, -1)))
        return logits.reshape((b, t) + logits.shape[1:])

    def _recon(self, params: Any, z: jax.Array, frames: jax.Array, valid: jax.Array, n: jax.Array
               ) -> jax.Array:
        """Bernoulli negative log-likelihood of uint8 frames [B, T, R, R, 3] under the decoder
        of latents z [B, T, Z], summed over the valid frames (`valid` float [B, T]) and divided by
        `n`. With `per_seed_frames`, decoder and likelihood run one seed at a time, value and
        gradient in one loop."""
        def nll(d: tuple[Any, jax.Array], f: jax.Array) -> jax.Array:
            logits = self._decode_logits(d[0], d[1])
            return optax.sigmoid_binary_cross_entropy(logits, _unit_frames(f)).sum(axis=(2, 3, 4))
        diff = ({"decoder": params["decoder"]}, z)  # what the decoder reads: its gradient alone
        if self.per_seed_frames:
            return per_seed_loss(nll)(diff, frames, valid / n)
        return (nll(diff, frames) * valid).sum() / n

    # ------------------------------------------------------------------ interface
    def init(self, key: jax.Array, frame_shape: tuple[int, int, int]) -> LearnerState:
        """Fresh float32 params and Adam state for frames of (static) shape (R, R, 3)."""
        r = check_frame_shape(frame_shape, len(self.config.conv_features))
        k_parts, k_dec = jax.random.split(key)
        params = dict(self._init_parts(k_parts, r))
        z = jnp.zeros((1, self.latent_dim), jnp.float32)
        params["decoder"] = self.decoder(r).init(k_dec, z)["params"]
        return LearnerState(params, self.optimizer.init(params), jnp.zeros((), jnp.int32))

    def loss(self, params: Any, windows: Windows, key: jax.Array) -> tuple[jax.Array, Metrics]:
        """Per-valid-frame negative ELBO on the first `window_length` steps, with its parts."""
        x, a_prev, valid = self._inputs(params, windows, self.window_length)
        z, kl_steps, kl_seq = self._loss_parts(params, x, a_prev, key)
        n = jnp.maximum(valid.sum(), 1.0)
        recon = self._recon(params, z, x, valid, n)
        kl = ((kl_steps * valid).sum() + kl_seq.sum()) / n
        loss = recon + self.config.beta * kl
        return loss, {"loss": loss, "recon": recon, "kl": kl, "valid_frac": valid.mean()}

    def update(self, state: LearnerState, windows: Windows, key: jax.Array
               ) -> tuple[LearnerState, Metrics]:
        """One Adam step on a batch of windows; metrics (float32 scalars) are the batch's before
        the step: check them host-side with `check_finite`."""
        grads, metrics = jax.grad(self.loss, has_aux=True)(state.params, windows, key)
        updates, opt_state = self.optimizer.update(grads, state.opt_state, state.params)
        return LearnerState(optax.apply_updates(state.params, updates), opt_state, state.step + 1), metrics

    def encode(self, params: Any, windows: Windows) -> jax.Array:
        """Per-step latents [B, sequence_length, latent_dim] float32 (see the module docstring)."""
        x, a_prev, _ = self._inputs(params, windows, self.sequence_length)
        return self._means(params, x, a_prev)[:, : self.sequence_length]

    def reconstruct(self, params: Any, windows: Windows) -> jax.Array:
        """Decoded latent means [B, T, R, R, 3] in [0, 1] (PRED: T = L + k, the forecast too)."""
        x, a_prev, _ = self._inputs(params, windows, self.sequence_length)
        return jax.nn.sigmoid(self._decode_logits(params, self._means(params, x, a_prev)))

    def frame_features(self, params: Any, frames: jax.Array) -> jax.Array:
        """The per-frame half of `encode`: uint8 frames `[B, T, R, R, 3]` -> features `[B, T, F]`
        float32, each frame's on its own (the conv stack, the costly part). A rolling window can
        keep them per frame and get `encode`'s latents from `encode_features`."""
        if frames.dtype != jnp.uint8 or frames.ndim != 5:
            raise TypeError(f"frames must be uint8 [B, T, R, R, 3], got {frames.dtype} {frames.shape}")
        return self._features(self._conv, params["conv"], frames)

    def encode_features(self, params: Any, features: jax.Array, actions: jax.Array) -> jax.Array:
        """`encode` from `frame_features` of a window's frames: features `[B, T, F]` and the
        actions into each frame `[B, T, A]` (as in `Windows`; step 0's is ignored), T >= L ->
        per-step latents `[B, L, latent_dim]`, the same numbers as `encode` on that window."""
        l = self.sequence_length
        if features.ndim != 3 or features.shape[1] < l or actions.shape[:2] != features.shape[:2] \
                or actions.shape[-1] != self.action_dim:
            raise ValueError(f"features [B, T >= {l}, F] and actions [B, T, {self.action_dim}] expected, "
                             f"got {features.shape} and {actions.shape}")
        return self._means_of_features(params, features[:, :l], _prev_actions(actions[:, :l]))[:, :l]

    # ------------------------------------------------------------------ per learner
    def _init_parts(self, key: jax.Array, resolution: int) -> dict[str, Any]:
        raise NotImplementedError

    @property
    def _conv(self) -> FrameFeatures:
        """The per-frame feature network (params["conv"])."""
        raise NotImplementedError

    def _posterior(self, params: Any, x: jax.Array, a_prev: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Gaussian posterior (mean, log-variance) per step [B, T', latent_dim]."""
        return self._posterior_of_features(params, self._features(self._conv, params["conv"], x), a_prev)

    def _posterior_of_features(self, params: Any, h: jax.Array, a_prev: jax.Array
                               ) -> tuple[jax.Array, jax.Array]:
        """`_posterior` from the per-frame features h [B, T, F]."""
        raise NotImplementedError

    def _loss_parts(self, params: Any, x: jax.Array, a_prev: jax.Array, key: jax.Array
                    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(decoder-input latents [B, T, Z], KL per step [B, T], KL per sequence [B]) from uint8
        frames x [B, T, R, R, 3], with sampled latents.
        Default (SVAE, PRED): reparameterised sample of `_posterior`, N(0, I) prior per step."""
        mean, logvar = self._posterior(params, x, a_prev)
        z = mean + jnp.exp(0.5 * logvar) * _normal(key, mean)
        return z, _kl_std_normal(mean, logvar), jnp.zeros(x.shape[:1])

    def _means(self, params: Any, x: jax.Array, a_prev: jax.Array) -> jax.Array:
        """Decoder-input latent means per step [B, T', latent_dim]."""
        return self._means_of_features(params, self._features(self._conv, params["conv"], x), a_prev)

    def _means_of_features(self, params: Any, h: jax.Array, a_prev: jax.Array) -> jax.Array:
        """`_means` from the per-frame features h [B, T, F]."""
        return self._posterior_of_features(params, h, a_prev)[0]


def _conv_out(config: LearnerConfig, resolution: int) -> int:
    """Width of the flattened conv stack output."""
    return (resolution // 2 ** len(config.conv_features)) ** 2 * config.conv_features[-1]


@dataclasses.dataclass(frozen=True)
class SVAE(SequentialVAE):
    """Sequential VAE: conv stack -> LSTM(hidden) over [conv features_t, a_{t-1}] -> z_t -> deconv.

    The prior of every z_t is N(0, I); the LSTM makes each z_t depend on frames 1..t and actions
    a_1..a_{t-1}, so reconstructions are conditioned on the actions.
    """

    @property
    def _conv(self) -> FrameFeatures:
        c = self.config
        return FrameFeatures(c.conv_features, 0, c.dtype, **c.conv_forms)  # conv output straight into the LSTM

    @property
    def _rnn(self) -> SequenceModel:
        return SequenceModel("lstm", self.config.hidden, unroll=self.config.rnn_unroll,
                             lstm_grad=self.config.lstm_grad)

    def _init_parts(self, key: jax.Array, resolution: int) -> dict[str, Any]:
        k1, k2, k3 = jax.random.split(key, 3)
        f = _conv_out(self.config, resolution)
        return {
            "conv": self._conv.init(k1, jnp.zeros((1, resolution, resolution, 3)))["params"],
            "rnn": self._rnn.init(k2, jnp.zeros((1, 2, f + self.action_dim)))["params"],
            "head": GaussianHead(self.latent_dim).init(k3, jnp.zeros((1, self.config.hidden)))["params"],
        }

    def _posterior_of_features(self, params: Any, h: jax.Array, a_prev: jax.Array
                               ) -> tuple[jax.Array, jax.Array]:
        o = self._rnn.apply({"params": params["rnn"]}, jnp.concatenate([h, a_prev], -1))
        return GaussianHead(self.latent_dim).apply({"params": params["head"]}, o)


class _PredictiveHead(nn.Module):
    """Aggregated window features [B, F] -> FC(hidden) x2 -> chunked Gaussian [B, chunks, Z] x2."""

    hidden: int
    chunks: int
    latent_dim: int

    @nn.compact
    def __call__(self, h: jax.Array) -> tuple[jax.Array, jax.Array]:
        for i in range(2):
            h = nn.relu(nn.Dense(self.hidden, name=f"fc{i}", kernel_init=lecun_normal_flat)(h))
        mean, logvar = GaussianHead(self.chunks * self.latent_dim, name="latent")(h)
        shape = (h.shape[0], self.chunks, self.latent_dim)
        return mean.reshape(shape), logvar.reshape(shape)


@dataclasses.dataclass(frozen=True)
class PRED(SequentialVAE):
    """Predictive VAE: conv stack (+FC) on each of frames 1..L, the L outputs and actions
    concatenated, two FC layers (hidden) to a latent of L + k chunks, each decoded by the deconv
    stack into frames 1..L+k (k = config.pred_horizon). Prior N(0, I) on every chunk."""

    @property
    def window_length(self) -> int:
        return self.sequence_length + self.config.pred_horizon

    @property
    def _conv(self) -> FrameFeatures:
        c = self.config
        return FrameFeatures(c.conv_features, c.hidden, c.dtype, **c.conv_forms)

    @property
    def _head(self) -> _PredictiveHead:
        return _PredictiveHead(self.config.hidden, self.window_length, self.latent_dim)

    def _init_parts(self, key: jax.Array, resolution: int) -> dict[str, Any]:
        k1, k2 = jax.random.split(key)
        agg = self.sequence_length * (self.config.hidden + self.action_dim)
        return {"conv": self._conv.init(k1, jnp.zeros((1, resolution, resolution, 3)))["params"],
                "head": self._head.init(k2, jnp.zeros((1, agg)))["params"]}

    def _posterior(self, params, x, a_prev):
        # only the L input frames are encoded (the loss's window also holds the k forecast frames)
        h = self._features(self._conv, params["conv"], x[:, : self.sequence_length])
        return self._posterior_of_features(params, h, a_prev)

    def _posterior_of_features(self, params, h, a_prev):
        l = self.sequence_length
        agg = jnp.concatenate([h[:, :l], a_prev[:, :l]], -1).reshape((h.shape[0], -1))
        return self._head.apply({"params": params["head"]}, agg)


@dataclasses.dataclass(frozen=True)
class DSA(SequentialVAE):
    """Disentangled Sequential Autoencoder (Li & Mandt, 2018), action-conditioned.

    q(f | x_1..T): sequence model over per-frame features, summarised, Gaussian head.
    q(z_t | x, f, a): sequence model over [features_t, a_{t-1}, f], Gaussian head per step.
    p(z_t | z_<t, a_<t): a causal LSTM over [z_{t-1}, a_{t-1}] with a Gaussian head (learned prior).
    p(f) = N(0, I); p(x_t | z_t, f): the deconv stack on [f, z_t].
    `config.dsa_encoder` picks the sequence model of both encoders (`lstm`, `bilstm` as in the
    paper's DSA, `gru`, `rnn`, `conv`, `fc`); the prior stays a causal LSTM.
    """

    hybrid_vmapped: ClassVar[bool] = True

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.latent_dim < 2:
            raise ValueError(f"dsa needs latent_dim >= 2 (static + dynamic parts), got {self.latent_dim}")

    @property
    def static_dim(self) -> int:
        return max(1, self.latent_dim // 4)

    @property
    def dynamic_dim(self) -> int:
        return self.latent_dim - self.static_dim

    @property
    def _conv(self) -> FrameFeatures:
        c = self.config
        return FrameFeatures(c.conv_features, c.hidden, c.dtype, **c.conv_forms)

    def _seq(self, kind: str | None = None) -> SequenceModel:
        return SequenceModel(kind or self.config.dsa_encoder, self.config.hidden, unroll=self.config.rnn_unroll,
                             lstm_grad=self.config.lstm_grad)

    def _init_parts(self, key: jax.Array, resolution: int) -> dict[str, Any]:
        ks = jax.random.split(key, 7)
        h, a, fd, zd = self.config.hidden, self.action_dim, self.static_dim, self.dynamic_dim
        seq_out = 2 * h if self.config.dsa_encoder == "bilstm" else h
        zeros = lambda *s: jnp.zeros(s, jnp.float32)  # noqa: E731
        return {
            "conv": self._conv.init(ks[0], zeros(1, resolution, resolution, 3))["params"],
            "static_seq": self._seq().init(ks[1], zeros(1, 2, h))["params"],
            "static_head": GaussianHead(fd).init(ks[2], zeros(1, seq_out))["params"],
            "dynamic_seq": self._seq().init(ks[3], zeros(1, 2, h + a + fd))["params"],
            "dynamic_head": GaussianHead(zd).init(ks[4], zeros(1, seq_out))["params"],
            "prior_seq": self._seq("lstm").init(ks[5], zeros(1, 2, zd + a))["params"],
            "prior_head": GaussianHead(zd).init(ks[6], zeros(1, h))["params"],
        }

    def _static(self, params: Any, h: jax.Array) -> tuple[jax.Array, jax.Array]:
        seq = self._seq()
        out = seq.apply({"params": params["static_seq"]}, h)
        return GaussianHead(self.static_dim).apply({"params": params["static_head"]}, seq.summary(out))

    def _dynamic(self, params: Any, h: jax.Array, a_prev: jax.Array, f: jax.Array
                 ) -> tuple[jax.Array, jax.Array]:
        fb = jnp.broadcast_to(f[:, None], h.shape[:2] + f.shape[-1:])
        out = self._seq().apply({"params": params["dynamic_seq"]}, jnp.concatenate([h, a_prev, fb], -1))
        return GaussianHead(self.dynamic_dim).apply({"params": params["dynamic_head"]}, out)

    def _prior(self, params: Any, z: jax.Array, a_prev: jax.Array) -> tuple[jax.Array, jax.Array]:
        z_prev = jnp.concatenate([jnp.zeros_like(z[:, :1]), z[:, :-1]], axis=1)
        out = self._seq("lstm").apply({"params": params["prior_seq"]}, jnp.concatenate([z_prev, a_prev], -1))
        mean, logvar = GaussianHead(self.dynamic_dim).apply({"params": params["prior_head"]}, out)
        return mean, jnp.clip(logvar, -8.0, 8.0)  # keeps exp(-logvar) in the KL finite

    @staticmethod
    def _join(f: jax.Array, z: jax.Array) -> jax.Array:
        return jnp.concatenate([jnp.broadcast_to(f[:, None], z.shape[:2] + f.shape[-1:]), z], -1)

    def _loss_parts(self, params, x, a_prev, key):
        k_f, k_z = jax.random.split(key)
        h = self._features(self._conv, params["conv"], x)
        f_mean, f_logvar = self._static(params, h)
        f = f_mean + jnp.exp(0.5 * f_logvar) * _normal(k_f, f_mean)
        z_mean, z_logvar = self._dynamic(params, h, a_prev, f)
        z = z_mean + jnp.exp(0.5 * z_logvar) * _normal(k_z, z_mean)
        p_mean, p_logvar = self._prior(params, z, a_prev)
        kl_z = _kl_normal(z_mean, z_logvar, p_mean, p_logvar)
        return self._join(f, z), kl_z, _kl_std_normal(f_mean, f_logvar)

    def _means_of_features(self, params, h, a_prev):
        f_mean, _ = self._static(params, h)
        z_mean, _ = self._dynamic(params, h, a_prev, f_mean)
        return self._join(f_mean, z_mean)


SEQUENTIAL_LEARNERS: dict[str, type[SequentialVAE]] = {"svae": SVAE, "pred": PRED, "dsa": DSA}
