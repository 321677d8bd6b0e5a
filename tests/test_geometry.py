import numpy as np
import pytest

from lunarloc.core.errors import DegenerateGeometryError, InputError
from lunarloc.core.geometry import (
    arun,
    arun_yaw,
    euler_to_rotation,
    invert_transform,
    make_transform,
    matrix_to_pose,
    pose_to_matrix,
    rot_z,
    rotation_angle,
    rotation_to_euler,
    transform_points,
)


def test_euler_round_trip(rng):
    for _ in range(50):
        rpy = rng.uniform([-3, -1.5, -3], [3, 1.5, 3])
        R = euler_to_rotation(*rpy)
        assert np.allclose(R @ R.T, np.eye(3))
        assert np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(euler_to_rotation(*rotation_to_euler(R)), R)


def test_pose_matrix_round_trip():
    pose = (1.0, -2.0, 0.5, 0.1, -0.2, 2.5)
    assert np.allclose(matrix_to_pose(pose_to_matrix(*pose)), pose)


def test_arun_recovers_transform_with_noise(rng):
    P = rng.uniform(-10, 10, (30, 3))
    T = pose_to_matrix(3, -4, 1, 0.2, -0.1, 1.3)
    Q = transform_points(T, P) + rng.normal(0, 0.001, P.shape)
    T_est = arun(P, Q)
    assert np.allclose(T_est[:3, 3], T[:3, 3], atol=5e-3)
    assert rotation_angle(T_est[:3, :3] @ T[:3, :3].T) < 1e-3


def test_arun_returns_rotation_not_reflection_for_planar_points(rng):
    P = np.c_[rng.uniform(-5, 5, (20, 2)), np.zeros(20)]
    Q = P * np.array([-1.0, 1.0, 1.0])  # a mirror image: the best orthogonal map is a reflection
    T = arun(P, Q)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)


def test_arun_rejects_collinear_and_too_few():
    line = np.c_[np.linspace(0, 5, 10), np.zeros(10), np.zeros(10)]
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        arun(line, line + 1)
    with pytest.raises(InputError, match="at least 3"):
        arun(line[:2], line[:2])


def test_arun_rejects_nan_and_mismatched(rng):
    P = rng.normal(size=(5, 3))
    bad = P.copy()
    bad[2, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        arun(bad, P)
    with pytest.raises(InputError, match="differ in size"):
        arun(P, P[:4])
    with pytest.raises(InputError, match="shape"):
        arun(P[:, :2], P[:, :2])


def test_arun_yaw_recovers_heading(rng):
    P = rng.uniform(-10, 10, (15, 3))
    T = make_transform(rot_z(2.0), [5, 6, -1])
    T_est = arun_yaw(P, transform_points(T, P))
    assert np.allclose(T_est, T, atol=1e-9)


def test_invert_transform():
    T = pose_to_matrix(1, 2, 3, 0.3, 0.2, 0.1)
    assert np.allclose(invert_transform(T) @ T, np.eye(4))
