"""SE(3) helpers, Arun's method and pose-error metrics (numpy only).

Conventions
-----------
* `T_a_b` is a 4x4 homogeneous transform that maps points expressed in frame `b`
  into frame `a`: ``p_a = T_a_b @ p_b``.
* Euler angles follow the Lunar Autonomy Challenge / CARLA convention in a
  right-handed frame (x forward, y left, z up): ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
* Angles are radians unless a name ends in ``_deg``; distances are metres.
"""

from __future__ import annotations

import math

import numpy as np

from lunarloc.core.errors import DegenerateGeometryError, InputError

__all__ = [
    "as_points",
    "rot_x",
    "rot_y",
    "rot_z",
    "euler_to_rotation",
    "rotation_to_euler",
    "make_transform",
    "pose_to_matrix",
    "matrix_to_pose",
    "invert_transform",
    "transform_points",
    "rotation_angle",
    "tilt_angle",
    "yaw_of",
    "arun",
    "arun_yaw",
    "collinearity",
]


def as_points(points, name: str = "points", *, min_count: int = 0) -> np.ndarray:
    """Validate and return an (N, 3) float64 array of finite points.

    Raises InputError naming `name` when the shape is wrong, values are not finite,
    or fewer than `min_count` points are given.
    """
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.size == 0:
        arr = arr.reshape(0, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(arr), axis=1))[0])
        raise InputError(f"{name} contains NaN or infinite values (first at row {bad})")
    if arr.shape[0] < min_count:
        raise InputError(f"{name} needs at least {min_count} points, got {arr.shape[0]}")
    return arr


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_to_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (radians)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def rotation_to_euler(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`euler_to_rotation`: returns (roll, pitch, yaw) in radians."""
    R = np.asarray(R, dtype=float)
    pitch = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(R[2, 1], R[2, 2]))
    yaw = float(np.arctan2(R[1, 0], R[0, 0]))
    return roll, pitch, yaw


def make_transform(R: np.ndarray, t) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def pose_to_matrix(
    x: float, y: float, z: float, roll: float, pitch: float, yaw: float
) -> np.ndarray:
    """4x4 transform of a pose given as position and LAC Euler angles (radians)."""
    return make_transform(euler_to_rotation(roll, pitch, yaw), (x, y, z))


def matrix_to_pose(T: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """(x, y, z, roll, pitch, yaw) of a 4x4 transform."""
    T = np.asarray(T, dtype=float)
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3]), *rotation_to_euler(T[:3, :3]))


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    T = np.asarray(T, dtype=float)
    R = T[:3, :3]
    return make_transform(R.T, -R.T @ T[:3, 3])


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    T = np.asarray(T, dtype=float)
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    return P @ T[:3, :3].T + T[:3, 3]


def rotation_angle(R: np.ndarray) -> float:
    """Geodesic angle (radians) of a rotation matrix."""
    c = (np.trace(np.asarray(R)[:3, :3]) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def tilt_angle(R: np.ndarray) -> float:
    """Angle (radians) between the rotated z axis and z: how far R is from a pure yaw."""
    return float(np.arccos(np.clip(np.asarray(R)[2, 2], -1.0, 1.0)))


def yaw_of(R: np.ndarray) -> float:
    """Heading (radians) of the rotated x axis projected on the horizontal plane."""
    R = np.asarray(R)
    return float(np.arctan2(R[1, 0], R[0, 0]))


def collinearity(points: np.ndarray) -> float:
    """Ratio of the second to the first principal standard deviation (0 = collinear).

    Used to reject point sets that cannot fix a rotation. Returns 0 for < 2 points.
    """
    P = np.asarray(points, dtype=float)
    if P.shape[0] < 2:
        return 0.0
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    return float(s[1] / s[0]) if s[0] > 0 else 0.0


def _check_pairs(src, dst, min_count: int):
    src = as_points(src, "source points", min_count=min_count)
    dst = as_points(dst, "target points", min_count=min_count)
    if src.shape != dst.shape:
        raise InputError(f"point sets differ in size: {src.shape[0]} vs {dst.shape[0]}")
    return src, dst


def _pair_weights(weights, n: int) -> np.ndarray:
    """Weights normalised to sum 1 (uniform when None); InputError unless finite,
    non-negative, one per pair and not all zero."""
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    if w.shape[0] != n or np.any(w < 0) or not np.all(np.isfinite(w)) or w.sum() <= 0:
        raise InputError("weights must be finite, non-negative, one per pair, and not all zero")
    return w / w.sum()


def arun(src, dst, weights=None, *, min_spread: float = 1e-3) -> np.ndarray:
    """Least-squares rigid transform ``T`` with ``dst ~ R @ src + t`` (Arun et al. 1987).

    Minimises ``sum_i w_i ||dst_i - (R src_i + t)||^2`` by SVD of the cross-covariance,
    with the reflection fix (det(R) = +1; Umeyama 1991, eq. 39).

    Raises DegenerateGeometryError for fewer than 3 pairs or (near-)collinear sources,
    whose rotation about their common line is undetermined.
    """
    src, dst = _check_pairs(src, dst, 3)
    w = _pair_weights(weights, len(src))
    mu_s = w @ src
    mu_d = w @ dst
    A = src - mu_s
    B = dst - mu_d
    sv = np.linalg.svd(A * np.sqrt(w)[:, None], compute_uv=False)
    if sv[0] < min_spread or sv[1] < min_spread * max(1.0, 1e-3 * sv[0] / min_spread):
        raise DegenerateGeometryError(
            f"{len(src)} source points are coincident or collinear (spread {sv[0]:.3g} m, "
            f"width {sv[1]:.3g} m): the rotation is undetermined"
        )
    H = (A * w[:, None]).T @ B  # 3x3 cross-covariance (Arun eq. 11)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    t = mu_d - R @ mu_s
    return make_transform(R, t)


def arun_yaw(src, dst, weights=None, *, min_spread: float = 1e-3) -> np.ndarray:
    """4-DoF variant of :func:`arun`: rotation about z only, plus 3D translation.

    For gravity-aligned maps (IMU-levelled): the closed-form yaw maximising the
    weighted horizontal cross-covariance, then the translation from the centroids.
    Raises DegenerateGeometryError when fewer than 2 pairs or all sources coincide
    in the horizontal plane.
    """
    src, dst = _check_pairs(src, dst, 2)
    w = _pair_weights(weights, len(src))
    mu_s = w @ src
    mu_d = w @ dst
    A = src[:, :2] - mu_s[:2]
    B = dst[:, :2] - mu_d[:2]
    if np.sqrt(w @ (A**2).sum(axis=1)) < min_spread:
        raise DegenerateGeometryError(
            "source points coincide horizontally: the yaw is undetermined"
        )
    sxx = w @ (A[:, 0] * B[:, 0] + A[:, 1] * B[:, 1])
    sxy = w @ (A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0])
    R = rot_z(float(np.arctan2(sxy, sxx)))
    return make_transform(R, mu_d - R @ mu_s)


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector `w` (Rodrigues)."""
    th = math.sqrt(float(w @ w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-9:
        return np.eye(3) + K
    return np.eye(3) + (math.sin(th) / th) * K + ((1.0 - math.cos(th)) / th**2) * (K @ K)
