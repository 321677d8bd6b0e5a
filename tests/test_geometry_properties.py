"""Properties of the geometry core that must hold for every input, checked over many seeded
random cases: Arun's method and its yaw variant return proper rigid transforms (det +1), map
the weighted source centroid onto the weighted target centroid, recover an exact transform,
and the SE(3) helpers invert and round-trip."""

import numpy as np
import pytest

from lunarloc.core.geometry import (
    arun,
    arun_yaw,
    euler_to_rotation,
    exp_so3,
    invert_transform,
    make_transform,
    matrix_to_pose,
    pose_to_matrix,
    rot_z,
    rotation_to_euler,
    transform_points,
)

CASES = range(200)


def _random_transform(rng, yaw_only=False):
    R = (
        rot_z(rng.uniform(-np.pi, np.pi))
        if yaw_only
        else exp_so3(rng.normal(size=3) * rng.uniform(0, 3))
    )
    return make_transform(R, rng.normal(0, 50, 3))


def _is_rigid(T):
    R = T[:3, :3]
    return (
        np.allclose(R.T @ R, np.eye(3), atol=1e-9)
        and np.isclose(np.linalg.det(R), 1.0, atol=1e-9)
        and np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    )


@pytest.mark.parametrize("solver", [arun, arun_yaw])
def test_arun_is_rigid_and_maps_the_weighted_centroids_for_any_points(solver):
    rng = np.random.default_rng(1)
    for _ in CASES:
        n = int(rng.integers(3, 40))
        src, dst = rng.normal(0, 5, (n, 3)), rng.normal(0, 5, (n, 3))  # unrelated sets: any fit
        w = rng.uniform(0.0, 1.0, n)
        T = solver(src, dst, w)
        assert _is_rigid(T)
        if solver is arun_yaw:
            assert np.allclose(T[:3, 2], [0, 0, 1]) and np.allclose(T[2, :3], [0, 0, 1])
        c_src, c_dst = w @ src / w.sum(), w @ dst / w.sum()
        assert np.allclose(transform_points(T, c_src[None])[0], c_dst, atol=1e-9)


@pytest.mark.parametrize("solver,yaw_only", [(arun, False), (arun_yaw, True)])
def test_arun_recovers_an_exact_transform(solver, yaw_only):
    rng = np.random.default_rng(2)
    for _ in CASES:
        T = _random_transform(rng, yaw_only)
        src = rng.normal(0, 10, (int(rng.integers(3, 30)), 3))
        est = solver(src, transform_points(T, src), rng.uniform(0.1, 1.0, len(src)))
        assert np.allclose(est, T, atol=1e-8)


def test_arun_never_returns_a_reflection_even_for_mirrored_points():
    rng = np.random.default_rng(3)
    for _ in CASES:
        src = rng.normal(0, 5, (int(rng.integers(4, 30)), 3))
        T = arun(src, src * np.array([1.0, 1.0, -1.0]))  # the best fit would be a reflection
        assert _is_rigid(T)


def test_transforms_invert_and_poses_round_trip():
    rng = np.random.default_rng(4)
    for _ in CASES:
        T = _random_transform(rng)
        assert np.allclose(invert_transform(T) @ T, np.eye(4), atol=1e-9)
        assert np.allclose(invert_transform(invert_transform(T)), T, atol=1e-9)
        assert np.allclose(pose_to_matrix(*matrix_to_pose(T)), T, atol=1e-9)
        pts = rng.normal(0, 20, (10, 3))
        assert np.allclose(
            transform_points(invert_transform(T), transform_points(T, pts)), pts, atol=1e-8
        )
        roll, pitch, yaw = (
            rng.uniform(-np.pi, np.pi),
            rng.uniform(-1.5, 1.5),
            rng.uniform(-np.pi, np.pi),
        )
        assert np.allclose(
            rotation_to_euler(euler_to_rotation(roll, pitch, yaw)), (roll, pitch, yaw), atol=1e-9
        )
