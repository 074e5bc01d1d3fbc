"""YCB objects for bulb's Rearrange and Incline domains: per-object numbers and the mesh pipeline.

The meshes are not in the repo: they are read from the YCB set's `google_16k` models in a folder
given by the caller or `$BULBJAX_YCB_DIR` (`<dir>/<name>/google_16k/textured.obj`, with
`texture_map.png` where the set has one). `load_ycb_object` scales an object as bulb does,
decimates a visual mesh that keeps its texture coordinates, builds a convex collision hull,
computes inertia from the mesh, downsamples the texture, and caches the result on disk.
Coordinates stay in the model file's own frame (scaled): the object's body frame is the mesh
origin, as with PyBullet's `createMultiBody` in bulb.

The YCB models (Calli et al., ICAR 2015) are CC BY 4.0: credit their authors wherever shown.
"""

from __future__ import annotations

import io
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import trimesh

from bulbjax.assets import mesh as meshlib
from bulbjax.assets.cache import cache_root, content_key, read_entry, write_entry

YCB_DIR_ENV = "BULBJAX_YCB_DIR"
OBJ_FILE = "google_16k/textured.obj"
TEXTURE_FILE = "google_16k/texture_map.png"
# Bump when the processing changes what ends up in the cache.
PIPELINE_VERSION = 3


@dataclass(frozen=True)
class YcbInfo:
    """bulb's numbers for one object: scale `s` of the model file, mass (kg), resting
    half-height `z` (m), and a flat colour for when the texture map is missing."""

    scale: tuple[float, float, float]
    mass: float
    half_height: float
    rgb: tuple[float, float, float]
    in_bulb: bool = True  # False: not one of bulb's objects; the numbers are ours


YCB_INFO: dict[str, YcbInfo] = {
    "002_master_chef_can": YcbInfo((1.0, 1.0, 0.95), 0.2, 0.068, (0.15, 0.35, 0.75)),
    # Not used by bulb: its own model scale, a box's mass as in bulb, half its height.
    "003_cracker_box": YcbInfo((1.0, 1.0, 1.0), 0.05, 0.107, (0.80, 0.15, 0.12), in_bulb=False),
    "004_sugar_box": YcbInfo((1.1, 1.1, 0.85), 0.05, 0.086, (0.95, 0.85, 0.25)),
    "005_tomato_soup_can": YcbInfo((1.3, 1.3, 1.2), 0.2, 0.05, (0.75, 0.12, 0.10)),
    "007_tuna_fish_can": YcbInfo((1.1, 1.1, 1.8), 0.2, 0.016, (0.45, 0.55, 0.70)),
    "008_pudding_box": YcbInfo((1.2, 1.2, 1.2), 0.05, 0.054, (0.45, 0.28, 0.15)),
    "009_gelatin_box": YcbInfo((1.4, 1.4, 1.4), 0.05, 0.0425, (0.85, 0.20, 0.20)),
    "013_apple": YcbInfo((1.1, 1.1, 1.1), 0.1, 0.04, (0.75, 0.15, 0.12)),
    "014_lemon": YcbInfo((1.3, 1.3, 1.3), 0.1, 0.033, (0.95, 0.85, 0.20)),
    "015_peach": YcbInfo((1.1, 1.1, 1.1), 0.1, 0.034, (0.95, 0.60, 0.40)),
    "016_pear": YcbInfo((1.1, 1.1, 1.1), 0.1, 0.04, (0.70, 0.75, 0.25)),
    "017_orange": YcbInfo((1.1, 1.1, 1.1), 0.1, 0.04, (0.98, 0.55, 0.10)),
    "018_plum": YcbInfo((1.4, 1.4, 1.4), 0.1, 0.03, (0.40, 0.10, 0.30)),
}


@dataclass(frozen=True, eq=False)
class YcbAsset:
    """One processed object, in metres, in the scaled model file's frame (origin = body frame).

    `visual_*` is the decimated render mesh (vertex i has texture coordinate `visual_uv[i]`,
    OBJ convention); `collision_*` its convex hull; `com` and `inertia` (about `com`, mesh axes)
    are those of the closed mesh (or its hull when the mesh is not closed) at bulb's mass.
    `rgba` is the colour to give the geom: white where there is a texture (the MuJoCo Warp
    renderer draws mesh textures; `texture_mean_rgb` is there for renderers that do not), else
    the object's flat colour.
    Files (`visual_path`, `collision_path`, `texture_path`) live in the cache folder."""

    name: str
    scale: tuple[float, float, float]  # bulb's s times the caller's scale
    mass: float
    visual_vertices: np.ndarray = field(repr=False)  # [V, 3]
    visual_faces: np.ndarray = field(repr=False)  # [F, 3]
    visual_uv: np.ndarray | None = field(repr=False)  # [V, 2]
    collision_vertices: np.ndarray = field(repr=False)  # [H, 3]
    collision_faces: np.ndarray = field(repr=False)  # [G, 3]
    com: np.ndarray  # [3]
    inertia: np.ndarray  # [3, 3]
    bounds: np.ndarray  # [2, 3] axis-aligned bounds of the full-resolution scaled mesh
    rgba: tuple[float, float, float, float]
    texture_path: Path | None
    texture_mean_rgb: tuple[float, float, float] | None  # mean colour of the textured surface
    visual_path: Path
    collision_path: Path
    inertia_source: str  # "mesh" or "hull"
    cache_path: Path
    from_cache: bool
    build_seconds: float  # processing time when built (as recorded in the cache)

    @property
    def half_extents(self) -> np.ndarray:
        return 0.5 * (self.bounds[1] - self.bounds[0])

    @property
    def bbox_center(self) -> np.ndarray:
        return 0.5 * (self.bounds[1] + self.bounds[0])

    @property
    def origin_offset(self) -> np.ndarray:
        """Position of the mesh origin (body frame) relative to the centre of mass."""
        return -self.com

    @property
    def rest_height(self) -> float:
        """Height of the body frame above a plane the object stands on upright (+z up)."""
        return float(-self.bounds[0, 2])


class YcbModelsNotFound(FileNotFoundError, ValueError):
    """The YCB models are not where the settings say. A FileNotFoundError for library code, and a
    ValueError, which the CLI turns into its one-line error (its message says what to set)."""


def _missing(reason: str) -> FileNotFoundError:
    names = ", ".join(YCB_INFO)
    return YcbModelsNotFound(
        f"YCB models not found: {reason}. Set {YCB_DIR_ENV} (or pass ycb_dir=) to a folder laid out "
        f"as in the YCB google_16k download: <dir>/<name>/{OBJ_FILE} (with texture_map.png beside "
        f"it where available), for the objects: {names}.")


def ycb_dir(ycb_dir: str | os.PathLike | None = None) -> Path:
    """Folder of the YCB models: `ycb_dir`, else `$BULBJAX_YCB_DIR`; raises FileNotFoundError
    (naming the variable, the path and the layout) when it is unset or not a folder."""
    if ycb_dir is None:
        ycb_dir = os.environ.get(YCB_DIR_ENV)
        if not ycb_dir:
            raise _missing(f"no ycb_dir was given and {YCB_DIR_ENV} is not set")
    path = Path(ycb_dir).expanduser()
    if not path.is_dir():
        raise _missing(f"{str(path)!r} (tried) is not a directory")
    return path


def ycb_object_files(name: str, root: str | os.PathLike | None = None) -> tuple[Path, Path | None]:
    """Paths of `name`'s mesh and texture map (None when the set has none for it), in the
    folder `root` (else `$BULBJAX_YCB_DIR`)."""
    if name not in YCB_INFO:
        raise KeyError(f"unknown YCB object {name!r}; known: {', '.join(YCB_INFO)}")
    folder = ycb_dir(root)
    obj = folder / name / OBJ_FILE
    if not obj.is_file():
        raise _missing(f"{str(obj)!r} (tried) does not exist")
    tex = folder / name / TEXTURE_FILE
    return obj, (tex if tex.is_file() else None)


def _scale3(name: str, scale: float | Sequence[float]) -> tuple[float, float, float]:
    mult = np.broadcast_to(np.asarray(scale, np.float64), (3,))
    if not np.all(mult > 0):
        raise ValueError(f"scale must be positive, got {scale}")
    return tuple(float(x) for x in np.asarray(YCB_INFO[name].scale) * mult)


def load_ycb_object(name: str, scale: float | Sequence[float] = 1.0,
                    ycb_dir: str | os.PathLike | None = None,
                    cache_dir: str | os.PathLike | None = None, max_faces: int = 2000,
                    texture_size: int = 256, max_hull_faces: int = 200) -> YcbAsset:
    """Processed object `name` at bulb's scale times `scale` (a number or a 3-vector).

    Read from the cache when these inputs (file bytes) and settings were processed before, else
    built and cached (see the module docstring); `asset.from_cache` says which."""
    if max_faces < 4 or max_hull_faces < 4 or texture_size < 1:
        raise ValueError("max_faces and max_hull_faces must be >= 4 and texture_size >= 1")
    obj_path, tex_path = ycb_object_files(name, ycb_dir)
    obj_bytes = obj_path.read_bytes()
    tex_bytes = tex_path.read_bytes() if tex_path is not None else None
    s = _scale3(name, scale)
    settings = {"name": name, "scale": s, "mass": YCB_INFO[name].mass, "max_faces": max_faces,
                "max_hull_faces": max_hull_faces, "texture_size": texture_size,
                "version": PIPELINE_VERSION}
    blobs = [obj_bytes] + ([tex_bytes] if tex_bytes is not None else [])
    folder = cache_root(cache_dir) / "ycb" / f"{name}-{content_key(blobs, settings)[:20]}"
    meta = read_entry(folder)
    if meta is None:
        files, meta = _build(name, s, obj_bytes, tex_bytes, max_faces, max_hull_faces, texture_size)
        write_entry(folder, files, meta)
        return _asset(folder, meta, from_cache=False)
    return _asset(folder, meta, from_cache=True)


def _build(name: str, s: tuple[float, float, float], obj_bytes: bytes, tex_bytes: bytes | None,
           max_faces: int, max_hull_faces: int, texture_size: int) -> tuple[dict[str, bytes], dict]:
    """The cache entry's files and metadata for one object."""
    t0 = time.perf_counter()
    info = YCB_INFO[name]
    src = trimesh.load(io.BytesIO(obj_bytes), file_type="obj", process=False, skip_materials=True)
    verts = np.asarray(src.vertices, np.float64) * np.asarray(s)
    faces = np.asarray(src.faces, np.int64)
    uv = getattr(src.visual, "uv", None)
    uv = None if uv is None or len(uv) != len(verts) else np.asarray(uv, np.float64)
    # UV seams split vertices in the file; merged, the surface is one closed mesh again
    closed = trimesh.Trimesh(verts, faces, process=True)

    dv, df = meshlib.decimate(np.asarray(closed.vertices), np.asarray(closed.faces), max_faces)
    n_fallback = 0
    if uv is not None:
        dv, df, duv, n_fallback = meshlib.transfer_uv(verts, faces, uv, dv, df)
    else:
        duv = None
    hv, hf = meshlib.simplified_hull(np.asarray(closed.vertices), max_hull_faces)
    if closed.is_watertight and closed.is_winding_consistent:
        com, inertia = meshlib.mass_properties(closed.vertices, closed.faces, info.mass)
        inertia_source = "mesh"
    else:
        full_hull = closed.convex_hull
        com, inertia = meshlib.mass_properties(full_hull.vertices, full_hull.faces, info.mass)
        inertia_source = "hull"

    files = {"visual.obj": meshlib.obj_text(dv, df, duv).encode(),
             "collision.obj": meshlib.obj_text(hv, hf).encode()}
    tex_mean = None
    if tex_bytes is not None and uv is not None:
        files["texture.png"], pixels = meshlib.downsample_texture(tex_bytes, texture_size, uv, faces)
        tex_mean = [float(x) for x in meshlib.mean_surface_colour(pixels, verts, faces, uv)]
        rgba = (1.0, 1.0, 1.0, 1.0)
    else:
        rgba = (*info.rgb, 1.0)
    arrays = {"visual_vertices": dv, "visual_faces": df.astype(np.int32),
              "collision_vertices": hv, "collision_faces": hf.astype(np.int32),
              "com": com, "inertia": inertia, "bounds": np.asarray(closed.bounds)}
    if duv is not None:
        arrays["visual_uv"] = duv
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    files["arrays.npz"] = buf.getvalue()
    meta = {"name": name, "scale": list(s), "mass": info.mass, "rgba": list(rgba),
            "texture_mean_rgb": tex_mean, "inertia_source": inertia_source,
            "visual_faces": len(df), "collision_faces": len(hf), "uv_fallback_corners": n_fallback,
            "pipeline_version": PIPELINE_VERSION, "build_seconds": time.perf_counter() - t0,
            "source": "YCB Object and Model Set (Calli et al. 2015), CC BY 4.0"}
    json.dumps(meta)  # fail here, not half-way through writing the entry
    return files, meta


def _asset(folder: Path, meta: dict, from_cache: bool) -> YcbAsset:
    with np.load(folder / "arrays.npz") as z:
        a = {k: z[k] for k in z.files}
    tex = folder / "texture.png"
    return YcbAsset(
        name=meta["name"], scale=tuple(meta["scale"]), mass=float(meta["mass"]),
        visual_vertices=a["visual_vertices"], visual_faces=a["visual_faces"],
        visual_uv=a.get("visual_uv"), collision_vertices=a["collision_vertices"],
        collision_faces=a["collision_faces"], com=a["com"], inertia=a["inertia"],
        bounds=a["bounds"], rgba=tuple(meta["rgba"]),
        texture_path=tex if tex.is_file() else None,
        texture_mean_rgb=tuple(meta["texture_mean_rgb"]) if meta["texture_mean_rgb"] else None,
        visual_path=folder / "visual.obj", collision_path=folder / "collision.obj",
        inertia_source=meta["inertia_source"], cache_path=folder, from_cache=from_cache,
        build_seconds=float(meta["build_seconds"]))
