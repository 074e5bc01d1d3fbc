"""Does a Pallas kernel move the learners' ReLU-backward and bias-gradient pass at the card's
bandwidth, where XLA's fusions reach about a third of it? (issue 63)

Why: in a VAE update (bf16, batch 1,024, one H200: 2.9 ms) ~0.6 ms are reduction fusions: each
conv layer's ReLU mask applied to the incoming gradient, fused with the first pass of its bias
gradient (`networks._bias_sum`: a sum over the batch axis, then over the pixels). The two at full
resolution move ~200 MB each at ~1 TB/s (docs/performance.md, "Learner updates"). If a form below
runs near ~3 TB/s, the learners' updates lose ~0.3-0.4 ms each (~10%): its `bias_grad` option
(`networks.add_bias` / `bias_relu`) becomes the default. If none does, the options and this leave.

For each layer shape of the conv stack it times, inside one jitted loop of `--steps` dependent
iterations (so nothing is hoisted and no host dispatch is counted), the forms the learners can
run: XLA's mask with `networks._bias_sum` in its "split" (today's), "split_apart" and "pallas"
forms, and `kernels.masked_column_sum` ("pallas_relu") at several block sizes; besides them two
forms the learners do not have (the batch sum in 32-row blocks first; a Pallas kernel per column
block walking its rows). Each is checked against today's (the masked gradient exactly, the bias
gradient to f32 summation order) and its GB/s printed (reads of the gradient and the ReLU
output, the write of the masked gradient).

    python benchmarks/diagnostics/relu_bias_grad.py --out-dir "$OUT"         # GPU
    python benchmarks/diagnostics/relu_bias_grad.py --small   # CPU smoke (Pallas's interpret mode)
"""

from __future__ import annotations

import argparse
import datetime as dt
import functools
import json
import math
import os
import sys
import time
from typing import Any, Callable

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, REPO)

# The conv stack's ReLU'd layer outputs in a VAE update (batch 1,024, 64x64 frames, bf16): the
# encoder's four, the decoder's three before its last layer (which has no ReLU).
SHAPES = {"enc0 / dec2 (32x32x64)": (1024, 32, 32, 64),
          "enc1 / dec1 (16x16x64)": (1024, 16, 16, 64),
          "enc2 / dec0 (8x8x128)": (1024, 8, 8, 128), "enc3 (4x4x256)": (1024, 4, 4, 256)}
SMALL = {"small (8x8x16)": (64, 8, 8, 16)}


def _masked(g: Any, y: Any) -> Any:
    import jax.numpy as jnp

    return jnp.where(y > 0, g, jnp.zeros_like(g))


def bias_grad_form(form: str) -> Callable:
    """The masked gradient (XLA's, as a ReLU's autodiff gives it) and the bias gradient as
    `networks._bias_sum(., form)` sums it: "split" (today's default), "split_apart" (the masked
    gradient in a kernel of its own first), "pallas" (the batch sum as `kernels.column_sum`)."""
    from bulbjax.learners.networks import _bias_sum

    def form_(g: Any, y: Any) -> tuple[Any, Any]:
        gx = _masked(g, y)
        return gx, _bias_sum(gx, form)

    return form_


def xla_row_blocks(g: Any, y: Any, rows: int = 32) -> tuple[Any, Any]:
    """XLA's form with the batch sum taken in blocks of `rows` rows first ([B / rows, rows, N]
    summed over its middle axis), then over the blocks and the pixels."""
    import jax
    import jax.numpy as jnp

    b, c = g.shape[0], g.shape[-1]
    gx = _masked(g, y)
    part = gx.reshape(b // rows, rows, -1).sum(1, dtype=jnp.float32)
    part = jax.lax.optimization_barrier(part)
    return gx, part.sum(0).reshape(-1, c).sum(0)


def pallas_relu_form(g: Any, y: Any, rows: int, cols: int) -> tuple[Any, Any]:
    """The mask and the batch sum in one kernel (`kernels.masked_column_sum`, as
    `bias_grad="pallas_relu"` runs it) at `rows` x `cols` blocks of the [B, H*W*C] view."""
    from bulbjax.learners.kernels import masked_column_sum

    b, c = g.shape[0], g.shape[-1]
    gx, first = masked_column_sum(g.reshape(b, -1), y.reshape(b, -1), rows, cols)
    return gx.reshape(g.shape), first.reshape(-1, c).sum(0)


XLA_FORMS = {"xla": bias_grad_form("split"), "xla_two_kernels": bias_grad_form("split_apart"),
             "xla_row_blocks": xla_row_blocks, "pallas_sum": bias_grad_form("pallas")}


def pallas_loop_form(g: Any, y: Any, rows: int, cols: int) -> tuple[Any, Any]:
    """The same from a kernel whose program takes a whole column block ([B, cols]) and walks it
    `rows` rows at a time, its column sums held in f32 across the walk: no per-block partial
    sums written (the grid form writes B / rows of them)."""
    import jax
    import jax.numpy as jnp
    from jax.experimental import pallas as pl

    b, c = g.shape[0], g.shape[-1]
    n = math.prod(g.shape[1:])

    def kernel(g_ref, y_ref, gx_ref, sum_ref):
        def step(r, acc):
            at = pl.ds(r * rows, rows)
            gv = g_ref[at, :]
            m = jnp.where(y_ref[at, :] > 0, gv, jnp.zeros_like(gv))
            gx_ref[at, :] = m
            return acc + jnp.sum(m.astype(jnp.float32), axis=0, keepdims=True)

        sum_ref[...] = jax.lax.fori_loop(0, b // rows, step, jnp.zeros((1, cols), jnp.float32))

    block = pl.BlockSpec((b, cols), lambda j: (0, j))
    gx, sums = pl.pallas_call(
        kernel, grid=(n // cols,), in_specs=[block, block],
        out_specs=[block, pl.BlockSpec((1, cols), lambda j: (0, j))],
        out_shape=[jax.ShapeDtypeStruct((b, n), g.dtype),
                   jax.ShapeDtypeStruct((1, n), jnp.float32)],
        interpret=jax.default_backend() == "cpu")(g.reshape(b, n), y.reshape(b, n))
    return gx.reshape(g.shape), sums.reshape(-1, c).sum(0)


def timed_loop(form: Callable, g: Any, y: Any, steps: int) -> tuple[float, float]:
    """Seconds per call of `form` in a jitted loop of `steps` calls, each on the last one's masked
    gradient (so XLA cannot hoist it), and the first call's compile-and-run seconds."""
    import jax

    def body(_, carry):
        gi, acc = carry
        gx, gb = form(gi, y)
        return gx, acc + gb.sum()

    run = jax.jit(lambda g0: jax.lax.fori_loop(0, steps, body, (g0, jax.numpy.float32(0))))
    t0 = time.perf_counter()
    jax.block_until_ready(run(g))
    first = time.perf_counter() - t0
    best = math.inf
    for _ in range(5):
        t0 = time.perf_counter()
        jax.block_until_ready(run(g))
        best = min(best, time.perf_counter() - t0)
    return best / steps, first


def measure(name: str, shape: tuple[int, ...], blocks: list[tuple[str, int, int]],
            steps: int) -> dict[str, Any]:
    """One layer shape: XLA's forms (`XLA_FORMS`) and each Pallas form ("grid" or "loop") at
    each block size that divides it, each checked against XLA's form of today."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    kg, ky = jax.random.split(jax.random.PRNGKey(0))
    g = jax.random.normal(kg, shape, jnp.bfloat16)
    y = jax.nn.relu(jax.random.normal(ky, shape, jnp.bfloat16))
    moved = 3 * g.size * g.dtype.itemsize  # g and y read, the masked gradient written
    ref_gx, ref_gb = jax.jit(XLA_FORMS["xla"])(g, y)
    out: dict[str, Any] = {"shape": list(shape), "bytes_moved": moved}
    n = math.prod(shape[1:])
    forms = [(k, f) for k, f in XLA_FORMS.items() if k != "xla_row_blocks" or shape[0] % 32 == 0]
    forms += [(f"pallas_{'relu' if how == 'grid' else how}_{rows}x{cols}",
               functools.partial(pallas_relu_form, rows=rows, cols=cols) if how == "grid" else
               functools.partial(pallas_loop_form, rows=rows, cols=cols))
              for how, rows, cols in blocks if not (shape[0] % rows or n % cols)]
    for label, form in forms:
        try:
            gx, gb = jax.jit(form)(g, y)
            same_gx = bool(jnp.array_equal(gx, ref_gx))
            gb_err = float(np.max(np.abs(np.asarray(gb) - np.asarray(ref_gb)))
                           / (np.max(np.abs(np.asarray(ref_gb))) + 1e-30))
            s, first = timed_loop(form, g, y, steps)
        except Exception as e:  # a block size the backend refuses: said, the others go on
            out[label] = {"error": f"{type(e).__name__}: {str(e)[:300]}"}
            print(f"{name}: {label}: {type(e).__name__}: {str(e)[:200]}", flush=True)
            continue
        out[label] = {"s": s, "gb_per_s": moved / s / 1e9, "first_s": first,
                      "masked_equal": same_gx, "bias_grad_rel_err": gb_err}
        print(f"{name}: {label} {s * 1e3:.3f} ms ({moved / s / 1e9:.0f} GB/s), masked "
              f"gradient {'equal' if same_gx else 'DIFFERENT'}, bias gradient rel. err "
              f"{gb_err:.1e}", flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--small", action="store_true", help="one small shape (a CPU smoke run)")
    p.add_argument("--steps", type=int, default=50, help="calls in each timed loop")
    p.add_argument("--blocks", default="16x512,32x512,32x1024,L8x512,L16x256,L16x512,L32x256",
                   help="Pallas block sizes, rows x columns of the [batch, H*W*C] view; L: the "
                        "loop form (a program per column block, walking its rows that many at "
                        "a time)")
    p.add_argument("--out-dir", default=os.path.join(REPO, "benchmarks", "results"))
    a = p.parse_args()
    import jax

    blocks = [("loop" if b.startswith("L") else "grid", *(int(x) for x in b.lstrip("L").split("x")))
              for b in ("16x256,L8x256" if a.small else a.blocks).split(",")]
    kind = jax.devices()[0].device_kind
    results = {"question": __doc__.split("\n\n")[0], "device_kind": kind, "jax": jax.__version__,
               "steps": a.steps, "interpret": jax.default_backend() == "cpu",
               "shapes": {n: measure(n, s, blocks, a.steps)
                          for n, s in (SMALL if a.small else SHAPES).items()}}
    slug = "".join(ch if ch.isalnum() else "_" for ch in kind.lower()).strip("_")
    stamp = dt.datetime.now().strftime("%Y%m%d_%H%M%S")
    os.makedirs(a.out_dir, exist_ok=True)
    path = os.path.join(a.out_dir, f"relu_bias_grad_{slug}_{stamp}.json")
    with open(path, "w") as f:
        json.dump(results, f, indent=1)
    print(f"written: {path}")


if __name__ == "__main__":
    main()
