"""Reconstruction error per object region (`bulbjax.eval.regions`) and the Fig. 5 claim built on
it ("on YCB no learner's reconstruction is clear", `findings_objects.reconstruction_clear`):
synthetic frames whose objects sit at known pixels, reconstructions whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from bulbjax.eval import regions
from bulbjax.report.findings_objects import reconstruction_clear


def scene(rng: np.random.Generator, frames: int = 16, size: int = 32, radius: float = 4.0):
    """Black frames with a white disc (object 0) and a red disc (object 1) at random positions."""
    pos = rng.uniform(6, size - 6, (frames, 2, 2))
    img = np.zeros((frames, size, size, 3))
    masks = regions.disc_masks(pos, radius, size, size)
    img[masks[:, 0]] = 1.0
    img[masks[:, 1]] = (1.0, 0.0, 0.0)
    return img, pos


def test_disc_masks_are_the_pixels_within_the_radius() -> None:
    m = regions.disc_masks(np.array([[[16.0, 10.0], [-20.0, 5.0]]]), 3.0, 32, 24)
    assert m.shape == (1, 2, 32, 24)
    ys, xs = np.nonzero(m[0, 0])
    assert np.all((xs + 0.5 - 16) ** 2 + (ys + 0.5 - 10) ** 2 <= 9) and len(xs) == 32  # centres at half pixels: 32 within 3 px
    assert not m[0, 1].any()  # outside the frame: an empty disc


def test_region_ratio_is_zero_when_perfect_one_for_the_mean_image_and_above_when_erased() -> None:
    img, pos = scene(np.random.default_rng(0))
    perfect = regions.region_scores(img, img, pos, 4.0)
    np.testing.assert_allclose(perfect["ratio"], 0.0)
    mean = regions.region_scores(img, np.broadcast_to(img.mean(0), img.shape), pos, 4.0)
    np.testing.assert_allclose(mean["ratio"], 1.0, rtol=1e-12)
    erased = regions.region_scores(img, np.zeros_like(img), pos, 4.0)
    assert all(r > 0.9 for r in erased["ratio"])  # no better than the blurred mean image
    half = regions.region_scores(img, img * 0.5, pos, 4.0)  # the objects at half their brightness
    assert all(0.1 < r < regions.CLEAR for r in half["ratio"])
    # one object drawn perfectly, the other erased: only the first region is clear
    one = img.copy()
    one[regions.disc_masks(pos, 4.0, 32, 32)[:, 1]] = 0.0
    got = regions.region_scores(img, one, pos, 4.0)["ratio"]
    assert got[0] < 0.1 and got[1] > 0.9  # obj0 not 0: where the discs overlap, erasing obj1 erases it too
    assert perfect["pixels"][0] == pytest.approx(16 * 52, abs=16 * 8)  # ~pi r^2 per frame
    with pytest.raises(ValueError, match="must both be"):
        regions.region_scores(img, img[:, :16], pos, 4.0)


def test_an_object_never_in_view_has_no_ratio() -> None:
    img, pos = scene(np.random.default_rng(1))
    pos[:, 1] = -50.0
    got = regions.region_scores(img, img * 0.5, pos, 4.0)
    assert np.isnan(got["ratio"][1]) and got["pixels"][1] == 0 and np.isfinite(got["ratio"][0])


def fake_regions(ratios: dict[str, list[list[float]]]) -> dict:
    return {"epoch": 500, "objects": ["obj0", "obj1"], "radius_px": 6.4, "frames": 64, "seeds": 3,
            "clear_below": regions.CLEAR, "learners": {n: {"ratio": r} for n, r in ratios.items()}}


def test_the_claim_holds_only_when_every_region_is_clearly_not_clear() -> None:
    blurred = [[0.95, 1.1], [0.9, 1.05], [1.0, 1.2]]
    verdict, detail = reconstruction_clear(fake_regions({"vae_rpl": blurred, "spair": blurred}))
    assert verdict == "holds" and "vae_rpl: obj0 0.95" in detail and "64 held-out frames" in detail
    sharp = [[0.1, 1.1], [0.15, 1.05], [0.12, 1.2]]  # spair draws obj0 clearly
    verdict, detail = reconstruction_clear(fake_regions({"vae_rpl": blurred, "spair": sharp}))
    assert verdict == "does not hold" and "spair: obj0 0.12" in detail
    straddling = [[0.2, 1.1], [0.9, 1.05], [0.6, 1.2]]  # obj0's band contains 0.5
    assert reconstruction_clear(fake_regions({"vae_rpl": straddling}))[0] == "undecided"
    nowhere = [[float("nan")] * 2] * 3
    assert reconstruction_clear(fake_regions({"vae_rpl": nowhere}))[0].startswith("not tested")
