"""Tests of the learner figures (bulbjax/report/figures.py): the PNGs show the true frames
where the layout says, reconstructions below them, and SPAIR's present boxes (only those) in
their cell's colour at the box's edges. Small sizes, CPU."""

from __future__ import annotations

import jax
import matplotlib.image as mpimg
import numpy as np
import pytest

from bulbjax.data.sequence import Windows
from bulbjax.learners import LearnerConfig, make_learner
from bulbjax.learners.spair import synthetic_scene
from bulbjax.report import figures

RES = 16


def _frames(n: int, res: int = RES, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, res, res, 3), dtype=np.uint8)


def _block(png: np.ndarray, lay: figures.Layout, row: int, col: int) -> np.ndarray:
    """The frame at (row, col) read back from the PNG, downsampled to frame pixels."""
    y, x = lay.origin(row, col)
    s = lay.scale
    tile = png[y: y + lay.height * s, x: x + lay.width * s, :3]
    return tile[::s, ::s]


class Invert:
    """A stand-in frame learner whose reconstruction is 1 - frame (so the row is known)."""

    def reconstruct(self, params: object, frames: np.ndarray) -> np.ndarray:
        return 1.0 - np.asarray(frames, np.float32) / 255.0


def test_recon_figure_pixels(tmp_path) -> None:
    frames = _frames(5)
    path = str(tmp_path / "recon.png")
    lay = figures.recon_figure(path, {"inv": Invert()}, {"inv": None}, frames,
                               figures.FigureConfig(frames=4, scale=3), title="test")
    png = mpimg.imread(path)
    assert png.shape[:2] == lay.shape and (lay.rows, lay.cols) == (2, 4)
    for j in range(4):
        np.testing.assert_allclose(_block(png, lay, 0, j), frames[j] / 255.0, atol=1 / 255 + 1e-6)
        np.testing.assert_allclose(_block(png, lay, 1, j), 1 - frames[j] / 255.0, atol=1 / 255 + 1e-6)
    # the fifth frame is not drawn, and a wrong layout would not match: row 1 is not row 0
    assert np.abs(_block(png, lay, 1, 0) - frames[0] / 255.0).max() > 0.5
    with pytest.raises(ValueError, match="no params"):
        figures.recon_figure(path, {"inv": Invert()}, {}, frames)


def test_boxes_drawn_where_given(tmp_path) -> None:
    n, k, s = 2, 4, 4
    frames = np.full((n, RES, RES, 3), 0.5, np.float32)
    centres = np.zeros((n, k, 2), np.float32)
    sizes = np.full((n, k, 2), 4.0, np.float32)
    pres = np.zeros((n, k), np.float32)
    centres[0, 2], sizes[0, 2], pres[0, 2] = (8.0, 6.0), (6.0, 8.0), 0.9  # x 5..11, y 2..10
    centres[1, 1], pres[1, 1] = (4.0, 4.0), 0.3  # below the threshold: not drawn
    out = {"frames": frames, "centres": centres, "sizes": sizes, "pres": pres,
           "recon": frames * 0 + 0.25, "background": frames * 0 + 0.75}
    path = str(tmp_path / "boxes.png")
    lay, drawn = figures.save_boxes_figure(path, out, scale=s, threshold=0.5, line=1)
    assert drawn == 1
    png = mpimg.imread(path)[..., :3]
    y0, x0 = lay.origin(0, 0)
    colour = figures.cell_colours(k)[2]
    # left edge: column 5*s, rows 2*s .. 10*s-1; top edge: row 2*s, columns 5*s .. 11*s-1
    np.testing.assert_allclose(png[y0 + 2 * s: y0 + 10 * s, x0 + 5 * s], np.broadcast_to(colour, (8 * s, 3)), atol=1e-2)
    np.testing.assert_allclose(png[y0 + 2 * s, x0 + 5 * s: x0 + 11 * s], np.broadcast_to(colour, (6 * s, 3)), atol=1e-2)
    np.testing.assert_allclose(png[y0 + 10 * s - 1, x0 + 5 * s: x0 + 11 * s], np.broadcast_to(colour, (6 * s, 3)), atol=1e-2)
    np.testing.assert_allclose(png[y0 + 2 * s: y0 + 10 * s, x0 + 11 * s - 1], np.broadcast_to(colour, (8 * s, 3)), atol=1e-2)
    # inside the box and the whole second frame (its box is not present) keep the frame's grey
    np.testing.assert_allclose(png[y0 + 4 * s: y0 + 8 * s, x0 + 7 * s: x0 + 9 * s], 0.5, atol=1e-2)
    np.testing.assert_allclose(_block(png, lay, 0, 1), 0.5, atol=1e-2)
    np.testing.assert_allclose(_block(png, lay, 1, 0), 0.25, atol=1e-2)
    np.testing.assert_allclose(_block(png, lay, 2, 1), 0.75, atol=1e-2)


def test_spair_and_sequential_learners(tmp_path) -> None:
    """Real learners: SPAIR's boxes figure and a Fig. 4 grid with a frame and a sequential
    learner on windows (consecutive frames of the windows, in order)."""
    res = 32
    cfg = LearnerConfig(spair_grid=4, spair_glimpse=8, spair_what_dim=4, conv_features=(8, 8, 8, 8),
                        hidden=32, sequence_length=3)
    spair = make_learner("spair", 8, cfg)
    svae = make_learner("svae", 4, cfg, action_dim=1)
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)
    params = {"spair": spair.init(k1, (res, res, 3)).params, "svae": svae.init(k2, (res, res, 3)).params}
    frames, _ = synthetic_scene(k3, 6, res, num_objects=2, size=6)
    frames = np.asarray(frames).reshape(2, 3, res, res, 3)
    w = Windows(frames=frames, actions=np.zeros((2, 3, 1), np.float32),
                states=np.zeros((2, 3, 1), np.float32), valid=np.ones((2, 3), bool))
    cfg_fig = figures.FigureConfig(frames=5, scale=2, threshold=0.0)  # every box present
    lay = figures.recon_figure(str(tmp_path / "r.png"), {"spair": spair, "svae": svae}, params, w, cfg_fig)
    png = mpimg.imread(str(tmp_path / "r.png"))
    assert (lay.rows, lay.cols) == (3, 5)
    flat = frames.reshape(6, res, res, 3)
    for j in range(5):
        np.testing.assert_allclose(_block(png, lay, 0, j), flat[j] / 255.0, atol=1 / 255 + 1e-6)
    lay_b, drawn = figures.boxes_figure(str(tmp_path / "b.png"), spair, params["spair"], w, cfg_fig)
    assert drawn == 5 * 16 and (lay_b.rows, lay_b.cols) == (3, 5)
    with pytest.raises(ValueError, match="boxes figure is SPAIR's"):
        figures.boxes_figure(str(tmp_path / "x.png"), svae, params["svae"], w, cfg_fig)
    with pytest.raises(ValueError, match="pass Windows"):
        figures.recon_figure(str(tmp_path / "y.png"), {"svae": svae}, params, flat)


def test_a_learner_s_figure_passes_are_jitted_once() -> None:
    """The figures run a learner's reconstruction as one jitted program, traced once for the
    pictures of every epoch (called eagerly, a first Fig. 5 picture compiled op by op for ~a
    minute on an H200); a reconstruction written in NumPy (no tracing) still runs."""
    import jax.numpy as jnp

    class Count:
        traces = 0

        def reconstruct(self, params: object, frames: np.ndarray) -> jax.Array:
            Count.traces += 1
            return 1.0 - jnp.asarray(frames, jnp.float32) / 255.0

    learner, frames = Count(), _frames(3)
    for _ in range(3):
        _, rec = figures.reconstructions({"c": learner}, {"c": None}, frames, 3)
        np.testing.assert_allclose(rec["c"], 1 - frames / 255.0, atol=1e-6)
    assert Count.traces == 1
    _, rec = figures.reconstructions({"inv": Invert()}, {"inv": None}, frames, 3)
    np.testing.assert_allclose(rec["inv"], 1 - frames / 255.0, atol=1e-6)
