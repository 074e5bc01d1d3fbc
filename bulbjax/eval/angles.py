"""Major-axis angles of objects on a table, as regression targets (paper Sec. IV.C: VAE_rpl
encodes "location & partly orientation (major axis) of the largest objects").

The angle of an object's major axis in the table plane, theta, is defined modulo the object's
symmetry: pi for a box (its footprint is a rectangle) and for a cylinder lying down (its axis
points both ways). A regression probe is given it as the pair (cos 2 theta, sin 2 theta):
- theta itself has a jump (at 0 = pi) where a probe's MAE would count a perfect direction as an
  error of pi, and its MAE would depend on where the cut is put;
- (cos theta, sin theta) is not a function of the object's pose: theta and theta + pi are the
  same pose but give opposite pairs;
- (cos 2 theta, sin 2 theta) is continuous in the pose and one-to-one on angles modulo pi: the
  usual encoding of an axis (a "nematic" direction). Both entries are targets; the angle error
  of a prediction (c, s) is read back as |theta_hat - theta| modulo pi with theta_hat =
  atan2(s, c) / 2 (in [0, pi/2] rad, `angle_error`).
Where no major axis is defined (a sphere; a cylinder standing up, whose footprint is a disc; an
object tilted so far that the axis points mostly up) the target is (0, 0), the centre of the
circle, the mean of (cos 2 theta, sin 2 theta) over uniform angles: a constant that the reference
spread marks as excluded when it is constant over the run (a sphere's entries), and rows that
`angle_error` leaves out.

Which axis: the top-down silhouette's long side. For a box resting on a face, the body axis
pointing most nearly up is dropped and the longer of the other two (by half-extent) is the
major axis (bulb's block 5 x 10 x 15 cm: lying on its 10 x 15 face, the 15 cm axis; standing on
its 5 x 10 face, the 10 cm axis). For a cylinder it is its symmetry axis (lying down: bulb's
cylinder is as long as it is wide, 12 x 12 cm, so its silhouette is a square and the axis shows
only in shading and edges: "partly"). Defined when the axis's projection on the table plane is
at least `MIN_PROJECTION` long (the axis at most 45 degrees out of the plane).
"""

from __future__ import annotations

import math

import jax.numpy as jnp

MIN_PROJECTION = math.sqrt(0.5)  # the axis within 45 degrees of the table plane
SPHERE, CYLINDER, BOX = 0, 1, 2  # shape codes (bulb's: sphere 0, cylinder 1, box 2, mesh 3)


def major_axis_c2s2(rot: jnp.ndarray, shape: jnp.ndarray, half_extents: jnp.ndarray) -> jnp.ndarray:
    """`[..., 2]` (cos 2 theta, sin 2 theta) of the major axis of objects with rotation matrices
    `rot [..., 3, 3]` (body axis j in the world = column j), shape codes `shape [...]` (ints) and
    body-frame half-extents `half_extents [..., 3]`; (0, 0) where no axis is defined (module
    docstring)."""
    vertical = jnp.abs(rot[..., 2, :])  # [..., 3]: how much each body axis points up
    up = jnp.argmax(vertical, axis=-1)
    ext = jnp.where(jnp.arange(3) == up[..., None], -jnp.inf, half_extents)  # drop the upright axis
    long = jnp.argmax(ext, axis=-1)
    others = jnp.sort(ext, axis=-1)[..., 1:]  # the two kept extents, ascending
    distinct = others[..., 1] > 1.05 * others[..., 0]  # a square footprint has no long side
    axis_box = jnp.take_along_axis(rot, jnp.broadcast_to(long[..., None, None], rot.shape[:-1] + (1,)), -1)[..., 0]
    axis = jnp.where((shape == CYLINDER)[..., None], rot[..., :, 2], axis_box)
    p = axis[..., :2]
    norm = jnp.linalg.norm(p, axis=-1)
    ok = (((shape == BOX) & distinct) | (shape == CYLINDER)) & (norm >= MIN_PROJECTION)
    u = p / jnp.maximum(norm, 1e-9)[..., None]
    c2s2 = jnp.stack([u[..., 0] ** 2 - u[..., 1] ** 2, 2.0 * u[..., 0] * u[..., 1]], axis=-1)
    return jnp.where(ok[..., None], c2s2, 0.0)


def defined(c2s2: jnp.ndarray) -> jnp.ndarray:
    """`[...]` bool: the targets with a major axis (on the unit circle, not the (0, 0) centre)."""
    return jnp.linalg.norm(c2s2, axis=-1) > 0.5


def angle_of(c2s2: jnp.ndarray) -> jnp.ndarray:
    """theta in (-pi/2, pi/2] (rad) of (cos 2 theta, sin 2 theta) pairs `[..., 2]`."""
    return 0.5 * jnp.arctan2(c2s2[..., 1], c2s2[..., 0])


def angle_error(pred: jnp.ndarray, target: jnp.ndarray) -> jnp.ndarray:
    """`[...]` rad in [0, pi/2]: the angle between predicted and true axes, modulo pi, of
    (cos 2 theta, sin 2 theta) pairs `[..., 2]` (a predicted pair need not be on the circle: its
    direction is read)."""
    d = angle_of(pred) - angle_of(target)
    return jnp.abs(jnp.mod(d + 0.5 * jnp.pi, jnp.pi) - 0.5 * jnp.pi)


def mean_angle_error(pred: jnp.ndarray, target: jnp.ndarray, weights: jnp.ndarray | None = None) -> jnp.ndarray:
    """`[M]` mean `angle_error` (rad) of predictions `[B, M, 2]` for targets `[B, M, 2]` over the
    rows where the target is `defined` (and `weights [B]` > 0); NaN for an object with none."""
    w = defined(target).astype(jnp.float32)  # [B, M]
    if weights is not None:
        w = w * (weights > 0).astype(jnp.float32)[:, None]
    n = jnp.sum(w, axis=0)
    total = jnp.sum(angle_error(pred, target) * w, axis=0)
    return jnp.where(n > 0, total / jnp.maximum(n, 1.0), jnp.nan)
