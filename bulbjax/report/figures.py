"""Figures of learners: the paper's reconstruction grid (Fig. 4) and SPAIR's boxes (Fig. 5).

Fig. 4 (`recon_figure`): a row of true frames, then one row of reconstructions per learner
(frame learners reconstruct each frame, sequential learners each window). Fig. 5
(`boxes_figure`): SPAIR's present boxes (presence above a threshold) drawn over the true frames,
one colour per grid cell, then SPAIR's reconstruction and its background model's output.

The images are composed in numpy at an integer upscale (nearest neighbour, so every frame pixel
is a `scale x scale` block) and written by matplotlib at exactly their pixel size, labels in a
left margin; `Layout` says where each frame lies in the PNG (tests compare pixel blocks). All
inputs are host arrays or what the learners' `reconstruct`/`boxes`/`background` return for
one seed's params; `seed_params` picks a seed out of a run's vmapped learner states.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import jax
import numpy as np

from bulbjax.data.sequence import Windows
from bulbjax.learners import is_sequential


@dataclass(frozen=True)
class FigureConfig:
    """What the figures show: `frames` columns, the learners of `seed`, frames upscaled by
    `scale`, SPAIR boxes whose presence exceeds `threshold`, drawn `line` px wide."""

    frames: int = 8
    seed: int = 0
    scale: int = 2
    threshold: float = 0.5
    line: int = 1

    def __post_init__(self) -> None:
        if self.frames < 1 or self.scale < 1 or self.line < 1:
            raise ValueError(f"frames, scale and line must be >= 1, got {self}")


@dataclass(frozen=True)
class Layout:
    """Pixel geometry of a figure: frame `col` of row `row` occupies rows
    `[y, y + h*scale)` and columns `[x, x + w*scale)` of the PNG, `(y, x) = origin(row, col)`."""

    rows: int
    cols: int
    height: int  # frame size in frame pixels
    width: int
    scale: int
    left: int = 96  # label margin
    top: int = 24  # title margin
    gap: int = 4

    def origin(self, row: int, col: int) -> tuple[int, int]:
        return (self.top + row * (self.height * self.scale + self.gap),
                self.left + col * (self.width * self.scale + self.gap))

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the whole PNG in pixels."""
        return self.origin(self.rows, self.cols)  # the last gap is the bottom/right margin


# ---------------------------------------------------------------------------- host arrays
def seed_params(states: Mapping[str, Any], seed: int = 0) -> dict[str, Any]:
    """The params of one seed out of vmapped learner states `{name: LearnerState [S]}`."""
    out = {}
    for name, st in states.items():
        n = jax.tree.leaves(st.params)[0].shape[0]
        if not 0 <= seed < n:
            raise ValueError(f"seed {seed} out of range: learner {name} has {n} seeds (0..{n - 1})")
        out[name] = jax.tree.map(lambda x: x[seed], st.params)
    return out


def _as_windows(batch: Windows | np.ndarray | jax.Array) -> Windows:
    """Windows [B, L, ...] from Windows or from uint8 frames [B, H, W, 3] (one-step windows)."""
    if isinstance(batch, Windows):
        if batch.frames.ndim != 5:
            raise ValueError(f"figure batch: windows' frames must be [B, L, H, W, 3] (one seed), "
                             f"got {batch.frames.shape}")
        return batch
    f = np.asarray(batch)
    if f.ndim != 4 or f.dtype != np.uint8:
        raise ValueError(f"figure batch: uint8 frames [B, H, W, 3] or Windows, got {f.dtype} {f.shape}")
    b = f.shape[0]
    return Windows(frames=f[:, None], actions=np.zeros((b, 1, 1), np.float32),
                   states=np.zeros((b, 1, 0), np.float32), valid=np.ones((b, 1), bool))


def _take(batch: Windows, n: int) -> tuple[Windows, np.ndarray]:
    """The first ceil(n / L) windows and their first `n` frames (uint8 [n', H, W, 3])."""
    w = _as_windows(batch)
    length = w.frames.shape[1]
    k = min(w.frames.shape[0], -(-n // length))
    w = jax.tree.map(lambda x: x[:k], w)
    frames = np.asarray(w.frames).reshape((-1,) + tuple(w.frames.shape[2:]))[:n]
    return w, frames


_JITTED: dict[tuple[int, str], tuple[Any, Any]] = {}  # (learner, its call)


def jitted(learner: Any, method: str) -> Any:
    """`learner.<method>` under `jax.jit`, made once per learner and method. Called eagerly, a
    learner's forward pass compiles each of its operations on first use: a run's first pictures
    on an H200 took ~55-100 s (Fig. 5's SPAIR decoders) and later ones seconds; jitted, each is one
    program, which the compile cache also keeps for the next process. A method that does not
    trace (host code: NumPy on its inputs) runs as it is, from its first call on. The entry keeps
    its learner alive, so no other learner takes its id."""
    key = (id(learner), method)
    if key not in _JITTED:
        plain, fast = getattr(learner, method), jax.jit(getattr(learner, method))
        traces = [True]

        def call(*args: Any) -> Any:
            if traces[0]:
                try:
                    return fast(*args)
                except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
                    traces[0] = False
            return plain(*args)

        _JITTED[key] = (learner, call)
    return _JITTED[key][1]


def reconstructions(learners: Mapping[str, Any], params: Mapping[str, Any],
                    batch: Windows | np.ndarray, n: int = 8) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """True frames float [n', H, W, 3] in [0, 1] (the first `n` frames of `batch`, window by
    window) and each learner's reconstruction of them `{name: [n', H, W, 3]}`. Sequential
    learners need Windows of at least their window length; frame learners take any batch."""
    w, frames = _take(batch, n)
    n_ = frames.shape[0]
    out = {}
    for name, learner in learners.items():
        if name not in params:
            raise ValueError(f"no params for learner {name!r} (have {sorted(params)})")
        if is_sequential(learner):
            if not isinstance(batch, Windows):
                raise ValueError(f"sequential learner {name!r} reconstructs windows: pass Windows")
            rec = np.asarray(jitted(learner, "reconstruct")(params[name], jax.tree.map(np.asarray, w)))
            rec = rec[:, : w.frames.shape[1]]  # PRED appends its forecast
            rec = rec.reshape((-1,) + rec.shape[2:])[:n_]
        else:
            rec = np.asarray(jitted(learner, "reconstruct")(params[name], frames))
        out[name] = np.clip(rec.astype(np.float32), 0.0, 1.0)
    return frames.astype(np.float32) / 255.0, out


def spair_outputs(spair: Any, params: Any, batch: Windows | np.ndarray, n: int = 8) -> dict[str, np.ndarray]:
    """What Fig. 5 shows for the first `n` frames: `frames` [n, H, W, 3] in [0, 1], `centres`,
    `sizes` [n, K, 2] px (x, y), `pres` [n, K], `recon` and `background` [n, H, W, 3]."""
    if not hasattr(spair, "boxes"):
        raise ValueError(f"{type(spair).__name__} has no boxes: the boxes figure is SPAIR's")
    _, frames = _take(batch, n)
    centres, sizes, pres = (np.asarray(a) for a in jitted(spair, "boxes")(params, frames))
    return {"frames": frames.astype(np.float32) / 255.0, "centres": centres, "sizes": sizes,
            "pres": pres, "recon": np.clip(np.asarray(jitted(spair, "reconstruct")(params, frames)), 0, 1),
            "background": np.clip(np.asarray(jitted(spair, "background")(params, frames)), 0, 1)}


# ---------------------------------------------------------------------------- images
def cell_colours(k: int) -> np.ndarray:
    """One distinct RGB colour in [0, 1] per grid cell [k, 3] (fully saturated hues)."""
    import matplotlib.colors as mcolors

    hues = (np.arange(k) * 0.618033988749895) % 1.0  # golden-ratio steps: neighbours differ
    return mcolors.hsv_to_rgb(np.stack([hues, np.ones(k), np.ones(k)], -1)).astype(np.float32)


def compose(rows: Sequence[np.ndarray], scale: int = 2) -> tuple[np.ndarray, Layout]:
    """Rows of frames (each [k, H, W, 3] float in [0, 1]) as one white RGB image with the
    margins of `Layout`; frames upscaled by `scale` (nearest neighbour)."""
    if not rows:
        raise ValueError("no rows to draw")
    h, w = rows[0].shape[1:3]
    cols = max(r.shape[0] for r in rows)
    lay = Layout(rows=len(rows), cols=cols, height=h, width=w, scale=scale)
    img = np.ones(lay.shape + (3,), np.float32)
    for i, row in enumerate(rows):
        if row.shape[1:] != (h, w, 3):
            raise ValueError(f"row {i}: frames of shape {row.shape[1:]}, expected {(h, w, 3)}")
        for j in range(row.shape[0]):
            y, x = lay.origin(i, j)
            big = np.repeat(np.repeat(np.clip(row[j], 0, 1), scale, 0), scale, 1)
            img[y: y + h * scale, x: x + w * scale] = big
    return img, lay


def draw_boxes(img: np.ndarray, lay: Layout, row: int, centres: np.ndarray, sizes: np.ndarray,
               pres: np.ndarray, threshold: float = 0.5, line: int = 1) -> int:
    """Draw the present boxes (pres > threshold) of each frame of `row` in place: centres and
    sizes [n, K, 2] in frame pixels (x, y), box k in `cell_colours(K)[k]`, outlines `line` px
    wide clipped to the frame. Returns the number of boxes drawn."""
    k = centres.shape[1]
    colours = cell_colours(k)
    s, hh, ww = lay.scale, lay.height * lay.scale, lay.width * lay.scale
    drawn = 0
    for j in range(centres.shape[0]):
        y0, x0 = lay.origin(row, j)
        tile = img[y0: y0 + hh, x0: x0 + ww]
        for c in range(k):
            if not pres[j, c] > threshold:
                continue
            (cx, cy), (bw, bh) = centres[j, c], sizes[j, c]
            left = int(np.clip(np.floor((cx - bw / 2) * s), 0, ww - 1))
            right = int(np.clip(np.ceil((cx + bw / 2) * s) - 1, 0, ww - 1))
            upper = int(np.clip(np.floor((cy - bh / 2) * s), 0, hh - 1))
            lower = int(np.clip(np.ceil((cy + bh / 2) * s) - 1, 0, hh - 1))
            col = colours[c]
            tile[upper: upper + line, left: right + 1] = col
            tile[max(lower - line + 1, 0): lower + 1, left: right + 1] = col
            tile[upper: lower + 1, left: left + line] = col
            tile[upper: lower + 1, max(right - line + 1, 0): right + 1] = col
            drawn += 1
    return drawn


def save_image(path: str, img: np.ndarray, lay: Layout, labels: Sequence[str], title: str = "") -> None:
    """Write `img` as a PNG of exactly its pixel size, with one label per row in the left
    margin and `title` in the top margin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dpi = 100
    hgt, wid = img.shape[:2]
    fig = plt.figure(figsize=(wid / dpi, hgt / dpi), dpi=dpi)
    fig.figimage(img, xo=0, yo=0, origin="upper")
    for i, label in enumerate(labels):
        y, _ = lay.origin(i, 0)
        yc = y + lay.height * lay.scale / 2
        fig.text(4 / wid, 1 - yc / hgt, label, fontsize=8, va="center", ha="left")
    if title:
        fig.text(4 / wid, 1 - (lay.top / 2) / hgt, title, fontsize=9, va="center", ha="left")
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


# ---------------------------------------------------------------------------- the figures
def save_recon_figure(path: str, frames: np.ndarray, recons: Mapping[str, np.ndarray], title: str = "",
                      scale: int = 2, true_label: str = "true") -> Layout:
    """Fig. 4 from host arrays: `frames` [n, H, W, 3] in [0, 1] on top, then one row per
    entry of `recons` ({name: [n, H, W, 3]}). Returns the layout."""
    rows = [np.asarray(frames, np.float32)] + [np.asarray(r, np.float32) for r in recons.values()]
    img, lay = compose(rows, scale)
    save_image(path, img, lay, [true_label, *recons], title)
    return lay


def save_boxes_figure(path: str, out: Mapping[str, np.ndarray], title: str = "", scale: int = 2,
                      threshold: float = 0.5, line: int = 1) -> tuple[Layout, int]:
    """Fig. 5 from `spair_outputs`: the true frames with the present boxes, SPAIR's
    reconstruction and its background. Returns the layout and the number of boxes drawn."""
    rows = [np.asarray(out[k], np.float32) for k in ("frames", "recon", "background")]
    img, lay = compose(rows, scale)
    drawn = draw_boxes(img, lay, 0, np.asarray(out["centres"]), np.asarray(out["sizes"]),
                       np.asarray(out["pres"]), threshold, line)
    save_image(path, img, lay, [f"true + boxes\n(pres > {threshold:g})", "reconstruction", "background"], title)
    return lay, drawn


def recon_figure(path: str, learners: Mapping[str, Any], params: Mapping[str, Any],
                 batch: Windows | np.ndarray, config: FigureConfig = FigureConfig(),
                 title: str = "") -> Layout:
    """Fig. 4 for `learners` (one seed's `params` each) on the first frames of `batch`."""
    frames, recons = reconstructions(learners, params, batch, config.frames)
    return save_recon_figure(path, frames, recons, title, config.scale)


def boxes_figure(path: str, spair: Any, params: Any, batch: Windows | np.ndarray,
                 config: FigureConfig = FigureConfig(), title: str = "") -> tuple[Layout, int]:
    """Fig. 5 for a SPAIR learner (one seed's `params`) on the first frames of `batch`."""
    out = spair_outputs(spair, params, batch, config.frames)
    return save_boxes_figure(path, out, title, config.scale, config.threshold, config.line)


def spair_names(learners: Mapping[str, Any]) -> list[str]:
    """The learners that have boxes (SPAIR)."""
    return [n for n, l in learners.items() if hasattr(l, "boxes")]
