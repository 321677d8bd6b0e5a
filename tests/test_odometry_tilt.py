"""Gravity-aided chaining of visual odometry (``lunarloc.odometry.tilt``): roll and pitch
follow gravity, heading and distance stay the visual odometry's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.core.geometry import (
    invert_transform,
    matrix_to_pose,
    pose_to_matrix,
    rotation_angle,
    yaw_of,
)
from lunarloc.odometry.tilt import GravityAlignedChain, align_tilt


def _R(roll, pitch, yaw):
    return pose_to_matrix(0, 0, 0, roll, pitch, yaw)[:3, :3]


@pytest.mark.parametrize(
    "roll,pitch,yaw", [(0.03, -0.02, 1.0), (-0.05, 0.04, -2.5), (0.0, 0.0, 0.3)]
)
def test_align_tilt_takes_gravity_up_and_keeps_heading(roll, pitch, yaw):
    R_true = _R(0.01, -0.015, yaw)
    R_drifted = _R(roll, pitch, yaw)
    R = align_tilt(R_drifted, R_true[2, :])
    np.testing.assert_allclose(R[2, :], R_true[2, :], atol=1e-12)  # the up direction is gravity's
    assert abs(yaw_of(R) - yaw) < 1e-3  # heading kept (second order in the 4 deg correction)
    assert rotation_angle(R.T @ R_true) < 1e-3
    half = align_tilt(R_drifted, R_true[2, :], gain=0.5)
    a_full, a_half = math.acos(R_drifted[2, :] @ R_true[2, :]), math.acos(half[2, :] @ R_true[2, :])
    assert a_half == pytest.approx(a_full / 2, abs=1e-9)
    np.testing.assert_allclose(align_tilt(R_drifted, R_true[2, :], gain=0.0), R_drifted, atol=1e-12)


def test_align_tilt_refuses_a_degenerate_gravity():
    with pytest.raises(InputError, match="gravity"):
        align_tilt(np.eye(3), np.zeros(3))
    with pytest.raises(InputError, match="gravity"):
        align_tilt(np.eye(3), np.array([0.0, np.nan, 1.0]))


def _drive(n=200, step_m=0.1, turn_rad=0.01):
    """True poses over rolling terrain: forward steps along the body x axis, slow turn, pitch and roll waves."""
    out = []
    p = np.zeros(3)
    for k in range(n):
        roll, pitch, yaw = 0.04 * math.sin(k / 15), 0.05 * math.sin(k / 23), turn_rad * k
        T = pose_to_matrix(*p, roll, pitch, yaw)
        out.append(T)
        p = p + T[:3, 0] * step_m
    return np.stack(out)


def test_chain_removes_visual_tilt_drift_and_the_height_drift_it_causes():
    truth = _drive()
    # visual odometry whose every step carries a small pitch and roll error: its tilt drifts
    bias = pose_to_matrix(0, 0, 0, 2e-4, 3e-4, 0)
    vo = [np.eye(4)]
    for a, b in zip(truth[:-1], truth[1:]):
        vo.append(vo[-1] @ invert_transform(a) @ b @ bias)
    vo = np.stack(vo)
    imu = truth.copy()  # the IMU's attitude: true up (only its rotation's last row is used)
    imu[:, :3, 3] = np.nan  # ... and its position is not used at all
    chain, plain = GravityAlignedChain(), GravityAlignedChain(gain=0.0)
    fused = np.stack([chain.add(T, I, truth[0]) for T, I in zip(vo, imu)])
    raw = np.stack([plain.add(T, I, truth[0]) for T, I in zip(vo, imu)])

    def up_error_deg(est):  # angle between the estimated and the true "up" in the rover frame
        return [math.degrees(math.acos(min(1.0, e[2, :3] @ t[2, :3]))) for e, t in zip(est, truth)]

    assert max(up_error_deg(fused)) < 1e-4 and max(up_error_deg(raw)) > 2.0
    dz_fused = abs(fused[-1, 2, 3] - truth[-1, 2, 3])
    dz_raw = abs(raw[-1, 2, 3] - truth[-1, 2, 3])
    assert dz_raw > 0.15 and dz_fused < 0.02  # 20 m of driving
    # heading and distance are the visual odometry's
    yaw_f = np.array([matrix_to_pose(T)[5] for T in fused])
    yaw_t = np.array([matrix_to_pose(T)[5] for T in truth])
    assert np.max(np.abs(yaw_f - yaw_t)) < math.radians(0.2)
    step_f = np.linalg.norm(np.diff(fused[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(step_f, 0.1, atol=1e-9)
    # gain 0 is the plain chain of visual motions from the start pose
    np.testing.assert_allclose(raw, np.einsum("ij,njk->nik", truth[0], vo), atol=1e-9)


def test_chain_starts_at_the_imu_pose_without_a_start_and_checks_gain():
    T0 = pose_to_matrix(1, 2, 3, 0, 0, 0.5)
    assert np.allclose(GravityAlignedChain().add(np.eye(4), T0), T0)
    with pytest.raises(ConfigError, match="gain"):
        GravityAlignedChain(gain=1.5)
