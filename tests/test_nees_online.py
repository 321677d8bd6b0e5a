"""The online loop's stated uncertainty: the covariance OnlineLocalizer propagates from its last
fix, and the covariance a loop fix is stated with, judged by the NEES (docs/calibration.md,
"The online loop's uncertainty")."""

import math

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError
from lunarloc.online.component import CovarianceAnchor, propagate_covariance
from lunarloc.online.loop import (
    LoopConfig,
    OdometryBounds,
    fix_model_terms,
    fix_model_yaw_variance,
    fix_stated_covariance,
    fix_stated_yaw_variance,
    window_carried_path_m,
    window_centre_bias_covariance,
    window_ray_geometry,
    window_yaw_bias_variance,
)
from lunarloc.pipeline.nees_online import (
    NEES1_68,
    NEES1_997,
    NEES_68,
    NEES_997,
    nees,
    nees_shares,
    yaw_nees_shares,
)


def _drifted_runs(n: int, bounds: OdometryBounds, P0: np.ndarray, yaw_var: float, seed: int = 0):
    """`n` generated odometry runs of 1-10 m on curved paths, each with a scale error and a
    heading drift drawn from `bounds` (as one sigma), an anchor error drawn from `P0` and
    `yaw_var`: (errors (n, 3), stated covariances (n, 3, 3))."""
    rng = np.random.default_rng(seed)
    E, C = [], []
    for _ in range(n):
        length, steps = rng.uniform(1.0, 10.0), 100
        ds = length / steps
        heading = rng.uniform(0, 2 * math.pi) + rng.uniform(-0.3, 0.3) * ds * np.arange(steps)
        s = rng.normal(0, bounds.scale_error)
        d = rng.normal(0, math.radians(bounds.heading_drift_deg_per_m))
        herr = rng.normal(0, math.sqrt(yaw_var)) + d * ds * np.arange(steps)
        true = np.sum(np.column_stack([np.cos(heading), np.sin(heading)]) * ds, axis=0)
        est = np.sum(
            np.column_stack([np.cos(heading + herr), np.sin(heading + herr)]) * ds * (1 + s), axis=0
        )
        e0 = rng.multivariate_normal(np.zeros(3), P0)
        z = rng.normal(0, bounds.scale_error) * length
        E.append(np.r_[est - true + e0[:2], e0[2] + z])
        anchor = CovarianceAnchor(P0, yaw_var, 0.0, np.zeros(3))
        C.append(propagate_covariance(anchor, length, bounds, np.r_[true, 0.0])[0])
    return np.array(E), np.array(C)


def test_the_propagated_covariance_is_calibrated_on_generated_drift():
    """Odometry drifting as its bounds say (one sigma) from an anchor known as stated: the
    propagated covariance's NEES stays in the calibrated band."""
    P0 = np.diag([0.01**2, 0.01**2, 0.005**2])
    E, C = _drifted_runs(300, OdometryBounds(0.01, 0.06), P0, math.radians(0.3) ** 2)
    n, under68, under997 = nees_shares(nees(E, C))
    assert n == 300
    assert 0.60 <= under68 <= 0.80, under68
    assert under997 >= 0.99, under997


def test_the_band_catches_a_covariance_that_ignores_the_drift():
    """The same runs judged against the anchor's covariance alone (no growth) leave the band:
    the check can fail."""
    P0 = np.diag([0.01**2, 0.01**2, 0.005**2])
    E, _ = _drifted_runs(300, OdometryBounds(0.01, 0.06), P0, math.radians(0.3) ** 2)
    _, under68, under997 = nees_shares(nees(E, np.repeat(P0[None], len(E), axis=0)))
    assert under68 < 0.60 and under997 < 0.99


def test_propagation_grows_along_and_across_the_chord():
    anchor = CovarianceAnchor(np.eye(3) * 1e-4, 0.0, 2.0, np.zeros(3))
    P, yaw_var = propagate_covariance(anchor, 7.0, OdometryBounds(0.01, 0.0), [5.0, 0.0, 0.0])
    assert P[0, 0] == pytest.approx(1e-4 + (0.01 * 5.0) ** 2)  # along x: the scale error over 5 m
    assert P[1, 1] == pytest.approx(1e-4)  # across: no heading error, no drift
    assert P[2, 2] == pytest.approx(1e-4 + (0.01 * 5.0) ** 2)
    assert yaw_var == 0.0
    # before the anchor's path length nothing grows
    P, _ = propagate_covariance(anchor, 1.0, OdometryBounds(0.01, 0.06), [5.0, 0.0, 0.0])
    assert np.allclose(P, np.eye(3) * 1e-4)


class _Res:
    def __init__(self, C, d, rot_deg=0.0):
        self.covariance, self.distortion_error_m = C, d
        self.distortion_rotation_deg = rot_deg


def test_a_fix_states_its_distortion_in_sigmas_and_the_window_centre_bias():
    C = np.diag([1e-6, 1e-6, 1e-6, 0.0, 0.0, 0.0])
    C[0, 0] += 0.02**2 / 2  # the distortion allowance (2 cm) localize() splits over x and y
    C[1, 1] += 0.02**2 / 2
    cfg = LoopConfig(fix_distortion_sigmas=2.0, fix_centre_bias_m=0.003, fix_centre_bias_z_m=0.001)
    S = fix_stated_covariance(_Res(C, 0.02), [0.0, 0.0, 0.0], 2, cfg)
    assert S[0, 0] == pytest.approx(1e-6 + 0.01**2 / 2 + 0.003**2)
    assert S[2, 2] == pytest.approx(1e-6 + 0.001**2)
    # one map built from detections: half the bias variance; none: none
    S1 = fix_stated_covariance(_Res(C, 0.02), [0.0, 0.0, 0.0], 1, cfg)
    assert S1[0, 0] == pytest.approx(1e-6 + 0.01**2 / 2 + 0.003**2 / 2)
    with pytest.raises(ConfigError):
        LoopConfig(fix_distortion_sigmas=0.0)
    with pytest.raises(ConfigError):
        LoopConfig(fix_centre_bias_m=-1.0)


def test_a_fix_states_its_heading_drift_in_sigmas_and_the_windows_turn():
    # localize()'s yaw variance: the registration's (1e-6) and a 0.2 degree allowance
    rot = math.radians(0.2)
    C = np.zeros((6, 6))
    C[5, 5] = 1e-6 + rot**2
    square = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    cfg = LoopConfig(fix_heading_drift_sigmas=2.0, fix_centre_bias_spread_m=0.01)
    # rms radius of the square's corners about their centroid: sqrt(8) m
    assert window_yaw_bias_variance(square, 2, cfg) == pytest.approx(0.01**2 / 8)
    assert window_yaw_bias_variance(square, 1, cfg) == pytest.approx(0.01**2 / 16)
    assert window_yaw_bias_variance(square, 0, cfg) == 0.0
    assert window_yaw_bias_variance(square[:1], 2, cfg) == math.inf  # one point: no turn known
    v = fix_stated_yaw_variance(_Res(C, 0.05, 0.2), square, 2, cfg)
    assert v == pytest.approx(1e-6 + (rot / 2) ** 2 + 0.01**2 / 8)
    # a wider window turns less; what the model adds is the stated less localize()'s
    assert fix_stated_yaw_variance(_Res(C, 0.05, 0.2), 2 * square, 2, cfg) < v
    assert v - C[5, 5] == pytest.approx(fix_model_yaw_variance(rot, square, 2, cfg))
    # no allowance where localize() added none (not finite): the registration's alone
    C[5, 5] = 1e-6
    inf = fix_stated_yaw_variance(_Res(C, math.inf, math.inf), square, 0, cfg)
    assert inf == pytest.approx(1e-6)
    # the defaults (one sigma, no spread) state localize()'s own
    assert fix_stated_yaw_variance(_Res(C, 0.05, 0.0), square, 2, LoopConfig()) == 1e-6
    with pytest.raises(ConfigError):
        LoopConfig(fix_centre_bias_spread_m=-0.01)
    with pytest.raises(ConfigError):
        LoopConfig(fix_heading_drift_sigmas=0.0)


def test_a_fix_states_the_heading_error_the_graph_grew_since_its_last_fix():
    C = np.zeros((6, 6))
    C[5, 5] = 1e-6
    square = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    cfg = LoopConfig(fix_heading_rate_sigma_rad_s=2e-4)
    v = fix_stated_yaw_variance(_Res(C, 0.05, 0.0), square, 2, cfg, 20.0)
    assert v == pytest.approx(1e-6 + (2e-4 * 20.0) ** 2)
    # longer since the last fix: wider; no fix yet (NaN): the window is the odometry's, none
    assert fix_stated_yaw_variance(_Res(C, 0.05, 0.0), square, 2, cfg, 40.0) > v
    assert fix_stated_yaw_variance(_Res(C, 0.05, 0.0), square, 2, cfg) == pytest.approx(1e-6)
    assert fix_model_yaw_variance(0.0, square, 2, cfg, 20.0) == pytest.approx((2e-4 * 20) ** 2)
    with pytest.raises(ConfigError):
        LoopConfig(fix_heading_rate_sigma_rad_s=-1e-4)


def test_nees_shares_count_the_finite_cases():
    assert nees_shares([1.0, NEES_68 + 1, NEES_997 + 1, math.nan]) == (3, 1 / 3, 2 / 3)
    assert math.isnan(nees(np.ones((1, 3)), np.zeros((1, 3, 3)))[0])  # singular: not judged
    assert nees(np.ones((1, 3)), 4 * np.eye(3)[None])[0] == pytest.approx(0.75)


def test_the_window_centre_bias_is_what_a_fix_and_the_anchor_add():
    cfg = LoopConfig(fix_centre_bias_m=0.03, fix_centre_bias_z_m=0.01)
    assert np.allclose(window_centre_bias_covariance(1, cfg), np.diag([0.03**2, 0.03**2, 1e-4]) / 2)
    assert np.allclose(window_centre_bias_covariance(0, cfg), 0.0)
    # with the distortion counted as one sigma the model adds the bias alone
    assert np.allclose(fix_model_terms(0.05, 2, cfg), window_centre_bias_covariance(2, cfg))


def test_the_window_bias_along_the_heading_widens_that_axis_only():
    cfg = LoopConfig(fix_centre_bias_along_m=0.02, fix_centre_bias_z_m=0.01)
    # heading 90 degrees: along is the map's y axis; one map built from detections: half
    B = window_centre_bias_covariance(1, cfg, math.pi / 2)
    assert np.allclose(B, np.diag([0.0, 0.02**2, 0.01**2]) / 2)
    # at 45 degrees the along variance is shared by x and y, and correlates them
    B45 = window_centre_bias_covariance(2, cfg, math.pi / 4)
    assert np.allclose(B45[:2, :2], 0.02**2 / 2 * np.ones((2, 2)))
    # no heading known: the along part is left out (the anchor's vertical part is unchanged)
    assert np.allclose(window_centre_bias_covariance(2, cfg), np.diag([0.0, 0.0, 0.01**2]))
    C = np.diag([1e-6, 1e-6, 1e-6, 0.0, 0.0, 0.0])
    S = fix_stated_covariance(_Res(C, 0.0), [0.0, 0.0, 0.0], 2, cfg, 0.0)
    assert S[0, 0] == pytest.approx(1e-6 + 0.02**2) and S[1, 1] == pytest.approx(1e-6)
    with pytest.raises(ConfigError):
        LoopConfig(fix_centre_bias_along_m=-0.01)


def test_the_odometry_scale_term_grows_with_the_carried_path_along_the_heading():
    cfg = LoopConfig(fix_odometry_scale_sigma=0.01)
    # heading along y: 2 m carried at 1 % is 2 cm along y only
    T = fix_model_terms(math.nan, 0, cfg, math.pi / 2, 2.0)
    assert np.allclose(T, np.diag([0.0, 0.02**2, 0.0]))
    # nothing carried, no path known or no heading: no term
    for c, h in ((0.0, 0.0), (math.nan, 0.0), (2.0, math.nan)):
        assert np.allclose(fix_model_terms(math.nan, 0, cfg, h, c), 0.0)
    C = np.diag([1e-6, 1e-6, 1e-6, 0.0, 0.0, 0.0])
    S = fix_stated_covariance(_Res(C, 0.0), [0.0, 0.0, 0.0], 0, cfg, 0.0, 3.0)
    assert S[0, 0] == pytest.approx(1e-6 + 0.03**2) and S[1, 1] == pytest.approx(1e-6)
    with pytest.raises(ConfigError):
        LoopConfig(fix_odometry_scale_sigma=-0.01)


def test_the_carried_path_counts_the_sightings_after_the_last_fix_per_rock():
    inliers = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    # rock 0 seen from keyframes at path 1 m (before the last fix) and 6 m (after); rock 1 from
    # 8 m (after); a detection of no inlier is left out; the rover is at 10 m
    P = np.array([[0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [5.0, 0.01, 0.0], [20.0, 0.0, 0.0]])
    path = np.array([1.0, 6.0, 8.0, 9.0])
    carried = np.array([False, True, True, True])
    # rock 0: (0 + 4) / 2 = 2 m, rock 1: 2 m
    assert window_carried_path_m(inliers, P, path, carried, 10.0, 0.3) == pytest.approx(2.0)
    # before a first fix all are carried: rock 0 (9 + 4) / 2, rock 1 2 m
    assert window_carried_path_m(inliers, P, path, np.ones(4, bool), 10.0, 0.3) == pytest.approx(
        (6.5 + 2.0) / 2
    )
    assert math.isnan(window_carried_path_m(inliers, P[3:], path[3:], carried[3:], 10.0, 0.3))


def test_yaw_nees_shares_use_the_one_dof_quantiles():
    assert NEES1_68 == 1.0 and NEES1_997 == 9.0
    assert yaw_nees_shares([0.5, 2.0, 10.0, math.nan]) == (3, 1 / 3, 2 / 3)
    assert yaw_nees_shares([])[0] == 0


def test_the_anchor_is_the_graphs_marginal_plus_the_windows_vertical_bias():
    """OnlineLocalizer restarts its covariance at an accepted fix from the pose graph's marginal
    plus the vertical part of the window centre bias (horizontal: the graph's own)."""
    from types import SimpleNamespace

    from lunarloc.online.component import OnlineConfig, OnlineLocalizer

    loc = OnlineLocalizer.__new__(OnlineLocalizer)  # the anchor needs no detector or reference
    C = np.diag([1e-4, 2e-4, 3e-4, 1e-6])
    loc.loop = SimpleNamespace(graph=SimpleNamespace(newest_covariance=C))
    loc.config = OnlineConfig()
    loc._loop_config = LoopConfig(fix_centre_bias_m=0.02, fix_centre_bias_z_m=0.02)
    loc._path_m = 3.0
    fix = SimpleNamespace(
        fix_maps_from_detections=1, fix_covariance_xyz=np.eye(3).tolist(), fix_sigma_yaw_rad=1.0
    )
    a = loc._fix_anchor(fix, np.eye(4))
    assert np.allclose(a.position_covariance, np.diag([1e-4, 2e-4, 3e-4 + 0.02**2 / 2]))
    assert a.yaw_variance == pytest.approx(1e-6) and a.path_m == 3.0
    loc.config = OnlineConfig(covariance_source="fix")
    assert np.allclose(loc._fix_anchor(fix, np.eye(4)).position_covariance, np.eye(3))


def test_a_fix_record_judges_the_heading_against_its_stated_sigma():
    from lunarloc.online.loop import Attempt
    from lunarloc.pipeline.nees_online import _fix_record

    cfg = LoopConfig(fix_centre_bias_m=0.02, fix_centre_bias_z_m=0.02)
    a = Attempt(3, 1.0, 7, 20, 12, True, True)
    a.fix_error_xyz, a.fix_covariance_xyz = [0.01, 0.0, 0.0], (np.eye(3) * 1e-3).tolist()
    a.fix_distortion_m, a.fix_maps_from_detections = 0.0, 1
    a.fix_error_yaw_rad, a.fix_sigma_yaw_rad = 0.004, 0.002
    r = _fix_record(a, cfg, site="seed_1")
    assert r["nees_yaw"] == pytest.approx(4.0) and r["site"] == "seed_1"
    # no heading model in cfg: localize()'s own yaw sigma is the stated one
    assert r["nees_yaw_localize"] == pytest.approx(4.0)
    # a window's turn: localize()'s own is the stated less it, over the inliers' radius
    a.inlier_vehicle_xyz = [[-3.0, 0.0, 0.0], [3.0, 0.0, 0.0]]
    a.fix_distortion_yaw_rad = 0.0
    cfg_yaw = LoopConfig(fix_centre_bias_spread_m=0.006)
    r2 = _fix_record(a, cfg_yaw, site="seed_1")
    assert r2["inlier_radius_m"] == pytest.approx(3.0)
    own = math.sqrt(0.002**2 - 0.006**2 / 9 / 2)
    assert r2["sigma_yaw_localize_rad"] == pytest.approx(own)
    assert r["nees"] == pytest.approx(0.1)
    # localize()'s own covariance: the stated one less the window centre bias
    assert np.allclose(r["covariance_localize_xyz"], np.eye(3) * (1e-3 - 0.02**2 / 2))
    assert r["nees_localize"] == pytest.approx(1e-4 / 8e-4)


def test_the_heading_turn_the_graph_carried_is_stated_as_an_error():
    """fix_heading_turn_factor: the turn the graph's bias carried into the prediction since its
    last solve, times the factor, added in quadrature to the heading; none where not finite."""
    square = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    cfg = LoopConfig(fix_heading_turn_factor=2.0)
    turn = math.radians(0.1)
    assert fix_model_yaw_variance(0.0, square, 2, cfg, 20.0, turn) == pytest.approx((2 * turn) ** 2)
    assert fix_model_yaw_variance(0.0, square, 2, cfg, 20.0, -turn) == pytest.approx(
        (2 * turn) ** 2
    )
    assert fix_model_yaw_variance(0.0, square, 2, cfg, 20.0, math.nan) == 0.0
    assert fix_model_yaw_variance(0.0, square, 2, LoopConfig(), 20.0, turn) == 0.0
    with pytest.raises(ConfigError):
        LoopConfig(fix_heading_turn_factor=-1.0)


def test_the_inliers_viewing_rays_and_range():
    """Two rocks, each detected from two viewpoints: the mean ray over the rocks of each rock's
    mean ray (viewpoint to detection), and the mean range; a detection of no inlier is left out."""
    rocks = np.array([[3.0, 0.0, 0.0], [0.0, 4.0, 0.0]])
    pts = np.array([[3.0, 0.0, 0.0], [3.01, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 4.0, 0.0], [9, 9, 0]])
    views = np.array(
        [[0.0, 0.0, 0.0], [1.01, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0, 0, 0]]
    )
    ray, rng = window_ray_geometry(rocks, pts, views, 0.2)
    # rock 1: rays (3, 0), (2, 0) -> (2.5, 0); rock 2: (0, 4), (0, 2) -> (0, 3)
    assert np.allclose(ray, [1.25, 1.5])
    assert rng == pytest.approx((2.5 + 3.0) / 2)
    ray0, rng0 = window_ray_geometry(rocks, pts[4:], views[4:], 0.2)
    assert np.all(np.isnan(ray0)) and math.isnan(rng0)
