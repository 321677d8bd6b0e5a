"""The small-rock stage (perception/small_rocks.py): a small rock on a textured plane, ray-cast
into a synthetic stereo pair, is found from its full-resolution stereo height above a local
ground, whether the ground is level or tilted (a rover rolled on a slope), and a bare plane
gives nothing."""

from __future__ import annotations

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError
from lunarloc.perception.camera import PinholeCamera, ipex_rig
from lunarloc.perception.detector import Detector, DetectorConfig
from lunarloc.perception.small_rocks import (
    SmallRockConfig,
    detect_small_rocks,
    ground_plane,
)

CAM = PinholeCamera(1280, 720, 70.0)
BASELINE_M = 0.162
CAM_HEIGHT_M = 0.45


def _render(
    roll_deg: float,
    rock: tuple[float, float, float, float] | None,
    seed: int = 0,
    dark: bool = False,
    texture_std: float = 35.0,
    plain: bool = False,
):
    """Left and right images (uint8) of a plane CAM_HEIGHT_M below the cameras, rolled by
    roll_deg about the optical axis, with an optional rock: a sphere (x_m, z_m, radius_m,
    top_m) standing top_m above the plane at lateral x_m and depth z_m (before the roll).
    The regolith is a smooth random texture fixed to the plane; the rock is brighter (lit), or,
    with `dark`, lit from behind by a low sun ahead of the cameras: its visible side unlit and its
    shadow cast towards the cameras, both darker than the regolith. With `plain` the rock is
    neither: its surface carries the regolith's texture and brightness (no shading)."""
    import cv2

    rng = np.random.default_rng(seed)
    res_m = 0.004  # texture pixels on the plane
    tex = cv2.GaussianBlur(rng.normal(0, 1, (2600, 1600)).astype(np.float32), (0, 0), 1.2)
    tex = 100 + texture_std * tex / tex.std()
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    n = Rz @ np.array([0.0, 1.0, 0.0])  # plane normal, pointing away from the cameras (y down)
    e_lat, e_fwd = Rz @ np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    sphere = None
    if rock is not None:
        x, z, rad, top = rock
        g = CAM_HEIGHT_M * n + x * e_lat + z * e_fwd  # the ground point under the rock
        sphere = (g - n * (top - rad), rad)
    vv, uu = np.mgrid[0 : CAM.height, 0 : CAM.width].astype(float)
    d = np.stack([(uu - CAM.cx) / CAM.fx, (vv - CAM.cy) / CAM.fx, np.ones_like(uu)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    out = []
    for ox in (0.0, BASELINE_M):
        o = np.array([ox, 0.0, 0.0])
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (CAM_HEIGHT_M - o @ n) / den
        t[~(den > 1e-6)] = np.inf
        X = o + np.where(np.isfinite(t), t, 0.0)[..., None] * d
        a = (X @ e_lat) / res_m + 800
        b = (X @ e_fwd) / res_m
        img = cv2.remap(
            tex, a.astype(np.float32), b.astype(np.float32), cv2.INTER_LINEAR, borderValue=0
        )
        img[~np.isfinite(t)] = 0
        if sphere is not None:
            C, rad = sphere
            oc = o - C
            bq = d @ oc
            disc = bq * bq - (oc @ oc - rad * rad)
            ts = -bq - np.sqrt(np.maximum(disc, 0))
            Xs = o + ts[..., None] * d
            hit = (disc > 0) & (ts > 0) & (ts < t) & ((Xs @ n) < CAM_HEIGHT_M)
            # lit from above-right: brighter where the surface faces the light
            nrm = (Xs - C) / rad
            light = -n * 0.7 + e_lat * 0.7
            shade = 150 + 90 * np.clip(nrm @ (light / np.linalg.norm(light)), 0, 1)
            if dark:
                shade = np.full_like(shade, 30.0)
            # its texture fixed to its surface (the same in both views)
            ta = cv2.remap(
                tex,
                ((Xs @ e_lat) / res_m * 2 + 800).astype(np.float32),
                ((Xs @ e_fwd + Xs @ n) / res_m * 2).astype(np.float32),
                cv2.INTER_LINEAR,
            )
            img[hit] = ta[hit] if plain else shade[hit] + 0.3 * (ta[hit] - 100)
            if dark:  # the ground in the rock's shadow (the sun 15 degrees up, ahead)
                to_sun = -n * np.sin(np.radians(15.0)) + e_fwd * np.cos(np.radians(15.0))
                rel = X - C
                along = rel @ to_sun
                miss = np.linalg.norm(rel - along[..., None] * to_sun, axis=-1)
                img[(miss < rad) & (along < 0) & ~hit & np.isfinite(t)] *= 0.3
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


def _small_rocks(L, R, cfg=None, with_heights=False):
    """The stage's rocks (with_heights: given the height map's heights, as the detector gives
    them: its pre-check and its height candidates), the view's ground normal and the mount."""
    det = Detector(DetectorConfig(), CAM)
    T_ro = ipex_rig(CAM)["FrontLeft"].T_rover_optical
    hm = det.height_map(L, R, T_ro)  # levelled on the stereo ground plane when tilted
    n_up = ground_plane(hm.points_rover, hm.depth)
    up = hm.T_rover_optical[:3, :3].T @ n_up if n_up is not None else None
    rocks = detect_small_rocks(
        L,
        R,
        hm.disparity,
        hm.scale,
        CAM,
        BASELINE_M,
        cfg or SmallRockConfig(),
        up,
        height_lowres=hm.height if with_heights else None,
    )
    if n_up is not None and hm.T_level_rover is not None:
        n_up = hm.T_level_rover[:3, :3].T @ n_up  # back in the rover frame
    return rocks, n_up, T_ro


def _uv(x, z, roll_deg):
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    p = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([x, CAM_HEIGHT_M, z])
    return CAM.cx + CAM.fx * p[0] / p[2], CAM.cy + CAM.fx * p[1] / p[2]


@pytest.mark.parametrize("roll_deg", [0.0, 15.0])
def test_a_small_rock_is_found_on_level_and_tilted_ground(roll_deg):
    # a rock 5 cm wide standing 2.5 cm high, 2.5 m ahead: the half-resolution height map's
    # thresholds (3.5 cm seeds) cannot see it
    x, z, rad, top = 0.3, 2.5, 0.025, 0.025
    L, R = _render(roll_deg, (x, z, rad, top))
    rocks, _, _ = _small_rocks(L, R)
    u, v = _uv(x, z, roll_deg)
    near = [
        r
        for r in rocks
        if abs(r.u0 + r.crop.shape[1] / 2 - u) < 25 and abs(r.v0 + r.crop.shape[0] / 2 - v) < 25
    ]
    assert len(near) == 1, [(r.u0, r.v0, r.top_m) for r in rocks]
    r = near[0]
    assert 0.4 * top < r.top_m < 1.6 * top
    assert abs(r.depth_m - z) < 0.25
    assert 0.5 * 2 * rad < r.width_m < 2.0 * 2 * rad
    assert len(rocks) == 1  # nothing else on the bare texture


@pytest.mark.parametrize("roll_deg", [0.0, 15.0])
def test_bare_ground_gives_no_small_rock_and_its_tilt_is_measured(roll_deg):
    L, R = _render(roll_deg, None, seed=1)
    rocks, n_up, T_ro = _small_rocks(L, R)
    assert rocks == []
    # the ground's normal from stereo alone: the plane's true up direction, in the rover frame
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    up_optical = -(
        np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([0.0, 1.0, 0.0])
    )
    up_rover = T_ro[:3, :3] @ up_optical
    assert n_up is not None
    assert np.degrees(np.arccos(np.clip(n_up @ up_rover, -1, 1))) < 2.0


def test_the_detector_reports_the_small_rock_by_default_and_not_with_the_stage_off():
    from dataclasses import replace

    L, R = _render(10.0, (-0.2, 2.0, 0.02, 0.02), seed=2)
    T_ro = ipex_rig(CAM)["FrontLeft"].T_rover_optical
    off_cfg = replace(DetectorConfig(), small_rocks=SmallRockConfig(enabled=False))
    on = Detector(DetectorConfig(), CAM).detect_pair(L, R, T_ro)
    off = Detector(off_cfg, CAM).detect_pair(L, R, T_ro)
    u, v = _uv(-0.2, 2.0, 10.0)
    hits = [d for d in on.detections if abs(d.uv[0] - u) < 25 and abs(d.uv[1] - v) < 25]
    assert len(hits) == 1 and abs(hits[0].depth_m - 2.0) < 0.25 and 0.01 < hits[0].radius_m < 0.05
    assert hits[0].small_rock and DetectorConfig().small_rocks.enabled
    assert not [d for d in off.detections if abs(d.uv[0] - u) < 25 and abs(d.uv[1] - v) < 25]


def test_a_dark_small_rock_is_found_by_the_dark_candidates_only():
    """A rock darker than the regolith (its unlit side) gives no bright candidate; a dark
    candidate's window is judged by its raised part (the rock), so with dark_contrast_z it is
    found, at its range, and bare ground still gives nothing. (The rock network's candidate
    finds it without the dark ones.)"""
    x, z, rad, top = 0.3, 2.0, 0.015, 0.02
    L, R = _render(0.0, (x, z, rad, top), seed=4, dark=True, texture_std=15.0)
    u, v = _uv(x, z, 0.0)

    def near(rocks):
        return [
            r
            for r in rocks
            if abs(r.u0 + r.crop.shape[1] / 2 - u) < 25 and abs(r.v0 + r.crop.shape[0] / 2 - v) < 25
        ]

    # the bright candidates alone miss it (the rock network, on by default, finds it too)
    assert near(_small_rocks(L, R, SmallRockConfig(dark_contrast_z=0.0, net_candidates=0))[0]) == []
    assert len(near(_small_rocks(L, R, SmallRockConfig(dark_contrast_z=0.0))[0])) == 1
    dark_cfg = SmallRockConfig(dark_contrast_z=2.0)
    rocks, _, _ = _small_rocks(L, R, dark_cfg)
    assert len(near(rocks)) == 1 and len(rocks) == 1, [(r.u0, r.v0, r.top_m) for r in rocks]
    assert abs(rocks[0].depth_m - z) < 0.25 and 0.4 * top < rocks[0].top_m < 1.6 * top
    bare_L, bare_R = _render(0.0, None, seed=5, texture_std=15.0)
    assert _small_rocks(bare_L, bare_R, dark_cfg)[0] == []


@pytest.mark.parametrize(
    "bad",
    [
        dict(min_range_m=7.0),
        dict(min_width_m=0.2),
        dict(candidate_scale=3),
        dict(block_size=15.5),
        dict(dark_contrast_z=-1.0),
        dict(refine_margin=float("nan")),
        dict(min_median_snr=-0.5),
        dict(max_dark_candidates=-2),
        dict(enabled=1),
        dict(block_size=4),
        dict(band_px=20),
        dict(max_tilt_deg=0.0),
        dict(min_top_m=0.0),
        dict(max_candidates=-1),
        dict(contrast_z=0.0),
        dict(max_aspect=float("nan")),
        dict(window_margin=0.0),
        dict(max_band_px=40),
        dict(min_lowres_height_m=float("inf")),
        dict(low_top_snr=-1.0),
        dict(height_candidates=-1),
        dict(height_candidate_m=0.0),
    ],
)
def test_bad_settings_are_refused(bad):
    with pytest.raises(ConfigError):
        SmallRockConfig(**bad)


def test_the_detector_sees_the_same_rock_on_level_ground_and_rolled_20_degrees():
    """No level-rover assumption: the roll is unknown to the detector (the rover frame is all it
    has); it levels its height map on the plane fitted to the pair's own stereo points. Rolled
    20 degrees, a 0.1 m rock at 4 m is found as on level ground. (Unlevelled, in the rover frame,
    it was lost while the crop match ran in SGBM's 3WAY mode; with HH4, the default since, this
    rock is found either way.)"""
    T_ro = ipex_rig(CAM)["FrontLeft"].T_rover_optical
    x, z, rad, top = -0.5, 4.0, 0.1, 0.09
    found = {}
    for roll in (0.0, 20.0):
        L, R = _render(roll, (x, z, rad, top), seed=3)
        pr = Detector(DetectorConfig(), CAM).detect_pair(L, R, T_ro)
        u, v = _uv(x, z, roll)
        hits = [d for d in pr.detections if abs(d.uv[0] - u) < 30 and abs(d.uv[1] - v) < 30]
        assert len(hits) == 1, (roll, [d.uv for d in pr.detections])
        found[roll] = hits[0]
    a, b = found[0.0], found[20.0]
    assert abs(a.radius_m - b.radius_m) < 0.2 * a.radius_m and abs(a.height_m - b.height_m) < 0.02
    assert abs(a.depth_m - b.depth_m) < 0.15
    # p_rover stays in the rover frame: the rock's distance from the camera is the same
    cam = T_ro[:3, 3]
    assert abs(np.linalg.norm(a.p_rover - cam) - np.linalg.norm(b.p_rover - cam)) < 0.1


def test_the_stages_order_statistics_are_numpys_value_for_value():
    """The stage's partition-based statistics (its speed) give numpy's values bit for bit:
    NaN medians of rows (NaN for an all-NaN row), medians and paired quantiles."""
    import warnings

    from lunarloc.perception.small_rocks import _median, _nanmedian_rows, _quantile, _quantiles

    rng = np.random.default_rng(5)
    for dtype in (np.float32, np.float64):
        a = (rng.random((200, 25)) * 60).astype(dtype)
        a[rng.random(a.shape) < 0.5] = np.nan
        a[0] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ref = np.nanmedian(a, axis=1)
        got = _nanmedian_rows(a)
        assert got.dtype == ref.dtype and np.array_equal(got, ref, equal_nan=True)
    for n in (1, 2, 7, 50, 51):
        x = rng.normal(size=n)
        assert _median(x.copy()) == np.median(x)
        assert _quantiles(x, 0.05, 0.95) == (_quantile(x, 0.05), _quantile(x, 0.95))
        assert _quantile(x, 0.95) == pytest.approx(np.quantile(x, 0.95), abs=1e-12)


def test_the_stages_fast_helpers_give_the_plain_forms_values():
    """The stage's speed helpers against the plain numpy forms they replace, value for value:
    the in-place median and MAD of float64 arrays, the candidates' 5 x 5 disparity medians from
    the padded map, the components touching a blob (unique + isin), and the blob's box size."""
    import cv2

    from lunarloc.perception.small_rocks import (
        _box_size,
        _Grid,
        _median64,
        _nanmedian_rows,
        _quantile,
        _robust_spread,
        _touching,
    )

    rng = np.random.default_rng(11)
    for n in (1, 2, 3, 8, 51, 400):
        x = rng.normal(size=n)
        m = _quantile(x, 0.5)
        assert _median64(x.copy()) == m
        y = x.copy()
        assert _robust_spread(y) == (m, 1.4826 * _quantile(np.abs(x - m), 0.5) + 1e-4)
        assert np.array_equal(y, x)  # not reordered
    D = (rng.random((40, 60)) * 30).astype(np.float32)
    D[rng.random(D.shape) < 0.3] = np.nan
    grid = _Grid(D, 2, 2, 6, 900.0, 900.0 * 0.162)
    pv, pu = rng.integers(0, 37, 300), rng.integers(0, 60, 300)
    d0, Z = grid.depth(pv, pu)
    pad = np.pad(D, 2, constant_values=np.nan)
    cu = np.clip(pu * 2 // 2, 0, 59)
    cv = np.clip((pv * 2 + 6) // 2, 0, 39)
    win = np.stack([pad[cv + 2 + a, cu + 2 + b] for a in range(-2, 3) for b in range(-2, 3)], 1)
    ref = _nanmedian_rows(win) * 2
    assert np.array_equal(d0, ref, equal_nan=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        assert np.array_equal(Z, grid.fb / ref, equal_nan=True)
    for _ in range(20):
        region = (rng.random((30, 40)) < 0.3).astype(np.uint8)
        blob = np.zeros((30, 40), bool)
        blob[rng.integers(0, 30, 3), rng.integers(0, 40, 3)] = True
        region |= blob.astype(np.uint8)
        _, lab = cv2.connectedComponents(region, connectivity=8)
        ids = np.unique(lab[blob])
        assert np.array_equal(_touching(region, blob), np.isin(lab, ids[ids > 0]))
        ys, xs = np.nonzero(region)
        assert _box_size(region) == (xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)


def test_the_view_s_ground_normal_is_fitted_once_and_kept_on_the_height_map():
    """The detector's levelling fit of the view's ground is kept on the height map (the stage's
    tilt test reuses it instead of fitting the same points again); it points up and, levelled,
    along the levelled frame's z."""
    L, R = _render(20.0, None, seed=4)
    T_ro = ipex_rig(CAM)["FrontLeft"].T_rover_optical
    hm = Detector(DetectorConfig(), CAM).height_map(L, R, T_ro)
    assert hm.up_rover is not None and hm.T_level_rover is not None
    assert abs(np.linalg.norm(hm.up_rover) - 1.0) < 1e-9 and hm.up_rover[2] > 0.999
    n = ground_plane(hm.points_rover, hm.depth)
    assert np.degrees(np.arccos(np.clip(n @ hm.up_rover, -1, 1))) < 1.0


@pytest.mark.parametrize("seed", [6, 7])
def test_a_rock_the_image_does_not_show_is_found_by_the_height_candidates(seed):
    """A rock with the regolith's own texture and brightness (no lit face, no shadow) gives no
    appearance candidate; the height map's local peak over it does (height_candidates), its
    full-resolution height is measured as any candidate's, and bare ground still gives
    nothing."""
    x, z, rad, top = 0.3, 2.0, 0.025, 0.03
    L, R = _render(0.0, (x, z, rad, top), seed=seed, plain=True)
    u, v = _uv(x, z, 0.0)
    # (the rock network, on by default, finds it on one of the two seeds: off here)
    assert _small_rocks(L, R, SmallRockConfig(height_candidates=0, net_candidates=0), True)[0] == []
    cfg = SmallRockConfig(height_candidates=20)
    rocks, _, _ = _small_rocks(L, R, cfg, True)
    assert len(rocks) == 1, [(r.u0, r.v0, r.top_m) for r in rocks]
    r = rocks[0]
    assert abs(r.u0 + r.crop.shape[1] / 2 - u) < 15 and abs(r.v0 + r.crop.shape[0] / 2 - v) < 15
    assert 0.5 * top < r.top_m < 1.5 * top and abs(r.depth_m - z) < 0.25
    bare_L, bare_R = _render(0.0, None, seed=seed)
    assert _small_rocks(bare_L, bare_R, cfg, True)[0] == []


def test_the_candidate_limits_count_only_candidates_that_get_a_window():
    """With count_checked a candidate centred on an excluded pixel (a height-map
    blob) or failing the height map's pre-check takes no place within max_candidates: the
    strongest blob excluded, the only place goes to the next one; without it the excluded blob
    takes the place and the stage would match nothing."""
    from dataclasses import replace

    from lunarloc.perception.small_rocks import small_rock_candidates

    L, R = _render(0.0, (0.3, 2.0, 0.025, 0.025), seed=8)
    T_ro = ipex_rig(CAM)["FrontLeft"].T_rover_optical
    hm = Detector(DetectorConfig(), CAM).height_map(L, R, T_ro)
    one = SmallRockConfig(
        max_candidates=1,
        dark_contrast_z=0.0,
        min_lowres_height_m=0.0,
        count_checked=True,
        net_candidates=0,  # the bright candidates alone
    )

    def centres(cfg, exclude=None):
        cands = small_rock_candidates(
            L, hm.disparity, hm.scale, CAM.fx, BASELINE_M, cfg, exclude, hm.height
        )
        return [(u0 + c.shape[1] // 2, v0 + c.shape[0] // 2) for u0, v0, c, *_ in cands]

    ((u, v),) = centres(one)  # the strongest blob
    exclude = np.zeros(L.shape, bool)
    exclude[v - 20 : v + 20, u - 20 : u + 20] = True
    assert centres(replace(one, count_checked=False), exclude) == [(u, v)]
    ((u2, v2),) = centres(one, exclude)
    assert not exclude[v2, u2]
