"""Functions that run one seed at a time when vmapped over seeds, forward and backward.

Why: the learners of a run are vmapped (or `lax.map`ped) over seeds with per-seed weights. A
vmapped convolution becomes a grouped one (seeds = feature groups), which cuDNN runs at about
half the rate of S plain ones (`bench_seed_axis.py`: benchmarks/diagnostics/README.md), so on one GPU the
experiment runs each seed's update alone (`lax.map`). That serialises the sequential learners' LSTMs too:
24 steps of a few small kernels each, at ~42 windows per seed, which leave the GPU idle. With
these wrappers around the frame networks, a learner can be vmapped over seeds (its LSTMs, heads
and Adam batched: one kernel per step for all seeds) while its convolutions still run one seed at
a time (`jax.custom_batching.sequential_vmap`, forward and backward).

`sequential_vmap` alone has no reverse-mode rule, so each wrapper is a `jax.custom_vjp` whose
forward and backward are `sequential_vmap` functions. What crosses from the forward loop to the
backward loop is stacked over seeds in memory, and a convolution reads and writes whole buffers,
so large activations saved there are copied into and out of the stacks (measured on the H100:
+25% on SVAE's update). Hence:
- `per_seed(fn, remat=True)` saves only its inputs and recomputes `fn`'s forward in the backward
  loop (`remat=False` saves `jax.vjp`'s residuals);
- `per_seed_loss(fn)` is for a function that ends in the loss: a weighted sum of per-item terms
  whose weights are known up front. Its forward loop computes the value and the gradient
  together (one loop, nothing large saved) and the backward scales that gradient.
Unbatched (one seed, or not under vmap) each computes exactly `fn` and its gradient.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
from jax.custom_batching import sequential_vmap


def per_seed(fn: Callable[[Any, Any], Any], remat: bool = True) -> Callable[[Any, Any], Any]:
    """`fn(diff, const)` that, vmapped, loops over the batch axis (forward and backward) instead
    of batching `fn`'s operations. Differentiable in `diff` (a pytree of float arrays); `const`
    (e.g. uint8 frames) gets no cotangent. `remat`: recompute the forward in the backward loop
    rather than save its activations."""
    tree: dict[str, Any] = {}  # the vjp's pytree structure, recorded when the forward is traced

    @sequential_vmap
    def primal(diff: Any, const: Any) -> Any:
        return fn(diff, const)

    @sequential_vmap
    def forward_saving(diff: Any, const: Any) -> tuple[Any, list]:
        out, vjp = jax.vjp(lambda d: fn(d, const), diff)
        leaves, tree["vjp"] = jax.tree.flatten(vjp)  # arrays only: a loop can stack them
        return out, leaves

    @sequential_vmap
    def backward_saved(leaves: list, ct: Any) -> Any:
        return jax.tree.unflatten(tree["vjp"], leaves)(ct)[0]

    @sequential_vmap
    def backward_recomputing(diff: Any, const: Any, ct: Any) -> Any:
        return jax.vjp(lambda d: fn(d, const), diff)[1](ct)[0]

    @jax.custom_vjp
    def wrapped(diff: Any, const: Any) -> Any:
        return primal(diff, const)

    if remat:
        wrapped.defvjp(lambda d, c: (primal(d, c), (d, c)),
                       lambda res, ct: (backward_recomputing(*res, ct), None))
    else:
        wrapped.defvjp(forward_saving, lambda leaves, ct: (backward_saved(leaves, ct), None))
    return wrapped


def per_seed_loss(fn: Callable[[Any, Any], jax.Array]) -> Callable[[Any, Any, jax.Array], jax.Array]:
    """`(fn(diff, const) * weights).sum()` (a scalar per seed) that, vmapped, loops over the batch
    axis, computing the gradient in `diff` in the same loop as the value. `fn` gives per-item
    terms shaped like `weights`; `const` and `weights` get no cotangent."""
    def total(diff: Any, const: Any, weights: jax.Array) -> jax.Array:
        return (fn(diff, const) * weights).sum()

    value = sequential_vmap(total)
    value_and_grad = sequential_vmap(jax.value_and_grad(total))

    @jax.custom_vjp
    def wrapped(diff: Any, const: Any, weights: jax.Array) -> jax.Array:
        return value(diff, const, weights)

    def backward(grad: Any, ct: jax.Array) -> tuple[Any, None, None]:
        return jax.tree.map(lambda g: (g * ct).astype(g.dtype), grad), None, None

    wrapped.defvjp(value_and_grad, backward)
    return wrapped
