"""Object-level probe for structured learners (SPAIR): do present boxes sit on the true objects?

Given a learner's boxes (`SPAIR.boxes`: centres in pixels, presence probabilities) and each
true object's image position in pixels (both (x, y) from the frame's top-left corner), the
probe measures per object the distance to the nearest *present* box centre (presence above
`threshold`) and whether one lies within `radius` pixels, and per frame the present boxes that
are near no object (spurious). `object_scores` is the jittable core (per frame and object);
`summarise` is the host-side summary (per object and averaged). Frames without any present box
give the object an infinite distance: it counts as not found and is left out of the mean error
(the share of such objects is reported as `missing`).
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np


def object_scores(
    centres: jax.Array,
    pres: jax.Array,
    positions: jax.Array,
    radius: float,
    threshold: float = 0.5,
) -> dict[str, jax.Array]:
    """Per-frame object scores; pure and jittable.

    centres [B, K, 2] box centres (px), pres [B, K] presence probabilities, positions [B, M, 2]
    true object positions (px). Returns `distance` [B, M] (to the nearest present box centre;
    inf if none is present), `found` [B, M] (distance <= radius), `nearest` [B, M] (index of
    that box; -1 if none), `spurious` [B] (present boxes farther than radius from every
    object) and `present` [B] (present boxes)."""
    on = pres > threshold  # [B, K]
    d = jnp.linalg.norm(positions[:, :, None, :] - centres[:, None, :, :], axis=-1)  # [B, M, K]
    d_on = jnp.where(on[:, None, :], d, jnp.inf)
    distance = d_on.min(axis=-1)
    nearest = jnp.where(jnp.isfinite(distance), d_on.argmin(axis=-1), -1)
    near_any = (d <= radius).any(axis=1)  # [B, K]: box within radius of some object
    return {
        "distance": distance,
        "found": distance <= radius,
        "nearest": nearest,
        "spurious": (on & ~near_any).sum(-1),
        "present": on.sum(-1),
    }


def summarise(scores: dict[str, jax.Array], names: Sequence[str] | None = None,
              valid: np.ndarray | None = None) -> dict[str, object]:
    """Host-side summary of `object_scores` (any leading axes before [B, M] are pooled; with
    `valid` (bool, the scores' leading shape) only those frames count).

    Returns `error` (mean distance in px over frames where a box is present) and `found`
    (share found within the radius) per object (keyed by `names`, default "object0", ...) and
    averaged over objects (`error_mean`, `found_share`), plus `missing` (share of objects in
    frames without any present box), `spurious_per_frame` and `present_per_frame`."""
    dist = np.asarray(jax.device_get(scores["distance"]), np.float64)
    found = np.asarray(jax.device_get(scores["found"]), np.float64)
    m = dist.shape[-1]
    dist, found = dist.reshape(-1, m), found.reshape(-1, m)
    spurious = np.asarray(jax.device_get(scores["spurious"]), np.float64).reshape(-1)
    present = np.asarray(jax.device_get(scores["present"]), np.float64).reshape(-1)
    if valid is not None:
        keep = np.asarray(valid, bool).reshape(-1)
        dist, found, spurious, present = dist[keep], found[keep], spurious[keep], present[keep]
    names = list(names) if names is not None else [f"object{i}" for i in range(m)]
    if len(names) != m:
        raise ValueError(f"{len(names)} names for {m} objects")
    finite = np.isfinite(dist)

    def mean_err(col: np.ndarray, ok: np.ndarray) -> float:
        return float(col[ok].mean()) if ok.any() else float("inf")

    per_object = {
        n: {"error": mean_err(dist[:, i], finite[:, i]), "found": float(found[:, i].mean())}
        for i, n in enumerate(names)
    }
    return {
        "per_object": per_object,
        "error_mean": mean_err(dist, finite),
        "found_share": float(found.mean()),
        "missing": float(1.0 - finite.mean()),
        "spurious_per_frame": float(spurious.mean()),
        "present_per_frame": float(present.mean()),
    }


def reduce_scores(scores: dict[str, jax.Array], valid: jax.Array | None = None) -> dict[str, jax.Array]:
    """The numbers of `summarise` as arrays, jittable (in the experiment's epoch, per seed):
    `error` [M] and `found` [M] per object, `error_mean`, `found_share`, `missing`,
    `spurious_per_frame`, `present_per_frame` (scalars). Leading axes before [B, M] are pooled;
    with `valid` (bool, the scores' leading shape) only those frames count. An object never seen
    next to a present box has error inf (as in `summarise`); no valid frame gives NaN shares."""
    dist = scores["distance"]
    m = dist.shape[-1]
    dist, found = dist.reshape((-1, m)), scores["found"].reshape((-1, m))
    v = jnp.ones(dist.shape[:1], bool) if valid is None else jnp.asarray(valid, bool).reshape(-1)
    vf = v.astype(jnp.float32)
    ok = jnp.isfinite(dist) & v[:, None]  # a present box in a valid frame
    safe = jnp.where(ok, dist, 0.0)
    n_obj, n_all = ok.sum(0), ok.sum()
    frames = vf.sum()
    per = lambda x: (x.reshape(-1).astype(jnp.float32) * vf).sum() / frames  # noqa: E731
    found_o = (found & v[:, None]).sum(0).astype(jnp.float32) / frames
    return {
        "error": jnp.where(n_obj > 0, safe.sum(0) / jnp.maximum(n_obj, 1), jnp.inf),
        "found": found_o,
        "error_mean": jnp.where(n_all > 0, safe.sum() / jnp.maximum(n_all, 1), jnp.inf),
        "found_share": found_o.mean(),
        "missing": 1.0 - n_all / (frames * m),
        "spurious_per_frame": per(scores["spurious"]),
        "present_per_frame": per(scores["present"]),
    }


def summary_of(reduced: dict, names: Sequence[str] | None = None) -> dict[str, object]:
    """`reduce_scores`' arrays of one evaluation (host side) as `summarise`'s dict: `per_object`
    {name: {error, found}}, `error_mean`, `found_share`, `missing`, `spurious_per_frame`,
    `present_per_frame`, and `radius` (px) where `reduced` carries it."""
    err = np.asarray(reduced["error"], np.float64).reshape(-1)
    fnd = np.asarray(reduced["found"], np.float64).reshape(-1)
    names = list(names) if names is not None else [f"object{i}" for i in range(len(err))]
    if len(names) != len(err):
        raise ValueError(f"{len(names)} names for {len(err)} objects")
    out: dict[str, object] = {
        "per_object": {n: {"error": float(err[i]), "found": float(fnd[i])} for i, n in enumerate(names)}}
    for k in ("error_mean", "found_share", "missing", "spurious_per_frame", "present_per_frame", "radius"):
        if k in reduced:
            out[k] = float(np.asarray(reduced[k]))
    return out


# ---------------------------------------------------------------------------- true positions
def project_points(points: jax.Array, cam_pos: jax.Array, cam_mat: jax.Array, fovy_deg: float,
                   resolution: int) -> jax.Array:
    """World points [..., 3] -> image positions [..., 2] in pixels, (x, y) from the frame's
    top-left corner (a pixel's centre at +0.5), for a square frame of `resolution` pixels seen by
    a pinhole camera at `cam_pos` [3] with orientation `cam_mat` [3, 3] (columns: the camera's
    x right, y up, z backwards, MuJoCo's `cam_xmat`) and vertical field of view `fovy_deg`: the
    convention of the renderer's rays (`bulbjax.envs.render.camera_rays`). Jittable."""
    local = (points - cam_pos) @ cam_mat  # camera frame
    half = np.tan(np.deg2rad(fovy_deg) / 2.0)
    depth = -local[..., 2]
    u = local[..., 0] / (depth * half)
    v = local[..., 1] / (depth * half)
    return jnp.stack([(1.0 + u) * resolution / 2.0, (1.0 - v) * resolution / 2.0], axis=-1)


def world_camera(mj_model, camera: str = "bulb") -> tuple[np.ndarray, np.ndarray, float]:
    """(position [3], orientation [3, 3], fovy in degrees) of a camera fixed in the world
    (host-side, from the model at its reference pose); other cameras move with their body and
    are refused."""
    import mujoco

    cid = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    if cid < 0:
        raise ValueError(f"no camera {camera!r} in the model")
    if mj_model.cam_bodyid[cid] != 0 or mj_model.cam_mode[cid] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED:
        raise ValueError(f"camera {camera!r} moves with its body: object pixels need a world-fixed camera")
    data = mujoco.MjData(mj_model)
    mujoco.mj_kinematics(mj_model, data)
    mujoco.mj_camlight(mj_model, data)
    return (np.array(data.cam_xpos[cid], np.float32), np.array(data.cam_xmat[cid], np.float32).reshape(3, 3),
            float(mj_model.cam_fovy[cid]))


# ---------------------------------------------------------------------------- in the experiment
def default_radius(resolution: int) -> float:
    """The radius (px) within which a present box counts as finding an object: a tenth of the
    frame (6.4 px at 64 px, about half the size of a Rearrange object in the image)."""
    return resolution / 10.0


def object_names(spec: Sequence) -> list[str]:
    """Objects whose x, y, z are state entries `<name>_x/_y/_z` of group `object_position`."""
    names = {e.name for e in spec}
    objs = sorted({e.name.rsplit("_", 1)[0] for e in spec
                   if e.group == "object_position" and e.name.rsplit("_", 1)[-1] in ("x", "y", "z")})
    return [o for o in objs if all(f"{o}_{a}" in names for a in "xyz")]


def table(records: Sequence[dict], last: int = 1) -> str:
    """Markdown table of the object-level probe in metrics.jsonl records (`record["objects"]
    [learner][stream]`, from `summarise`): mean error (px) and share found per object and
    averaged, mean over seeds and the `last` epochs that have it. Empty without such records."""
    recs = [r for r in records if r.get("objects")]
    if not recs:
        return ""
    epochs = sorted({r["epoch"] for r in recs})[-last:]
    recs = [r for r in recs if r["epoch"] in epochs]
    first = recs[0]["objects"]
    learner = next(iter(first))
    stream = next(iter(first[learner]))
    objs = list(first[learner][stream]["per_object"])
    head = "| learner | stream | mean error (px) | found | " + " | ".join(f"{o} (px)" for o in objs) + " | spurious/frame |"
    lines = [head, "|" + "---|" * (5 + len(objs))]

    def avg(vals: list[float]) -> str:
        v = np.asarray(vals, np.float64)
        v = v[np.isfinite(v)]
        return f"{v.mean():.2f}" if v.size else "–"

    for name in first:
        for st in first[name]:
            rows = [r["objects"][name][st] for r in recs]
            cells = [avg([x["error_mean"] for x in rows]), avg([x["found_share"] for x in rows])]
            cells += [avg([x["per_object"][o]["error"] for x in rows]) for o in objs]
            cells.append(avg([x["spurious_per_frame"] for x in rows]))
            lines.append(f"| {name} | {st} | " + " | ".join(cells) + " |")
    seeds = len({r["seed"] for r in recs})
    lines.append("")
    lines.append(f"Object-level probe: distance from each true object's image position to the nearest "
                 f"present box centre; found = within the radius; epochs {', '.join(map(str, epochs))}, "
                 f"mean over {seeds} seeds.")
    return "\n".join(lines)


_STREAM_LABELS = {"curr": "π_curr", "rand": "π_rand"}


def comparison_table(records: Sequence[dict], spec: Sequence, last: int = 1) -> str:
    """Markdown table of the object-level probes side by side, one row per learner and stream
    (mean over seeds and the `last` probed epochs): the standard MLP probe's normalised error on
    the `object_position` group (every learner; the comparable probe of VAE_rpl & co.) and, for
    learners with boxes (`record["objects"]`), the box probe's mean distance (px) from each true
    object to the nearest present box centre, the share found within the radius and spurious
    boxes per frame; then per object `MLP / boxes`: the MLP's normalised error averaged over the
    object's x, y, z and the box error (px). Empty for domains without objects in the state."""
    objs = object_names(spec)
    recs = [r for r in records if r.get("probes") or r.get("objects")]
    if not objs or not recs:
        return ""
    epochs = sorted({r["epoch"] for r in recs})[-last:]
    recs = [r for r in recs if r["epoch"] in epochs]
    learners = list(dict.fromkeys(n for r in recs for n in (*r.get("probes", {}), *r.get("objects", {}))))
    streams = list(dict.fromkeys(st for r in recs for n in learners
                                 for st in (*r.get("probes", {}).get(n, {}), *r.get("objects", {}).get(n, {}))))

    def avg(vals: list, digits: int) -> str:
        v = np.asarray([x for x in vals if x is not None], np.float64)
        v = v[np.isfinite(v)]
        return f"{v.mean():.{digits}f}" if v.size else "–"

    def mlp(r: dict, name: str, st: str, obj: str | None) -> float | None:
        p = r.get("probes", {}).get(name, {}).get(st)
        if p is None:
            return None
        if obj is None:
            g = p["groups"].get("object_position")
            return None if g is None else g["mae_norm"]
        vals = [p["entries"][f"{obj}_{a}"]["mae_norm"] for a in "xyz" if f"{obj}_{a}" in p["entries"]]
        return float(np.nanmean(vals)) if vals and np.isfinite(vals).any() else None

    def box(r: dict, name: str, st: str, key: str, obj: str | None = None) -> float | None:
        o = r.get("objects", {}).get(name, {}).get(st)
        if o is None:
            return None
        return o["per_object"].get(obj, {}).get("error") if obj else o.get(key)

    head = ("| learner | stream | MLP: object_position (norm. MAE) | boxes: mean error (px) | boxes: found | "
            "boxes: spurious/frame | " + " | ".join(f"{o}: MLP / boxes (px)" for o in objs) + " |")
    lines = [head, "|" + "---|" * (6 + len(objs))]
    for name in learners:
        for st in streams:
            if not any(r.get("probes", {}).get(name, {}).get(st) or r.get("objects", {}).get(name, {}).get(st)
                       for r in recs):
                continue
            cells = [avg([mlp(r, name, st, None) for r in recs], 3),
                     avg([box(r, name, st, "error_mean") for r in recs], 2),
                     avg([box(r, name, st, "found_share") for r in recs], 2),
                     avg([box(r, name, st, "spurious_per_frame") for r in recs], 2)]
            cells += [f"{avg([mlp(r, name, st, o) for r in recs], 3)} / {avg([box(r, name, st, '', o) for r in recs], 2)}"
                      for o in objs]
            lines.append(f"| {name} | {_STREAM_LABELS.get(st, st)} | " + " | ".join(cells) + " |")
    radii = sorted({o[st]["radius"] for r in recs for o in r.get("objects", {}).values() for st in o
                    if "radius" in o[st]})
    rad = f" ({', '.join(f'{x:g}' for x in radii)} px)" if radii else ""
    seeds = len({r["seed"] for r in recs})
    lines.append("")
    lines.append(f"Object-level probes, epochs {', '.join(map(str, epochs))}, mean over {seeds} seeds. MLP: the "
                 "standard probe's normalised error (MAE / reference spread) on the objects' positions "
                 "(per object: mean over x, y, z). Boxes (learners with boxes): distance from each true "
                 "object's image position to the nearest present box centre (presence > 0.5), in pixels, "
                 f"over frames with a present box; found = share of objects with one within the radius{rad}.")
    return "\n".join(lines)
