"""Common pieces of the learners: config, training state, the learner interface, NaN guard.

The learner interface. The experiment relies only on one of the two protocols below, so any
learner satisfying one can be registered (`bulbjax/learners/registry.py`) and trained, probed and
fed to PPO beside the paper's:
- `FrameLearner`: trains on single uint8 frames `[B, H, W, 3]`, one latent per frame;
- `SequenceLearner`: trains on `Windows` (`bulbjax/data/sequence.py`: frames `[B, T, H, W, 3]`,
  the actions into them `[B, T, A]`, true states, a `valid` mask that is False on padding after
  an episode's end), one latent per step.
Both are pure and jittable: a learner is an immutable (frozen dataclass) description, its
parameters and optimiser state live in `LearnerState`, randomness comes in as keys. Per epoch the
experiment calls `update` `ExperimentConfig.learner_batches` times per seed on batches it samples
(`batch_size` frames, or `batch_size` windows), and `encode` for the probes (on replay frames and
held-out windows) and, with `--rl-input latent:<name>`, for PPO's observations (no gradient flows
back into the learner). Everything runs under `jax.vmap` or `lax.map` over seeds.

The equal-compute rule (the paper, Sec. IV.A): every learner sees about the same number of frames
per update, `LearnerConfig.batch_size` (1,024). A frame learner's `batch_size` is that number; a
sequential one's is `batch_size // sequence_length` windows; a learner whose per-frame cost is
far higher says how it scales down and why (SPAIR: 64 frames). A learner that looks at two views
or two steps of each sample (contrastive ones) counts the frames it encodes.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from bulbjax.learners.networks import BIAS_GRADS, DECONV_IMPLS, EDGE_LAYERS
from bulbjax.learners.temporal import LSTM_GRADS

COMPUTE_DTYPES: tuple[str, ...] = ("float32", "bfloat16")
# DSA's encoder variants (the paper tried all of them); see temporal.SequenceModel.
DSA_ENCODERS: tuple[str, ...] = ("lstm", "bilstm", "gru", "rnn", "conv", "fc")
# LearnerConfig fields that say how the learners compute, not what (same parameters, same
# function, up to floating-point rounding): runs that differ only in them are one configuration
# (`config.computed_config`; e.g. seeds of one preset run before and after a default changed).
LEARNER_FORM_FIELDS: tuple[str, ...] = ("deconv_impl", "channel_pad", "bias_grad", "edge_layers",
                                        "rnn_unroll", "lstm_grad")


@dataclasses.dataclass(frozen=True)
class LearnerConfig:
    """Hyperparameters shared by the frame learners (defaults follow the paper, sec. IV.A).

    `batch_size` is what the caller should sample from replay per update; `update` itself
    trains on whatever batch it is given. `compute_dtype='bfloat16'` runs the conv stacks in
    bf16 (XLA's fp32 transposed convs are slow on GPU) while params, optimiser state and the
    loss stay float32. `retain_fraction` is the share of the initial replay content the
    learner asks the caller to keep for the whole run (VAE_rpl's replay of early frames).
    Sequential learners train on windows of `sequence_length` steps and take
    `batch_size // sequence_length` windows per batch (the paper's equalised compute).
    """

    lr: float = 1e-4
    batch_size: int = 1024
    beta: float = 1.0
    conv_features: tuple[int, ...] = (64, 64, 128, 256)
    hidden: int = 512
    compute_dtype: str = "float32"
    retain_fraction: float = 0.0
    # How the decoder's transposed convs are computed (networks.DECONV_IMPLS; same parameters,
    # same function): "transpose" (flax ConvTranspose), "subpixel" (3x3 conv + depth-to-space) or
    # "dgrad" (a stride-2 conv's input gradient, as PyTorch runs ConvTranspose2d; fastest on the
    # H100 and on the CPU, and the quickest to compile: docs/performance.md).
    deconv_impl: str = "dgrad"
    # How, not what, the conv stacks compute (same parameters, same function; networks.Conv4x4,
    # networks.add_bias): the frames' 3 colour channels padded with zero channels to a multiple of
    # `channel_pad` in the first conv and the decoder's last (1: none; 0: 8 in bf16, where cuDNN's
    # tensor-core kernels want multiples of 8, else 1), and the convs' bias gradients summed in one
    # reduction ("reduce"), in two passes ("split": faster on the H100 and on the CPU), or with
    # each layer's ReLU mask in one Pallas kernel ("pallas_relu": on an H200 the learners of the
    # locomotion epoch 4-8% faster, as XLA's own masked reductions are slower inside the update
    # than alone; also "split_apart" and "pallas"; networks.add_bias / bias_relu). "auto":
    # pallas_relu in bf16 on a GPU, split otherwise (on a CPU the Pallas kernel runs interpreted;
    # in float32 it is not measured). docs/performance.md, "Learner updates", has the figures.
    channel_pad: int = 0
    bias_grad: str = "auto"
    # The first conv and the decoder's last layer (full resolution, 3 colour channels) computed
    # over 2x2 pixel blocks as 3x3 stride-1 convolutions ("blocked") or as 4x4 stride-2 ones
    # ("strided"); same parameters, same function (networks.blocked_conv_down). "auto": blocked
    # in bf16 (10% faster VAE updates on the H100), strided in float32 (equal on the H100,
    # slower on the CPU); docs/performance.md, "Learner updates".
    edge_layers: str = "auto"
    # Sequential learners only (svae, pred, dsa); the frame learners ignore these.
    sequence_length: int = 24  # steps per window (paper: 24 pendulums, 16 locomotion)
    pred_horizon: int = 4  # PRED reconstructs sequence_length + pred_horizon frames
    dsa_encoder: str = "bilstm"  # DSA's static/dynamic encoders: one of DSA_ENCODERS
    rnn_unroll: int = 1  # recurrent steps per scan iteration (temporal.SequenceModel.unroll; same numbers)
    # The LSTMs' backward pass: "written" (temporal.lstm_scan: W_h's gradient as one matmul after
    # the loop; each LSTM's forward + backward 1.25-1.5x faster on the H100) or "autodiff" (JAX's
    # own); same function and gradients. A config.json written before the field reads "autodiff".
    lstm_grad: str = "written"
    # ST-DIM only (contrastive.py): 0, AtariARI's bilinear scores of the raw features (unbounded:
    # in 4 of 12 seeds of docs/results/fig2_contrastive_h200 the local-local loss grew from ~6 to
    # 10-360 nats after ~700 epochs); > 0, scores of L2-normalised vectors over this temperature
    # (cosine / T, bounded by 1/T). The other learners ignore it.
    stdim_temperature: float = 0.0
    # SPAIR only (spair/); the other learners ignore these. Defaults follow the original
    # (Crawford & Pineau 2019) where it says, and the bulb paper (28 px glimpses, 4x4 grid).
    spair_grid: int = 4  # G: cells per side of the grid (paper: 4 or 6)
    spair_glimpse: int = 28  # side in pixels of the glimpse an object encoder sees
    spair_what_dim: int = 50  # z_what (appearance) size per cell; the original's A=50
    spair_bg_dim: int = 4  # latent size of the background VAE (kept small: a smooth backdrop)
    spair_count_odds_start: float = 1e6  # prior odds of "object in a cell": start of annealing,
    spair_count_odds_end: float = 0.0125  # ... and end (original: 1e6 -> 0.0125)
    spair_count_decay_steps: int = 1000  # the odds' excess over the end shrinks x0.1 per this many updates
    spair_temperature: float = 1.0  # Concrete (relaxed Bernoulli) temperature of z_pres
    spair_training_wheels: int = 1000  # first updates: no gradient into the where/depth/pres heads
    spair_pixel_std: float = 0.15  # > 0: Gaussian likelihood with this std; 0: Bernoulli (the original's)

    def __post_init__(self) -> None:
        # Accept lists for conv_features but store a tuple, so the config stays hashable.
        object.__setattr__(self, "conv_features", tuple(int(f) for f in self.conv_features))
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr must be a positive finite number, got {self.lr!r}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size!r}")
        if not (math.isfinite(self.beta) and self.beta >= 0):
            raise ValueError(f"beta must be a finite number >= 0, got {self.beta!r}")
        if not self.conv_features or any(f < 1 for f in self.conv_features):
            raise ValueError(
                f"conv_features must be a non-empty tuple of positive ints, got {self.conv_features!r}"
            )
        if self.hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {self.hidden!r}")
        if self.compute_dtype not in COMPUTE_DTYPES:
            raise ValueError(
                f"compute_dtype must be one of {COMPUTE_DTYPES}, got {self.compute_dtype!r}"
            )
        if self.deconv_impl not in DECONV_IMPLS:
            raise ValueError(f"deconv_impl must be one of {DECONV_IMPLS}, got {self.deconv_impl!r}")
        if self.channel_pad < 0:
            raise ValueError(f"channel_pad must be >= 0 (1: no padding, 0: 8 in bf16 else 1), got {self.channel_pad!r}")
        if self.bias_grad not in ("auto", *BIAS_GRADS):
            raise ValueError(f"bias_grad must be one of {('auto', *BIAS_GRADS)}, got {self.bias_grad!r}")
        if self.edge_layers not in ("auto", *EDGE_LAYERS):
            raise ValueError(f"edge_layers must be one of {('auto', *EDGE_LAYERS)}, got {self.edge_layers!r}")
        if self.sequence_length < 2:
            raise ValueError(f"sequence_length must be >= 2, got {self.sequence_length!r}")
        if self.pred_horizon < 0:
            raise ValueError(f"pred_horizon must be >= 0, got {self.pred_horizon!r}")
        if self.rnn_unroll < 1:
            raise ValueError(f"rnn_unroll must be >= 1, got {self.rnn_unroll!r}")
        if self.lstm_grad not in LSTM_GRADS:
            raise ValueError(f"lstm_grad must be one of {LSTM_GRADS}, got {self.lstm_grad!r}")
        if self.dsa_encoder not in DSA_ENCODERS:
            raise ValueError(f"dsa_encoder must be one of {DSA_ENCODERS}, got {self.dsa_encoder!r}")
        if not (math.isfinite(self.stdim_temperature) and self.stdim_temperature >= 0):
            raise ValueError(f"stdim_temperature must be >= 0 (0: unnormalised scores), got {self.stdim_temperature!r}")
        for name in ("spair_grid", "spair_glimpse", "spair_what_dim", "spair_bg_dim",
                     "spair_count_decay_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if self.spair_training_wheels < 0:
            raise ValueError(f"spair_training_wheels must be >= 0, got {self.spair_training_wheels!r}")
        odds = (self.spair_count_odds_start, self.spair_count_odds_end)
        if not (all(math.isfinite(o) and o > 0 for o in odds) and odds[0] >= odds[1]):
            raise ValueError(f"spair count odds must be positive and finite with start >= end, got {odds!r}")
        if not (math.isfinite(self.spair_pixel_std) and self.spair_pixel_std >= 0):
            raise ValueError(f"spair_pixel_std must be >= 0, got {self.spair_pixel_std!r}")
        if not (math.isfinite(self.spair_temperature) and self.spair_temperature > 0):
            raise ValueError(f"spair_temperature must be > 0, got {self.spair_temperature!r}")
        if not 0.0 <= self.retain_fraction < 1.0:
            raise ValueError(f"retain_fraction must be in [0, 1), got {self.retain_fraction!r}")

    @property
    def dtype(self) -> jnp.dtype:
        """The compute dtype as a JAX dtype."""
        return jnp.dtype(self.compute_dtype)

    @property
    def conv_forms(self) -> dict[str, Any]:
        """Keyword arguments of the conv modules that pick their forms (`channel_pad` with its
        0 resolved: 8 in bf16, 1 in float32; `bias_grad` with "auto" resolved: pallas_relu in
        bf16 on a GPU, split otherwise; `edge_layers` with "auto" resolved: blocked in bf16,
        strided in float32). Read where the learner's modules are built, so "auto" follows the
        backend the program is traced for (`jax.default_backend()`)."""
        bf16 = self.compute_dtype == "bfloat16"
        pad = self.channel_pad or (8 if bf16 else 1)
        grad = self.bias_grad
        if grad == "auto":
            grad = "pallas_relu" if bf16 and jax.default_backend() == "gpu" else "split"
        edge = self.edge_layers if self.edge_layers != "auto" else ("blocked" if bf16 else "strided")
        return {"channel_pad": pad, "bias_grad": grad, "edge_layers": edge}


def parse_learner_options(items: Sequence[str]) -> dict[str, Any]:
    """`KEY=VALUE` strings (a command line's `--learner-option`s) -> `LearnerConfig` field values,
    each converted to the field's type (int, float, str, bool; tuples as comma-separated ints).
    An unknown key is a clear error naming the fields."""
    defaults = LearnerConfig()
    fields = {f.name for f in dataclasses.fields(LearnerConfig)}
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in fields:
            raise ValueError(f"learner option {item!r} must be KEY=VALUE with KEY one of: {', '.join(sorted(fields))}")
        default = getattr(defaults, key)
        try:
            if isinstance(default, bool):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError("not a boolean")
                out[key] = value.lower() in ("true", "1")
            elif isinstance(default, tuple):
                out[key] = tuple(int(v) for v in value.split(",") if v.strip())
            else:
                out[key] = type(default)(value)
        except ValueError as err:
            raise ValueError(f"learner option {item!r}: {value!r} is not a {type(default).__name__} ({err})") from None
    return out


@flax.struct.dataclass
class LearnerState:
    """Training state of one learner (one seed); a pytree, so it vmaps and scans.

    `step` is an int32 scalar counting updates.
    """

    params: Any
    opt_state: Any
    step: jax.Array


Metrics = dict[str, jax.Array]


@runtime_checkable
class FrameLearner(Protocol):
    """What the evaluation loop needs from a frame learner. All methods are pure and jittable.

    Required: the attributes and methods below; `sequential` is False or absent. Optional
    capabilities the experiment looks for: `reconstruct(params, frames) -> [B, H, W, 3]` float32
    in [0, 1] (the reconstruction figures; learners without it are left out of them), `update_key` (learners equal up to a
    traced keyword of `update` share one update program: vae, vae_rpl, beta_vae),
    `boxes_of_latents` (SPAIR's object probe)."""

    latent_dim: int
    config: LearnerConfig

    @property
    def retain_fraction(self) -> float:
        """Share of the initial replay content to keep for the whole run."""
        ...

    def init(self, key: jax.Array, frame_shape: tuple[int, int, int]) -> LearnerState:
        """Fresh params and optimiser state for frames of shape (H, W, 3)."""
        ...

    @property
    def batch_size(self) -> int:
        """Frames the caller samples from replay per update (the equal-compute rule above)."""
        ...

    def update(
        self, state: LearnerState, frames: jax.Array, key: jax.Array
    ) -> tuple[LearnerState, Metrics]:
        """One gradient step on uint8 frames [B, H, W, 3] (B = `batch_size`; any B must work);
        metrics are float32 scalars, `loss` among them (logged per epoch, NaN-checked)."""
        ...

    def encode(self, params: Any, frames: jax.Array) -> jax.Array:
        """Latents [B, latent_dim] float32 for uint8 frames [B, H, W, 3], deterministic (a VAE's
        posterior means): what the probes regress the state from and PPO may observe."""
        ...


def check_finite(metrics: Mapping[str, Any], where: str) -> None:
    """Host-side: raise FloatingPointError if any metric is NaN or infinite.

    Jitted code cannot raise on a NaN, so the loss travels out in `metrics`; call this on
    the fetched metrics (any leading seed/step axes are fine). `where` names the caller,
    e.g. "vae_rpl update, epoch 3", and is put in the message.
    """
    bad = []
    for name, value in metrics.items():
        arr = np.asarray(jax.device_get(value), dtype=np.float64)
        if not np.all(np.isfinite(arr)):
            bad.append(f"{name}={arr.tolist() if arr.size <= 8 else '<array with non-finite entries>'}")
    if bad:
        raise FloatingPointError(
            f"non-finite learner metrics in {where}: {', '.join(bad)}. "
            "The training diverged: lower the learning rate (LearnerConfig.lr), try "
            "compute_dtype='float32' if bf16 was used, and check that the input frames are "
            "valid uint8 images of the expected shape."
        )


@runtime_checkable
class SequenceLearner(Protocol):
    """What the evaluation loop needs from a sequential learner (svae, pred, dsa).

    Inputs are `Windows` (bulbjax.data.sequence) with at least `window_length` steps; longer
    windows are cut to the first `window_length`. Latents are per step: `encode` gives one
    latent per step of the first `sequence_length` steps, and the probe maps the latent at
    step t to the true state at step t (padded steps are left out via `Windows.valid`). The run
    stores windows of `ExperimentConfig.seq_len` steps (`sequence_length`, set from it), plus
    PRED's horizon when pred runs: a new sequential learner needs `window_length ==
    sequence_length`. Registered with `sequential=True` (registry.py) so that the run keeps
    window buffers. `--rl-input latent:<name>` also needs `frame_features(params, frames)` and
    `encode_features(params, features, actions)` (as `SequentialVAE` has).
    """

    latent_dim: int
    config: LearnerConfig
    action_dim: int
    sequential: bool  # True

    @property
    def window_length(self) -> int:
        """Steps a training window needs (PRED: sequence_length + pred_horizon)."""
        ...

    @property
    def sequence_length(self) -> int:
        """Steps per window whose latents `encode` gives (config.sequence_length)."""
        ...

    @property
    def batch_size(self) -> int:
        """Windows per batch: config.batch_size // sequence_length (the equal-compute rule)."""
        ...

    @property
    def retain_fraction(self) -> float: ...

    def init(self, key: jax.Array, frame_shape: tuple[int, int, int]) -> LearnerState: ...

    def update(self, state: LearnerState, windows: Any, key: jax.Array) -> tuple[LearnerState, Metrics]:
        """One gradient step on `batch_size` windows; metrics as `FrameLearner.update`'s."""
        ...

    def encode(self, params: Any, windows: Any) -> jax.Array:
        """Per-step latents [B, sequence_length, latent_dim] float32."""
        ...
