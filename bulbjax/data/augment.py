"""Image augmentation shared by the learners and PPO: random shifts of frames.

A frame padded by `pad` pixels with its edge pixels and cropped back at a random offset (RAD's
translate, DrQ's shift, CURL's crop without a change of resolution). CURL contrasts two shifts of
one frame (`learners.contrastive`); PPO from pixels can train on shifted frames
(`PPOConfig.pixel_shift`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def random_shift(key: jax.Array, x: jax.Array, pad: int) -> jax.Array:
    """Frames `[B, H, W, C]` padded by `pad` px with their edge pixels and cropped back to
    `[B, H, W, C]` at a random offset per frame (shifts of up to `pad` px each way); all C
    channels of a frame (e.g. stacked frames) move together. `pad` <= 0: `x` unchanged."""
    if pad <= 0:
        return x
    b, h, w, c = x.shape
    xp = jnp.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    off = jax.random.randint(key, (b, 2), 0, 2 * pad + 1)
    return jax.vmap(lambda img, o: jax.lax.dynamic_slice(img, (o[0], o[1], 0), (h, w, c)))(xp, off)
