"""Conv encoder and deconv decoder of the paper's VAE-based learners (sec. IV.A).

Encoder: len(features) conv layers (4x4, stride 2, ReLU; 64,64,128,256 filters by
default), a 512-unit FC layer, then two linear heads for the posterior mean and
log-variance. Decoder mirrors it: FC 512 -> FC to (R/16)x(R/16)x256 -> transposed convs
(4x4, stride 2) with 128,64,64 filters and ReLU, and a last one to 3 channels of logits.

The decoder's transposed convs have three exact implementations with the same parameters
(`DECONV_IMPLS`): `transpose` (flax's `ConvTranspose`: a convolution over a zero-dilated input),
`subpixel` (the same 4x4 stride-2 kernel rearranged into a 3x3 convolution with 4x the output
channels, then depth-to-space) and `dgrad` (the input-gradient of a 4x4 stride-2 convolution, with
the gradients of a convolution as its own gradients: the form PyTorch's `ConvTranspose2d` runs,
cuDNN's data-gradient kernels). They compute the same function; which is faster depends on the
device (XLA's dilated-input convolutions are slow on GPU in fp32): see `benchmarks/`.

Two more switches change how, not what, is computed (same parameters, same function;
`LearnerConfig.channel_pad`, `.bias_grad`): the frames' 3 colour channels padded with zero
channels to a multiple of `channel_pad` in the first convolution and in the decoder's last
(cuDNN's tensor-core kernels take channels in multiples of 8 and otherwise pad the tensors on
every call), and a bias gradient summed in two passes (`add_bias`). A third
(`LearnerConfig.edge_layers`) computes the first convolution and the decoder's last layer, the two
at full resolution, over 2x2 pixel blocks as 3x3 stride-1 convolutions (`blocked_conv_down`).

Encoder and decoder are separate modules so the sequential learners can reuse them (with their
temporal models, `temporal.py`). Params are
always float32; `dtype` sets the compute dtype of the conv/FC stacks. The posterior
heads run in float32 (they are tiny and their output is what the probes see), and all
outputs are float32.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from bulbjax.learners.kernels import column_sum, masked_column_sum

DEFAULT_FEATURES: tuple[int, ...] = (64, 64, 128, 256)

# Std of a standard normal truncated to [-2, 2]; dividing by it gives unit variance.
_TRUNC_STD = 0.87962566103423978


def lecun_normal_flat(key: jax.Array, shape: Sequence[int], dtype: Any = jnp.float32) -> jax.Array:
    """Flax's default kernel init (LeCun truncated normal, fan_in = prod(shape[:-1])).

    Same distribution as `nn.initializers.lecun_normal()`, but drawn as a flat vector and
    reshaped: with jax_threefry_partitionable (the default), XLA:CPU takes seconds to
    compile each multi-dimensional random draw, which made init take ~40 s on CPU.
    """
    fan_in = math.prod(shape[:-1])
    std = math.sqrt(1.0 / fan_in) / _TRUNC_STD
    flat = jax.random.truncated_normal(key, -2.0, 2.0, (math.prod(shape),), jnp.float32)
    return (flat * std).reshape(shape).astype(dtype)


def check_frame_shape(
    frame_shape: Sequence[int], num_layers: int = len(DEFAULT_FEATURES), channels: int = 3
) -> int:
    """Return the resolution R of frames shaped (R, R, channels), or raise ValueError.

    Each conv layer halves the resolution, so R must be a positive multiple of
    2**num_layers (16 for the default 4 layers).
    """
    if any(isinstance(d, jax.core.Tracer) for d in frame_shape):
        raise TypeError(
            "frame_shape must be a static tuple of ints, not traced values: bind it with "
            "functools.partial(learner.init, frame_shape=...) before jit/vmap/eval_shape"
        )
    shape = tuple(int(d) for d in frame_shape)
    step = 2**num_layers
    ok = len(shape) == 3 and shape[0] == shape[1] and shape[2] == channels and shape[0] > 0
    ok = ok and shape[0] % step == 0
    if not ok:
        raise ValueError(
            f"frames must have shape (R, R, {channels}) per frame: square with R a positive "
            f"multiple of {step} ({num_layers} stride-2 conv layers; R=64 is the default); "
            f"got frame shape {shape}"
        )
    return shape[0]


_NHWC = ("NHWC", "HWIO", "NHWC")  # the convolution layouts of the encoder and decoder forms
BIAS_GRADS: tuple[str, ...] = ("reduce", "split", "split_apart", "pallas", "pallas_relu")  # add_bias
# How the first conv and the decoder's last layer (the two at full resolution with 3 channels)
# are computed: "strided" (4x4 stride-2 convolutions over pixels) or "blocked" (the same kernels
# rearranged into 3x3 stride-1 convolutions over 2x2 pixel blocks; `blocked_conv_down`).
EDGE_LAYERS: tuple[str, ...] = ("strided", "blocked")


def pad_axis(x: jax.Array, axis: int, multiple: int) -> jax.Array:
    """`x` with zeros appended along `axis` up to a multiple of `multiple` (unchanged if it is one)."""
    extra = -x.shape[axis] % multiple
    if extra == 0:
        return x
    widths = [(0, 0)] * x.ndim
    widths[axis] = (0, extra)
    return jnp.pad(x, widths)


def _bias_sum(g: jax.Array, form: str = "split") -> jax.Array:
    """sum of `g [B, ..., C]` over all but its last axis, in two passes: over the batch axis
    first (a reduction that keeps the H*W*C other entries, wide enough for the GPU's
    column-reduction kernels), then over the rest. In one pass, XLA keeps only C columns and
    runs slowly where C is small (3 for the decoder's output). The barrier stops XLA merging
    the two back into one. `form` ("split", "split_apart", "pallas"; `add_bias`): the first pass
    as one XLA reduction fused with what made `g` (a ReLU's mask), the same after a barrier that
    has `g` written by a kernel of its own, or as `kernels.column_sum`."""
    if form in ("pallas", "pallas_relu"):  # the latter where no ReLU follows (`bias_relu`)
        first = column_sum(g.reshape(g.shape[0], -1))
    else:
        if form == "split_apart":
            g = jax.lax.optimization_barrier(g)
        first = jax.lax.optimization_barrier(g.reshape(g.shape[0], -1).sum(0, dtype=jnp.float32))
    return first.reshape(-1, g.shape[-1]).sum(0)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _add_bias_two_pass(h: jax.Array, b: jax.Array, form: str) -> jax.Array:
    return h + b


def _add_bias_two_pass_fwd(h: jax.Array, b: jax.Array, form: str) -> tuple[jax.Array, None]:
    return h + b, None


def _add_bias_two_pass_bwd(form: str, _: None, g: jax.Array) -> tuple[jax.Array, jax.Array]:
    return g, _bias_sum(g, form).astype(g.dtype)


_add_bias_two_pass.defvjp(_add_bias_two_pass_fwd, _add_bias_two_pass_bwd)


def add_bias(h: jax.Array, b: jax.Array, grad: str = "reduce") -> jax.Array:
    """`h + b` (b over the last axis); `grad` picks how the bias gradient is summed: "reduce"
    (autodiff's one reduction), "split" (`_bias_sum`, two passes), "split_apart" (the same with
    the incoming gradient written by a kernel of its own first) or "pallas" (its first pass a
    Pallas kernel, `kernels.column_sum`; "pallas_relu" the same here, see `bias_relu`). Same
    values, summed in other orders."""
    if grad not in BIAS_GRADS:
        raise ValueError(f"unknown bias_grad {grad!r}; accepted: {', '.join(BIAS_GRADS)}")
    b = b.astype(h.dtype)
    return h + b if grad == "reduce" else _add_bias_two_pass(h, b, grad)


@jax.custom_vjp
def _bias_relu_fused(h: jax.Array, b: jax.Array) -> jax.Array:
    return jax.nn.relu(h + b)


def _bias_relu_fused_fwd(h: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    y = jax.nn.relu(h + b)
    return y, y


def _bias_relu_fused_bwd(y: jax.Array, g: jax.Array) -> tuple[jax.Array, jax.Array]:
    gx, first = masked_column_sum(g.reshape(g.shape[0], -1), y.reshape(y.shape[0], -1))
    return gx.reshape(g.shape), first.reshape(-1, g.shape[-1]).sum(0).astype(g.dtype)


_bias_relu_fused.defvjp(_bias_relu_fused_fwd, _bias_relu_fused_bwd)


def bias_relu(h: jax.Array, b: jax.Array, grad: str = "reduce", relu: bool = True) -> jax.Array:
    """`relu(h + b)`, a conv layer's bias and activation (`h + b` alone where `relu` is False);
    `grad` as `add_bias` says, and with "pallas_relu" the ReLU's backward mask and the bias
    gradient's first pass in one Pallas kernel (`kernels.masked_column_sum`). Same values."""
    if not relu:
        return add_bias(h, b, grad)
    if grad == "pallas_relu":
        return _bias_relu_fused(h, b.astype(h.dtype))
    return nn.relu(add_bias(h, b, grad))


def _conv_down(u: jax.Array, w: jax.Array) -> jax.Array:
    """4x4 stride-2 'SAME' convolution [B, 2H, 2W, Cout] -> [B, H, W, Cin], w [4, 4, Cout, Cin]."""
    return jax.lax.conv_general_dilated(u, w, (2, 2), ((1, 1), (1, 1)), dimension_numbers=_NHWC)


class Conv4x4(nn.Module):
    """`nn.Conv(features, (4, 4), strides=(2, 2), padding="SAME")` on inputs of even size, with
    the same parameters (`kernel [4, 4, in, features]`, `bias [features]`, same init and names):
    the encoder's layer. Input channels are zero-padded (with zero kernel rows) to a multiple of
    `channel_pad`, and the bias gradient is summed as `bias_grad` says; neither changes the
    function."""

    features: int
    dtype: jnp.dtype = jnp.float32
    channel_pad: int = 1
    bias_grad: str = "reduce"
    blocked: bool = False  # compute it as a 3x3 convolution over 2x2 pixel blocks (see below)
    relu: bool = False  # its ReLU too (`bias_relu`: with bias_grad "pallas_relu", one backward kernel)

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        kernel = self.param("kernel", lecun_normal_flat, (4, 4, x.shape[-1], self.features), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
        if self.blocked:
            y = blocked_conv_down(x.astype(self.dtype), kernel, self.channel_pad)
        else:
            x = pad_axis(x.astype(self.dtype), -1, self.channel_pad)
            y = _conv_down(x, pad_axis(kernel, 2, self.channel_pad).astype(self.dtype))
        return bias_relu(y, bias, self.bias_grad, self.relu)


def space_to_depth(x: jax.Array) -> jax.Array:
    """[B, 2H, 2W, C] -> [B, H, W, 4C]: each 2x2 pixel block as one position, channels ordered
    (row phase, column phase, channel)."""
    b, h, w, c = x.shape
    x = x.reshape(b, h // 2, 2, w // 2, 2, c).transpose(0, 1, 3, 2, 4, 5)
    return x.reshape(b, h // 2, w // 2, 4 * c)


def depth_to_space(y: jax.Array) -> jax.Array:
    """The inverse of `space_to_depth`: [B, H, W, 4C] -> [B, 2H, 2W, C]."""
    b, h, w, c4 = y.shape
    y = y.reshape(b, h, w, 2, 2, c4 // 4).transpose(0, 1, 3, 2, 4, 5)
    return y.reshape(b, 2 * h, 2 * w, c4 // 4)


# A 4x4 stride-2 convolution with padding 1 reads, for output i, input rows 2i-1 .. 2i+2, i.e.
# row phase p of pixel block i+d-1 for d = 0, 1, 2 with tap 2(d-1)+p+1. _BLOCK_TAPS[p][d] is that
# tap, -1 where it falls outside the 4-wide kernel.
_BLOCK_TAPS: tuple[tuple[int, ...], ...] = ((-1, 1, 3), (0, 2, -1))


def blocked_kernel(kernel: jax.Array) -> jax.Array:
    """A 4x4 stride-2 kernel [4, 4, C, F] as the 3x3 stride-1 kernel [3, 3, 4C, F] over 2x2
    pixel blocks (`space_to_depth` channel order) that computes the same convolution."""
    sel = jnp.asarray([[[1.0 if t == tap else 0.0 for t in range(4)] for tap in row]
                       for row in _BLOCK_TAPS], kernel.dtype)
    k3 = jnp.einsum("pat,qbs,tscf->abpqcf", sel, sel, kernel)
    return k3.reshape(3, 3, 4 * kernel.shape[2], kernel.shape[3])


def blocked_conv_down(x: jax.Array, kernel: jax.Array, channel_pad: int = 1) -> jax.Array:
    """`_conv_down(x, kernel)` ([B, 2H, 2W, C] -> [B, H, W, F], 4x4 stride 2, padding 1) computed
    as a 3x3 stride-1 convolution over 2x2 pixel blocks, the block channels zero-padded to a
    multiple of `channel_pad`. Where C is small (3 colours) this runs as an ordinary
    tensor-core convolution instead of a strided one over a few channels; same function."""
    xb = pad_axis(space_to_depth(x), -1, channel_pad)
    w = pad_axis(blocked_kernel(kernel), 2, channel_pad).astype(x.dtype)
    return jax.lax.conv_general_dilated(xb, w, (1, 1), ((1, 1), (1, 1)), dimension_numbers=_NHWC)


def check_edge_layers(edge_layers: str) -> None:
    """Refuse an `edge_layers` value that is not one of `EDGE_LAYERS`, naming the accepted ones."""
    if edge_layers not in EDGE_LAYERS:
        raise ValueError(f"unknown edge_layers {edge_layers!r}; accepted: {', '.join(EDGE_LAYERS)}")


def conv_layers(x: jax.Array, features: tuple[int, ...], dtype: jnp.dtype, channel_pad: int = 1,
                bias_grad: str = "reduce", edge_layers: str = "strided") -> jax.Array:
    """The shared conv stack, flattened: frames [B, R, R, 3] -> [B, (R/2^n)^2 * features[-1]].

    Call it inside a module's `nn.compact` method: the layers become that module's
    submodules `conv0..conv{n-1}` (so every learner's conv params are laid out alike).
    `edge_layers="blocked"` computes the first layer over 2x2 pixel blocks (same function).
    """
    check_frame_shape(x.shape[1:], len(features))
    check_edge_layers(edge_layers)
    h = x.astype(dtype)
    for i, f in enumerate(features):
        blocked = i == 0 and edge_layers == "blocked"
        h = Conv4x4(f, dtype, channel_pad, bias_grad, blocked, relu=True, name=f"conv{i}")(h)
    return h.reshape((h.shape[0], -1))


class ConvEncoder(nn.Module):
    """Frames [B, R, R, 3] in [0, 1] -> (mean, logvar), each [B, latent_dim] float32."""

    latent_dim: int
    features: tuple[int, ...] = DEFAULT_FEATURES
    hidden: int = 512
    dtype: jnp.dtype = jnp.float32
    channel_pad: int = 1  # see Conv4x4
    bias_grad: str = "reduce"
    edge_layers: str = "strided"  # see conv_layers

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        h = conv_layers(x, self.features, self.dtype, self.channel_pad, self.bias_grad, self.edge_layers)
        dense = dict(param_dtype=jnp.float32, kernel_init=lecun_normal_flat)
        h = nn.relu(nn.Dense(self.hidden, dtype=self.dtype, name="fc", **dense)(h))
        h = h.astype(jnp.float32)
        mean = nn.Dense(self.latent_dim, name="mean", **dense)(h)
        logvar = nn.Dense(self.latent_dim, name="logvar", **dense)(h)
        return mean, logvar


DECONV_IMPLS: tuple[str, ...] = ("transpose", "subpixel", "dgrad")

# For a 4x4 stride-2 'SAME' transposed conv (lax.conv_transpose pads the 2x-dilated input by 2
# on each side): output 2i+0 reads input i-1 with tap 0 and i with tap 2; output 2i+1 reads i
# with tap 1 and i+1 with tap 3. _PHASE_TAPS[p][d] is the tap that output phase p applies to
# input offset d-1 (d = 0, 1, 2 of a 3-wide window), -1 where none.
_PHASE_TAPS: tuple[tuple[int, ...], ...] = ((0, 2, -1), (-1, 1, 3))


def _phase_selector() -> jax.Array:
    """[2 phases, 3 offsets, 4 taps] one-hot: which tap of the 4-wide kernel each phase applies
    at each offset of the 3-wide window."""
    sel = [[[1.0 if t == tap else 0.0 for t in range(4)] for tap in row] for row in _PHASE_TAPS]
    return jnp.asarray(sel, jnp.float32)


class _Deconv4x4(nn.Module):
    """The parameters of `nn.ConvTranspose(features, (4, 4), strides=(2, 2), padding="SAME")`
    (`kernel [4, 4, in, features]`, `bias [features]`, same init), shared by the forms below so
    that every form reads the same checkpoint."""

    features: int
    dtype: jnp.dtype = jnp.float32
    param_dtype: jnp.dtype = jnp.float32
    kernel_init: Any = lecun_normal_flat
    channel_pad: int = 1  # output channels padded to a multiple of this (see Conv4x4)
    bias_grad: str = "reduce"  # see add_bias
    relu: bool = False  # its ReLU too (see Conv4x4)

    def kernel_and_bias(self, cin: int) -> tuple[jax.Array, jax.Array]:
        kernel = self.param("kernel", self.kernel_init, (4, 4, cin, self.features), self.param_dtype)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), self.param_dtype)
        return kernel, bias


class SubpixelConvTranspose(_Deconv4x4):
    """`nn.ConvTranspose(features, (4, 4), strides=(2, 2), padding="SAME")` computed as a 3x3
    stride-1 convolution to 4 * features channels followed by depth-to-space. Same parameters and
    the same function, so the forms are interchangeable; this one avoids convolutions over
    zero-dilated inputs."""

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        cin = x.shape[-1]
        kernel, bias = self.kernel_and_bias(cin)
        sel = _phase_selector()
        # k3[dy, dx, c, py, px, f] = kernel[tap(py, dy), tap(px, dx), c, f] (0 where no tap)
        k3 = jnp.einsum("pat,qbs,tscf->abcpqf", sel, sel, kernel)
        k3 = k3.reshape((3, 3, cin, 4 * self.features))
        k3 = pad_axis(k3, 3, self.channel_pad).astype(self.dtype)  # zero channels, cut below
        y = jax.lax.conv_general_dilated(x.astype(self.dtype), k3, (1, 1), "SAME",
                                         dimension_numbers=_NHWC)
        y = depth_to_space(y[..., : 4 * self.features])
        return bias_relu(y, bias, self.bias_grad, self.relu)


@jax.custom_vjp
def conv_up(x: jax.Array, w: jax.Array) -> jax.Array:
    """The transpose of `_conv_down(., w)`: [B, H, W, Cin] -> [B, 2H, 2W, Cout]. Forward and both
    gradients are the three patterns of an ordinary convolution's autodiff (data gradient, forward,
    filter gradient), which XLA hands to cuDNN's kernels for them."""
    b, h, wd, _ = x.shape
    u = jax.ShapeDtypeStruct((b, 2 * h, 2 * wd, w.shape[2]), x.dtype)
    (y,) = jax.linear_transpose(lambda v: _conv_down(v, w), u)(x)
    return y


def _conv_up_fwd(x: jax.Array, w: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    return conv_up(x, w), (x, w)


def _conv_up_bwd(res: tuple[jax.Array, jax.Array], g: jax.Array) -> tuple[jax.Array, jax.Array]:
    # y = A_w^T x with A_w = _conv_down(., w): dx = A_w g, and <g, A_w^T x> = <A_w g, x> gives dw
    # as the filter gradient of _conv_down at input g with output cotangent x.
    x, w = res
    _, vjp_w = jax.vjp(lambda v: _conv_down(g, v), w)
    return _conv_down(g, w), vjp_w(x)[0]


conv_up.defvjp(_conv_up_fwd, _conv_up_bwd)


class DgradConvTranspose(_Deconv4x4):
    """`nn.ConvTranspose(features, (4, 4), strides=(2, 2), padding="SAME")` computed as `conv_up`,
    the input-gradient of a stride-2 convolution whose kernel is this one flipped in space with
    its channel axes swapped. Same parameters and the same function as the other forms."""

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        kernel, bias = self.kernel_and_bias(x.shape[-1])
        # flax's output 2i+a reads input j with tap 2j-(2i+a)+2; the transpose of the stride-2
        # conv (padding 1) reads it with tap (2i+a)-2j+1 = 3 - that: the kernel flipped in space.
        w = jnp.flip(kernel, (0, 1)).swapaxes(2, 3)
        w = pad_axis(w, 2, self.channel_pad).astype(self.dtype)  # zero output channels, cut below
        y = conv_up(x.astype(self.dtype), w)[..., : self.features]
        return bias_relu(y, bias, self.bias_grad, self.relu)


class DeconvDecoder(nn.Module):
    """Latents [B, latent_dim] -> pixel logits [B, R, R, 3] float32 (sigmoid gives [0, 1]).

    `features` are the encoder's conv features; the decoder walks them in reverse.
    """

    resolution: int = 64
    features: tuple[int, ...] = DEFAULT_FEATURES
    hidden: int = 512
    channels: int = 3
    dtype: jnp.dtype = jnp.float32
    impl: str = "transpose"  # one of DECONV_IMPLS (same parameters, same function)
    channel_pad: int = 1  # output channels padded to a multiple of this ("dgrad" form; see Conv4x4)
    bias_grad: str = "reduce"  # see add_bias ("subpixel" and "dgrad" forms)
    # "blocked": the last layer as a 3x3 convolution to 2x2 pixel blocks (the sub-pixel form,
    # the transpose of `blocked_conv_down`) whatever `impl`; "strided": as `impl` says.
    edge_layers: str = "strided"

    @nn.compact
    def __call__(self, z: jax.Array) -> jax.Array:
        if self.impl not in DECONV_IMPLS:
            raise ValueError(f"unknown deconv impl {self.impl!r}; accepted: {', '.join(DECONV_IMPLS)}")
        check_edge_layers(self.edge_layers)
        check_frame_shape(
            (self.resolution, self.resolution, self.channels), len(self.features), self.channels
        )
        start = self.resolution // 2 ** len(self.features)
        dense = dict(dtype=self.dtype, param_dtype=jnp.float32, kernel_init=lecun_normal_flat)
        h = nn.relu(nn.Dense(self.hidden, name="fc", **dense)(z.astype(self.dtype)))
        h = nn.relu(nn.Dense(start * start * self.features[-1], name="fc_grid", **dense)(h))
        h = h.reshape((h.shape[0], start, start, self.features[-1]))
        out_features = (*reversed(self.features[:-1]), self.channels)
        for i, f in enumerate(out_features):
            last = i == len(out_features) - 1
            if self.impl == "subpixel" or (last and self.edge_layers == "blocked"):
                pad = self.channel_pad if last else 1
                h = SubpixelConvTranspose(f, name=f"deconv{i}", channel_pad=pad,
                                          bias_grad=self.bias_grad, relu=not last, **dense)(h)
            elif self.impl == "dgrad":
                h = DgradConvTranspose(f, name=f"deconv{i}", channel_pad=self.channel_pad,
                                       bias_grad=self.bias_grad, relu=not last, **dense)(h)
            else:
                h = nn.ConvTranspose(
                    f, (4, 4), strides=(2, 2), padding="SAME", name=f"deconv{i}", **dense
                )(h)
                h = h if last else nn.relu(h)
        return h.astype(jnp.float32)


class FrameFeatures(nn.Module):
    """Per-frame features of the sequential learners: frames [B, R, R, 3] in [0, 1] -> [B, F].

    `hidden=0` returns the flattened conv stack output (SVAE feeds it straight to its LSTM,
    as the paper says); otherwise an FC layer of `hidden` units with ReLU follows, as in
    the frame VAEs' encoder. Output float32.
    """

    features: tuple[int, ...] = DEFAULT_FEATURES
    hidden: int = 512
    dtype: jnp.dtype = jnp.float32
    channel_pad: int = 1  # see Conv4x4
    bias_grad: str = "reduce"
    edge_layers: str = "strided"  # see conv_layers

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        h = conv_layers(x, self.features, self.dtype, self.channel_pad, self.bias_grad, self.edge_layers)
        if self.hidden:
            dense = dict(dtype=self.dtype, param_dtype=jnp.float32, kernel_init=lecun_normal_flat)
            h = nn.relu(nn.Dense(self.hidden, name="fc", **dense)(h))
        return h.astype(jnp.float32)


class GaussianHead(nn.Module):
    """Features [..., F] -> (mean, logvar), each [..., latent_dim] float32 (two linear maps)."""

    latent_dim: int

    @nn.compact
    def __call__(self, h: jax.Array) -> tuple[jax.Array, jax.Array]:
        dense = dict(param_dtype=jnp.float32, kernel_init=lecun_normal_flat)
        h = h.astype(jnp.float32)
        return (nn.Dense(self.latent_dim, name="mean", **dense)(h),
                nn.Dense(self.latent_dim, name="logvar", **dense)(h))
