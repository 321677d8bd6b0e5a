"""Classical segmenter on small synthetic scenes (lit domes, cast shadows, sky)."""

from __future__ import annotations


import numpy as np
import pytest

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.perception.masks import mask_stats
from lunarloc.perception.segment import (
    ClassicalConfig,
    ClassicalSegmenter,
    Segmenter,
    SegmenterKind,
    make_segmenter,
)


def scene(h=360, w=640, seed=0):
    """Textured mid-grey ground, black sky band, two lit rocks, one long cast shadow."""
    import cv2

    rng = np.random.default_rng(seed)
    img = 150 + cv2.GaussianBlur(rng.normal(0, 12, (h, w)).astype(np.float32), (0, 0), 1.5)
    img[:60] = 0  # sky
    v, u = np.mgrid[:h, :w]
    rocks = [(200, 220, 30), (450, 260, 22)]
    for cu, cv, r in rocks:
        d = (u - cu) ** 2 + (v - cv) ** 2 <= r * r
        img[d] = 215 + rng.normal(0, 3, d.sum())
    shadow = (np.abs(v - 300) < 5) & (u > 60) & (u < 400)
    img[shadow] = 25
    return np.clip(img, 0, 255).astype(np.uint8), rocks


def test_classical_finds_rocks_and_not_the_sky():
    img, rocks = scene()
    seg = make_segmenter("classical")
    assert isinstance(seg, Segmenter)
    masks = seg.segment(img)
    stats = [mask_stats(m, masks.image_shape) for m in masks]
    for cu, cv, r in rocks:
        best = min(stats, key=lambda s: np.hypot(s.centroid_uv[0] - cu, s.centroid_uv[1] - cv))
        assert np.hypot(best.centroid_uv[0] - cu, best.centroid_uv[1] - cv) < 2.0
        assert best.sigma_px == pytest.approx(r / 2, rel=0.15)
        assert best.eig_ratio < 1.5
    for m in masks:  # nothing in the sky
        assert m.bbox[3] > 60
    # the shadow strip, if segmented, is long and thin (the elongation filter drops it)
    strip = [s for s in stats if abs(s.centroid_uv[1] - 300) < 6]
    assert all(s.eig_ratio > 20 for s in strip)


def test_classical_blank_and_bad_inputs():
    seg = ClassicalSegmenter()
    assert len(seg.segment(np.zeros((100, 100), np.uint8))) == 0
    assert len(seg.segment(np.full((100, 100), 128, np.uint8))) == 0
    with pytest.raises(InputError):
        seg.segment(np.zeros((8, 8), np.uint8))
    with pytest.raises(ConfigError):
        ClassicalConfig(bright_hi_sigma=1.0, bright_lo_sigma=2.0)
    assert SegmenterKind("classical") is SegmenterKind.CLASSICAL


def test_classical_full_resolution_frame():
    """A 1280x720 frame (the LAC size) segments with the rocks found where they are.
    Speed is measured by benchmarks/bench_perception.py, not asserted here."""
    img, rocks = scene(720, 1280)
    masks = ClassicalSegmenter().segment(img)
    assert masks.image_shape == (720, 1280)
    stats = [mask_stats(m, masks.image_shape) for m in masks]
    for cu, cv, r in rocks:
        best = min(stats, key=lambda s: np.hypot(s.centroid_uv[0] - cu, s.centroid_uv[1] - cv))
        assert np.hypot(best.centroid_uv[0] - cu, best.centroid_uv[1] - cv) < 2.0


def test_height_blobs_become_full_resolution_masks():
    """Blobs standing above the ground in a (low-resolution) HeightMap are segmented
    with hysteresis; low bumps without a seed, tiny blobs and blobs in the columns
    SGBM cannot match are dropped."""
    from lunarloc.perception.stereo import HeightMap

    h, w, k = 180, 320, 2
    H = np.zeros((h, w), np.float32)
    v, u = np.mgrid[:h, :w]
    H[(u - 200) ** 2 + (v - 100) ** 2 <= 64] = 0.08  # a rock: seed and region
    H[(u - 200) ** 2 + (v - 100) ** 2 <= 16] = 0.12
    H[(u - 100) ** 2 + (v - 120) ** 2 <= 64] = 0.02  # a low bump: no seed
    H[5:7, 300:302] = 0.1  # tiny
    H[(u - 20) ** 2 + (v - 100) ** 2 <= 64] = 0.1  # in the unmatched strip
    depth = np.full((h, w), 3.0, np.float32)
    hm = HeightMap(H, depth, np.zeros((h, w, 3), np.float32), H, k, 64, np.eye(4))
    seg = ClassicalSegmenter()
    assert seg.uses_stereo
    masks = seg.segment(np.full((2 * h, 2 * w), 100, np.uint8), height=hm)
    assert len(masks) == 1
    st = mask_stats(masks[0], masks.image_shape)
    assert np.hypot(st.centroid_uv[0] - 400.5, st.centroid_uv[1] - 200.5) < 2.0
    assert masks.image_shape == (2 * h, 2 * w)
