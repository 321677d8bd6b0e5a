"""Pose-graph fusion: calibration, gating, landmark fixes (synthetic, no data)."""

import math

import numpy as np
import pytest

from lunarloc.core.errors import InputError
from lunarloc.fusion.factors import wrap_angle
from lunarloc.fusion.posegraph import FusionConfig, PoseGraph


def _square_drive(K=150, scale=1.03, bias=5e-4):
    yaw = np.cumsum(np.where(np.arange(K) % 40 == 0, 1.3, 0.0))
    p = np.zeros((K, 3))
    for i in range(1, K):
        p[i] = p[i - 1] + 0.3 * np.array([math.cos(yaw[i - 1]), math.sin(yaw[i - 1]), 0.0])
    oy = yaw + bias * np.arange(K)
    o = np.zeros((K, 3))
    for i in range(1, K):
        o[i] = o[i - 1] + scale * 0.3 * np.array([math.cos(oy[i - 1]), math.sin(oy[i - 1]), 0.0])
    return p, yaw, o, oy


def test_pose_fixes_remove_drift_and_calibrate_scale():
    rng = np.random.default_rng(0)
    p, yaw, o, oy = _square_drive()
    g = PoseGraph()
    for i in range(len(p)):
        g.add_keyframe(float(i), np.r_[o[i], oy[i]])
        if i % 8 == 7:
            fx = np.r_[p[i] + rng.normal(0, 0.01, 3), yaw[i] + rng.normal(0, 0.002)]
            assert g.gate(i, fx, 0.02, 0.003).accepted
            g.add_fix(i, fx, 0.02, 0.003)
            g.solve()
    est = g.poses()
    odo_err = np.linalg.norm(o - p, axis=1).max()
    rmse = math.sqrt(np.mean(np.sum((est[:, :3] - p) ** 2, axis=1)))
    assert odo_err > 0.5
    assert rmse < 0.03
    assert g.scale == pytest.approx(1 / 1.03, abs=0.005)


def test_gate_rejects_a_fix_far_from_the_prediction():
    p, yaw, o, oy = _square_drive(K=20, scale=1.0, bias=0.0)
    g = PoseGraph()
    for i in range(20):
        g.add_keyframe(float(i), np.r_[o[i], oy[i]])
    ok = g.gate(19, np.r_[p[19], yaw[19]], 0.02, 0.003)
    bad = g.gate(19, np.r_[p[19] + [2.0, 0, 0], yaw[19]], 0.02, 0.003)
    assert ok.accepted and not bad.accepted
    assert bad.d2 > bad.threshold


def test_landmark_observations_pull_the_trajectory():
    rng = np.random.default_rng(1)
    p, yaw, o, oy = _square_drive(K=120)
    rocks = rng.uniform(-3, 12, size=(200, 2))
    rocks = np.column_stack([rocks, np.zeros(len(rocks))])
    g = PoseGraph()
    keys, kfs, pr, rp, tg = [], [], [], [], []
    for i in range(len(p)):
        g.add_keyframe(float(i), np.r_[o[i], oy[i]])
        near = np.flatnonzero(np.linalg.norm(rocks[:, :2] - p[i, :2], axis=1) < 3)
        c, s = math.cos(yaw[i]), math.sin(yaw[i])
        for j in near:
            d = rocks[j] - p[i]
            pr.append([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
            keys.append((i, int(j)))
            kfs.append(i)
            rp.append([0.0, 0.0])
            tg.append(rocks[j])
        if i % 10 == 9:
            g.add_landmark_observations(keys, kfs, pr, rp, tg, 0.03)
            keys, kfs, pr, rp, tg = [], [], [], [], []
            g.solve(active_window_m=10.0)
    g.solve()
    err = np.linalg.norm(g.poses()[:, :3] - p, axis=1)
    assert err.max() < 0.05
    assert np.abs(wrap_angle(g.poses()[:, 3] - yaw)).max() < 0.01


def test_bad_inputs():
    g = PoseGraph(FusionConfig())
    with pytest.raises(InputError):
        g.add_keyframe(0.0, [np.nan, 0, 0, 0])
    g.add_keyframe(0.0, [0, 0, 0, 0])
    with pytest.raises(InputError):
        g.add_keyframe(-1.0, [0, 0, 0, 0])
    with pytest.raises(InputError):
        g.add_fix(5, [0, 0, 0, 0], 0.1, 0.1)
    assert g.solve() == 0.0  # nothing to fuse yet


# ------------------------------------------------------------------ factor graph
from lunarloc.fusion.posegraph import Keyframe  # noqa: E402
from lunarloc.fusion.factors import (  # noqa: E402
    LandmarkFactor,
    OdometryFactor,
    PoseFixFactor,
    StateLayout,
    jacobian_sparsity,
    stacked_residual,
)


def _level_detections(rocks, p, yaw, rp):
    """Rocks seen from (p, yaw) with roll/pitch `rp`: rover-frame coordinates."""
    r, pi = rp
    cr, sr, cp, sp = math.cos(r), math.sin(r), math.cos(pi), math.sin(pi)
    c, s = math.cos(yaw), math.sin(yaw)
    R = (
        np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    )
    return (rocks - p) @ R  # rows: R.T @ (rock - p)


def _graph_with_everything(
    K=60, scale=1.03, bias=5e-4, config=None, seed=3, obs_noise=0.0, fix_noise=0.0, odo_noise=0.0
):
    """Drifting odometry (scale and heading bias), tilted rover, landmarks every keyframe
    and a pose fix every 15th: returns (graph, true positions, true yaw)."""
    rng = np.random.default_rng(seed)
    p, yaw, o, oy = _square_drive(K, scale, bias)
    p[:, 2] = 0.3 * np.sin(p[:, 0] / 2)
    o[:, 2] = scale * p[:, 2]
    o += rng.normal(0, odo_noise, o.shape)
    rocks = np.column_stack([rng.uniform(-3, 12, size=(150, 2)), rng.normal(0, 0.1, 150)])
    g = PoseGraph(config)
    for i in range(K):
        rp = (0.05 * math.sin(i / 4), 0.04 * math.cos(i / 3))
        near = rocks[np.linalg.norm(rocks[:, :2] - p[i, :2], axis=1) < 2.5][:8]
        det = _level_detections(near, p[i], yaw[i], rp) + rng.normal(0, obs_noise, (len(near), 3))
        g.add_keyframe(
            float(i),
            np.r_[o[i], oy[i]],
            frame=10 * i,
            roll_pitch_rad=rp,
            detections_rover=det,
            path_m=0.31 * i,
        )
        g.add_landmark_observations(
            [(i, j) for j in range(len(near))], [i] * len(near), det, [rp] * len(near), near, 0.03
        )
        if i % 15 == 14:
            g.add_fix(i, np.r_[p[i] + rng.normal(0, fix_noise, 3), yaw[i]], 0.02, 0.003)
    return g, p, yaw


def test_landmarks_and_fixes_recover_a_known_drift_scale_and_bias():
    g, p, yaw = _graph_with_everything(K=90, obs_noise=0.005, fix_noise=0.005)
    odo = np.array([kf.odo_pose4 for kf in g.keyframes])
    assert np.linalg.norm(odo[:, :3] - p, axis=1).max() > 0.5  # the drift is real
    g.solve()
    est = g.poses()
    assert np.linalg.norm(est[:, :3] - p, axis=1).max() < 0.02
    assert np.abs(wrap_angle(est[:, 3] - yaw)).max() < 0.005
    assert g.scale == pytest.approx(1 / 1.03, abs=0.003)
    assert np.median(g.biases) == pytest.approx(5e-4, abs=1e-4)  # rad per second of motion


def test_exact_measurements_have_zero_residual_at_the_truth():
    g, p, yaw = _graph_with_everything(K=45, scale=1.0, bias=0.0)
    truth = np.r_[np.column_stack([p, yaw]).ravel(), np.zeros(len(g)), 1.0]
    r = stacked_residual(g.factors(), truth)
    assert np.abs(r).max() < 1e-9
    r_odo = stacked_residual(g.factors(), g.state())  # the odometry start is not the truth
    assert np.abs(r_odo).max() < 1e-9  # ... here it is: exact odometry
    g.solve()
    assert np.abs(g.poses()[:, :3] - p).max() < 1e-6


def test_derived_sparsity_covers_the_numerical_jacobian():
    g, _, _ = _graph_with_everything(
        K=30, odo_noise=0.01
    )  # noise: no step exactly along the heading
    rng = np.random.default_rng(0)
    K = len(g)
    first = 5
    layout = StateLayout(K)
    factors = g.factors(first)
    kinds = {type(f).__name__ for f in factors}
    assert kinds == {
        "OdometryFactor",
        "PoseFixFactor",
        "LandmarkFactor",
        "BiasWalkFactor",
        "PriorFactor",
    }
    active = layout.active(first, True)
    S = jacobian_sparsity(factors, active, layout.size).toarray()
    z = g.state() + rng.normal(0, 0.05, layout.size)
    r0 = stacked_residual(factors, z)
    assert S.shape == (len(r0), len(active))
    J = np.zeros_like(S)
    for j, c in enumerate(active):
        zz = z.copy()
        zz[c] += 1e-6
        J[:, j] = (stacked_residual(factors, zz) - r0) / 1e-6
    assert np.all(S[J != 0] == 1)  # every true dependency is in the pattern (none can be missed)
    assert np.array_equal(S == 1, J != 0)  # ... and `reads` adds none that is not there


def test_window_solve_holds_older_keyframes_fixed():
    g, p, _ = _graph_with_everything(K=60)
    before = g.poses()
    first = g.first_active(4.0)
    assert 0 < first < len(g) - 1
    g.solve(active_window_m=4.0)
    after = g.poses()
    assert np.array_equal(after[:first, :3], before[:first, :3])
    assert np.abs(wrap_angle(after[:first, 3] - before[:first, 3])).max() < 1e-12  # re-wrapped only
    assert np.abs(after[first:] - before[first:]).max() > 1e-3
    assert g.distance(len(g) - 1) - g.distance(first) <= 4.0


def test_keyframe_record_carries_the_loop_data_and_the_correction():
    g, p, yaw = _graph_with_everything(K=40)
    g.solve()
    kf = g.keyframes[17]
    assert isinstance(kf, Keyframe) and kf.index == 17 and kf.frame == 170 and kf.t_s == 17.0
    from lunarloc.core.geometry import matrix_to_pose

    assert matrix_to_pose(kf.T_odo_rover)[3:5] == pytest.approx(kf.roll_pitch_rad, abs=1e-12)
    assert kf.T_odo_rover[:3, 3] == pytest.approx(kf.odo_pose4[:3])
    assert kf.detections_rover.shape[1] == 3
    assert kf.path_m == pytest.approx(0.31 * 17)
    T = kf.T_map_odo
    assert (T @ np.r_[kf.odo_pose4[:3], 1.0])[:3] == pytest.approx(kf.estimate_pose4[:3], abs=1e-12)
    assert np.allclose(g.correction_transforms()[17], T)
    assert g.pose(17) == pytest.approx(kf.estimate_pose4)


def test_without_calibration_scale_and_bias_stay_put():
    g, p, _ = _graph_with_everything(K=40, config=FusionConfig(calibrate=False))
    assert {type(f).__name__ for f in g.factors()} == {
        "OdometryFactor",
        "PoseFixFactor",
        "LandmarkFactor",
    }
    g.solve()
    assert g.scale == 1.0 and np.all(g.biases == 0.0)
    assert np.linalg.norm(g.poses()[:, :3] - p, axis=1).max() < 0.05


def test_factor_kinds_give_their_residual_dimensions():
    L = StateLayout(3)
    odo = np.array([[0, 0, 0, 0], [1, 0, 0, 0.1], [2, 0.1, 0, 0.2]], float)
    f = OdometryFactor(L, [0, 1], odo, [1.0, 1.0], FusionConfig().noise)
    assert f.columns.shape == (2, 10) and f.dim == 4
    assert PoseFixFactor(L, [2], odo[2], 0.1, 0.01).columns.tolist() == [[8, 9, 10, 11]]
    lm = LandmarkFactor(
        L, [1, 2], np.ones((2, 3)), np.zeros((2, 2)), np.zeros((2, 3)), [0.05, 0.05]
    )
    assert lm.residual(np.zeros((2, 4))).shape == (2, 3)
