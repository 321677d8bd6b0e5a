"""SGBM depth on synthetic rectified pairs with a known disparity."""

from __future__ import annotations

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.perception.camera import PinholeCamera
from lunarloc.perception.stereo import StereoConfig, StereoMatcher, depth_at, to_gray_u8


def _textured_pair(disp: int, h: int = 240, w: int = 480, seed: int = 0):
    """Random texture (blurred noise); right image = left shifted by `disp` px (x_r = x_l - d)."""
    import cv2

    rng = np.random.default_rng(seed)
    tex = rng.uniform(0, 255, size=(h, w + disp)).astype(np.float32)
    tex = cv2.GaussianBlur(tex, (0, 0), 1.2)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    left = tex[:, :w]  # texture column c appears at x_l = c in the left image
    right = tex[:, disp : disp + w]  # and at x_r = c - disp in the right image
    return np.ascontiguousarray(left), np.ascontiguousarray(right)


@pytest.mark.parametrize("disp", [20, 47])
def test_sgbm_recovers_known_disparity_and_depth(disp):
    cam = PinholeCamera(width=480, height=240, hfov_deg=70.0)
    left, right = _textured_pair(disp)
    m = StereoMatcher(StereoConfig(), camera=cam, baseline_m=0.162)
    d = m.disparity(left, right)
    core = d[20:-20, 160:-20]
    valid = np.isfinite(core)
    assert valid.mean() > 0.9
    assert np.median(core[valid]) == pytest.approx(disp, abs=0.25)
    z = m.depth(left, right)
    expected = cam.fx * 0.162 / disp
    assert np.nanmedian(z[20:-20, 160:-20]) == pytest.approx(expected, rel=0.01)
    # the median in a window at an interior pixel
    assert depth_at(z, 300, 120, half_window=3) == pytest.approx(expected, rel=0.01)


def test_sgbm_downscaled_is_close():
    cam = PinholeCamera(width=480, height=240, hfov_deg=70.0)
    left, right = _textured_pair(40)
    m = StereoMatcher(StereoConfig(downscale=2), camera=cam)
    d = m.disparity(left, right)
    assert np.nanmedian(d[20:-20, 160:-20]) == pytest.approx(40, abs=1.0)


def test_left_band_without_search_range_is_invalid():
    cam = PinholeCamera(width=480, height=240)
    left, right = _textured_pair(20)
    d = StereoMatcher(camera=cam).disparity(left, right)
    assert np.isnan(d[:, :100]).mean() > 0.9  # no match possible left of numDisparities


def test_depth_at_window_mask_and_invalid():
    z = np.full((20, 20), np.nan, dtype=np.float32)
    assert np.isnan(depth_at(z, 10, 10))
    z[8:13, 8:13] = 2.0
    z[8:13, 11:13] = 5.0  # background on the right of the window
    assert depth_at(z, 10, 10, half_window=2) == pytest.approx(2.0)
    mask = np.zeros_like(z, dtype=bool)
    mask[8:13, 11:13] = True
    assert depth_at(z, 10, 10, half_window=2, mask=mask) == pytest.approx(5.0)
    assert np.isnan(depth_at(z, 100, 100))


def test_config_and_input_errors():
    with pytest.raises(ConfigError):
        StereoConfig(num_disparities=100)
    with pytest.raises(ConfigError):
        StereoConfig(block_size=10)
    assert StereoConfig().P1 == 8 * 3 * 121 and StereoConfig().P2 == 32 * 3 * 121
    m = StereoMatcher()
    with pytest.raises(InputError):
        m.disparity(np.zeros((10, 10), np.uint8), np.zeros((10, 12), np.uint8))
    with pytest.raises(InputError):
        to_gray_u8(np.zeros((2, 3, 5)))
    assert to_gray_u8(np.ones((4, 4), dtype=np.float32)).max() == 255


def test_row_band_matches_full_image_inside_band():
    cam = PinholeCamera(width=480, height=240)
    left, right = _textured_pair(30)
    m = StereoMatcher(camera=cam)
    full = m.disparity(left, right)
    band = m.disparity(left, right, rows=(100, 140))
    assert np.all(np.isnan(band[:50])) and np.all(np.isnan(band[-50:]))
    inner = band[100:140, 160:-20]
    assert np.nanmedian(np.abs(inner - full[100:140, 160:-20])) < 0.1


def test_ground_height_map_flat_plane_and_a_box():
    """Disparity of a flat ground plane (camera 0.331 m up) gives ~zero heights; a
    raised patch stands at its height."""
    from lunarloc.perception.camera import ipex_rig
    from lunarloc.perception.stereo import GroundConfig, ground_height_map

    cam = PinholeCamera()
    T = ipex_rig(cam)["FrontLeft"].T_rover_optical
    k = 2
    h, w = cam.height // k, cam.width // k
    fx = cam.fx / k
    cy = (cam.cy - (k - 1) / 2.0) / k
    v = np.arange(h, dtype=np.float32)[:, None].repeat(w, 1)
    hc = 0.331
    z = np.where(v > cy + 1, fx * hc / np.maximum(v - cy, 1e-3), np.inf)  # flat ground depth
    disp = (fx * 0.162 / z).astype(np.float32)
    disp[~np.isfinite(z) | (z > 12)] = np.nan
    # a 5 cm step: rows of a patch seen as if 5 cm higher -> depth of a plane at hc - 0.05
    patch = (slice(230, 240), slice(300, 330))
    disp[patch] = fx * 0.162 / (fx * (hc - 0.05) / (v[patch] - cy))
    hm = ground_height_map(disp, k, cam, 0.162, T, GroundConfig())
    H = hm.height
    ok = np.isfinite(H)
    ok[patch] = False
    assert np.nanmedian(np.abs(H[ok])) < 0.005
    assert np.nanmedian(H[patch]) == pytest.approx(0.05, abs=0.015)


def test_refine_disparity_recovers_subpixel_shift():
    import cv2

    from lunarloc.perception.stereo import refine_disparity

    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.normal(128, 40, (80, 400)).astype(np.float32), (0, 0), 1.5)
    d_true = 20.4
    u = np.arange(400, dtype=np.float32)[None].repeat(80, 0)
    vv = np.arange(80, dtype=np.float32)[:, None].repeat(400, 1)
    left = np.clip(base, 0, 255).astype(np.uint8)
    right = np.clip(cv2.remap(base, u + d_true, vv, cv2.INTER_CUBIC), 0, 255).astype(np.uint8)
    crop = np.ones((40, 60), bool)
    d = refine_disparity(left, right, crop, 200, 20, 19.0, search_px=3, erode_px=1)
    assert d == pytest.approx(d_true, abs=0.15)


def test_tiny_images_clamp_the_search_range():
    # Regression: at 160x90 the detector's SGBM (192 disparities at half resolution:
    # 96 on an 80 px wide image) failed with an OpenCV allocation of absurd size.
    from lunarloc.perception.detector import DetectorConfig
    from lunarloc.perception.stereo import max_num_disparities

    assert max_num_disparities(80, 5) == 64 and max_num_disparities(1280, 11) == 1264
    cam = PinholeCamera(width=160, height=90, hfov_deg=70.0)
    left, right = _textured_pair(10, h=90, w=160)
    full = StereoMatcher(StereoConfig(), camera=cam)
    assert full.num_disparities_lowres == 128
    d = full.disparity(left, right)
    assert np.nanmedian(d[15:-15, 130:150]) == pytest.approx(10, abs=0.5)
    half = StereoMatcher(DetectorConfig().height_stereo, camera=cam)
    assert half.num_disparities_lowres == 64  # clamped from 96
    low = half.disparity_lowres(left, right)
    assert low.shape == (45, 80)
    assert np.nanmedian(low[8:-8, 66:76]) == pytest.approx(5, abs=0.5)
    # an image narrower than the camera's narrows the range again instead of failing
    assert np.isfinite(full.disparity(left[:, :100], right[:, :100])).any()
    # too small for any search range: a clear error naming the size
    with pytest.raises(InputError, match="24x16"):
        StereoMatcher(StereoConfig(), camera=PinholeCamera(width=24, height=16))
    with pytest.raises(InputError, match="20x90"):
        full.disparity(left[:, :20], right[:, :20])


def test_detector_runs_on_160x90_pairs():
    from lunarloc.perception.camera import ipex_rig
    from lunarloc.perception.detector import Detector
    from lunarloc.config.run import scaled_detector_config

    cam = PinholeCamera(width=160, height=90)
    left, right = _textured_pair(6, h=90, w=160)
    det = Detector(scaled_detector_config(160), cam)
    pr = det.detect_pair(left, right, ipex_rig(cam)["FrontLeft"].T_rover_optical)
    assert isinstance(pr.detections, list)


def test_mask_disparity_fullres_recovers_shift_in_narrow_band():
    from lunarloc.perception.stereo import mask_disparity_fullres

    rng = np.random.default_rng(3)
    base = (rng.random((200, 400)) * 255).astype(np.uint8)
    import cv2

    left = cv2.GaussianBlur(base, (3, 3), 0)
    right = np.roll(left, -24, axis=1)  # true disparity 24 px everywhere
    crop = np.ones((40, 50), bool)
    d = mask_disparity_fullres(left, right, crop, 200, 80, d0=22.6, span_px=16, block_size=5)
    assert d is not None and d.shape == crop.shape
    assert abs(float(np.nanmedian(d)) - 24.0) < 0.2
    # a band that would leave the image gives None
    assert mask_disparity_fullres(left, right, crop, 5, 80, d0=22.6) is None


def _slanted_pair(slope_px_per_row: float, d_mid: float = 20.0, h: int = 200, w: int = 400):
    """A textured pair whose disparity grows down the image by `slope_px_per_row` (as level
    ground's does), d_mid at row h // 2; returns (left, right, true disparity per row)."""
    import cv2

    rng = np.random.default_rng(5)
    base = cv2.GaussianBlur((rng.random((h, 2 * w)) * 255).astype(np.float32), (3, 3), 0)
    d_true = d_mid + slope_px_per_row * (np.arange(h) - h // 2)
    xs = np.repeat(np.arange(w, dtype=np.float32)[None, :] + 100, h, 0)
    ys = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, 1)
    left = cv2.remap(base, xs, ys, cv2.INTER_CUBIC)
    # right(u) = left(u + d): a point at column u of the left image lies at u - d in the right
    right = cv2.remap(base, xs + d_true[:, None].astype(np.float32), ys, cv2.INTER_CUBIC)
    as_u8 = [np.clip(im, 0, 255).astype(np.uint8) for im in (left, right)]
    return as_u8[0], as_u8[1], d_true


def test_mask_disparity_fullres_hh4_follows_a_disparity_growing_down_the_image():
    from lunarloc.perception.stereo import mask_disparity_fullres

    left, right, d_true = _slanted_pair(0.25)
    crop = np.ones((60, 80), bool)
    err = {}
    for mode in ("3way", "hh4"):
        d = mask_disparity_fullres(left, right, crop, 200, 70, d0=20.0, mode=mode)
        assert d is not None and np.isfinite(d).mean() > 0.8
        err[mode] = float(np.nanmedian(d - d_true[70:130, None]))
    # the default (hh4) aggregates both ways along the columns: no lag; 3way's top-down-only
    # pass lags behind the growing disparity (the surface put too far)
    assert abs(err["hh4"]) < 0.03
    assert err["3way"] < -0.03


def test_sgbm_modes_by_name():
    import cv2

    from lunarloc.perception.detector_config import PointsConfig
    from lunarloc.perception.stereo import SGBM_MODES, sgbm_mode_flag

    assert sgbm_mode_flag("hh4") == cv2.STEREO_SGBM_MODE_HH4
    assert len({sgbm_mode_flag(m) for m in SGBM_MODES}) == len(SGBM_MODES)
    with pytest.raises(ConfigError, match="hh4"):
        sgbm_mode_flag("fast")
    assert PointsConfig().sgbm_mode == "hh4"
    with pytest.raises(ConfigError):
        PointsConfig(sgbm_mode="fast")


def test_full_width_matches_the_left_band_where_the_match_exists():
    cam = PinholeCamera(width=480, height=240)
    left, right = _textured_pair(20)
    d = StereoMatcher(StereoConfig(full_width=True), camera=cam).disparity_lowres(left, right)
    band = d[20:-20, 30:100]  # OpenCV alone leaves the first 128 columns unmatched
    assert np.isfinite(band).mean() > 0.9
    assert np.nanmedian(band) == pytest.approx(20, abs=0.25)
    # a match never lies left of the right image (d <= u), so the first columns,
    # left of the true disparity, are mostly invalid
    u = np.arange(d.shape[1])[None, :].repeat(d.shape[0], 0)
    ok = np.isfinite(d)
    assert (d[ok] <= u[ok]).all()
    assert np.isnan(d[:, :15]).mean() > 0.9


def test_scaled_config_scales_the_near_rock_pixel_size():
    from lunarloc.perception.detector import DetectorConfig
    from lunarloc.config.run import scaled_detector_config

    base = DetectorConfig()
    half = scaled_detector_config(640)
    assert half.height_filters.near_sigma_px == pytest.approx(base.height_filters.near_sigma_px / 2)
    assert scaled_detector_config(1280) == base


def _ray_cast_disparity(cam, T, k, box):
    """Low-resolution disparity of level ground 0.331 m under the camera with an upright box
    (x0, x1, y0, y1, top_m above the ground, rover frame) on it: the nearest hit per pixel."""
    h, w = cam.height // k, cam.width // k
    fx = cam.fx / k
    cx, cy = (cam.cx - (k - 1) / 2.0) / k, (cam.cy - (k - 1) / 2.0) / k
    uu, vv = np.meshgrid(np.arange(w), np.arange(h))
    rays_o = np.stack([(uu - cx) / fx, (vv - cy) / fx, np.ones((h, w))], -1)  # optical, z = 1
    R, c = np.asarray(T)[:3, :3], np.asarray(T)[:3, 3]
    d = rays_o @ R.T  # rover-frame direction per unit optical depth
    zg = c[2] - 0.331
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d[..., 2] < 0, (zg - c[2]) / d[..., 2], np.inf)
        x0, x1, y0, y1, top = box
        for tt in ((x0 - c[0]) / d[..., 0], (zg + top - c[2]) / d[..., 2]):  # front face, top
            p = c + tt[..., None] * d
            on = (
                (tt > 0)
                & (p[..., 0] >= x0 - 1e-9)
                & (p[..., 0] <= x1)
                & (p[..., 1] >= y0)
                & (p[..., 1] <= y1)
                & (p[..., 2] <= zg + top + 1e-9)
            )
            t = np.where(on & (tt < t), tt, t)
    disp = (fx * 0.162 / t).astype(np.float32)
    disp[~np.isfinite(t) | (t > 12)] = np.nan
    return disp


def test_ground_footprint_weights_keep_a_far_rock_off_the_ground():
    """A 12 cm high, 0.25 m deep rock at 4.3 m fills many pixels of its 0.35 m ground cells
    (its face is seen square-on, the ground around it at a grazing angle, and it hides the
    ground behind it): one vote per pixel lifts the cells' median towards the rock and its top
    stands 9 cm above that ground; weighted by the ground each point covers, it stands at its
    12 cm and the open ground stays at zero."""
    from lunarloc.perception.camera import ipex_rig
    from lunarloc.perception.stereo import GroundConfig, ground_height_map

    cam = PinholeCamera()
    T = ipex_rig(cam)["FrontLeft"].T_rover_optical
    box = (4.3, 4.55, -0.2, 0.2, 0.12)
    disp = _ray_cast_disparity(cam, T, 2, box)
    hm_w = ground_height_map(disp, 2, cam, 0.162, T, GroundConfig(footprint_weights=True))
    hm_1 = ground_height_map(disp, 2, cam, 0.162, T, GroundConfig())
    assert not GroundConfig().footprint_weights  # opt-in
    P = hm_w.points_rover
    zg = T[2, 3] - 0.331
    on_box = (
        (P[..., 0] > box[0] - 0.01)
        & (P[..., 0] < box[1] + 0.01)
        & (np.abs(P[..., 1]) < 0.19)
        & (P[..., 2] > zg + 0.001)
    )
    assert on_box.sum() > 100
    top_w, top_1 = np.nanmax(hm_w.height[on_box]), np.nanmax(hm_1.height[on_box])
    assert top_w == pytest.approx(0.12, abs=0.01)
    assert top_1 < top_w - 0.02  # the unweighted ground sits partly on the rock
    ground = np.isfinite(hm_w.height) & ~on_box & (np.hypot(P[..., 0], P[..., 1]) < 4.0)
    assert np.nanmedian(np.abs(hm_w.height[ground])) < 0.005
    with pytest.raises(ConfigError):
        GroundConfig(footprint_span_px=0)


def _far_rock_scene(seed):
    """The front camera over level ground with a 12 cm box rock 4.3-4.55 m ahead: the camera,
    its mount, the box and the ray-cast half-resolution disparity with 0.02 px of noise."""
    from lunarloc.perception.camera import ipex_rig

    cam = PinholeCamera()
    T = ipex_rig(cam)["FrontLeft"].T_rover_optical
    box = (4.3, 4.55, -0.2, 0.2, 0.12)
    disp = _ray_cast_disparity(cam, T, 2, box)
    disp = disp + np.random.default_rng(seed).normal(0, 0.02, disp.shape).astype(np.float32)
    return cam, T, box, disp


def _on_far_rock(P, T, box):
    """The rover-frame points of `_far_rock_scene`'s box (above the level ground by 1 mm)."""
    return (
        (P[..., 0] > box[0] - 0.01)
        & (P[..., 0] < box[1] + 0.01)
        & (np.abs(P[..., 1]) < 0.19)
        & (P[..., 2] > T[2, 3] - 0.331 + 0.001)
    )


def test_ground_footprint_min_drop_keeps_the_plain_ground_off_the_rock():
    """footprint_min_drop_m: the weighted level replaces the plain one only in cells where it
    lies that much lower (the far rock's cells); on noisy open ground, where the two differ by
    millimetres, the heights are the plain ground's, bit for bit, while the rock's top stands
    higher above its ground than over the plain one."""
    from lunarloc.perception.stereo import GroundConfig, ground_height_map

    cam, T, box, disp = _far_rock_scene(seed=3)
    plain = ground_height_map(disp, 2, cam, 0.162, T, GroundConfig())
    fw = ground_height_map(disp, 2, cam, 0.162, T, GroundConfig(footprint_weights=True))
    cfg = GroundConfig(footprint_weights=True, footprint_min_drop_m=0.02)
    hyb = ground_height_map(disp, 2, cam, 0.162, T, cfg)
    P = plain.points_rover
    on_box = _on_far_rock(P, T, box)
    assert np.nanmax(hyb.height[on_box]) > np.nanmax(plain.height[on_box]) + 0.01
    # open ground well clear of the rock's cells (bilinear interpolation reaches one cell)
    far_off = np.isfinite(plain.height) & (np.hypot(P[..., 0] - 4.4, P[..., 1]) > 1.2)
    assert far_off.sum() > 1000
    assert np.any(fw.height[far_off] != plain.height[far_off])  # the weights move it
    np.testing.assert_array_equal(hyb.height[far_off], plain.height[far_off])
    with pytest.raises(ConfigError):
        GroundConfig(footprint_min_drop_m=-0.01)


def test_ground_far_quantile_lowers_the_far_cells_only():
    """far_quantile: cells whose centre lies far_range_m or more from the camera take the lower
    quantile, so the far rock that lifts its cells' median stands higher above its ground;
    near the camera (well inside far_range_m, beyond the bilinear reach of one cell) the
    heights are the plain ground's, bit for bit."""
    from lunarloc.perception.stereo import GroundConfig, ground_height_map

    cam, T, box, disp = _far_rock_scene(seed=5)
    plain = ground_height_map(disp, 2, cam, 0.162, T, GroundConfig())
    low = ground_height_map(disp, 2, cam, 0.162, T, GroundConfig(far_quantile=0.4, far_range_m=3.0))
    assert GroundConfig().far_quantile == 0.0  # off by default
    P = plain.points_rover
    on_box = _on_far_rock(P, T, box)
    assert np.nanmax(low.height[on_box]) > np.nanmax(plain.height[on_box]) + 0.005
    rng = np.hypot(P[..., 0] - T[0, 3], P[..., 1] - T[1, 3])
    near = np.isfinite(plain.height) & (rng < 2.0)
    assert near.sum() > 1000
    np.testing.assert_array_equal(low.height[near], plain.height[near])
    for bad in ({"far_quantile": 1.0}, {"far_quantile": -0.1}, {"far_range_m": -1.0}):
        with pytest.raises(ConfigError, match="far_"):
            GroundConfig(**bad)
