"""Mask statistics and the paper's filters."""

from __future__ import annotations

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.perception.masks import (
    InstanceMask,
    MaskFilterConfig,
    RejectReason,
    classify_mask,
    mask_stats,
    masks_from_labels,
    size_from_sigma,
)


def _disc(shape, cu, cv, r):
    v, u = np.mgrid[: shape[0], : shape[1]]
    return (u - cu) ** 2 + (v - cv) ** 2 <= r * r


def test_disc_stats():
    shape = (100, 200)
    m = InstanceMask.from_full(_disc(shape, 80.0, 40.0, 20.0))
    s = mask_stats(m, shape)
    assert s.centroid_uv == pytest.approx((80.0, 40.0), abs=1e-6)
    assert s.sigma_px == pytest.approx(10.0, rel=0.02)  # r / 2
    assert s.eig_ratio == pytest.approx(1.0, abs=0.02)
    assert not s.touches_border
    assert s.area == m.area == np.count_nonzero(m.to_full(shape))


def test_ellipse_ratio_and_rotation():
    shape = (200, 200)
    v, u = np.mgrid[:200, :200]
    a, b, th = 40.0, 10.0, np.radians(30)
    x = (u - 100) * np.cos(th) + (v - 100) * np.sin(th)
    y = -(u - 100) * np.sin(th) + (v - 100) * np.cos(th)
    m = InstanceMask.from_full((x / a) ** 2 + (y / b) ** 2 <= 1)
    s = mask_stats(m, shape)
    assert s.eig_ratio == pytest.approx(16.0, rel=0.05)  # (a / b)^2
    w, V = np.linalg.eigh(s.cov)
    assert abs(abs(V[:, 1] @ [np.cos(th), np.sin(th)]) - 1) < 1e-3


def test_border_and_line():
    shape = (50, 50)
    full = np.zeros(shape, bool)
    full[0:5, 10:15] = True
    assert mask_stats(InstanceMask.from_full(full), shape).touches_border
    line = np.zeros(shape, bool)
    line[25, 10:40] = True
    s = mask_stats(InstanceMask.from_full(line), shape)
    assert s.eig_ratio > 100 and np.isfinite(s.eig_ratio)
    with pytest.raises(InputError):
        InstanceMask.from_full(np.zeros(shape, bool))


def test_masks_from_labels():
    lab = np.zeros((30, 30), np.int32)
    lab[2:6, 2:6] = 1
    lab[10:20, 10:12] = 3
    lab[25, 25] = 4
    ms = masks_from_labels(lab, min_area=2)
    assert len(ms) == 2
    assert ms[0].bbox == (2, 2, 6, 6) and ms[1].bbox == (10, 10, 12, 20)
    assert len(masks_from_labels(np.zeros((4, 4), int))) == 0


def test_size_and_filters_in_order():
    cfg = MaskFilterConfig(
        s_min_m=0.04, s_max_m=0.5, tau_elong=4.0, max_range_m=8.0, min_range_m=1.3
    )
    alpha = 1.0 / 914.0
    shape = (720, 1280)
    s = mask_stats(InstanceMask.from_full(_disc(shape, 640, 400, 20)), shape)
    # sigma 10 px at 4 m -> 10 * 4 / 914 = 0.0438 m
    assert size_from_sigma(10, 4.0, alpha) == pytest.approx(0.04376, rel=1e-3)
    assert classify_mask(s, 4.0, alpha, cfg)[0] is None
    assert classify_mask(s, 3.0, alpha, cfg)[0] is RejectReason.TOO_SMALL
    assert (
        classify_mask(s, 100.0, alpha, MaskFilterConfig(max_range_m=200))[0]
        is RejectReason.TOO_LARGE
    )
    assert classify_mask(s, 9.0, alpha, cfg)[0] is RejectReason.TOO_FAR
    assert classify_mask(s, 1.2, alpha, MaskFilterConfig(s_min_m=0.001))[0] is RejectReason.TOO_NEAR
    assert classify_mask(s, float("nan"), alpha, cfg)[0] is RejectReason.NO_DEPTH
    assert classify_mask(s, None, alpha, cfg)[0] is RejectReason.NO_DEPTH
    edge = mask_stats(InstanceMask.from_full(_disc(shape, 5, 400, 20)), shape)
    assert classify_mask(edge, 4.0, alpha, cfg)[0] is RejectReason.BORDER
    tiny = mask_stats(InstanceMask.from_full(_disc(shape, 600, 400, 2)), shape)
    assert classify_mask(tiny, 4.0, alpha, cfg)[0] is RejectReason.TOO_FEW_PIXELS


def test_config_validation():
    with pytest.raises(ConfigError):
        MaskFilterConfig(s_min_m=0.6, s_max_m=0.5)
    with pytest.raises(ConfigError):
        MaskFilterConfig(tau_elong=0.5)
    with pytest.raises(ConfigError):
        MaskFilterConfig(max_range_m=1.0, min_range_m=1.3)


def test_small_rock_close_by_is_kept_when_its_mask_is_large():
    alpha = 1.0 / 914.0
    shape = (720, 1280)
    big = mask_stats(InstanceMask.from_full(_disc(shape, 640, 400, 16)), shape)  # sigma 8 px
    small = mask_stats(InstanceMask.from_full(_disc(shape, 640, 400, 8)), shape)  # sigma 4 px
    off = MaskFilterConfig(s_min_m=0.03, min_range_m=0.5)
    on = MaskFilterConfig(s_min_m=0.03, min_range_m=0.5, near_sigma_px=6.0, near_s_min_m=0.008)
    # 8 px at 1.5 m: s = 0.013 m, below s_min but a large mask
    assert classify_mask(big, 1.5, alpha, off)[0] is RejectReason.TOO_SMALL
    assert classify_mask(big, 1.5, alpha, on)[0] is None
    # the same physical size far away spans too few pixels; a tiny one near is still dropped
    assert classify_mask(small, 3.0, alpha, on)[0] is RejectReason.TOO_SMALL
    assert (
        classify_mask(big, 0.6, alpha, on)[0] is RejectReason.TOO_SMALL
    )  # s = 0.005 < near_s_min_m
