"""The surface-fit rock centre (CentreMethod.SURFACE_FIT): an ellipsoid fitted to the
visible stereo points of one side of a rock; partial views, degenerate input, its config."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lunarloc.config import RunConfig
from lunarloc.errors import ConfigError
from lunarloc.perception.detector import (
    CentreMethod,
    Detector,
    DetectorConfig,
    _centre_from_points,
    _centre_from_surface_fit,
)

CAM_ROVER = np.array([0.0, 0.0, 0.7])  # a camera 0.7 m above the rover origin


def visible_points(centre, axes, cam=CAM_ROVER, n=4000, ground=None, noise_m=0.0, seed=0):
    """Points of an axis-aligned ellipsoid's surface that face `cam` (and lie above
    `ground`), with range noise along the viewing ray."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    axes = np.asarray(axes, float)
    P = np.asarray(centre, float) + u * axes
    normal = u / axes
    vis = np.einsum("ij,ij->i", cam - P, normal) > 0
    if ground is not None:
        vis &= P[:, 2] > ground
    P = P[vis]
    ray = (P - cam) / np.linalg.norm(P - cam, axis=1, keepdims=True)
    return P + rng.normal(scale=noise_m, size=(len(P), 1)) * ray


def fit(P, ground, radius, cfg=None):
    cfg = cfg or DetectorConfig(centre_method="surface-fit")
    return _centre_from_surface_fit(P, P[:, 2] - ground, CAM_ROVER, cfg, radius)


@pytest.mark.parametrize("centre, axes, ground", [
    ((3.0, 0.5, 0.0), (0.3, 0.3, 0.3), -0.2),     # a sphere, a third buried
    ((3.0, 0.5, 0.0), (0.3, 0.3, 0.2), -0.1),     # flatter than the prior, a quarter buried
    ((2.5, -0.8, 0.05), (0.5, 0.5, 0.35), -0.2),  # a boulder near the rover
])  # fmt: skip
def test_centre_of_an_ellipsoid_seen_from_one_side(centre, axes, ground):
    P = visible_points(centre, axes, ground=ground, noise_m=0.004)
    p, R = fit(P, ground, axes[1])
    assert R == pytest.approx(axes[1])  # the radius given (the silhouette's) is passed through
    err = np.asarray(p) - centre
    assert np.linalg.norm(err) < 0.08 * axes[0]
    # the fit sees the surface's curvature: nearer than the visible-surface offsets put it
    p0, _ = _centre_from_points(P, P[:, 2] - ground, CAM_ROVER, DetectorConfig(), axes[1])
    assert np.linalg.norm(err) <= np.linalg.norm(p0 - centre) + 0.005


def test_partial_view_of_the_top_only():
    # a mask that keeps only the upper half of the visible surface (the lower part cut
    # by the height threshold, as for large rocks whose ground cells rise under them)
    centre, axes, ground = np.array([3.0, 0.4, 0.05]), (0.45, 0.45, 0.32), -0.15
    P = visible_points(centre, axes, ground=ground, noise_m=0.004)
    P = P[P[:, 2] > centre[2]]
    p, _ = fit(P, ground, axes[1])
    assert np.all(np.isfinite(p))
    assert np.linalg.norm(np.asarray(p) - centre) < 0.15 * axes[0]


def test_a_wrong_silhouette_radius_is_corrected_by_the_curvature_of_a_near_boulder():
    centre, axes, ground = np.array([2.2, 0.0, 0.1]), (0.6, 0.6, 0.45), -0.2
    P = visible_points(centre, axes, ground=ground, noise_m=0.003, n=8000)
    p, _ = fit(P, ground, 0.45)  # the silhouette 25 % short
    p0, _ = _centre_from_points(P, P[:, 2] - ground, CAM_ROVER, DetectorConfig(), 0.45)
    assert np.linalg.norm(np.asarray(p) - centre) < 0.5 * np.linalg.norm(p0 - centre)


def test_degenerate_input_falls_back_or_stays_finite():
    cfg = DetectorConfig(centre_method="surface-fit")
    centre, axes = np.array([3.0, 0.0, 0.0]), (0.2, 0.2, 0.15)
    P = visible_points(centre, axes, ground=-0.1)
    # too few points: exactly the stereo-points centre
    few = P[: cfg.surface_fit_min_points - 1]
    p, R = fit(few, -0.1, 0.2, cfg)
    p0, R0 = _centre_from_points(few, few[:, 2] + 0.1, CAM_ROVER, cfg, 0.2)
    assert np.allclose(p, p0) and R == R0
    # a flat patch (no curvature) and identical points: finite, within two radii
    rng = np.random.default_rng(3)
    flat = np.column_stack([np.full(200, 3.0), rng.uniform(-0.2, 0.2, 200), rng.uniform(-0.1, 0.1, 200)])
    same = np.tile([[3.0, 0.0, 0.05]], (50, 1))
    for Q in (flat, same):
        p, _ = fit(Q, -0.15, 0.2, cfg)
        p0, _ = _centre_from_points(Q, Q[:, 2] + 0.15, CAM_ROVER, cfg, 0.2)
        assert np.all(np.isfinite(p)) and np.linalg.norm(np.asarray(p) - p0) <= 2 * 0.2 + 1e-9


def test_config_round_trips_and_bad_values_are_refused():
    cfg = RunConfig().with_options(detector__centre_method="surface-fit", detector__surface_fit_height_ratio=0.8)
    d = json.loads(json.dumps(cfg.to_dict()))
    assert d["detector"]["centre_method"] == "surface-fit"
    back = RunConfig.from_dict(d)
    assert back == cfg and back.detector.centre_method is CentreMethod.SURFACE_FIT
    assert back.detector.surface_fit_height_ratio == 0.8
    for key, bad in (("surface_fit_lateral_sigma", 0.0), ("surface_fit_noise_m", float("nan")),
                     ("surface_fit_iterations", 0), ("surface_fit_min_points", 2.5)):  # fmt: skip
        with pytest.raises(ConfigError, match=key):
            DetectorConfig(**{key: bad})
    with pytest.raises(ConfigError, match="surface_fit_height_ratio"):
        RunConfig.from_dict({"detector": {"surface_fit_height_ratio": -1}})


def test_detector_uses_the_height_map_with_the_surface_fit():
    assert Detector(DetectorConfig(centre_method="surface-fit")).uses_height
