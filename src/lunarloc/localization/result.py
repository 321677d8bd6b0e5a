"""What a localization returns."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class LocalizationResult:
    """Outcome of :func:`localize`.

    T_ref_veh : 4x4 transform mapping vehicle-map points into the reference frame
        (the best hypothesis; all NaN when there is none). Trust it only if `success`.
    inliers : (k, 2) int rows ``[vehicle_index, reference_index]``.
    predicted_error_m : 1-sigma position error of the pose at the query points (default:
        every vehicle landmark), largest over them: the registration's own uncertainty and
        the distortion allowance (``distortion_error_m``) of the odometry bounds in the config.
    covariance : 6x6 covariance of the pose error ``xi = (rho, phi)`` (metres, radians), a
        left perturbation in the reference frame: ``T_true = exp(xi) T_ref_veh``, i.e. a
        reference point p is off by ``rho + phi x p``. From the inlier residuals, plus the
        distortion allowance (when there is one) taken as one sigma of horizontal position
        and yaw at the query point where the predicted error is largest
        (:func:`distortion_covariance`).
    distortion_rotation_deg : the rotation part of that allowance (1 sigma of yaw, degrees; the
        heading drift of the odometry bounds over the path between the inliers and the query,
        or the fitted bend's): ``covariance[5, 5]`` holds its square on top of the
        registration's yaw variance (none when the allowance is not finite).
    near_misses : vehicle landmarks that land just outside the inlier radius of a reference
        rock (``refinement.radius_m`` .. ``acceptance.near_miss_outer_m``), against
        ``near_misses_expected``
        by chance (local reference density): an excess means the map is not rigid.
    """

    success: bool
    T_ref_veh: np.ndarray
    inliers: np.ndarray
    residual_rmse_m: float
    reason: str
    clique_size: int = 0
    competitor_size: int = 0
    required_inliers: int = 0
    num_associations: int = 0
    num_edges: int = 0
    predicted_error_m: float = float("nan")
    scale_error: float = float("nan")
    yaw_deg: float = float("nan")
    tilt_deg: float = float("nan")
    distortion_error_m: float = float("nan")
    predicted_rotation_deg: float = float("nan")
    distortion_rotation_deg: float = float("nan")
    near_misses: int = 0
    near_misses_expected: float = float("nan")
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    timings: dict = field(default_factory=dict)
    # the acceptance tests (:class:`Check`) of :func:`verify`
    checks: list = field(default_factory=list)
    # :class:`BendFit` when no odometry bounds were stated
    distortion_fit: dict = field(default_factory=dict)
    # where the odometry bounds came from (:class:`lunarloc.localization.provenance.OdometryBounds`)
    odometry_bounds: dict = field(default_factory=dict)

    @property
    def num_inliers(self) -> int:
        return int(len(self.inliers))

    @property
    def time_s(self) -> float:
        return float(sum(self.timings.values()))

    def to_dict(self) -> dict:
        """JSON-ready dictionary (NaN becomes None)."""

        def clean(x):
            return None if isinstance(x, float) and not math.isfinite(x) else x

        T = [[clean(float(v)) for v in row] for row in self.T_ref_veh]
        return {
            "success": bool(self.success),
            "T_ref_veh": T,
            "num_inliers": self.num_inliers,
            "inliers": self.inliers.astype(int).tolist(),
            "residual_rmse_m": clean(float(self.residual_rmse_m)),
            "time_s": round(self.time_s, 6),
            "reason": self.reason,
            "clique_size": self.clique_size,
            "competitor_size": self.competitor_size,
            "required_inliers": self.required_inliers,
            "num_associations": self.num_associations,
            "num_edges": self.num_edges,
            "predicted_error_m": clean(float(self.predicted_error_m)),
            "scale_error": clean(float(self.scale_error)),
            "yaw_deg": clean(float(self.yaw_deg)),
            "tilt_deg": clean(float(self.tilt_deg)),
            "distortion_error_m": clean(float(self.distortion_error_m)),
            "predicted_rotation_deg": clean(float(self.predicted_rotation_deg)),
            "distortion_rotation_deg": clean(float(self.distortion_rotation_deg)),
            "near_misses": int(self.near_misses),
            "near_misses_expected": clean(float(self.near_misses_expected)),
            "covariance": [[clean(float(v)) for v in row] for row in self.covariance],
            "timings_s": {k: round(v, 6) for k, v in self.timings.items()},
            "checks": [c.to_dict() for c in self.checks],
            "distortion_fit": {k: clean(v) for k, v in self.distortion_fit.items()},
            "odometry_bounds": self.odometry_bounds,
        }


def _nan_T() -> np.ndarray:
    return np.full((4, 4), np.nan)
