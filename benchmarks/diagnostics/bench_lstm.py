"""The sequential learners' LSTMs alone, forward + backward, as the epoch runs them (issue 13).

Why: a DSA update costs ~2x a frame VAE's on the H100 although its convolutions are the same;
the difference is three LSTM recurrences (two bidirectional) over 24 steps at ~42 windows, each
step a few small kernels in a row. This times one LSTM's forward and backward (gradients for the
input and the weights) in two forms with the same parameters and function:
- `scan`: `temporal.lstm_scan` (the input projection as one matmul, the recurrence in a
  `lax.scan` unrolled `--unrolls` steps, the backward pass written out with W_h's gradient as
  one matmul after the loop), what the learners run;
- `autodiff`: the same forward with autodiff's backward pass (`temporal.lstm_scan_autodiff`);
- `cudnn`: `jax.experimental.rnn.lstm`, cuDNN's RNN kernels (GPU only), the weights packed
  into cuDNN's flat layout by `cudnn_lstm_weights` below;
under `lax.map` over `--seeds` per-seed weight sets (the epoch's seed loop on one GPU), at the
shapes of SVAE's LSTM and DSA's three. It also reports the largest difference between the two
forms' outputs and gradients.

Imports `bulbjax.learners` without `bulbjax/__init__`, so it needs only jax and flax (no MuJoCo):

    python benchmarks/diagnostics/bench_lstm.py --out "$OUT"   # GPU
    python benchmarks/diagnostics/bench_lstm.py --small        # CPU smoke: the scan forms, the packing

Writes <out>/lstm_<device>_<stamp>.json and prints a table.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import types
from typing import Any, Callable

import jax
import jax.numpy as jnp
from jax.experimental import rnn

HERE = os.path.dirname(os.path.abspath(__file__))
BENCH = os.path.dirname(HERE)
ROOT = os.path.dirname(BENCH)
sys.path.insert(0, BENCH)
from timing import time_fn  # noqa: E402  (jax only)

if "bulbjax" not in sys.modules:  # the learners without bulbjax/__init__ (which imports MuJoCo)
    _pkg = types.ModuleType("bulbjax")
    _pkg.__path__ = [os.path.join(ROOT, "bulbjax")]
    sys.modules["bulbjax"] = _pkg
from bulbjax.learners import temporal  # noqa: E402

# (name, directions, input width) at fig2-invpend's sizes: hidden 512, action 1, latent 12 (DSA:
# static 3, dynamic 9); SVAE's LSTM reads the flattened conv stack (4 x 4 x 256) and the action.
CASES: tuple[tuple[str, int, int], ...] = (
    ("svae", 1, 4097),
    ("dsa_static", 2, 512),
    ("dsa_dynamic", 2, 516),
    ("dsa_prior", 1, 10),
)


def _weights(key: jax.Array, seeds: int, d: int, n_in: int, h: int) -> tuple[jax.Array, ...]:
    k1, k2, k3 = jax.random.split(key, 3)
    wi = jax.random.normal(k1, (seeds, d, n_in, 4 * h)) / jnp.sqrt(n_in)
    wh = jax.random.normal(k2, (seeds, d, h, 4 * h)) / jnp.sqrt(h)
    b = 0.1 * jax.random.normal(k3, (seeds, d, 4 * h))
    return wi, wh, b


def scan_form(unroll: int, scan: Callable | None = None) -> Callable:
    scan = scan or temporal.lstm_scan

    def run(x, wi, wh, b):
        xs = [x if i == 0 else jnp.flip(x, axis=1) for i in range(wi.shape[0])]
        xi = jnp.stack([xx @ wi[i] + b[i] for i, xx in enumerate(xs)])
        hs = scan(xi, wh, unroll)
        outs = [hs[0]] + ([jnp.flip(hs[1], axis=1)] if wi.shape[0] == 2 else [])
        return jnp.concatenate(outs, axis=-1)
    return run


def cudnn_lstm_weights(wi: jax.Array, wh: jax.Array, b: jax.Array) -> jax.Array:
    """Fused LSTM weights (`wi [D, in, 4H]`, `wh [D, H, 4H]`, `b [D, 4H]`, gates i, f, g, o; D = 1
    or the two directions of a bidirectional LSTM) in cuDNN's flat layout, as
    `jax.experimental.rnn` reads it: per direction `W_ih [4H, in]`, `W_hh [4H, H]`, then per
    direction `b_ih`, `b_hh` (ours is one bias, so `b_hh` is zero). Same gate order."""
    mats = [m for d in range(wi.shape[0]) for m in (wi[d].T, wh[d].T)]
    biases = [v for d in range(wi.shape[0]) for v in (b[d], jnp.zeros_like(b[d]))]
    return jnp.concatenate([m.reshape(-1) for m in mats + biases])


def cudnn_lstm(x: jax.Array, wi: jax.Array, wh: jax.Array, b: jax.Array) -> jax.Array:
    """One LSTM (D = 1) or a bidirectional one (D = 2) over `x [B, T, in]` from a zero carry with
    cuDNN's RNN kernels (`jax.experimental.rnn.lstm`, GPU only): `[B, T, D * H]`, the backward
    direction's outputs in the input's time order. Same function as `lstm_scan` over the
    projected inputs; the whole recurrence, forward and backward, is one cuDNN call each instead
    of a loop of small kernels per step."""
    d, n_in, four_h = wi.shape
    h_dim = four_h // 4
    batch, steps = x.shape[:2]
    zeros = jnp.zeros((d, batch, h_dim), jnp.float32)
    y, _, _ = rnn.lstm(x.astype(jnp.float32), zeros, zeros, cudnn_lstm_weights(wi, wh, b),
                       jnp.full((batch,), steps, jnp.int32), input_size=n_in, hidden_size=h_dim,
                       num_layers=1, dropout=0.0, bidirectional=d == 2)
    return y


def cudnn_layout_error(key: jax.Array, d: int, n_in: int = 7, h: int = 6) -> float:
    """Largest difference between `scan_form` and `jax.experimental.rnn.lstm_ref` (the pure-JAX
    reference of cuDNN's LSTM, any backend) on weights packed by `cudnn_lstm_weights`: checks
    the packing (layout, gate order) where cuDNN itself is not available."""
    x = jax.random.normal(key, (3, 5, n_in))
    wi, wh, b = (w[0] for w in _weights(key, 1, d, n_in, h))
    w_ih, w_hh, b_ih, b_hh = rnn.unpack_lstm_weights(cudnn_lstm_weights(wi, wh, b), n_in, h, 1, d == 2)
    zeros = jnp.zeros((d, 3, h))
    y, _, _ = rnn.lstm_ref(x, zeros, zeros, w_ih, w_hh, b_ih, b_hh, jnp.full((3,), 5, jnp.int32),
                           n_in, h, 1, 0.0, d == 2)
    return float(jnp.max(jnp.abs(y - scan_form(1)(x, wi, wh, b))))


def grad_fn(form: Callable) -> Callable:
    """Per seed: outputs and d(sum(y * r))/d(x, wi, wh, b), the seeds under `lax.map`."""
    def one(args):
        x, wi, wh, b, r = args
        y, vjp = jax.vjp(form, x, wi, wh, b)
        return (y, *vjp(r))
    return jax.jit(lambda *a: jax.lax.map(one, a))


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=6)
    p.add_argument("--batch", type=int, default=42, help="windows per update (1,024 // 24)")
    p.add_argument("--steps", type=int, default=24)
    p.add_argument("--hidden", type=int, default=512)
    p.add_argument("--unrolls", default="1,4,24")
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--small", action="store_true", help="CPU smoke sizes, scan form only")
    p.add_argument("--out", default=os.path.join(BENCH, "results"))
    a = p.parse_args(argv)
    if a.small:
        a.seeds, a.batch, a.steps, a.hidden, a.repeats = 2, 4, 6, 16, 2
    gpu = jax.default_backend() == "gpu"
    device = jax.devices()[0].device_kind
    rows: list[dict[str, Any]] = []
    key = jax.random.PRNGKey(0)
    layout = {d: cudnn_layout_error(key, d) for d in (1, 2)}
    print("cuDNN weight packing against lstm_ref, max abs difference (1 / 2 directions):",
          f"{layout[1]:.1e} / {layout[2]:.1e}")
    for name, d, n_in in CASES:
        if a.small:
            n_in = min(n_in, 24)
        kx, kw, kr, key = jax.random.split(key, 4)
        x = jax.random.normal(kx, (a.seeds, a.batch, a.steps, n_in))
        wi, wh, b = _weights(kw, a.seeds, d, n_in, a.hidden)
        r = jax.random.normal(kr, (a.seeds, a.batch, a.steps, d * a.hidden))
        args = (x, wi, wh, b, r)
        forms = {}
        for u in a.unrolls.split(","):
            forms[f"autodiff_u{u}"] = scan_form(int(u), temporal.lstm_scan_autodiff)
            forms[f"scan_u{u}"] = scan_form(int(u))
        if gpu:
            forms["cudnn"] = cudnn_lstm
        outs = {}
        for form_name, form in forms.items():
            f = grad_fn(form)
            t = time_fn(lambda f=f: f(*args), a.repeats)
            first, med = t["first_s"], t["median_s"]
            outs[form_name] = f(*args)
            row = {"case": name, "directions": d, "input": n_in, "form": form_name,
                   "first_s": first, "median_s": med, "ms_per_seed": 1e3 * med / a.seeds}
            ref = outs[next(iter(outs))]
            row["max_rel_diff_vs_first"] = max(
                float(jnp.max(jnp.abs(o - q)) / (jnp.max(jnp.abs(q)) + 1e-30))
                for o, q in zip(outs[form_name], ref))
            rows.append(row)
            print(f"{name:12s} D={d} in={n_in:5d} {form_name:8s} {row['ms_per_seed']:8.3f} ms/seed"
                  f"  (first call {first:6.2f} s)  max rel diff {row['max_rel_diff_vs_first']:.2e}",
                  flush=True)
    result = {"device": device, "cudnn_layout_error": layout, "seeds": a.seeds, "batch": a.batch, "steps": a.steps,
              "hidden": a.hidden, "jax": jax.__version__, "rows": rows}
    if not a.small:
        os.makedirs(a.out, exist_ok=True)
        stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
        tag = device.lower().replace(" ", "_")
        path = os.path.join(a.out, f"lstm_{tag}_{stamp}.json")
        with open(path, "w") as fh:
            json.dump(result, fh, indent=1)
        print("wrote", path)
    return result


if __name__ == "__main__":
    main()
