"""bulb's camera: PyBullet's `computeViewMatrixFromYawPitchRoll` placed as a MuJoCo camera.

PyBullet puts the eye at ``target + R_z(yaw) R_x(pitch) (0, -distance, 0)`` with z up and looks at
the target, vertical field of view 60 degrees. We attach a MuJoCo camera with that offset and
orientation to the body whose position is the target (the cart, the robot's base), so the camera
follows it exactly as bulb re-aims at the base every frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

FOVY_DEG = 60.0


@dataclass(frozen=True)
class CameraConfig:
    """Distance (m), yaw and pitch (degrees) as PyBullet's `_cam_dist`, `_cam_yaw`, `_cam_pitch`."""

    distance: float
    yaw: float
    pitch: float
    body: str
    target_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


def eye_offset(cfg: CameraConfig) -> np.ndarray:
    """Eye position relative to the target, as PyBullet computes it."""
    y, p = np.deg2rad(cfg.yaw), np.deg2rad(cfg.pitch)
    return cfg.distance * np.array([np.sin(y) * np.cos(p), -np.cos(y) * np.cos(p), -np.sin(p)])


def camera_axes(cfg: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """Right and up axes of a camera looking from the eye at the target with z up."""
    forward = -eye_offset(cfg)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return right, up


def add_bulb_camera(spec: mujoco.MjSpec, cfg: CameraConfig, name: str = "bulb") -> None:
    """Add the bulb camera to `spec`, attached to `cfg.body` so that it tracks that body."""
    body = spec.body(cfg.body)
    if body is None:
        raise ValueError(f"camera body {cfg.body!r} not found in the model")
    right, up = camera_axes(cfg)
    cam = body.add_camera(name=name, pos=eye_offset(cfg) + np.asarray(cfg.target_offset), fovy=FOVY_DEG)
    cam.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    cam.alt.xyaxes = np.concatenate([right, up])
