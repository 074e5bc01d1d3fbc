"""The Incline domains' constants and scene parts: bulb's numbers (episode, physics steps, the
reset's ranges, bounds, state scales), the objects, colours and camera, the state spec, and the
scene composed with `dm_control.mjcf` (`build_scene`). Kept apart from the env classes
(`incline.Incline`: dynamics, state, resets) so that each reads on its own; facts:
`../shared/reference/bulb-multiobject.md`, differences from bulb: `incline`'s docstring."""

from __future__ import annotations

import math
import os
from typing import Callable

import mujoco
import numpy as np

from bulbjax.envs.camera import CameraConfig
from bulbjax.eval.spec import StateEntry

os.environ.setdefault("MUJOCO_GL", "disable")  # dm_control needs no GL context to build models
from dm_control import mjcf  # noqa: E402

NUM_VERSIONS = 6
NUM_TEXTURES = 6
EPISODE_STEPS = 50
BULLET_DT = 0.01  # one stepSimulation
BULLET_SUBSTEPS = 2  # numSubSteps
STEPS_PER_ACTION = 4  # bulb's _nskip
MAX_FORCE = 2.0  # N, bulb's action space [-2, 2]
INCLINE_POS = (0.0, 0.0, 0.55)
INCLINE_HALF = (1.2, 0.3, 0.02)
START_POS = (-0.05, 0.0, 0.7)
START_EPS = math.pi / 16  # orientation noise half-range
START_X = (0.05, 0.15)  # the initial fall ends once x passes U[START_X]
FALL_STEPS = 50
TARGET_X, MIN_X, MAX_X, MAX_Y = 0.5, 0.0, 1.0, 0.1
MASS = (0.05, 0.5)
FRICTION = (0.1, 0.5)
PITCH = (0.25, 0.5)
CLIP_DIST, CLIP_SPEED = 1.27, 3.10
SCALES = {"": 2.5, "Md": 1.5, "Sm": 1.0}
NAN_RETRIES = 2  # redraws of a world whose reset went non-finite
PARK_HEIGHT = 50.0  # objects of unused versions float here, out of every camera's view

YCB_OBJECTS = ("004_sugar_box", "008_pudding_box", "009_gelatin_box", "005_tomato_soup_can",
               "007_tuna_fish_can", "002_master_chef_can")
GEOM_COLOURS = ((1, 1, 0.5), (0.2, 0.2, 0.2), (1, 0, 0), (1, 0, 1), (0, 0.5, 1), (0, 0, 1))
INCLINE_COLOURS = ((1, 0.5, 0), (0.8, 0.8, 0.8), (0.9, 0.4, 0.4), (0, 1, 0), (0.5, 0.15, 0.15), (1, 0.6, 0))
GEOM_PLANE_COLOUR = (0.72, 0.72, 0.75)
# Ycb variants: bulb's plane textures (red marble, bright blue, purple squares, wood stripes, dark
# pattern, orange pattern) and incline textures (red metal strip, marble, birch, green, retro
# purple, wood) as mean colours of our own choosing.
YCB_PLANE_COLOURS = ((0.62, 0.28, 0.25), (0.2, 0.45, 0.9), (0.45, 0.3, 0.6), (0.62, 0.44, 0.27),
                     (0.16, 0.16, 0.18), (0.92, 0.55, 0.2))
YCB_INCLINE_COLOURS = ((0.62, 0.22, 0.16), (0.86, 0.86, 0.83), (0.86, 0.78, 0.67), (0.2, 0.7, 0.25),
                       (0.5, 0.3, 0.6), (0.66, 0.46, 0.28))
CAMERA = CameraConfig(distance=0.8, yaw=35.0, pitch=-45.0, body="world", target_offset=(0.5, 0.2, 0.1),
                      fovy=90.0)


def geom_object(version: int, scale: float) -> mjcf.RootElement:
    """bulb's geometric object of `version` (block, block, block, cylinder, cylinder_large,
    cylinder_short) scaled by `scale` (PyBullet's globalScaling: sizes x scale, inertia x scale^2),
    one colour per version."""
    rgba = (*GEOM_COLOURS[version], 1.0)
    model = mjcf.RootElement(model=f"geom{version}")
    body = model.worldbody.add("body", name="object")
    if version < 3:  # block.urdf: box 0.05 x 0.10 x 0.15 m, 0.05 kg, the URDF's inertia
        half = np.array([0.025, 0.05, 0.075]) * scale
        body.add("geom", name="visual", type="box", size=half, rgba=rgba)
        body.add("inertial", pos=[0, 0, 0], mass=0.05,
                 diaginertia=np.array([1.041666667e-4, 5.208333333e-5, 1.354166667e-4]) * scale ** 2)
    else:
        radius, half_height = {3: (0.06, 0.06), 4: (0.06, 0.065), 5: (0.06, 0.03)}[version]
        radius, half_height = radius * scale, half_height * scale
        body.add("geom", name="visual", type="cylinder", size=[radius, half_height], rgba=rgba)
        if version == 4:  # cylinder_large.urdf's inertia
            inertia = np.array([3.267e-4, 3.267e-4, 9e-5]) * scale ** 2
        else:  # a solid cylinder of 0.2 kg
            ixx = 0.2 * (3 * radius ** 2 + (2 * half_height) ** 2) / 12
            inertia = np.array([ixx, ixx, 0.2 * radius ** 2 / 2])
        body.add("inertial", pos=[0, 0, 0], mass=0.2, diaginertia=inertia)
    return model


def incline_state_spec(report_friction: bool = False) -> tuple[StateEntry, ...]:
    """bulb's low-dim state of the incline domains, each entry scaled to [0, 1] by bulb's range:
    texture id / 6, version / 6, (friction over [0.1, 0.5],) pitch over [0.25, 0.5] rad, distance
    over [0, 1.27] m, speed over [0, 3.1] m/s."""
    spec = [StateEntry("texture_id", "1/6", "static"), StateEntry("version", "1/6", "static")]
    if report_friction:
        spec.append(StateEntry("friction", "1/0.4 from 0.1", "static"))
    return tuple(spec + [StateEntry("theta", "1/0.25 rad from 0.25", "static"),
                         StateEntry("distance", "1.27 m", "position"),
                         StateEntry("speed", "3.1 m/s", "velocity")])


def build_scene(name: str, versions: tuple[int, ...],
                object_model: Callable[[int], mjcf.RootElement]) -> mujoco.MjSpec:
    """The Incline scene: bulb's physics options, light, plane and incline (a mocap body, so
    that its pitch is per world Data), and `object_model(v)` of each version in `versions`
    attached with a free joint, parked out of view (the reset places the world's object)."""
    root = mjcf.RootElement(model=name)
    root.compiler.angle = "radian"
    root.option.timestep = BULLET_DT / BULLET_SUBSTEPS
    root.option.gravity = [0, 0, -9.81]
    root.option.solver = "Newton"
    root.option.iterations = 10
    root.option.ls_iterations = 10
    root.visual.headlight.ambient = [0.45, 0.45, 0.45]
    root.visual.headlight.diffuse = [0.55, 0.55, 0.55]
    root.worldbody.add("light", name="key", directional=True, pos=[0, 0, 3], dir=[0.3, 0.3, -1],
                       diffuse=[0.5, 0.5, 0.5])
    root.worldbody.add("geom", name="plane", type="plane", size=[5, 5, 0.1],
                       rgba=(*GEOM_PLANE_COLOUR, 1), friction=[1.0, 0.005, 0.0001])
    incline = root.worldbody.add("body", name="incline_body", mocap=True, pos=INCLINE_POS)
    # drawn as a box; contacts with its top face as a plane (a half-space, robust where
    # MJX-Warp's box-box contacts of the blocks produced NaNs from deep starts)
    incline.add("geom", name="incline", type="box", size=INCLINE_HALF, rgba=(*INCLINE_COLOURS[0], 1),
                contype=0, conaffinity=0)
    incline.add("geom", name="incline_surface", type="plane", size=[INCLINE_HALF[0], INCLINE_HALF[1], 0.01],
                pos=[0, 0, INCLINE_HALF[2]], group=3, rgba=[0, 0, 0, 0])
    for v in versions:
        model = object_model(v)
        model.model = f"obj{v}"
        frame = root.worldbody.attach(model)
        frame.add("freejoint")
        body = model.find("body", "object")
        body.gravcomp = 1e-6  # compiled in so that per-world gravity compensation can park it
        frame.pos = [0.5, 0.2, PARK_HEIGHT]
    return mujoco.MjSpec.from_string(root.to_xml_string(), assets=root.get_assets())
