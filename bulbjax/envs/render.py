"""Batch rendering through the MuJoCo Warp renderer (`mjx.render`, impl='warp').

One `Renderer` owns one render context, whose number of worlds is fixed when it is made; it
turns a batch of MJX Data (positions already computed) into uint8 RGB frames. It runs inside
`jax.jit`, on CPU (Warp's CPU backend) and on GPU.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx


def _quiet_warp() -> None:
    """Warp prints one line per kernel module it loads; keep warnings only, unless
    BULBJAX_WARP_VERBOSE=1."""
    if os.environ.get("BULBJAX_WARP_VERBOSE") == "1":
        return
    import warp

    warp.config.log_level = warp.LOG_WARNING
    warp.config.quiet = True


_quiet_warp()


class Renderer:
    """Renders camera `cam_id` of `nworld` worlds at `resolution` x `resolution`."""

    def __init__(self, mj_model: mujoco.MjModel, nworld: int, resolution: int, cam_id: int = 0,
                 background: tuple[float, float, float] = (1.0, 1.0, 1.0)):
        self.nworld = nworld
        self.resolution = resolution
        self.cam_id = cam_id
        # The context object must stay alive as long as its pytree is used (see mjx-warp notes).
        self._context = mjx.create_render_context(
            mj_model, nworld=nworld, cam_res=(resolution, resolution), render_rgb=True,
            render_depth=False, use_textures=True, use_shadows=False,
            background_color=(*background, 1.0))
        self._pytree = self._context.pytree()

    def __del__(self) -> None:
        # Work still queued on this context would fail once it is released: wait for it first.
        try:
            jax.effects_barrier()
        except Exception:  # interpreter shutdown: nothing left to wait for
            pass

    def __call__(self, mx: mjx.Model, data: mjx.Data) -> tuple[jax.Array, mjx.Data]:
        """uint8 frames `[nworld, H, W, 3]` of `data` (batched over worlds, after kinematics),
        and the Data that comes out of the renderer.

        The returned Data carries the Warp ordering token: several renders in one jitted function
        must each start from the Data the previous one returned, else XLA may run them in any
        order over the context's shared buffers and frames get mixed up (seen on the H100).
        `mx` may carry per-world `geom_rgba` of shape `[nworld, ngeom, 4]` (multicolour)."""
        if data.qpos.shape[0] != self.nworld:
            raise ValueError(f"renderer was made for {self.nworld} worlds, got a batch of {data.qpos.shape[0]}")
        data = mjx.refit_bvh(mx, data, self._pytree)
        rgb, _, data = mjx.render(mx, data, self._pytree)
        frames = mjx.get_rgb(self._pytree, self.cam_id, rgb)
        return jnp.clip(jnp.round(frames * 255.0), 0, 255).astype(jnp.uint8), data
