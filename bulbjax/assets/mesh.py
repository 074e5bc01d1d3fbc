"""Mesh processing for object assets: decimation that keeps texture coordinates, simplified
convex hulls, mass properties, texture downsampling.

Pure functions on numpy arrays (vertices `[V, 3]`, faces `[F, 3]`, UVs `[V, 2]` in OBJ's
convention, v up from the image's bottom row); `ycb.py` strings them together and caches them.
"""

from __future__ import annotations

import io

import fast_simplification
import numpy as np
import trimesh
from PIL import Image, ImageDraw
from scipy import ndimage
from scipy.spatial import cKDTree


def decimate(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation (fast-simplification) to at most `max_faces` faces.

    The input should have coincident vertices merged (UV seams closed), else the seams tear."""
    if len(faces) <= max_faces:
        return vertices, faces
    target = max_faces
    for _ in range(8):  # the decimator can overshoot its target by a few faces: aim lower
        v, f = fast_simplification.simplify(vertices.astype(np.float64), faces.astype(np.int32),
                                            target_count=target)
        if len(f) <= max_faces:
            break
        target -= max(1, len(f) - max_faces)
    mesh = trimesh.Trimesh(v, f, process=True)  # drop unused vertices and degenerate faces
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.remove_unreferenced_vertices()
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def transfer_uv(src_vertices: np.ndarray, src_faces: np.ndarray, src_uv: np.ndarray,
                dst_vertices: np.ndarray, dst_faces: np.ndarray,
                k: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Texture coordinates for a simplified surface, from the original one.

    Each corner of each `dst` face takes the UV of its closest point on the `src` surface
    (barycentric interpolation of that triangle's UVs). Near a UV seam the closest point can lie
    on the far side of the seam, which would stretch one face across the texture atlas: so a
    corner only accepts source triangles whose UV lies near the UV of the face's own centre, and
    falls back to the affine map of the triangle under the face centre when none does.
    Returns (vertices, faces, uv) with vertices duplicated where corners disagree on their UV,
    and the number of corners that used the fallback."""
    src_faces = src_faces[trimesh.triangles.area(src_vertices[src_faces]) > 1e-14]  # no slivers
    tri = src_vertices[src_faces]  # [S, 3, 3]
    tri_uv = src_uv[src_faces]  # [S, 3, 2]
    tree = cKDTree(tri.mean(axis=1))
    k = min(k, len(src_faces))
    # UV length per metre of surface (median over edges), to turn 3-D distances into UV ones
    e3 = np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1)
    euv = np.linalg.norm(tri_uv[:, 1] - tri_uv[:, 0], axis=1)
    density = float(np.median(euv[e3 > 0] / e3[e3 > 0]))

    corners = dst_vertices[dst_faces]  # [F, 3, 3]
    centres = corners.mean(axis=1)
    ref_tri, _, ref_uv = _closest_on_surface(tree, tri, tri_uv, centres, k)

    pts = corners.reshape(-1, 3)
    n = len(pts)
    _, cand = tree.query(pts, k=k)  # [3F, k]
    cand_tri = tri[cand].reshape(-1, 3, 3)
    rep = np.repeat(pts, k, axis=0)
    cp = trimesh.triangles.closest_point(cand_tri, rep)
    dist = np.linalg.norm(cp - rep, axis=1).reshape(n, k)
    bary = trimesh.triangles.points_to_barycentric(cand_tri, cp)
    uv = np.einsum("ij,ijk->ik", bary, tri_uv[cand].reshape(-1, 3, 2)).reshape(n, k, 2)
    ref_uv_c = np.repeat(ref_uv, 3, axis=0)
    reach = np.linalg.norm(corners - centres[:, None], axis=-1).reshape(-1)
    radius = 3.0 * density * reach + 1e-3
    ok = np.linalg.norm(uv - ref_uv_c[:, None], axis=-1) <= radius[:, None]
    dist = np.where(ok, dist, np.inf)
    best = np.argmin(dist, axis=1)
    out_uv = uv[np.arange(n), best]
    fallback = ~np.isfinite(dist[np.arange(n), best])
    if fallback.any():
        t = np.repeat(ref_tri, 3)[fallback]
        b = trimesh.triangles.points_to_barycentric(tri[t], pts[fallback])
        out_uv[fallback] = np.einsum("ij,ijk->ik", b, tri_uv[t])

    # one output vertex per distinct (position, uv) pair
    vid = dst_faces.reshape(-1)
    key = np.column_stack([vid.astype(np.float64), np.round(out_uv, 6)])
    uniq, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    first = np.zeros(len(uniq), np.int64)
    first[inverse] = np.arange(n)
    return (dst_vertices[vid[first]], inverse.reshape(-1, 3).astype(np.int64),
            out_uv[first], int(fallback.sum()))


def _closest_on_surface(tree: cKDTree, tri: np.ndarray, tri_uv: np.ndarray, pts: np.ndarray,
                        k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest source triangle (among the `k` nearest by centroid), closest point and its UV."""
    _, cand = tree.query(pts, k=k)
    cand_tri = tri[cand].reshape(-1, 3, 3)
    rep = np.repeat(pts, k, axis=0)
    cp = trimesh.triangles.closest_point(cand_tri, rep)
    dist = np.linalg.norm(cp - rep, axis=1).reshape(len(pts), k)
    best = np.argmin(dist, axis=1)
    t = cand[np.arange(len(pts)), best]
    point = cp.reshape(len(pts), k, 3)[np.arange(len(pts)), best]
    bary = trimesh.triangles.points_to_barycentric(tri[t], point)
    return t, point, np.einsum("ij,ijk->ik", bary, tri_uv[t])


def uv_stretch(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Per face: UV area over 3-D area (texture density squared), for checking a UV transfer."""
    area3 = trimesh.triangles.area(vertices[faces])
    t = uv[faces]
    area_uv = 0.5 * np.abs((t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1])
                           - (t[:, 2, 0] - t[:, 0, 0]) * (t[:, 1, 1] - t[:, 0, 1]))
    return area_uv / np.maximum(area3, 1e-18)


def simplified_hull(vertices: np.ndarray, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull of `vertices` with at most `max_faces` faces, spanned by a subset of the full
    hull's vertices (so it lies inside it, and keeps its extreme points along each axis): the six
    axis extremes, then farthest-point sampling. A convex triangle mesh with n vertices has at
    most 2n - 4 faces."""
    hull = trimesh.convex.convex_hull(vertices)
    if len(hull.faces) <= max_faces:
        return np.asarray(hull.vertices), np.asarray(hull.faces)
    pts = np.asarray(hull.vertices)
    n = max(4, max_faces // 2 + 2)
    chosen = list(dict.fromkeys(np.concatenate([pts.argmin(0), pts.argmax(0)]).tolist()))
    d = np.min(np.linalg.norm(pts[:, None] - pts[chosen][None], axis=-1), axis=1)
    while len(chosen) < n:
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(pts - pts[i], axis=1))
    small = trimesh.convex.convex_hull(pts[chosen])
    return np.asarray(small.vertices), np.asarray(small.faces)


def mass_properties(vertices: np.ndarray, faces: np.ndarray, mass: float) -> tuple[np.ndarray, np.ndarray]:
    """Centre of mass and 3x3 inertia about it (mesh axes) of a closed mesh of uniform density
    and total `mass`."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if mesh.volume < 0:
        mesh.invert()
    props = trimesh.triangles.mass_properties(mesh.triangles, density=1.0, skip_inertia=False)
    volume = float(props.volume)
    inertia = np.asarray(props.inertia) * (mass / volume)
    return np.asarray(props.center_mass), 0.5 * (inertia + inertia.T)


def downsample_texture(png_bytes: bytes, size: int, uv: np.ndarray | None = None,
                       faces: np.ndarray | None = None) -> tuple[bytes, np.ndarray]:
    """The texture as a `size` x `size` RGB PNG and its pixels `[size, size, 3]`.

    With the mesh's `uv` and `faces`, only texels the mesh covers are averaged (the atlas'
    background does not darken the charts' borders) and the background is then filled with the
    nearest chart colour, so lookups that land a little outside a chart (filtering, or a
    decimated face across a seam) do not show the background."""
    img = Image.open(io.BytesIO(png_bytes)).convert("RGB")
    if uv is None or faces is None:
        small = img.resize((size, size), Image.Resampling.BOX) if img.size != (size, size) else img
        pixels = np.asarray(small)
    else:
        work = min(img.size[0], 4 * size)  # coverage at 4x the output's resolution is plenty
        if img.size != (work, work):
            img = img.resize((work, work), Image.Resampling.BOX)
        w, h = img.size
        mask = Image.new("L", img.size, 0)
        draw = ImageDraw.Draw(mask)
        tri = uv[faces] * np.array([w, h])
        tri[..., 1] = h - tri[..., 1]  # OBJ's v counts up from the image's bottom row
        for t in tri:
            draw.polygon([tuple(p) for p in t], fill=255, outline=255)
        img = Image.composite(img, Image.new("RGB", img.size), mask)
        m = np.asarray(mask.resize((size, size), Image.Resampling.BOX), np.float64)[..., None]
        c = np.asarray(img.resize((size, size), Image.Resampling.BOX), np.float64)
        covered = m[..., 0] > 0
        rgb = np.where(covered[..., None], c * 255.0 / np.maximum(m, 1e-9), 0.0)
        if covered.any() and not covered.all():
            _, (ri, ci) = ndimage.distance_transform_edt(~covered, return_indices=True)
            rgb = rgb[ri, ci]
        pixels = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format="PNG")
    return buf.getvalue(), pixels


def mean_surface_colour(pixels: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                        uv: np.ndarray) -> np.ndarray:
    """Area-weighted mean RGB in [0, 1] of the texture over the surface (sampled at face
    centres; the atlas' unused background does not count)."""
    h, w = pixels.shape[:2]
    c = uv[faces].mean(axis=1)
    col = np.clip((c[:, 0] % 1.0) * w, 0, w - 1).astype(int)
    row = np.clip((1.0 - c[:, 1] % 1.0) * h, 0, h - 1).astype(int)
    area = trimesh.triangles.area(vertices[faces])
    return (pixels[row, col].astype(np.float64) / 255.0 * area[:, None]).sum(0) / area.sum()


def obj_text(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None = None) -> str:
    """Wavefront OBJ text; with `uv`, vertex i has texture coordinate i (`f a/a b/b c/c`)."""
    lines = [f"v {x:.7g} {y:.7g} {z:.7g}" for x, y, z in vertices]
    if uv is not None:
        lines += [f"vt {u:.7g} {v:.7g}" for u, v in uv]
        lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in faces + 1]
    else:
        lines += [f"f {a} {b} {c}" for a, b, c in faces + 1]
    return "\n".join(lines) + "\n"
