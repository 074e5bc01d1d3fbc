"""bulb's camera: PyBullet's `computeViewMatrixFromYawPitchRoll` placed as a MuJoCo camera.

PyBullet puts the eye at ``target + R_z(yaw) R_x(pitch) (0, -distance, 0)`` with z up and looks at
the target, vertical field of view 60 degrees. We attach a MuJoCo camera with that offset and
orientation to the body whose position is the target (the cart, the robot's base), so the camera
follows it as bulb re-aims at the base every frame. bulb keeps yaw and pitch fixed in the world
whatever the base's orientation: for bodies that rotate (a walking robot's torso) the camera uses
MuJoCo's "track" mode (world-fixed offset from the body position and world-fixed orientation,
both taken at the model's reference pose) instead of being rigidly attached.
"""

from __future__ import annotations

import dataclasses
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
    # "fixed": rigidly attached to `body` (turns with it); "track": follows the body's position
    # with a world-fixed offset and orientation, as bulb's re-aimed view (needs the body to be
    # unrotated in the model's reference pose, so that the offset given here is a world offset)
    mode: str = "fixed"
    fovy: float = FOVY_DEG  # vertical field of view (degrees); bulb's multi-object domains use 90

    def __post_init__(self) -> None:
        if self.mode not in CAMERA_MODES:
            raise ValueError(f"camera mode must be one of {sorted(CAMERA_MODES)}, got {self.mode!r}")


CAMERA_MODES = {"fixed": mujoco.mjtCamLight.mjCAMLIGHT_FIXED, "track": mujoco.mjtCamLight.mjCAMLIGHT_TRACK}


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
    """Add the bulb camera to `spec`, attached to `cfg.body` so that it tracks that body
    (`body="world"`: a fixed camera aimed at `target_offset` in world coordinates)."""
    body = spec.worldbody if cfg.body == "world" else spec.body(cfg.body)
    if body is None:
        raise ValueError(f"camera body {cfg.body!r} not found in the model")
    right, up = camera_axes(cfg)
    cam = body.add_camera(name=name, pos=eye_offset(cfg) + np.asarray(cfg.target_offset), fovy=cfg.fovy)
    cam.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    cam.alt.xyaxes = np.concatenate([right, up])
    cam.mode = CAMERA_MODES[cfg.mode]


# bulb's point-cloud cameras (`ptcloud_utils.PanCamera`): seven views around the domain camera's
# target at its distance, as (yaw, pitch) in degrees, vertical field of view 90 degrees.
PAN_CAMERAS: tuple[tuple[float, float], ...] = (
    (-30.0, -70.0), (10.0, -10.0), (50.0, -65.0), (90.0, -40.0), (130.0, -10.0), (170.0, -25.0),
    (210.0, -60.0))
PAN_FOVY_DEG = 90.0


def pan_cameras(cfg: CameraConfig) -> list[CameraConfig]:
    """The point-cloud cameras of a domain: bulb's pan views around `cfg`'s target."""
    return [dataclasses.replace(cfg, yaw=yaw, pitch=pitch, fovy=PAN_FOVY_DEG) for yaw, pitch in PAN_CAMERAS]


def static_view(mj_model: mujoco.MjModel) -> bool:
    """Whether every camera and light of `mj_model` is fixed in the world frame (on the world body,
    mode fixed): their poses then never change, and a frame needs only the kinematics pass
    (geom poses) after a step, not MuJoCo's camera-and-light pass, which MJX's Warp backend runs
    only inside its full forward pass."""
    fixed = int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED)
    return bool(np.all(mj_model.cam_bodyid == 0) and np.all(mj_model.cam_mode == fixed)
                and np.all(mj_model.light_bodyid == 0) and np.all(mj_model.light_mode == fixed))


def view_poses(mj_model: mujoco.MjModel) -> dict[str, np.ndarray]:
    """World poses of the cameras and lights at `qpos0` (MuJoCo's forward pass on the CPU): for a
    model with a `static_view`, the poses every world keeps, set once in the template Data that
    resets start from (keys as `mjx.Data.tree_replace` takes them: MJX's Warp Data keeps the
    lights' under `_impl`)."""
    d = mujoco.MjData(mj_model)
    mujoco.mj_forward(mj_model, d)
    return {"cam_xpos": d.cam_xpos.copy(), "cam_xmat": d.cam_xmat.reshape(-1, 3, 3).copy(),
            "_impl.light_xpos": d.light_xpos.copy(), "_impl.light_xdir": d.light_xdir.copy()}
