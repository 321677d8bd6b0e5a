"""The pose's covariance and its predicted error where it is used, odometry distortion included."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from lunarloc.core.geometry import (
    transform_points,
)


def scale_check(T, P, Q, weights, sigma_floor: float = 0.005) -> tuple[float, float]:
    """Relative size of the vehicle map's inliers against their reference landmarks, and
    its standard error: ``(1/s - 1, se)`` with s the scale taking vehicle to reference. A rigid map
    gives s = 1 within noise; odometry
    scale drift inside the vehicle map shows up as s != 1 (the weighted least-squares
    scale of Umeyama 1991, eq. 42, about the weighted centroids)."""
    w = np.asarray(weights, float)
    Pt = transform_points(T, P)
    cp = (w @ Pt) / w.sum()
    cq = (w @ Q) / w.sum()
    X = Pt - cp
    Y = Q - cq
    sxx = float(w @ np.sum(X * X, axis=1))
    if sxx <= 0:
        return 0.0, float("inf")
    scale = float(w @ np.sum(X * Y, axis=1)) / sxx
    r2 = np.sum((scale * X - Y) ** 2, axis=1)
    sigma2 = max(float(w @ r2) / max(3 * w.sum() - 7, 1.0), sigma_floor**2)
    if scale <= 0:
        return float("inf"), 0.0
    return 1.0 / scale - 1.0, float(np.sqrt(sigma2 / sxx)) / scale**2


def _skew(v) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def pose_covariance(T, P, Q, weights, sigma_floor: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (6x6) of the registration error ``(dt, dtheta)`` about the weighted inlier
    centroid ``c`` (reference frame), and ``c``.

    Linearised weighted least squares: residual r_i = dt + dtheta x (p_i - c) + noise, the
    noise scale estimated from the weighted residuals (floored at `sigma_floor`); the
    covariance is sigma^2 (sum_i w_i J_i^T J_i)^-1 with J_i = [I, -[p_i - c]x]. Infinite
    when the inliers do not fix the pose."""
    Pt = transform_points(T, P)
    r2 = np.sum((Pt - Q) ** 2, axis=1)
    w = np.asarray(weights, float)
    dof = max(3 * w.sum() - 6, 1.0)
    sigma2 = max(float(w @ r2) / dof, sigma_floor**2)
    c = (w @ Pt) / w.sum()
    H = np.zeros((6, 6))
    for wi, x in zip(w, Pt - c):
        J = np.hstack([np.eye(3), -_skew(x)])
        H += wi * J.T @ J
    try:
        return sigma2 * np.linalg.inv(H), c
    except np.linalg.LinAlgError:
        return np.full((6, 6), np.inf), c


def covariance_at_origin(C_c: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Re-express a pose-error covariance about point c as one about the frame origin:
    an error dt + dtheta x (p - c) is (dt - dtheta x c) + dtheta x p."""
    A = np.eye(6)
    A[:3, 3:] = _skew(c)
    return A @ C_c @ A.T


def distortion_covariance(
    point_ref: np.ndarray, position_m: float, rotation_rad: float
) -> np.ndarray:
    """6x6 pose-error covariance about the reference origin of a distortion allowance at a
    reference-frame point: `position_m` as one sigma of horizontal position there (split
    over x and y) and `rotation_rad` as one sigma of yaw. Zero when there is no allowance,
    and when it is not finite (the pose is refused then)."""
    C = np.zeros((6, 6))
    if not (position_m > 0 or rotation_rad > 0) or not (
        math.isfinite(position_m) and math.isfinite(rotation_rad)
    ):
        return C
    C[0, 0] = C[1, 1] = position_m**2 / 2
    C[5, 5] = rotation_rad**2
    return covariance_at_origin(C, np.asarray(point_ref, float))


def shared_bias_covariance(
    bias_m: float,
    bias_yaw_deg: float,
    spread_m: float = 0.0,
    inliers_xyz: np.ndarray | None = None,
    weights=None,
) -> np.ndarray:
    """6x6 covariance, about the inliers' centroid, of the registration error their residuals
    cannot show (:data:`~lunarloc.localization.config.CENTRE_BIAS_M`): `bias_m` per horizontal
    axis; in yaw, `bias_yaw_deg` and `spread_m` over the inliers' weighted rms horizontal radius
    about their centroid (a bias that differs by `spread_m` across the set turns the fit by about
    that over its radius; it does not average down with their number). Infinite yaw when the
    inliers coincide horizontally."""
    yaw_var = math.radians(bias_yaw_deg) ** 2
    if spread_m > 0 and inliers_xyz is not None:
        P = np.asarray(inliers_xyz, float)[:, :2]
        w = np.ones(len(P)) if weights is None else np.asarray(weights, float)
        X = P - (w @ P) / w.sum()
        r2 = float(w @ np.sum(X * X, axis=1)) / w.sum()
        yaw_var += spread_m**2 / r2 if r2 > 0 else math.inf
    return np.diag([bias_m**2, bias_m**2, 0.0, 0.0, 0.0, yaw_var])


def predicted_error(
    T, P, Q, weights, query_xyz, sigma_floor: float = 0.005, shared_bias: np.ndarray | None = None
) -> np.ndarray:
    """1-sigma position error (m) of the registration T at each vehicle-frame query point:
    the error at q has covariance A C A^T with A = [I, -[q - c]x] (see :func:`pose_covariance`),
    C the residuals' covariance plus `shared_bias` (:func:`shared_bias_covariance`) when given."""
    C, c = pose_covariance(T, P, Q, weights, sigma_floor)
    if shared_bias is not None:
        C = C + shared_bias
    return error_at(C, c, T, query_xyz)


def error_at(C_c: np.ndarray, c: np.ndarray, T: np.ndarray, query_xyz) -> np.ndarray:
    """1-sigma position error (m) at each vehicle-frame query point of a pose error with
    covariance `C_c` about the reference-frame point `c` (trace of A C A^T, A = [I, -[q - c]x])."""
    C = C_c
    if not np.all(np.isfinite(C)):
        return np.full(len(np.asarray(query_xyz).reshape(-1, 3)), np.inf)
    Y = transform_points(T, np.asarray(query_xyz, float).reshape(-1, 3)) - c
    out = np.empty(len(Y))
    for k, y in enumerate(Y):
        A = np.hstack([np.eye(3), -_skew(y)])
        out[k] = math.sqrt(max(np.trace(A @ C @ A.T), 0.0))
    return out


def _arc_length_at(path_xyz: np.ndarray, *points_xyz: np.ndarray) -> list[np.ndarray]:
    """Distance travelled along `path_xyz` (F, 3) to its point nearest (horizontally) to
    each point of each set in `points_xyz`: when the odometry was there. One tree of the
    path for all the sets (a path at the frame rate holds thousands of poses)."""
    path = np.asarray(path_xyz, float)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
    # built for a few queries: the quick build
    tree = cKDTree(path[:, :2], balanced_tree=False, compact_nodes=False)
    return [s[tree.query(np.asarray(p, float)[:, :2])[1]] for p in points_xyz]


def distortion_allowance(
    query_xyz,
    inliers_xyz,
    weights,
    scale_error: float,
    heading_drift_rad_per_m: float,
    path_xyz: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (rad) error a non-rigid vehicle map can add at each query
    point beyond what the rigid fit sees, from bounds on its odometry's distortion.

    The fit is right where the inliers are (their weighted centroid, vehicle frame). A
    relative scale error moves a point at horizontal lever L from there by scale_error * L.
    A heading drift turns the map by drift * D between where the inliers were seen and
    the query point, D the distance travelled between them, and so moves the query point
    by about drift * D * L. With the vehicle's path (vehicle frame) D is measured along it
    (from the query to the farthest inlier, each placed at the path point nearest to it);
    without it D = L (the path was at least that long: an underestimate for winding paths)."""
    q = np.asarray(query_xyz, float).reshape(-1, 3)
    w = np.asarray(weights, float)
    centre = (w @ inliers_xyz) / w.sum()
    L = np.linalg.norm(q[:, :2] - centre[:2], axis=1)
    if path_xyz is not None and len(path_xyz) >= 2:
        # the fit's heading is a weighted mean of the inliers' local headings: it differs
        # from the query's by at most the drift over the longest stretch between them
        s_inl, s_q = _arc_length_at(path_xyz, inliers_xyz, q)
        D = np.maximum(np.abs(s_q - s_inl.min()), np.abs(s_q - s_inl.max()))
    else:
        D = L
    rot = heading_drift_rad_per_m * D
    return scale_error * L + rot * L, rot
