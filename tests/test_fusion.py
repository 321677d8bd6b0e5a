"""Pose-graph fusion: calibration, gating, landmark fixes (synthetic, no data)."""

import math

import numpy as np
import pytest

from lunarloc.errors import InputError
from lunarloc.fusion import FusionConfig, PoseGraph, wrap_angle


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
