"""MJCF sub-models of processed objects, for attaching into a scene with `dm_control.mjcf`.

    model = ycb_mjcf(load_ycb_object("013_apple"), "apple")
    frame = scene.attach(model)
    frame.add("freejoint")
    mujoco.MjModel.from_xml_string(scene.to_xml_string(), assets=scene.get_assets())
"""

from __future__ import annotations

import warnings

import numpy as np

from bulbjax.assets.ycb import YcbAsset

VISUAL_GROUP = 1  # drawn: the MuJoCo Warp renderer draws groups 0-2 by default
COLLISION_GROUP = 3  # not drawn by default (and transparent), collides


def _mjcf():
    # dm_control imports glfw, which warns when there is no display; nothing here renders
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from dm_control import mjcf
    return mjcf


def ycb_mjcf(asset: YcbAsset, name: str, origin: str = "mesh"):
    """A `dm_control.mjcf.RootElement` named `name` holding one body (`name`) at the mesh origin
    (`origin="mesh"`) or at the centre of mass (`origin="com"`: the meshes shifted by -com; YCB
    origins lie up to ~0.1 m from the object):
    the visual mesh (no contacts, group 1, textured where the asset has a texture, else its flat
    rgba), the convex hull as collision geom (group 3, rgba alpha 0), and the asset's mass,
    centre of mass and full inertia as an explicit `inertial`. Add a joint on the attachment
    frame (`frame.add('freejoint')`) to make it move."""
    if origin not in ("mesh", "com"):
        raise ValueError(f"origin must be 'mesh' or 'com', got {origin!r}")
    shift = -np.asarray(asset.com) if origin == "com" else np.zeros(3)
    mjcf = _mjcf()
    root = mjcf.RootElement(model=name)
    vis = root.asset.add("mesh", name="visual",
                         file=mjcf.Asset(asset.visual_path.read_bytes(), ".obj"))
    col = root.asset.add("mesh", name="collision",
                         file=mjcf.Asset(asset.collision_path.read_bytes(), ".obj"))
    if asset.texture_path is not None:
        tex = root.asset.add("texture", name="texture", type="2d",
                             file=mjcf.Asset(asset.texture_path.read_bytes(), ".png"))
        mat = root.asset.add("material", name="material", texture=tex, rgba=asset.rgba,
                             specular=0.1, shininess=0.1)
        vis_colour = {"material": mat}
    else:
        vis_colour = {"rgba": asset.rgba}
    body = root.worldbody.add("body", name=name)
    body.add("inertial", pos=np.asarray(asset.com) + shift, mass=asset.mass, fullinertia=fullinertia(asset))
    body.add("geom", name="visual", type="mesh", mesh=vis, contype=0, conaffinity=0,
             group=VISUAL_GROUP, mass=0, pos=shift, **vis_colour)
    body.add("geom", name="collision", type="mesh", mesh=col, group=COLLISION_GROUP,
             rgba=(0.5, 0.5, 0.5, 0.0), mass=0, pos=shift)
    return root


def fullinertia(asset: YcbAsset) -> np.ndarray:
    """`[ixx, iyy, izz, ixy, ixz, iyz]` of the asset, MJCF's `fullinertia` order."""
    i = asset.inertia
    return np.array([i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]])
