"""Registration of associated landmarks: Arun's SVD, robust refit, refinement, landmark sigmas."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from lunarloc.core.errors import DegenerateGeometryError
from lunarloc.core.geometry import (
    arun,
    arun_yaw,
    transform_points,
)
from lunarloc.io.maps import LandmarkMap
from lunarloc.localization.config import LocalizationConfig, Mode, Registration


def rmse_limit(cfg: "LocalizationConfig", sigma_h: float, sigma_z: float, k: int) -> float:
    """Largest residual RMSE of k inliers the chi-square test accepts: the sum of squared
    3D residuals over the per-axis variance (sigma_r^2 / 3, sigma_r^2 = 2 sigma_h^2 +
    sigma_z^2) stays below its `rmse_confidence` quantile with 3k - 6 degrees of freedom,
    i.e. RMSE <= sigma_r sqrt(q / 3k). Never below cfg.acceptance.max_rmse_m (the floor)."""
    dof = max(3 * k - 6, 1)
    sr = math.sqrt(2 * sigma_h**2 + sigma_z**2)
    return max(
        cfg.acceptance.max_rmse_m,
        sr * math.sqrt(_chi2_ppf(cfg.acceptance.rmse_confidence, dof) / (3 * max(k, 1))),
    )


def _chi2_ppf(q: float, dof: int) -> float:
    """Chi-square quantile, as scipy.stats.chi2.ppf computes it (2 gammaincinv(dof/2, q)),
    without importing scipy.stats (about 0.4 s at start-up)."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(dof / 2.0, q))


def _flattened(m: LandmarkMap) -> LandmarkMap:
    """The map with every height 0 and no vertical uncertainty (2D association)."""
    P = m.positions_xyz.copy()
    P[:, 2] = 0.0
    return LandmarkMap(
        P,
        m.sizes,
        m.sightings,
        m.frame,
        m.sigma_xy_m,
        None,
        m.sighting_arc_m,
        m.sighting_arc_min_m,
        m.sighting_arc_max_m,
    )


def _yaw_only(cfg: LocalizationConfig, k: int) -> bool:
    return cfg.registration is Registration.YAW or (cfg.mode is Mode.GRAVITY and k < 4)


def _register(P: np.ndarray, Q: np.ndarray, cfg: LocalizationConfig, w=None) -> np.ndarray:
    """Arun's SVD; the yaw-only fit when asked for, or in gravity mode when too few
    points fix a tilt."""
    return arun_yaw(P, Q, w) if _yaw_only(cfg, len(P)) else arun(P, Q, w)


def _residuals(T, P, Q):
    return np.linalg.norm(transform_points(T, P) - Q, axis=1)


def _register_robust(P, Q, cfg, T=None):
    """Registration re-weighted by a Cauchy loss (IRLS, `irls_rounds` rounds): correspondences
    with residuals well above `robust_scale_m` lose influence. Returns (T, weights)."""
    if T is None:
        T = _register(P, Q, cfg)
    w = np.ones(len(P))
    for _ in range(cfg.refinement.irls_rounds):
        r = _residuals(T, P, Q)
        w = 1.0 / (1.0 + (r / cfg.refinement.robust_scale_m) ** 2)
        try:
            T = _register(P, Q, cfg, w)
        except DegenerateGeometryError:
            break
    return T, w


def _refine(T, Pv, Pr, inl, cfg):
    """Mutual nearest neighbours within refine_radius under T, re-fitted (`refine_rounds`
    rounds)."""
    tree = cKDTree(Pr)
    best_T, best_inl = T, inl
    for _ in range(cfg.refinement.rounds):
        Pt = transform_points(best_T, Pv)
        d, j = tree.query(Pt, distance_upper_bound=cfg.refinement.radius_m)
        ok = np.isfinite(d)
        vi = np.flatnonzero(ok)
        ri = j[ok]
        # mutual: each reference landmark keeps its closest vehicle landmark
        order = np.argsort(d[ok])
        _, first = np.unique(ri[order], return_index=True)
        keep = order[first]
        pairs = np.stack([vi[keep], ri[keep]], axis=1)
        if len(pairs) < len(best_inl):
            break
        try:
            T_new, _ = _register_robust(Pv[pairs[:, 0]], Pr[pairs[:, 1]], cfg)
        except DegenerateGeometryError:
            break
        same = len(pairs) == len(best_inl) and np.array_equal(
            np.sort(pairs[:, 0]), np.sort(best_inl[:, 0])
        )
        best_T, best_inl = T_new, pairs
        if same:
            break
    return best_T, best_inl


def _handedness(P: np.ndarray, Q: np.ndarray, rng: np.random.Generator) -> float:
    """Share of inlier triangles whose horizontal orientation (sign of the signed area)
    agrees between the vehicle and reference maps (1.0 = same handedness; a mirror
    image gives ~0). Triangles with tiny area are ignored."""
    k = len(P)
    if k < 3:
        return 1.0
    tri = rng.integers(0, k, size=(min(2000, 20 * k), 3))
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]

    def area(X):
        a = X[tri[:, 1], :2] - X[tri[:, 0], :2]
        b = X[tri[:, 2], :2] - X[tri[:, 0], :2]
        return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]

    av, ar = area(P), area(Q)
    big = (np.abs(av) > 0.05) & (np.abs(ar) > 0.05)
    if not np.any(big):
        return 1.0
    return float(np.mean(np.sign(av[big]) == np.sign(ar[big])))
