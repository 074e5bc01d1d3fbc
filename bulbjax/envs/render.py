"""Batch rendering through the MuJoCo Warp renderer (`mjx.render`, impl='warp').

One `Renderer` owns one render context, whose number of worlds is fixed when it is made; it
turns a batch of MJX Data (positions already computed) into uint8 RGB frames. It runs inside
`jax.jit`, on CPU (Warp's CPU backend) and on GPU.
"""

from __future__ import annotations

import os
import sys
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx


# What Warp's native start-up prints to stderr, on every run, on a machine without the NVIDIA
# driver (warp/native/cuda_util.cpp, `init_cuda_driver`), although the CPU is a documented path.
NO_DRIVER_LINE = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver."


def _quiet_warp() -> None:
    """Warp prints one line per kernel module it loads; keep warnings only, and start it without
    its no-driver line where there is no CUDA driver (`init_warp_without_driver_line`), unless
    BULBJAX_WARP_VERBOSE=1."""
    if os.environ.get("BULBJAX_WARP_VERBOSE") == "1":
        return
    import warp

    warp.config.log_level = warp.LOG_WARNING
    warp.config.quiet = True
    if not _cuda_driver_loads():
        init_warp_without_driver_line()


def _cuda_driver_loads() -> bool:
    """Whether the NVIDIA driver library loads, as Warp's native init tries it (Linux:
    libcuda.so, then libcuda.so.1). Elsewhere (Windows, macOS) True: Warp is left alone."""
    import ctypes

    if not sys.platform.startswith("linux"):
        return True
    for name in ("libcuda.so", "libcuda.so.1"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            pass
    return False


def init_warp_without_driver_line() -> None:
    """Start Warp's runtime now without `NO_DRIVER_LINE` (`without_stderr_line`): only called
    where the driver does not load, so that line says nothing a CPU run needs; any other message
    (a real error, another warning) still reaches stderr. Warp keeps one runtime per process
    (`warp.init` of a started one does nothing)."""
    import warp

    without_stderr_line(warp.init, NO_DRIVER_LINE)


def without_stderr_line(fn: Any, prefix: str) -> Any:
    """`fn()` with stderr (file descriptor 2, where native code writes) captured, then written
    back without the lines that start with `prefix`; returns what `fn` returns."""
    import tempfile

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            return fn()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            lines = tmp.read().decode(errors="replace").splitlines(keepends=True)
            kept = "".join(x for x in lines if not x.startswith(prefix))
            if kept:
                sys.stderr.write(kept)
                sys.stderr.flush()


_quiet_warp()


def warp_devices(devices: list[jax.Device] | None = None) -> list[str] | None:
    """Warp device names (`cuda:<ordinal>`) of JAX GPU devices (default: JAX's default device);
    None off the GPU (Warp's single CPU device). A render context must live on the GPU its
    kernels run on, and Warp's own default is whichever CUDA context was current when Warp
    started: after JAX has opened every GPU of a machine, often not JAX's default (seen on two
    H200s: the context on cuda:1 while the env ran on cuda:0, a KeyError in the renderer)."""
    devices = devices or jax.local_devices()[:1]
    if devices[0].platform != "gpu":
        return None
    return [f"cuda:{d.local_hardware_id}" for d in devices]


# Geom groups: 0-2 the robot and objects (MuJoCo's defaults), SCENERY_GROUP the floor and other
# scenery that point clouds leave out (bulb keeps only the objects' points); frames show both.
# Group 3 is never drawn (collision-only geoms, e.g. a YCB object's convex hull).
SCENERY_GROUP = 4
FRAME_GROUPS = (0, 1, 2, SCENERY_GROUP)
POINT_GROUPS = (0, 1, 2)
DEPTH_FAR = 100.0  # bulb's far plane (m); depth is reported in metres up to it


def exclude_from_pointcloud(spec: mujoco.MjSpec, geoms: tuple[str, ...]) -> None:
    """Move the named geoms to the scenery group, which point clouds do not see."""
    for name in geoms:
        geom = spec.geom(name)
        if geom is None:
            raise ValueError(f"pointcloud_exclude names geom {name!r}, which is not in the model")
        geom.group = SCENERY_GROUP


class Renderer:
    """Renders camera `camera` of `nworld` worlds at `resolution` x `resolution` (RGB, and depth
    in metres when `depth`)."""

    def __init__(self, mj_model: mujoco.MjModel, nworld: int, resolution: int, camera: str = "bulb",
                 depth: bool = False, background: tuple[float, float, float] = (1.0, 1.0, 1.0),
                 devices: list[str] | None = None):
        """`devices`: Warp devices (e.g. ["cuda:0", "cuda:1"]) that each get a context of
        `nworld` worlds, for callers that render `nworld` worlds per device under `shard_map`;
        default JAX's default device (`warp_devices`)."""
        self.nworld = nworld
        self.resolution = resolution
        self.depth = depth
        # The context object must stay alive as long as its pytree is used (see mjx-warp notes).
        self._context = mjx.create_render_context(
            mj_model, nworld=nworld, devices=devices or warp_devices(), cam_res=(resolution, resolution), render_rgb=True,
            render_depth=depth, use_textures=True, use_shadows=False, cam_active=[camera],
            enabled_geom_groups=list(FRAME_GROUPS), background_color=(*background, 1.0))
        self._pytree = self._context.pytree()

    def __del__(self) -> None:
        # Work still queued on this context would fail once it is released: wait for it first.
        try:
            jax.effects_barrier()
        except Exception:  # interpreter shutdown: nothing left to wait for
            pass

    def __call__(self, mx: mjx.Model, data: mjx.Data) -> tuple[jax.Array, jax.Array | None, mjx.Data]:
        """uint8 frames `[nworld, H, W, 3]` of `data` (batched over worlds, after kinematics),
        depth `[nworld, H, W]` in metres (0 where no geometry is hit; None unless `depth`), and the
        Data that comes out of the renderer.

        The returned Data carries the Warp ordering token: several renders in one jitted function
        must each start from the Data the previous one returned, else XLA may run them in any
        order over the context's shared buffers and frames get mixed up (seen on the H100).
        `mx` may carry per-world `geom_rgba` of shape `[nworld, ngeom, 4]` (multicolour)."""
        if data.qpos.shape[0] != self.nworld:
            raise ValueError(f"renderer was made for {self.nworld} worlds, got a batch of {data.qpos.shape[0]}")
        data = mjx.refit_bvh(mx, data, self._pytree)
        rgb, depth, data = mjx.render(mx, data, self._pytree)
        frames = mjx.get_rgb(self._pytree, 0, rgb)
        frames = jnp.clip(jnp.round(frames * 255.0), 0, 255).astype(jnp.uint8)
        metres = mjx.get_depth(self._pytree, 0, depth, DEPTH_FAR)[..., 0] * DEPTH_FAR if self.depth else None
        return frames, metres, data


def camera_rays(fovy_deg: float, resolution: int) -> np.ndarray:
    """`[H, W, 3]` directions in the camera frame (x right, y up, -z forward) scaled so that
    their -z component is 1: a pixel at planar depth d lies at d times its ray."""
    half = np.tan(np.deg2rad(fovy_deg) / 2.0)
    c = (np.arange(resolution) + 0.5) / resolution * 2.0 - 1.0  # pixel centres in [-1, 1]
    x = np.broadcast_to(c[None, :] * half, (resolution, resolution))
    y = np.broadcast_to(-c[:, None] * half, (resolution, resolution))
    return np.stack([x, y, -np.ones_like(x)], axis=-1).astype(np.float32)


class PointCloudRenderer:
    """bulb's PT observation: depth from several cameras turned into world points, the points
    of the scene's objects (scenery groups left out) only, `num_points` of them drawn at random
    per world (zeros pad a cloud with fewer), clipped to the cube [-box, box]^3."""

    def __init__(self, mj_model: mujoco.MjModel, nworld: int, cameras: list[str], num_points: int,
                 box: float, resolution: int = 64):
        self.nworld, self.num_points, self.box = nworld, num_points, box
        self._cam_ids = [mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_CAMERA, c) for c in cameras]
        if min(self._cam_ids) < 0:
            raise ValueError(f"point-cloud cameras {cameras} not all in the model")
        fovy = [float(mj_model.cam_fovy[i]) for i in self._cam_ids]
        self._rays = jnp.asarray(np.stack([camera_rays(f, resolution) for f in fovy]))  # [C, H, W, 3]
        self._context = mjx.create_render_context(
            mj_model, nworld=nworld, devices=warp_devices(), cam_res=(resolution, resolution), render_rgb=False,
            render_depth=True, use_textures=False, use_shadows=False, cam_active=list(cameras),
            enabled_geom_groups=list(POINT_GROUPS))
        self._pytree = self._context.pytree()

    def __del__(self) -> None:
        try:
            jax.effects_barrier()
        except Exception:
            pass

    def __call__(self, mx: mjx.Model, data: mjx.Data, keys: jax.Array) -> tuple[jax.Array, mjx.Data]:
        """float32 points `[nworld, num_points, 3]` in world coordinates, and the renderer's Data."""
        data = mjx.refit_bvh(mx, data, self._pytree)
        _, depth, data = mjx.render(mx, data, self._pytree)
        depth = jnp.stack([mjx.get_depth(self._pytree, i, depth, DEPTH_FAR)[..., 0] * DEPTH_FAR
                           for i in range(len(self._cam_ids))], axis=1)  # [N, C, H, W]
        ids = jnp.asarray(self._cam_ids)
        pos, mat = data.cam_xpos[:, ids], data.cam_xmat[:, ids]  # [N, C, 3], [N, C, 3, 3]
        local = depth[..., None] * self._rays[None]  # [N, C, H, W, 3]
        world = jnp.einsum("ncij,nchwj->nchwi", mat, local) + pos[:, :, None, None, :]
        world = world.reshape(self.nworld, -1, 3)
        valid = depth.reshape(self.nworld, -1) > 0.0
        return jax.vmap(self._pick)(world, valid, keys), data

    def _pick(self, points: jax.Array, valid: jax.Array, key: jax.Array) -> jax.Array:
        """`num_points` of the valid points at random (without replacement), zeros after them."""
        score = jax.random.uniform(jax.random.fold_in(key, 7), valid.shape) + jnp.where(valid, 0.0, 2.0)
        _, idx = jax.lax.top_k(-score, self.num_points)
        chosen = jnp.where(valid[idx][:, None], points[idx], 0.0)
        return jnp.clip(chosen, -self.box, self.box)
