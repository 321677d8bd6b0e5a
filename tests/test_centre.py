"""Centre estimators of the stereo-points detector (CentreEstimator): the ring ground
plane, the BLEND estimator against MEDIAN, the settings' checks and round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError
from lunarloc.perception.detector_config import MOVED_KEYS
from lunarloc.perception.detector import (
    CentreEstimator,
    Detector,
    DetectorConfig,
    _centre_blend,
    _centre_for_mask,
    _centre_from_points,
    _ring_ground_plane,
)

CAM_ROVER = np.array([0.3, 0.0, 0.3])


def _grid(plane=(-0.2, 0.02, -0.03), n=60, noise=0.002, seed=0):
    """Rover-frame points (n, n, 3) of a tilted plane z = c0 + c1 x + c2 y over x 2-5 m,
    y -1.5..1.5 m, as the height map holds them, and the plane's coefficients."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:n, 0:n]
    x, y = 5.0 - 3.0 * r / (n - 1), -1.5 + 3.0 * c / (n - 1)
    z = plane[0] + plane[1] * x + plane[2] * y + rng.normal(0.0, noise, x.shape)
    return np.stack([x, y, z], axis=-1), np.asarray(plane)


def _visible_cap(centre, radius, cam=CAM_ROVER, n=4000, seed=0):
    """Points of a sphere's surface that face the camera and lie above the ground plane
    z = ground (a crude stand-in for a rock's visible, unburied surface)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    P = np.asarray(centre) + radius * u
    facing = np.einsum("ij,ij->i", u, cam - P) > 0
    return P[facing]


def test_ring_plane_recovers_the_ground_around_a_rock_and_ignores_its_skirt():
    pts, plane = _grid()
    blob = np.zeros(pts.shape[:2], bool)
    blob[25:32, 27:34] = True
    rows, cols = np.nonzero(blob)
    # the rock's skirt: the ring's pixels below the blob stand 10 cm above the ground
    skirt = pts.copy()
    skirt[32:40, 25:36, 2] += 0.10
    skirt[24, 27:34, 2] = np.nan  # some ring pixels have no depth
    c = _ring_ground_plane(skirt, rows, cols)
    assert c is not None
    xy = pts[blob][:, :2]
    g_true = plane[0] + xy @ plane[1:]
    g_fit = c[0] + xy @ c[1:]
    assert np.max(np.abs(g_fit - g_true)) < 0.005
    # a plain least-squares fit over the same ring is lifted by the skirt: the one-sided
    # rejection is what keeps it on the ground
    from lunarloc.perception.detector import _ring_mask

    (r0, r1, c0, c1), ring = _ring_mask(skirt.shape[:2], rows, cols, 6, 2)
    Q = skirt[r0:r1, c0:c1][ring]
    Q = Q[np.isfinite(Q[:, 2])]
    ls = np.linalg.lstsq(np.column_stack([np.ones(len(Q)), Q[:, :2]]), Q[:, 2], rcond=None)[0]
    assert np.max(np.abs(ls[0] + xy @ ls[1:] - g_true)) > 0.01
    # too few valid ring points: no plane
    holes = pts.copy()
    holes[..., 2] = np.nan
    assert _ring_ground_plane(holes, rows, cols) is None


def test_blend_with_no_near_weight_and_no_plane_is_the_median_estimator():
    cfg = DetectorConfig(centre_estimator=CentreEstimator.BLEND, centre_near_weight=0.0)
    P = _visible_cap((3.0, 0.2, -0.1), 0.15)
    h = P[:, 2] + 0.2  # heights above a ground at z = -0.2
    p_med, R_med = _centre_from_points(P, h, CAM_ROVER, cfg, 0.15)
    p_bl, R_bl = _centre_blend(P, h, CAM_ROVER, cfg, 0.15, None)
    assert R_bl == R_med and np.allclose(p_bl, p_med)
    # the dispatcher picks the estimator from the config
    pts, _ = _grid()
    rows, cols = np.nonzero(np.pad(np.ones((5, 5), bool), 20))
    p_def, _ = _centre_for_mask(P, h, CAM_ROVER, DetectorConfig(), 0.15, pts, rows, cols)
    assert np.allclose(p_def, p_med)


def test_blend_height_follows_the_ring_ground_and_its_range_the_near_edge():
    # a sphere of radius 0.15 m buried to a third of its height: centre 5 cm above the ground
    R, g = 0.15, -0.2
    centre = np.array([3.0, 0.2, g + 0.05])
    P = _visible_cap(centre, R)
    P = P[P[:, 2] > g]
    h = P[:, 2] - g
    cfg = DetectorConfig(centre_estimator=CentreEstimator.BLEND)
    plane = np.array([g, 0.0, 0.0])
    p, R_out = _centre_blend(P, h, CAM_ROVER, cfg, R, plane)
    assert R_out == R
    assert np.linalg.norm(p - centre) < 0.3 * R
    # the height moves with the ground under the rock by centre_ring_exposed_factor
    p_low, _ = _centre_blend(P, h, CAM_ROVER, cfg, R, np.array([g - 0.1, 0.0, 0.0]))
    assert p_low[2] - p[2] == pytest.approx(-0.1 * cfg.centre_ring_exposed_factor, abs=1e-9)
    assert np.allclose(p_low[:2], p[:2])
    # the near anchor: a mask that lost its nearest points moves the centre away
    far_only = P[P[:, 0] > 2.9]  # the front 5 cm of the rock lost
    p_far, _ = _centre_blend(far_only, far_only[:, 2] - g, CAM_ROVER, cfg, R, plane)
    w0 = DetectorConfig(centre_estimator=CentreEstimator.BLEND, centre_near_weight=0.0)
    p_far0, _ = _centre_blend(far_only, far_only[:, 2] - g, CAM_ROVER, w0, R, plane)
    assert p_far[0] > p[0] and p_far[0] != pytest.approx(p_far0[0], abs=1e-4)
    # stray points far in front of the rock (ground or mismatches in the mask, here 13 %)
    # move the near anchor by at most centre_near_clamp_radii x R
    stray = np.vstack(
        [P, np.column_stack([np.full(200, 2.3), np.full(200, 0.2), np.full(200, g + 0.01)])]
    )
    p_stray, _ = _centre_blend(stray, stray[:, 2] - g, CAM_ROVER, cfg, R, plane)
    assert abs(p_stray[0] - p[0]) < 0.05
    loose = DetectorConfig(centre_estimator=CentreEstimator.BLEND, centre_near_clamp_radii=10.0)
    p_loose, _ = _centre_blend(stray, stray[:, 2] - g, CAM_ROVER, loose, R, plane)
    assert p_stray[0] - p_loose[0] > 0.05


@pytest.mark.parametrize(
    "key, value",
    [
        ("centre_estimator", "ellipsoid"),
        ("centre_near_weight", 1.5),
        ("centre_near_weight", -0.1),
        ("centre_near_quantile", 0.0),
        ("centre_near_quantile", 0.6),
        ("centre_near_range_factor", -0.1),
        ("centre_ring_radius_factor", -0.1),
        ("centre_ring_exposed_factor", -0.1),
        ("centre_near_clamp_radii", -1.0),
    ],
)
def test_centre_settings_are_checked_and_round_trip(key, value, tmp_path):
    from lunarloc.config.run import RunConfig, load_config_file

    with pytest.raises(ConfigError, match=key):
        RunConfig.from_dict({"detector": {key: value}})
    good = {
        "centre_estimator": "blend",
        "centre_near_weight": 0.5,
        "centre_near_quantile": 0.1,
        "centre_near_range_factor": 0.7,
        "centre_ring_radius_factor": 0.2,
        "centre_ring_exposed_factor": 0.5,
        "centre_near_clamp_radii": 0.8,
    }[key]
    p = tmp_path / "config.json"
    p.write_text(json.dumps({"detector": {key: good}}))
    cfg, _ = load_config_file(p)
    assert RunConfig.from_dict(cfg.to_dict()) == cfg
    got = getattr(cfg.detector, key)
    assert (got.value if isinstance(got, CentreEstimator) else got) == good
    assert cfg.detector.to_dict()["centre"][MOVED_KEYS[key][1]] == good  # written in its section


def test_blend_detector_places_a_rock_on_the_ground():
    from test_detector import CAM, ground_scene

    c = np.array([3.28, 0.1, -0.15])
    left, right, rig = ground_scene(tuple(c), 0.15)
    det = Detector(DetectorConfig(centre_estimator=CentreEstimator.BLEND), CAM)
    pr = det.detect_pair(left, right, rig["FrontLeft"].T_rover_optical)
    assert len(pr.detections) == 1
    d = pr.detections[0]
    assert np.linalg.norm(d.p_rover[:2] - c[:2]) < 0.06
    assert abs(d.p_rover[2] - c[2]) < 0.08


def test_the_ground_behind_a_rock_in_its_mask_does_not_push_its_centre_away():
    # a 6 cm rock 3 m ahead; its half-resolution mask also holds ground behind it (a third of
    # its points, 4-15 cm beyond the rock's far side): the median range over all the points
    # would move 1.5 cm or more away; the points beyond a diameter of the nearest are left out
    R, g = 0.06, -0.2
    centre = np.array([3.0, 0.2, g + 0.02])
    P = _visible_cap(centre, R, n=3000)
    P = P[P[:, 2] > g]
    h = P[:, 2] - g
    rng = np.random.default_rng(1)
    n = len(P) // 2
    behind = np.column_stack(
        [rng.uniform(3.1, 3.21, n), rng.uniform(0.15, 0.25, n), np.full(n, g + 0.005)]
    )
    cfg = DetectorConfig()
    p, _ = _centre_from_points(P, h, CAM_ROVER, cfg, R)
    Pm = np.vstack([P, behind])
    p_mixed, _ = _centre_from_points(Pm, Pm[:, 2] - g, CAM_ROVER, cfg, R)
    plain_shift = np.median(Pm[:, 0] - CAM_ROVER[0]) - np.median(P[:, 0] - CAM_ROVER[0])
    assert plain_shift > 0.015
    assert abs(p_mixed[0] - p[0]) < 0.3 * plain_shift
    # the BLEND estimator's median term leaves them out too
    bl = DetectorConfig(centre_estimator=CentreEstimator.BLEND)
    q, _ = _centre_blend(P, h, CAM_ROVER, bl, R, None)
    q_mixed, _ = _centre_blend(Pm, Pm[:, 2] - g, CAM_ROVER, bl, R, None)
    assert abs(q_mixed[0] - q[0]) < 0.3 * plain_shift
