"""Temporal models of the sequential learners over per-step frame features [B, L, F]
(`SequenceModel`: LSTMs, a bidirectional LSTM, GRU, RNN, temporal convs, per-step dense; DSA's
variants), and the LSTM recurrence they run (`lstm_scan`): the input projection of all steps as
one matmul before the loop, the recurrence with a written-out backward pass.

The LSTMs compute flax's `nn.RNN(nn.OptimizedLSTMCell)` with the same parameters, names and init
(`LSTMWeights`), so params saved by either load in the other. Params are float32.
"""

from __future__ import annotations

from functools import partial

import flax.linen as nn
import jax
import jax.numpy as jnp

from bulbjax.learners.networks import lecun_normal_flat

LSTM_GRADS: tuple[str, ...] = ("written", "autodiff")  # SequenceModel.lstm_grad

# Temporal models a sequential learner can put over per-frame features (DSA's variants).
SEQUENCE_MODELS: tuple[str, ...] = ("lstm", "bilstm", "gru", "rnn", "conv", "fc")


class _GateParams(nn.Module):
    """One gate's dense weights of an LSTM, created as flax's `OptimizedLSTMCell` creates them
    (same names, shapes, init and RNG path): `kernel [in, hidden]` and, for the recurrent
    half, `bias [hidden]`."""

    features: int
    use_bias: bool

    @nn.compact
    def __call__(self, in_features: int) -> tuple[jax.Array, jax.Array | None]:
        kernel = self.param("kernel", lecun_normal_flat, (in_features, self.features), jnp.float32)
        bias = (self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
                if self.use_bias else None)
        return kernel, bias


class LSTMWeights(nn.Module):
    """An LSTM's weights with `nn.OptimizedLSTMCell`'s parameter layout (`ii, if, ig, io`
    input kernels, `hi, hf, hg, ho` recurrent kernels with the biases), returned fused:
    input kernel `[in, 4H]`, recurrent kernel `[H, 4H]`, bias `[4H]`, gates in i, f, g, o order.
    Named like the cell it replaces, so params saved by either load in the other."""

    hidden: int

    @nn.compact
    def __call__(self, in_features: int) -> tuple[jax.Array, jax.Array, jax.Array]:
        wi, wh, b = [], [], []
        for gate in "ifgo":
            wi.append(_GateParams(self.hidden, False, name=f"i{gate}")(in_features)[0])
            k, bias = _GateParams(self.hidden, True, name=f"h{gate}")(self.hidden)
            wh.append(k)
            b.append(bias)
        return jnp.concatenate(wi, -1), jnp.concatenate(wh, -1), jnp.concatenate(b, -1)


def _lstm_forward(xi: jax.Array, wh: jax.Array, unroll: int
                  ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The recurrence of `lstm_scan`, time-major: `xi [T, D, B, 4H]` -> hidden states, cell
    states `[T, D, B, H]` and gate activations `[T, D, B, 4H]` (sigmoid i, f, o; tanh g)."""
    _, d, b, four_h = xi.shape
    zeros = jnp.zeros((d, b, four_h // 4), xi.dtype)

    def step(carry: tuple[jax.Array, jax.Array], x_t: jax.Array):
        c, h = carry
        i, f, g, o = jnp.split(x_t + jnp.einsum("dbh,dhk->dbk", h, wh), 4, axis=-1)
        i, f, g, o = jax.nn.sigmoid(i), jax.nn.sigmoid(f), jnp.tanh(g), jax.nn.sigmoid(o)
        c = f * c + i * g
        h = o * jnp.tanh(c)
        return (c, h), (h, c, jnp.concatenate([i, f, g, o], -1))

    _, (hs, cs, acts) = jax.lax.scan(step, (zeros, zeros), xi, unroll=unroll)
    return hs, cs, acts


@partial(jax.custom_vjp, nondiff_argnums=(2,))
def _lstm_time_major(xi: jax.Array, wh: jax.Array, unroll: int) -> jax.Array:
    return _lstm_forward(xi, wh, unroll)[0]


def _lstm_time_major_fwd(xi: jax.Array, wh: jax.Array, unroll: int):
    hs, cs, acts = _lstm_forward(xi, wh, unroll)
    return hs, (hs, cs, acts, wh)


def _lstm_time_major_bwd(unroll: int, res: tuple[jax.Array, ...], g_hs: jax.Array):
    # Backward through time with only the recurrent matmul `dy_t @ W_h^T` left in the loop (one
    # elementwise fusion and one matmul per step); W_h's gradient, a sum over steps of
    # h_{t-1}^T dy_t, is one matmul over all steps after the loop instead of one per step.
    hs, cs, acts, wh = res
    zeros = jnp.zeros_like(hs[:1])
    c_prev = jnp.concatenate([zeros, cs[:-1]])
    h_prev = jnp.concatenate([zeros, hs[:-1]])

    def step(carry: tuple[jax.Array, jax.Array], xs: tuple[jax.Array, ...]):
        dh_next, dc_next = carry
        g_h, c, cp, a = xs
        i, f, g, o = jnp.split(a, 4, axis=-1)
        dh = g_h + dh_next
        tc = jnp.tanh(c)
        dc = dc_next + dh * o * (1.0 - tc * tc)
        dy = jnp.concatenate([dc * g * i * (1.0 - i), dc * cp * f * (1.0 - f),
                              dc * i * (1.0 - g * g), dh * tc * o * (1.0 - o)], -1)
        return (jnp.einsum("dbk,dhk->dbh", dy, wh), dc * f), dy

    carry0 = (jnp.zeros_like(hs[0]), jnp.zeros_like(cs[0]))
    _, dys = jax.lax.scan(step, carry0, (g_hs, cs, c_prev, acts), reverse=True, unroll=unroll)
    return dys, jnp.einsum("tdbh,tdbk->dhk", h_prev, dys)


_lstm_time_major.defvjp(_lstm_time_major_fwd, _lstm_time_major_bwd)


def lstm_scan(xi: jax.Array, wh: jax.Array, unroll: int = 1) -> jax.Array:
    """LSTM recurrence over input projections already computed for every step.

    `xi [D, B, T, 4H]` (x_t @ W_i + b for D independent LSTMs, e.g. the two directions of a
    bidirectional one, each already in its own time order), `wh [D, H, 4H]` -> hidden states
    `[D, B, T, H]` from a zero carry. Only `h @ W_h` stays inside the loop: the input projection,
    the large matmul, runs once over all steps outside it, and the D LSTMs share one loop. The
    gradient is written out (`_lstm_time_major_bwd`): autodiff's would also accumulate W_h's
    gradient step by step inside the backward loop. Same function and gradients.
    """
    hs = _lstm_time_major(jnp.moveaxis(xi, 2, 0), wh, unroll)
    return jnp.moveaxis(hs, 0, 2)


def lstm_scan_autodiff(xi: jax.Array, wh: jax.Array, unroll: int = 1) -> jax.Array:
    """`lstm_scan` with autodiff's gradient (the reference the written-out one is tested
    against, and the form the diagnostic `bench_lstm.py` compared it with; its answer is in
    benchmarks/diagnostics/README.md)."""
    return jnp.moveaxis(_lstm_forward(jnp.moveaxis(xi, 2, 0), wh, unroll)[0], 0, 2)


class SequenceModel(nn.Module):
    """Temporal layer over per-step features [B, L, F] -> [B, L, out] float32.

    `kind`: `lstm`, `gru`, `rnn` (unidirectional, causal; out = hidden), `bilstm` (forward and
    backward LSTMs concatenated; out = 2 * hidden), `conv` (two temporal convolutions of
    width 3; out = hidden), `fc` (a per-step dense layer, no mixing over time; out = hidden).
    Recurrent kernels use a scaled normal init, not the usual orthogonal one: QR inside a
    vmapped init hung XLA:CPU (see the PPO module).

    The LSTMs (`lstm`, `bilstm`) compute flax's `nn.RNN(nn.OptimizedLSTMCell)` with the same
    parameters (`lstm_scan`): the input projection of all steps as one matmul before the loop,
    and a bidirectional LSTM's two directions in one loop. That is the same function; it leaves
    the loop ~10x less work on SVAE's 4,097-wide input and DSA half the loop iterations.
    """

    kind: str = "lstm"
    hidden: int = 512
    # Steps of the recurrent scan unrolled per loop iteration: the same function; larger values
    # trade compile time for fewer loop iterations (each a small kernel group and, on the GPU, a
    # predicate copy), which is what a 24-step LSTM over ~42 windows is bound by. Ignored by
    # `conv` and `fc`.
    unroll: int = 1
    # The LSTMs' backward pass (`LSTM_GRADS`): "written" (`lstm_scan`) or "autodiff"
    # (`lstm_scan_autodiff`). Same function and gradients; the GRU and RNN use flax's cells.
    lstm_grad: str = "written"

    def _cell(self, kind: str) -> nn.RNNCellBase:
        inits = dict(kernel_init=lecun_normal_flat, recurrent_kernel_init=lecun_normal_flat)
        if kind == "gru":
            return nn.GRUCell(self.hidden, **inits)
        return nn.SimpleCell(self.hidden, **inits)

    def _lstms(self, x: jax.Array, directions: int) -> jax.Array:
        """`directions` LSTMs (1: forward; 2: forward and backward) over x [B, L, F] ->
        [B, L, directions * hidden]. Weights named `OptimizedLSTMCell_<d>` as the cells were."""
        ws = [LSTMWeights(self.hidden, name=f"OptimizedLSTMCell_{d}")(x.shape[-1])
              for d in range(directions)]
        xs = [x if d == 0 else jnp.flip(x, axis=1) for d in range(directions)]
        xi = jnp.stack([xx @ wi + b for xx, (wi, _, b) in zip(xs, ws)])
        if self.lstm_grad not in LSTM_GRADS:
            raise ValueError(f"unknown lstm_grad {self.lstm_grad!r}; accepted: {', '.join(LSTM_GRADS)}")
        scan = lstm_scan if self.lstm_grad == "written" else lstm_scan_autodiff
        hs = scan(xi, jnp.stack([wh for _, wh, _ in ws]), self.unroll)
        outs = [hs[0]] + ([jnp.flip(hs[1], axis=1)] if directions == 2 else [])
        return jnp.concatenate(outs, axis=-1)

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        if self.kind not in SEQUENCE_MODELS:
            raise ValueError(f"unknown sequence model {self.kind!r}; accepted: {', '.join(SEQUENCE_MODELS)}")
        x = x.astype(jnp.float32)
        if self.kind == "lstm":
            return self._lstms(x, 1)
        if self.kind == "bilstm":
            return self._lstms(x, 2)
        if self.kind in ("gru", "rnn"):
            return nn.RNN(self._cell(self.kind), unroll=self.unroll, name="rnn")(x)
        if self.kind == "conv":
            for i in range(2):
                x = nn.relu(nn.Conv(self.hidden, (3,), padding="SAME", name=f"tconv{i}",
                                    kernel_init=lecun_normal_flat)(x))
            return x
        return nn.relu(nn.Dense(self.hidden, name="fc", kernel_init=lecun_normal_flat)(x))

    def summary(self, out: jax.Array) -> jax.Array:
        """One vector per sequence [B, out] from `__call__`'s output: the last step's output for
        causal RNNs, the forward last and backward first outputs for `bilstm`, the mean over
        time for `conv`/`fc`. Pure function of `out` (no params)."""
        if self.kind in ("lstm", "gru", "rnn"):
            return out[:, -1]
        if self.kind == "bilstm":
            return jnp.concatenate([out[:, -1, : self.hidden], out[:, 0, self.hidden :]], axis=-1)
        return out.mean(axis=1)
