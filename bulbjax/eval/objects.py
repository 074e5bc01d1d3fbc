"""Object-level probe for structured learners (SPAIR): do present boxes sit on the true objects?

Given a learner's boxes (`SPAIR.boxes`: centres in pixels, presence probabilities) and each
true object's image position in pixels (both (x, y) from the frame's top-left corner), the
probe measures per object the distance to the nearest *present* box centre (presence above
`threshold`) and whether one lies within `radius` pixels, and per frame the present boxes that
are near no object (spurious). `object_scores` is the jittable core (per frame and object);
`summarise` is the host-side summary (per object and averaged). Frames without any present box
give the object an infinite distance: it counts as not found and is left out of the mean error
(the share of such objects is reported as `missing`).
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np


def object_scores(
    centres: jax.Array,
    pres: jax.Array,
    positions: jax.Array,
    radius: float,
    threshold: float = 0.5,
) -> dict[str, jax.Array]:
    """Per-frame object scores; pure and jittable.

    centres [B, K, 2] box centres (px), pres [B, K] presence probabilities, positions [B, M, 2]
    true object positions (px). Returns `distance` [B, M] (to the nearest present box centre;
    inf if none is present), `found` [B, M] (distance <= radius), `nearest` [B, M] (index of
    that box; -1 if none), `spurious` [B] (present boxes farther than radius from every
    object) and `present` [B] (present boxes)."""
    on = pres > threshold  # [B, K]
    d = jnp.linalg.norm(positions[:, :, None, :] - centres[:, None, :, :], axis=-1)  # [B, M, K]
    d_on = jnp.where(on[:, None, :], d, jnp.inf)
    distance = d_on.min(axis=-1)
    nearest = jnp.where(jnp.isfinite(distance), d_on.argmin(axis=-1), -1)
    near_any = (d <= radius).any(axis=1)  # [B, K]: box within radius of some object
    return {
        "distance": distance,
        "found": distance <= radius,
        "nearest": nearest,
        "spurious": (on & ~near_any).sum(-1),
        "present": on.sum(-1),
    }


def summarise(scores: dict[str, jax.Array], names: Sequence[str] | None = None) -> dict[str, object]:
    """Host-side summary of `object_scores` (any leading axes before [B, M] are pooled).

    Returns `error` (mean distance in px over frames where a box is present) and `found`
    (share found within the radius) per object (keyed by `names`, default "object0", ...) and
    averaged over objects (`error_mean`, `found_share`), plus `missing` (share of objects in
    frames without any present box), `spurious_per_frame` and `present_per_frame`."""
    dist = np.asarray(jax.device_get(scores["distance"]), np.float64)
    found = np.asarray(jax.device_get(scores["found"]), np.float64)
    m = dist.shape[-1]
    dist, found = dist.reshape(-1, m), found.reshape(-1, m)
    names = list(names) if names is not None else [f"object{i}" for i in range(m)]
    if len(names) != m:
        raise ValueError(f"{len(names)} names for {m} objects")
    finite = np.isfinite(dist)

    def mean_err(col: np.ndarray, ok: np.ndarray) -> float:
        return float(col[ok].mean()) if ok.any() else float("inf")

    per_object = {
        n: {"error": mean_err(dist[:, i], finite[:, i]), "found": float(found[:, i].mean())}
        for i, n in enumerate(names)
    }
    return {
        "per_object": per_object,
        "error_mean": mean_err(dist, finite),
        "found_share": float(found.mean()),
        "missing": float(1.0 - finite.mean()),
        "spurious_per_frame": float(np.asarray(scores["spurious"], np.float64).mean()),
        "present_per_frame": float(np.asarray(scores["present"], np.float64).mean()),
    }
