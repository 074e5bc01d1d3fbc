"""Functions that run one seed at a time when vmapped over seeds, forward and backward.

Why: the learners of a run are vmapped (or `lax.map`ped) over seeds with per-seed weights. A
vmapped convolution becomes a grouped one (seeds = feature groups), which cuDNN runs at about
half the rate of S plain ones (`benchmarks/bench_seed_axis.py`), so on one GPU the experiment
runs each seed's update alone (`lax.map`). That serialises the sequential learners' LSTMs too:
24 steps of a few small kernels each, at ~42 windows per seed, which leave the GPU idle. With
`per_seed(fn)` around the frame networks, a learner can be vmapped over seeds (its LSTMs, heads
and Adam batched: one kernel per step for all seeds) while its convolutions still run one seed at
a time (`jax.custom_batching.sequential_vmap`, forward and backward).

`jax.custom_batching.sequential_vmap` alone has no reverse-mode rule, so `per_seed` is a
`jax.custom_vjp` whose forward (the value and `jax.vjp`'s residuals) and backward (the
residuals applied to the cotangent) are each a `sequential_vmap` function. Unbatched (one seed,
or not under vmap) it computes exactly `fn` and its vjp.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
from jax.custom_batching import sequential_vmap


def per_seed(fn: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
    """`fn(diff, const)` that, vmapped, loops over the batch axis (forward and backward) instead
    of batching `fn`'s operations. Differentiable in `diff` (a pytree of float arrays); `const`
    (e.g. uint8 frames) gets no cotangent."""
    tree: dict[str, Any] = {}  # the vjp's pytree structure, recorded when the forward is traced

    @sequential_vmap
    def primal(diff: Any, const: Any) -> Any:
        return fn(diff, const)

    @sequential_vmap
    def forward(diff: Any, const: Any) -> tuple[Any, list]:
        out, vjp = jax.vjp(lambda d: fn(d, const), diff)
        leaves, tree["vjp"] = jax.tree.flatten(vjp)  # arrays only: a loop can stack them
        return out, leaves

    @sequential_vmap
    def backward(leaves: list, ct: Any) -> Any:
        return jax.tree.unflatten(tree["vjp"], leaves)(ct)[0]

    @jax.custom_vjp
    def wrapped(diff: Any, const: Any) -> Any:
        return primal(diff, const)

    wrapped.defvjp(forward, lambda leaves, ct: (backward(leaves, ct), None))
    return wrapped
