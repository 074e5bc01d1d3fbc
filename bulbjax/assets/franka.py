"""The Franka Emika Panda for the FrankaRearrange domains: `pybullet_data`'s `franka_panda/panda.urdf`
(Apache-2.0, ships with the `pybullet` package: `pip install 'bulbjax[pybullet]'`) converted to MJCF by
MuJoCo's URDF importer at first use, cached on disk (`bulbjax.assets.cache`).

What the conversion does: the two finger joints become fixed (bulb's Rearrange envs never actuate
them: its torque limit for them is 0); the visual meshes are kept at full resolution without
their `.mtl` colours (links are drawn light grey, the hand, fingers and flange dark grey); the collision meshes are
kept (MuJoCo uses their convex hulls); a torque motor per arm joint with the URDF's effort as its
limit. Inertias, joint ranges and frames are the URDF's. Collision geoms get `contype` 2 and
`conaffinity` 0 (they touch what has conaffinity bit 2: the objects and the floor of the Rearrange
scene), visual geoms do not collide.
"""

from __future__ import annotations

import io
import json
import os
import re
from pathlib import Path

import mujoco
import numpy as np
import trimesh

from bulbjax.assets import mesh as meshlib
from bulbjax.assets.cache import cache_root, content_key, read_entry, write_entry

ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
PIPELINE_VERSION = 2
LINK_RGBA = (0.92, 0.92, 0.92, 1.0)
DARK_RGBA = (0.25, 0.25, 0.27, 1.0)
DARK_PARTS = ("hand", "finger", "link7")


class PybulletNotInstalled(ModuleNotFoundError, ValueError):
    """pybullet, whose pybullet_data holds the Panda, is not installed. A ModuleNotFoundError for
    library code, and a ValueError, which the CLI turns into its one-line error (the message says
    what to install, for a wheel and for a checkout)."""


def panda_urdf_dir() -> Path:
    """`pybullet_data`'s franka_panda folder; `PybulletNotInstalled` when pybullet is not installed."""
    try:
        import pybullet_data
    except ImportError as e:
        raise PybulletNotInstalled("the FrankaRearrange domains need pybullet (the Franka Panda model is its "
                                   "pybullet_data's panda.urdf): pip install 'bulbjax[pybullet]' "
                                   "(in a checkout: pip install -e '.[pybullet]')", name="pybullet_data") from e
    folder = Path(pybullet_data.getDataPath()) / "franka_panda"
    if not (folder / "panda.urdf").is_file():
        raise FileNotFoundError(f"{folder / 'panda.urdf'} not found in pybullet_data; reinstall pybullet")
    return folder


def franka_mjcf(cache_dir: str | os.PathLike | None = None) -> Path:
    """Path of the converted Panda MJCF (`panda.xml`, meshes beside it), built at first use."""
    src = panda_urdf_dir()
    urdf = (src / "panda.urdf").read_bytes()
    meshes = sorted(set(re.findall(rb'filename="package://(meshes/[^"]+\.obj)"', urdf)))
    blobs = [urdf] + [(src / m.decode()).read_bytes() for m in meshes]
    settings = {"version": PIPELINE_VERSION, "link_rgba": LINK_RGBA,
                "dark_rgba": DARK_RGBA}
    folder = cache_root(cache_dir) / "franka" / f"panda-{content_key(blobs, settings)[:20]}"
    if read_entry(folder) is None:
        files, meta = _build(src, urdf.decode(), [m.decode() for m in meshes])
        write_entry(folder, files, meta)
    return folder / "panda.xml"


def _flat_name(mesh_path: str) -> str:
    """`meshes/visual/link1.obj` -> `visual_link1.obj`."""
    parts = Path(mesh_path).parts
    return f"{parts[-2]}_{parts[-1]}"


def _build(src: Path, urdf: str, meshes: list[str]) -> tuple[dict[str, bytes], dict]:
    files: dict[str, bytes] = {}
    for m in meshes:
        data = (src / m).read_bytes()
        if "/visual/" in m:
            # re-written without materials; not decimated: these open meshes come apart when
            # simplified (fast-simplification), and the Warp renderer's BVH handles their size
            tm = trimesh.load(io.BytesIO(data), file_type="obj", process=True, force="mesh", skip_materials=True)
            data = meshlib.obj_text(np.asarray(tm.vertices), np.asarray(tm.faces)).encode()
        files[_flat_name(m)] = data
    text = re.sub(r'filename="package://(meshes/[^"]+\.obj)"', lambda mt: f'filename="{_flat_name(mt.group(1))}"', urdf)
    for j in FINGER_JOINTS:  # fingers fixed
        text = re.sub(rf'(<joint name="{j}" type=)"prismatic"', r'\1"fixed"', text)
    text, n = re.subn(r"(<robot [^>]*>)", r'\1\n  <mujoco><compiler discardvisual="false" strippath="false" '
                      r'fusestatic="false"/></mujoco>', text, count=1)
    if n != 1:
        raise ValueError("unexpected panda.urdf: no <robot> element")
    spec = mujoco.MjSpec.from_string(text, assets=dict(files))
    _edit(spec, urdf_efforts(urdf))
    spec.compile()  # fail here, not at first use
    xml = spec.to_xml()
    files["panda.xml"] = xml.encode()
    meta = {"source": "pybullet_data franka_panda/panda.urdf (Apache-2.0)", "pipeline_version": PIPELINE_VERSION,
            "meshes": sorted(k for k in files if k.endswith(".obj"))}
    json.dumps(meta)
    return files, meta


def urdf_efforts(urdf: str) -> dict[str, float]:
    """The arm joints' `<limit effort=...>` from the URDF text."""
    out = {}
    for name in ARM_JOINTS:
        m = re.search(rf'<joint name="{name}".*?<limit [^>]*effort="([0-9.]+)"', urdf, re.S)
        if m is None:
            raise ValueError(f"{name}: no effort limit in the URDF")
        out[name] = float(m.group(1))
    return out


def _edit(spec: mujoco.MjSpec, efforts: dict[str, float]) -> None:
    """Contacts, colours and motors of the converted model."""
    for g in spec.geoms:
        body = g.parent.name
        dark = any(p in body for p in DARK_PARTS)
        mesh = g.meshname or ""
        if mesh.startswith("visual_") or (g.contype == 0 and g.conaffinity == 0):
            g.contype, g.conaffinity, g.group = 0, 0, 1
            g.rgba = DARK_RGBA if dark else LINK_RGBA
        else:
            g.contype, g.conaffinity, g.group = 2, 0, 3
            g.rgba = (0.5, 0.5, 0.5, 0.0)
    for name in ARM_JOINTS:
        effort = efforts[name]
        act = spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.gainprm[0] = 1.0
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.ctrlrange = [-effort, effort]


def arm_efforts(model: mujoco.MjModel, prefix: str = "") -> np.ndarray:
    """The arm joints' torque limits (the URDF's efforts) from a compiled model."""
    return np.array([model.actuator(prefix + j).ctrlrange[1] for j in ARM_JOINTS])
