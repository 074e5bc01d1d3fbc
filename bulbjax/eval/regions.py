"""Reconstruction error per object region: does a learner's reconstruction show each object?

The paper judges by eye that on YCB "no learner's reconstruction is clear" (Sec. IV.C, Fig. 4).
This measures it. Each object's region in a frame is the disc of `radius` pixels around its true
image position (`objects.project_points` of the state; no segmentation is needed, and the same
disc serves every learner). In that disc the squared error of the learner's reconstruction is
compared with that of the held-out frames' mean image, the reconstruction that knows nothing of
the frame at hand (it shows where objects usually are, blurred):

    ratio = sum over frames and disc pixels of (recon - frame)^2
            / sum over the same pixels of (mean_frame - frame)^2

0 is a perfect reconstruction of the object, 1 is no better than the mean image, above 1 is
worse (e.g. a sharp object drawn in the wrong place). A region is called *clear* when its ratio
is below `CLEAR` (the reconstruction removes more than half of the mean image's error there).
Frames whose object centre lies outside the image add nothing (an empty disc).
"""

from __future__ import annotations

import glob
import json
import os
from typing import Any

import numpy as np

CLEAR = 0.5  # ratio below which an object's region counts as reconstructed clearly
FILE = "regions_{epoch}.json"  # in a run folder: `RunFigures.regions` of that epoch


def disc_masks(positions: np.ndarray, radius: float, height: int, width: int) -> np.ndarray:
    """Boolean masks `[B, M, H, W]` of the discs of `radius` px around `positions` `[B, M, 2]`
    ((x, y) px from the top-left corner, a pixel's centre at +0.5, as `objects.project_points`)."""
    positions = np.asarray(positions, np.float64)
    ys = np.arange(height, dtype=np.float64) + 0.5
    xs = np.arange(width, dtype=np.float64) + 0.5
    dx = xs[None, None, None, :] - positions[..., 0][..., None, None]
    dy = ys[None, None, :, None] - positions[..., 1][..., None, None]
    return dx * dx + dy * dy <= float(radius) ** 2


def region_scores(frames: np.ndarray, recon: np.ndarray, positions: np.ndarray, radius: float) -> dict[str, Any]:
    """Per object: the reconstruction's squared error in its disc (`error`, mean per disc pixel
    and channel), the mean image's (`baseline`), their `ratio` (NaN where no frame shows the
    object) and the disc `pixels` counted. `frames`, `recon`: float `[B, H, W, C]` in [0, 1];
    `positions`: `[B, M, 2]` px. Lists of M floats (JSON-ready)."""
    frames = np.asarray(frames, np.float64)
    recon = np.asarray(recon, np.float64)
    if frames.shape != recon.shape or frames.ndim != 4:
        raise ValueError(f"frames {frames.shape} and reconstructions {recon.shape} must both be [B, H, W, C]")
    b, h, w, _ = frames.shape
    if positions.shape[:1] != (b,) or positions.shape[-1] != 2:
        raise ValueError(f"positions {positions.shape} must be [B, M, 2] for {b} frames")
    masks = disc_masks(positions, radius, h, w).astype(np.float64)  # [B, M, H, W]
    err = ((recon - frames) ** 2).sum(-1)  # [B, H, W]
    base = ((frames.mean(0, keepdims=True) - frames) ** 2).sum(-1)
    pixels = masks.sum((0, 2, 3))  # [M]
    e = np.einsum("bmhw,bhw->m", masks, err)
    z = np.einsum("bmhw,bhw->m", masks, base)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where((pixels > 0) & (z > 0), e / z, np.nan)
        channels = frames.shape[-1]
        error = np.where(pixels > 0, e / (pixels * channels), np.nan)
        baseline = np.where(pixels > 0, z / (pixels * channels), np.nan)
    return {"error": error.tolist(), "baseline": baseline.tolist(), "ratio": ratio.tolist(),
            "pixels": pixels.astype(int).tolist()}


def _epochs(run_dir: str) -> dict[int, str]:
    """{epoch: path} of the `regions_<epoch>.json` files in `run_dir`."""
    files = glob.glob(os.path.join(run_dir, FILE.format(epoch="*")))
    return {int(os.path.basename(f).split("_")[1].split(".")[0]): f for f in files}


def newest(run_dir: str) -> dict[str, Any] | None:
    """The region errors of the latest epoch in `run_dir` (`regions_<epoch>.json`), or None."""
    files = _epochs(run_dir)
    if not files:
        return None
    with open(files[max(files)]) as f:
        return json.load(f)


def pooled(run_dirs: list[str]) -> dict[str, Any] | None:
    """The region errors of several runs' seeds as one run's, as `merge.merge_seeds` pools their
    records: of the latest epoch that every run measured, each learner's per-seed lists
    concatenated run after run. None when some run measured no epoch that all did, or the runs
    measured differently (objects, disc radius, frames, learners): nothing is pooled then, and the
    merged findings say the claim is not tested, as for a run without the files."""
    found = [_epochs(d) for d in run_dirs]
    common = set.intersection(*(set(f) for f in found)) if found else set()
    if not common:
        return None
    epoch = max(common)
    runs = []
    for f in found:
        with open(f[epoch]) as fh:
            runs.append(json.load(fh))
    how = ("objects", "radius_px", "frames", "clear_below")
    if any([r.get(k) for k in how] != [runs[0].get(k) for k in how]
           or sorted(r["learners"]) != sorted(runs[0]["learners"]) for r in runs):
        return None
    learners = {name: {key: [row for r in runs for row in r["learners"][name][key]]
                       for key in scores}
                for name, scores in runs[0]["learners"].items()}
    return {**runs[0], "seeds": sum(int(r["seeds"]) for r in runs), "learners": learners}
