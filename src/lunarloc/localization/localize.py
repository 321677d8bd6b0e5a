"""One-shot global localization of a vehicle landmark map in a reference map.

``localize(reference, vehicle, config) -> LocalizationResult``:

1. putative associations (all-to-all, optionally pruned by size);
2. sparse consistency graph(s) (:mod:`lunarloc.association.graph`);
3. densest consistent set: exact maximum clique (default) or CLIPPER relaxation;
4. registration: Arun's SVD on the inliers, then optional refinement with the
   mutual nearest neighbours under the estimate;
5. verification: inliers vs. what chance produces at this map size, residual RMSE,
   spread of the inliers, fitted tilt and handedness (gravity mode), and the margin
   over the best competing hypothesis. ``success`` is False, with a reason, when the
   answer cannot be trusted.
"""

from __future__ import annotations

import enum
import functools
import logging
import math
import os
import threading
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from lunarloc.association.clique import bin_clique_bounds, max_clique, peel
from lunarloc.association.clipper import clipper_clique
from lunarloc.association.graph import (
    RefPairIndex, graph_3d, sweep_bin_chunks, sweep_yaw_bins, vehicle_pairs, yaw_bin_chunks,
)
from lunarloc.association.putative import putative_associations
from lunarloc.core.configs import check_settings, setting
from lunarloc.core.errors import ConfigError, DegenerateGeometryError, InputError
from lunarloc.core.geometry import (
    arun, arun_yaw, as_points, exp_so3, make_transform, tilt_angle, transform_points, yaw_of,
)
from lunarloc.io.maps import LandmarkMap, path_arc_length_m

log = logging.getLogger(__name__)

__all__ = ["Mode", "Registration", "Solver", "LocalizationConfig", "LocalizationResult", "Check", "Evidence", "verify",
           "localize", "chance_clique_size"]


class Mode(str, enum.Enum):
    """Which invariants the consistency graph uses."""

    GRAVITY = "gravity"  # horizontal distance + height difference + common yaw (rover maps, IMU-levelled)
    SIX_DOF = "6dof"  # 3D distance only: any relative rotation


class Registration(str, enum.Enum):
    """Which rigid transform is fitted to the inliers."""

    SE3 = "se3"  # Arun's SVD, full rotation (allows the residual tilt of an IMU-levelled map)
    YAW = "yaw"  # 4-DoF: rotation about the vertical only (maps levelled exactly)


class Solver(str, enum.Enum):
    """How the densest consistent set is found."""

    EXACT = "exact"  # exact maximum clique (robust; default)
    CLIPPER = "clipper"  # CLIPPER relaxation + rounding (the paper's solver)


def chance_clique_size(num_associations: int, mode: "Mode" = Mode.GRAVITY, epsilon_m: float = 0.05,
                       epsilon_z_m: float = 0.05) -> float:
    """Upper envelope of the largest consistent set found between UNRELATED maps with
    `num_associations` putative associations (measured; see docs/results.md, "The acceptance rule").

    Envelope ``a + b * log10(m)`` over the largest chance cliques of 184 unrelated map
    pairs at the default settings: 124 real traverse pairs with every shared rock
    removed and 60 synthetic uniform rock fields of 20-450 landmarks
    (``python benchmarks/chance_cliques.py``; largest seen: 6 real, 9 synthetic; with
    the full acceptance rule, 0 of these and of 136 mirrored real pairs were accepted).
    6-DoF mode: envelope over 40 synthetic pairs of 20-160 landmarks
    (``--mode 6dof --skip-real --synthetic 40 --synthetic-max 160``; largest seen 6).
    Wider search tolerances make chance sets larger: the envelope is scaled by
    ``rho ** gamma``, rho = sqrt(eps_h eps_z) / 5 cm (>= 1), gamma measured with
    ``--epsilon 0.08 / 0.15`` (see _TOLERANCE_EXPONENT).
    """
    a, b = _CHANCE_MODEL[Mode(mode)]
    rho = max(1.0, math.sqrt(max(epsilon_m, 1e-9) * max(epsilon_z_m if Mode(mode) is Mode.GRAVITY else epsilon_m, 1e-9))
              / _CHANCE_EPSILON_M)
    return (a + b * math.log10(max(num_associations, 1))) * rho**_TOLERANCE_EXPONENT


# (intercept, slope per decade of associations); measured by benchmarks/chance_cliques.py
_CHANCE_MODEL = {Mode.GRAVITY: (-0.30, 1.83), Mode.SIX_DOF: (-3.69, 2.35)}
_CHANCE_EPSILON_M = 0.05  # the search tolerance (horizontal and vertical) the envelope was measured at
_TOLERANCE_EXPONENT = 0.65  # measured: largest ratio of chance sets 2.0 at 3x the tolerance, 1.33 at 1.6x (gamma 0.63, 0.61)


#: The prior on the vehicle map's odometry distortion when no bounds are stated: 1-sigma heading
#: drift per metre travelled and relative scale error of real rover odometry. Source: lunarloc's
#: own stereo VO with the IMU prior (the dispatcher's ``visual`` source) on nine simulated
#: traverses of 30-102 m (docs/odometry-visual.md, both tables): final heading error per metre
#: 0.0006-0.025 deg/m, RMS 0.012; final position error 0.12-0.56 % of the path, RMS 0.31 % (an
#: upper bound on the scale error: it holds the heading drift's lever too). The bend fit is
#: regularised by it: two maps that do not fix the bend (few inliers, far from the query) fall
#: back on what real odometry does, not on an unconstrained fit (metres).
PRIOR_DRIFT_DEG_PER_M = 0.012
PRIOR_SCALE_ERROR = 0.003

#: The registration error that the inliers share and their residuals cannot show: each map's rock
#: centres carry a bias of the viewing geometry that built it (the visible side of a rock, the
#: detections' ranges), alike for neighbouring rocks, so part of it is common to the whole inlier set
#: (a translation and a turn the rigid fit absorbs) and does not shrink with their number. 1 sigma,
#: horizontal translation per axis and yaw about the inliers' centroid, for two maps built from
#: detections (``LandmarkMap.sightings`` given; half the variance for one, none for maps of true or
#: surveyed positions, whose errors are independent). Measured on the 131 real
#: pairs claimed with the maps stated rigid (random rigid motions, seed 0): with the residual-based
#: covariance alone the normalised position error at the rover (NEES, 3 dof) was under 3.53 for 40 %
#: and under 14.16 for 80 % (over-confident: the 8-9 cm errors of pairs 1-15, 2-15, 3-15, 5-15 had
#: 4-5 cm predicted); with these 64 % / 96 %. Checked on other inlier sets, the last 30 m and 60 m
#: of each vehicle traverse (57 and 105 claims): 60 / 96 % and 67 / 99 % (42 / 89 %, 45 / 87 % before).
#: docs/calibration.md.
CENTRE_BIAS_M = 0.002
CENTRE_BIAS_YAW_DEG = 0.03


@dataclass
class LocalizationConfig:
    """Parameters of :func:`localize`. Distances in metres, angles in degrees."""

    mode: Mode = Mode.GRAVITY
    solver: Solver = Solver.EXACT
    registration: Registration = Registration.SE3
    epsilon_m: float = setting(0.05, gt=0.0)  # max disagreement of a pairwise (horizontal) distance for consistency
    sigma_m: float | None = setting(None, gt=0.0)  # CLIPPER weight scale exp(-c^2/2sigma^2); None -> epsilon/2
    epsilon_z_m: float = setting(0.05, gt=0.0)  # gravity: max disagreement of a height difference (plus tilt allowance)
    max_tilt_deg: float = setting(1.5, ge=0.0, lt=45.0)  # gravity: residual tilt of the vehicle map after IMU levelling
    yaw_step_deg: float = setting(2.0, gt=0.0)  # gravity: spacing of the relative-yaw bins
    yaw_noise_factor: float = 1.5  # gravity: yaw tolerance of a pair at distance d is asin(k*eps/d)
    max_size_ratio: float | None = setting(None, ge=1.0)  # prune associations whose size ratio exceeds this (needs sizes)
    max_edges: int = 30_000_000  # 6-DoF memory bound on the consistency graph
    refine: bool = True  # re-fit with mutual nearest neighbours under the estimate
    refine_radius_m: float = setting(0.10, gt=0.0)  # max residual of a nearest-neighbour pair kept by refinement
    robust_scale_m: float = 0.02  # Cauchy scale of the robust (IRLS) re-weighting in refinement
    irls_rounds: int = setting(5, ge=1, le=100)  # re-weighting rounds of the robust registration
    refine_rounds: int = setting(3, ge=1, le=100)  # mutual-nearest-neighbour re-fits of refinement (fewer when the inliers settle)
    registration_sigma_floor_m: float = setting(0.005, gt=0.0)  # floor on the residual noise scale in the covariance, predicted error and scale check
    # --- acceptance (verification) ---
    min_inliers: int = setting(6, ge=3)  # absolute floor on the inlier count
    chance_margin: float = 2.5  # inliers must exceed the chance envelope at this map size by this many
    max_rmse_m: float = setting(0.05, gt=0.0)  # residual RMSE of the inliers after registration
    min_extent_m: float = 1.0  # inliers must spread at least this far (largest principal std x 2)
    min_planarity: float = 0.05  # second/first principal std of the inliers (0 = collinear)
    min_handedness: float = 0.9  # gravity: share of inlier triangles with matching orientation
    max_predicted_error_m: float = 0.10  # predicted 1-sigma error (x predicted_error_sigmas) at the query points
    predicted_error_sigmas: float = 1.0
    max_predicted_rotation_deg: float = 1.0  # predicted 1-sigma rotation error (x predicted_error_sigmas)
    max_scale_error: float = 0.005  # a rigid map's inliers match the reference's scale within 0.5 % ...
    scale_sigmas: float = 3.0  # ... or within this many standard errors of the fitted scale
    # --- uncertainty of the maps (tolerances above are floors; the maps' own sigma raises them) ---
    landmark_sigma_m: float = setting(0.0083, gt=0.0)  # horizontal 1-sigma per axis of a landmark whose map states none; added in quadrature to stated ones
    landmark_sigma_z_m: float = setting(0.0083, gt=0.0)  # vertical, likewise
    rmse_confidence: float = 0.999  # chi-square acceptance of the inlier residuals at this confidence
    search_sigmas: float = setting(2.0, ge=0.0)  # search tolerances >= this many sigma of a pairwise difference (sqrt(2) x combined sigma)
    # --- screen before an exhaustive search that would be large (:func:`_screen`) ---
    screen_min_incidences: float = setting(3e7, ge=0.0)  # predicted yaw-bin graph size from which the screen runs first (0: never)
    screen_fraction: float = setting(0.5, gt=0.0, le=1.0)  # a candidate pose passes with this share of the required inliers beyond chance
    screen_candidates: int = setting(8, ge=1)  # candidate poses of the triangle vote refined by the screen
    # --- distortion (non-rigid vehicle maps: odometry scale error, heading drift) ---
    near_miss_outer_m: float = setting(0.30, gt=0.0)  # vehicle landmarks landing refine_radius_m..this far from a reference rock are "near misses"
    max_near_miss_z: float = 3.0  # refuse when near misses exceed chance by this many standard deviations ...
    min_near_misses: int = 5  # ... and there are at least this many of them
    # Bounds on the distortion of the odometry that built the vehicle map (its specification):
    # relative scale error and heading drift. None (both): not stated, the distortion is fitted
    # from the maps (:func:`bending_fit`) and its effect where the pose is used is added to the
    # predicted error. 0 states a rigid map (e.g. built from ground-truth poses).
    odometry_scale_error: float | None = setting(None, ge=0.0)
    odometry_heading_drift_deg_per_m: float | None = setting(None, ge=0.0)
    distortion_fit_sigmas: float = 2.0  # no bounds stated: allowance = fitted bend's shift + this many sigmas
    # no bounds stated: 1-sigma prior on the odometry's heading drift (deg/m) and scale error that
    # regularises the bend fit (None: unconstrained, the fit from the maps alone). Defaults: what
    # real rover odometry shows (PRIOR_DRIFT_DEG_PER_M, PRIOR_SCALE_ERROR; docs/verification.md)
    odometry_prior_drift_deg_per_m: float | None = setting(PRIOR_DRIFT_DEG_PER_M, gt=0.0)
    odometry_prior_scale_error: float | None = setting(PRIOR_SCALE_ERROR, gt=0.0)
    distortion_fit_rounds: int = setting(3, ge=1, le=100)  # bent-model fits, inliers gathered again under the model between them
    min_inliers_distortion_fit: int = 6  # fewer inliers cannot fix the 8 parameters of the bent model: no allowance, refused
    max_sighting_span_m: float = setting(10.0, gt=0.0)  # a landmark seen over more path than this (passed twice) is left out of the bent-model fit
    competitor_ratio: float = 1.5  # best must be this many times the best competing hypothesis
    competitor_yaw_sep_deg: float = 10.0  # hypotheses whose yaws differ more than this compete
    seed: int = 0  # CLIPPER initialisation
    threads: int = field(default_factory=lambda: min(4, os.cpu_count() or 1))  # graph-building threads
    # landmark-centre bias shared by the inliers (1 sigma; added to the registration's covariance about
    # their centroid, not averaged down by their number; CENTRE_BIAS_M, docs/calibration.md):
    centre_bias_m: float = setting(CENTRE_BIAS_M, ge=0.0)  # horizontal translation, m per axis
    centre_bias_yaw_deg: float = setting(CENTRE_BIAS_YAW_DEG, ge=0.0)  # yaw about the inliers' centroid, deg

    def __post_init__(self) -> None:
        self.mode = Mode(self.mode)
        self.solver = Solver(self.solver)
        self.registration = Registration(self.registration)
        if self.registration is Registration.YAW and self.mode is not Mode.GRAVITY:
            raise ConfigError("yaw-only registration needs the gravity-aware mode")
        check_settings(self)  # every range declared beside its field

    @property
    def odometry_bounds_stated(self) -> bool:
        """Whether the odometry's distortion bounds are given (else they are fitted from the maps)."""
        return self.odometry_scale_error is not None or self.odometry_heading_drift_deg_per_m is not None

    @property
    def sigma(self) -> float:
        return self.sigma_m if self.sigma_m is not None else self.epsilon_m / 2.0

    def for_maps(self, reference: LandmarkMap, vehicle: LandmarkMap) -> "LocalizationConfig":
        """This config with its refinement and acceptance tolerances raised to what the
        maps' stated uncertainty needs (:func:`combined_sigma`): refinement radius
        ``3 sigma_r`` and robust scale ``sigma_r``, sigma_r = sqrt(2 sigma_h^2 + sigma_z^2)
        the 3D offset of a landmark from its partner; the residual RMSE limit follows from
        a chi-square test (:func:`rmse_limit`). The consistency search tolerances become
        ``search_sigmas`` standard deviations of the difference between a vehicle pair's
        distance and its reference pair's (four landmarks: sqrt(2) sigma_h horizontally,
        sqrt(2) sigma_z vertically; one degree of freedom each): 2 sigma keeps a true pair
        consistent with 95 % probability. Wider tolerances also make chance sets larger (the
        envelope scales with them, :func:`chance_clique_size`), so small vehicle maps need
        more inliers: 2 sigma, not 2.5 or 3, keeps a 13-landmark map localizable against a
        LAC grid (docs/scaling.md). The fixed values stay as floors: at the default
        landmark sigma, and on the real traverse maps (sigma_h 1.2 cm: 3.4 cm), they are
        what the rule gives; against a LAC grid (sigma_h about 4.4 cm) the search runs at
        about 12 cm horizontally."""
        sh, sz = combined_sigma(reference, vehicle, self)
        sr = math.sqrt(2 * sh**2 + sz**2)
        refine = max(self.refine_radius_m, 3 * sr)
        return replace(
            self, refine_radius_m=refine, robust_scale_m=max(self.robust_scale_m, sr),
            near_miss_outer_m=max(self.near_miss_outer_m, 3 * refine),
            epsilon_m=max(self.epsilon_m, self.search_sigmas * math.sqrt(2) * sh),
            epsilon_z_m=max(self.epsilon_z_m, self.search_sigmas * math.sqrt(2) * sz),
        )

    def to_dict(self) -> dict:
        d = asdict(self)
        d["mode"] = self.mode.value
        d["solver"] = self.solver.value
        d["registration"] = self.registration.value
        return d


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
    near_misses : vehicle landmarks that land just outside the inlier radius of a reference
        rock (``refine_radius_m`` .. ``near_miss_outer_m``), against ``near_misses_expected``
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
    near_misses: int = 0
    near_misses_expected: float = float("nan")
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    timings: dict = field(default_factory=dict)
    checks: list = field(default_factory=list)  # the acceptance tests (:class:`Check`) of :func:`verify`
    distortion_fit: dict = field(default_factory=dict)  # :class:`BendFit` when no odometry bounds were stated

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
            "near_misses": int(self.near_misses),
            "near_misses_expected": clean(float(self.near_misses_expected)),
            "covariance": [[clean(float(v)) for v in row] for row in self.covariance],
            "timings_s": {k: round(v, 6) for k, v in self.timings.items()},
            "checks": [c.to_dict() for c in self.checks],
            "distortion_fit": {k: clean(v) for k, v in self.distortion_fit.items()},
        }


# --------------------------------------------------------------------------- helpers


def landmark_sigmas(m: LandmarkMap, cfg: "LocalizationConfig") -> tuple[np.ndarray, np.ndarray]:
    """Per-landmark (horizontal per axis, vertical) 1-sigma of a map: its stated sigma with
    the configured landmark sigma added in quadrature (unmodelled session-to-session error),
    or the configured sigma alone where the map states none."""
    n = len(m)
    h = np.zeros(n) if m.sigma_xy_m is None else m.sigma_xy_m
    z = np.zeros(n) if m.sigma_z_m is None else m.sigma_z_m
    return np.hypot(h, cfg.landmark_sigma_m), np.hypot(z, cfg.landmark_sigma_z_m)


def combined_sigma(reference: LandmarkMap, vehicle: LandmarkMap, cfg: "LocalizationConfig") -> tuple[float, float]:
    """1-sigma per axis of the offset between a vehicle landmark and its reference landmark
    (horizontal, vertical): the maps' median landmark sigmas combined in quadrature."""
    rh, rz = landmark_sigmas(reference, cfg)
    vh, vz = landmark_sigmas(vehicle, cfg)
    return float(np.hypot(np.median(rh), np.median(vh))), float(np.hypot(np.median(rz), np.median(vz)))


def rmse_limit(cfg: "LocalizationConfig", sigma_h: float, sigma_z: float, k: int) -> float:
    """Largest residual RMSE of k inliers the chi-square test accepts: the sum of squared
    3D residuals over the per-axis variance (sigma_r^2 / 3, sigma_r^2 = 2 sigma_h^2 +
    sigma_z^2) stays below its `rmse_confidence` quantile with 3k - 6 degrees of freedom,
    i.e. RMSE <= sigma_r sqrt(q / 3k). Never below cfg.max_rmse_m (the floor)."""
    dof = max(3 * k - 6, 1)
    sr = math.sqrt(2 * sigma_h**2 + sigma_z**2)
    return max(cfg.max_rmse_m, sr * math.sqrt(_chi2_ppf(cfg.rmse_confidence, dof) / (3 * max(k, 1))))


def _chi2_ppf(q: float, dof: int) -> float:
    """Chi-square quantile, as scipy.stats.chi2.ppf computes it (2 gammaincinv(dof/2, q)),
    without importing scipy.stats (about 0.4 s at start-up)."""
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(dof / 2.0, q))


def _flattened(m: LandmarkMap) -> LandmarkMap:
    """The map with every height 0 and no vertical uncertainty (2D association)."""
    P = m.positions_xyz.copy()
    P[:, 2] = 0.0
    return LandmarkMap(P, m.sizes, m.sightings, m.frame, m.sigma_xy_m, None, m.sighting_arc_m,
                       m.sighting_arc_min_m, m.sighting_arc_max_m)


def _check_map(m: LandmarkMap, name: str) -> np.ndarray:
    if not isinstance(m, LandmarkMap):
        raise InputError(f"{name} must be a LandmarkMap, got {type(m).__name__}")
    P = m.positions_xyz
    if len(P) == 0:
        raise InputError(f"{name} map is empty: no landmarks to localize with")
    if len(P) < 3:
        raise InputError(f"{name} map has {len(P)} landmark(s); at least 3 are needed to fix a pose")
    spread = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    if spread[0] < 1e-6:
        raise DegenerateGeometryError(f"{name} landmarks all coincide: the pose is undetermined")
    if spread[1] < 1e-6 * max(1.0, spread[0]) or spread[1] / spread[0] < 1e-4:
        raise DegenerateGeometryError(
            f"{name} landmarks are collinear: the rotation about their line is undetermined"
        )
    return P


def _solve(solver: Solver, n: int, eu, ev, ew, lower_bound: int, seed: int, scratch=None) -> np.ndarray:
    if solver is Solver.EXACT:
        return max_clique(n, eu, ev, lower_bound, scratch)
    if lower_bound > 0 and len(eu):
        keep = peel(eu, ev, lower_bound, scratch)  # vertices of degree < lb cannot beat lb
        eu, ev, ew = eu[keep], ev[keep], ew[keep]
        if len(eu) < lower_bound * (lower_bound + 1) // 2:
            return np.empty(0, dtype=np.int32)
    c = clipper_clique(n, eu, ev, ew, seed=seed)
    return c if len(c) > lower_bound else np.empty(0, dtype=np.int32)


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
    for _ in range(cfg.irls_rounds):
        r = _residuals(T, P, Q)
        w = 1.0 / (1.0 + (r / cfg.robust_scale_m) ** 2)
        try:
            T = _register(P, Q, cfg, w)
        except DegenerateGeometryError:
            break
    return T, w


def _refine(T, Pv, Pr, inl, cfg):
    """Mutual nearest neighbours within refine_radius under T, re-fitted (`refine_rounds` rounds)."""
    tree = cKDTree(Pr)
    best_T, best_inl = T, inl
    for _ in range(cfg.refine_rounds):
        Pt = transform_points(best_T, Pv)
        d, j = tree.query(Pt, distance_upper_bound=cfg.refine_radius_m)
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
        same = len(pairs) == len(best_inl) and np.array_equal(np.sort(pairs[:, 0]), np.sort(best_inl[:, 0]))
        best_T, best_inl = T_new, pairs
        if same:
            break
    return best_T, best_inl


def scale_check(T, P, Q, weights, sigma_floor: float = 0.005) -> tuple[float, float]:
    """Relative size of the vehicle map's inliers against their reference landmarks, and
    its standard error: ``(1/s - 1, se)`` with s the scale taking vehicle to reference. A rigid map gives s = 1 within noise; odometry
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


def distortion_covariance(point_ref: np.ndarray, position_m: float, rotation_rad: float) -> np.ndarray:
    """6x6 pose-error covariance about the reference origin of a distortion allowance at a
    reference-frame point: `position_m` as one sigma of horizontal position there (split
    over x and y) and `rotation_rad` as one sigma of yaw. Zero when there is no allowance,
    and when it is not finite (the pose is refused then)."""
    C = np.zeros((6, 6))
    if not (position_m > 0 or rotation_rad > 0) or not (math.isfinite(position_m) and math.isfinite(rotation_rad)):
        return C
    C[0, 0] = C[1, 1] = position_m**2 / 2
    C[5, 5] = rotation_rad**2
    return covariance_at_origin(C, np.asarray(point_ref, float))


def shared_bias_covariance(bias_m: float, bias_yaw_deg: float) -> np.ndarray:
    """6x6 covariance, about the inliers' centroid, of the registration error their residuals
    cannot show (:data:`CENTRE_BIAS_M`): `bias_m` per horizontal axis, `bias_yaw_deg` in yaw."""
    return np.diag([bias_m**2, bias_m**2, 0.0, 0.0, 0.0, math.radians(bias_yaw_deg) ** 2])


def predicted_error(T, P, Q, weights, query_xyz, sigma_floor: float = 0.005,
                    shared_bias: np.ndarray | None = None) -> np.ndarray:
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
    tree = cKDTree(path[:, :2], balanced_tree=False, compact_nodes=False)  # built for a few queries: the quick build
    return [s[tree.query(np.asarray(p, float)[:, :2])[1]] for p in points_xyz]


def distortion_allowance(query_xyz, inliers_xyz, weights, scale_error: float, heading_drift_rad_per_m: float,
                         path_xyz: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
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


@dataclass
class BendFit:
    """A non-rigid model of the vehicle map fitted to its inliers (:func:`bending_fit`): the
    odometry that built it drifted in heading by ``drift_rad_per_m`` per metre travelled and
    mis-scaled its path by ``scale_error``, each with its standard error.

    ``shift_m`` : largest distance, over the query points, between where the rigid fit and the
        bent model put them (what the rigid pose gets wrong if the map is bent as fitted);
    ``sigma_m`` : largest 1-sigma position uncertainty of the bent model there beyond the rigid
        model's (how well the data fix the bending as seen from the query points: large when the
        inliers cover little of the path; the rigid pose's own uncertainty is the registration's,
        counted once in the predicted error, :func:`fitted_predicted_error`);
    ``rotation_shift_deg`` / ``rotation_sigma_deg`` : the same for the heading at the query points;
    ``chi2_drop`` : decrease of the inliers' chi-square from the rigid fit to the bent model
        (2 extra parameters: above ~13.8 the bend is real at 0.999 confidence);
    ``inliers`` : inlier pairs the bent model is fitted to; ``path_given`` : False when the path
        was not given and a straight path along the map's principal axis stood in for it;
    ``placement`` : where each landmark was placed along the path: ``"sightings"`` (the map's
        sighting arcs), ``"nearest path point"`` or ``"straight stand-in"``;
    ``left_out`` : inliers left out of the fit because where they were seen from is not known
        well enough (a path that passed them more than once);
    ``floor_sigma_m`` / ``rotation_floor_sigma_deg`` : largest 1-sigma effect at the query points
        of the apparent drift and scale of real maps (``DRIFT_FLOOR_DEG_PER_M``, ``SCALE_FLOOR``)
        that the fit's standard errors do not hold, with the rigid part re-fitted."""

    drift_rad_per_m: float
    drift_se: float
    scale_error: float
    scale_se: float
    shift_m: float
    sigma_m: float
    rotation_shift_deg: float
    rotation_sigma_deg: float
    chi2_drop: float
    inliers: int
    path_given: bool
    placement: str = "straight stand-in"
    left_out: int = 0
    floor_sigma_m: float = 0.0
    rotation_floor_sigma_deg: float = 0.0
    prior: str = "none"  # the odometry prior: "applied", "rejected: ..." (prior-data conflict) or "none"


def _straight_path(points_xyz: np.ndarray, step_m: float = 0.25) -> np.ndarray:
    """A stand-in odometry path: a straight line along the horizontal principal axis of the
    points, over their extent (a traverse that drove straight through its map)."""
    P = np.asarray(points_xyz, float)
    c = P.mean(axis=0)
    _, _, Vt = np.linalg.svd(P[:, :2] - c[:2], full_matrices=False)
    a = np.r_[Vt[0], 0.0]
    u = (P - c) @ a
    t = np.arange(u.min(), u.max() + step_m, step_m)
    return c + t[:, None] * a


class _Unbender:
    """Undo a heading drift ``delta`` (rad per metre travelled) and a path scale error
    ``kappa`` in vehicle-frame points, each placed at its nearest (horizontally) point of the
    odometry path: the path is re-integrated with every step turned back by -delta * s (s its
    distance travelled) and shrunk by 1 / (1 + kappa); a point keeps its offset from its path
    point (a stereo measurement, not odometry), turned back with it."""

    def __init__(self, path_xyz: np.ndarray, spacing_m: float = 0.25):
        path = np.asarray(path_xyz, float)
        arc = path_arc_length_m(path)
        keep = np.unique(np.r_[np.searchsorted(arc, np.arange(0.0, arc[-1], spacing_m)), len(path) - 1])
        self.path = path[keep]  # one point every spacing_m: the model's cost does not grow with the frame rate
        self.arc = arc[keep]  # the given path's own arc length at the kept points (where sightings are stated)
        self.steps = np.diff(self.path, axis=0)
        self.s = np.r_[0.0, np.cumsum(np.linalg.norm(self.steps[:, :2], axis=1))]
        self.tree = cKDTree(self.path[:, :2])
        self._last = None

    def index(self, points_xyz: np.ndarray) -> np.ndarray:
        """Each point's nearest (horizontally) path point: the stand-in for where it was seen from."""
        return self.tree.query(np.asarray(points_xyz, float)[:, :2])[1]

    def index_at_arc(self, arc_m: np.ndarray) -> np.ndarray:
        """The path point at each arc length (m from the path's first pose)."""
        a = np.clip(np.asarray(arc_m, float), 0.0, self.arc[-1])
        j = np.clip(np.searchsorted(self.arc, a), 1, max(len(self.arc) - 1, 1))
        return np.where(np.abs(self.arc[j - 1] - a) <= np.abs(self.arc[j] - a), j - 1, j) if len(self.arc) > 1 else \
            np.zeros(len(a), int)

    def passes(self, points_xyz: np.ndarray, range_m: float, margin_m: float) -> np.ndarray:
        """How many separate passes of the path come within sight of each point: path points
        within `range_m` (or `margin_m` beyond its nearest one, when farther) whose arc lengths
        form runs broken by gaps of more than 1 m. Without sighting arcs a landmark passed more
        than once may have been seen from any of the passes, and its nearest point may be the
        wrong one."""
        P = np.asarray(points_xyz, float)[:, :2]
        d = self.tree.query(P)[0]
        out = np.zeros(len(P), int)
        for i, near in enumerate(self.tree.query_ball_point(P, np.maximum(range_m, d + margin_m))):
            a = np.sort(self.arc[near])
            out[i] = 1 + int(np.count_nonzero(np.diff(a) > 1.0)) if len(a) else 0
        return out

    def _bent_path(self, delta: float, kappa: float) -> np.ndarray:
        # the last one is kept: a finite-difference Jacobian varies one parameter at a time,
        # so most of its calls share (delta, kappa) and the re-integration
        if self._last is None or self._last[0] != (delta, kappa):
            a = -delta * self.s[1:]
            c, sn = np.cos(a), np.sin(a)
            st = self.steps
            turned = np.stack([c * st[:, 0] - sn * st[:, 1], sn * st[:, 0] + c * st[:, 1], st[:, 2]], axis=1)
            path = self.path[0] + np.vstack([np.zeros((1, 3)), np.cumsum(turned / (1.0 + kappa), axis=0)])
            self._last = ((delta, kappa), path)
        return self._last[1]

    def __call__(self, points_xyz: np.ndarray, idx: np.ndarray, delta: float, kappa: float) -> np.ndarray:
        path = self._bent_path(float(delta), float(kappa))
        rel = np.asarray(points_xyz, float) - self.path[idx]
        b = -delta * self.s[idx]
        cb, sb = np.cos(b), np.sin(b)
        return path[idx] + np.stack([cb * rel[:, 0] - sb * rel[:, 1], sb * rel[:, 0] + cb * rel[:, 1], rel[:, 2]], axis=1)

    def heading(self, idx: np.ndarray, delta: float) -> np.ndarray:
        """Heading correction (rad) the model applies at path points `idx`."""
        return -delta * self.s[idx]


#: without sighting arcs a landmark may have been seen from any path point within this range
#: (the LunarLoc traverses: 99.9 % of detections within 5.9 m of the rover, all within 6.2 m),
#: or this margin beyond its nearest path point when that is farther
SIGHTING_RANGE_M = 6.0
PASS_MARGIN_M = 2.0
#: a query point this close to the path's last pose is the rover there (not an earlier pass)
QUERY_AT_END_M = 0.05
#: Apparent distortion of real maps that the bend model's own standard errors do not hold,
#: added in quadrature to them: heading drift (deg/m) and scale error. Measured on the 136
#: real pairs with no simulated distortion (30 m and 60 m windows, 70 and 112 fits; scratch
#: script, docs/verification.md): the fitted drift over its standard error had an RMS of 1.73
#: and 1.89 (1 if the errors were right; vehicle maps of traverses 8, 14 and 17 show 0.02-0.05
#: deg/m), the scale 1.64 and 1.54; with these floors 1.08 / 1.02 and 1.19 / 1.05.
DRIFT_FLOOR_DEG_PER_M = 0.02
SCALE_FLOOR = 0.002


def _sighting_placement(unb: "_Unbender", Pv: np.ndarray, given: bool, sighting_arcs, max_span_m: float):
    """Where along the path each vehicle landmark was seen from (index into ``unb.path``),
    whether that is known well enough to take part in the bend fit (its arc span at most
    `max_span_m`), and the source: ``"sightings"`` (the map's sighting arcs, mean placed),
    ``"nearest path point"`` (a path without sighting arcs: a landmark that more than one pass
    of the path comes within sight of is left out, :meth:`_Unbender.passes`) or
    ``"straight stand-in"`` (no path: a straight line, passed once)."""
    if given and sighting_arcs is not None:
        mean, lo, hi = (np.asarray(a, float) for a in sighting_arcs)
        if len(mean) == len(Pv) and (not len(hi) or float(hi.max()) <= unb.arc[-1] * 1.01 + 0.5):
            return unb.index_at_arc(mean), (hi - lo) <= max_span_m, "sightings"
        log.warning("bend fit: the vehicle map's sighting arcs (up to %.1f m) do not fit the given path (%.1f m);"
                    " using each landmark's nearest path point", float(hi.max()) if len(hi) else 0.0, unb.arc[-1])
    if given:
        return unb.index(Pv), unb.passes(Pv, SIGHTING_RANGE_M, PASS_MARGIN_M) <= 1, "nearest path point"
    return unb.index(Pv), np.ones(len(Pv), bool), "straight stand-in"


def bending_fit(T, Pv, Pr, inl, query_xyz, path_xyz, sigma_axis_m: float, radius_m: float, rounds: int = 3,
                sighting_arcs=None, max_sighting_span_m: float = 10.0, min_inliers: int = 6,
                prior_drift_rad_per_m: float | None = None, prior_scale_error: float | None = None) -> BendFit:
    """Fit a bent (heading drift) and scaled (path scale error) model of the vehicle map to
    its inliers, starting from the rigid fit T: parameters rotation vector, translation, drift
    per metre and scale error, by least squares on the 3D residuals over `sigma_axis_m` (the
    landmarks' per-axis noise; the residuals' own scale when larger). Inliers are gathered
    again under the model (mutual nearest neighbours within `radius_m`; at most `rounds` fits), so the
    part of a bent map the rigid fit left out can show its bend. Covariance from the Jacobian;
    the query points' positions and headings under the model, with their uncertainty beyond
    the rigid model's, are compared with the rigid fit's. Without `path_xyz` a straight path
    along the map's principal axis stands in (a rough proxy for a winding traverse).

    Each landmark is unbent from where it was seen: `sighting_arcs` ``(mean, min, max)`` (m of
    arc along `path_xyz`, per row of `Pv`; :attr:`LandmarkMap.sighting_arc_m`) places it at its
    mean sighting arc; one seen over more than `max_sighting_span_m` of arc (the path passed it
    twice: its aggregate mixes passes the model cannot tell apart) is left out of the fit.
    Without them, its nearest path point stands in, and a landmark that more than one pass of
    the path comes within sight of (:meth:`_Unbender.passes`) is left out. With fewer than `min_inliers` inliers
    left the bend is not determined: infinite sigma (refused).

    `prior_drift_rad_per_m` / `prior_scale_error`: a zero-mean Gaussian prior (1 sigma) on the drift
    and the scale error, two more residuals of the least squares (a maximum a posteriori fit): where
    the maps do not fix the bend, its uncertainty is the prior's, not metres."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    q = np.asarray(query_xyz, float).reshape(-1, 3)
    given = path_xyz is not None and len(path_xyz) >= 2
    unb = _Unbender(path_xyz if given else _straight_path(np.vstack([Pv, q])))
    idx_all, known, source = _sighting_placement(unb, Pv, given, sighting_arcs, max_sighting_span_m)
    idx_q = unb.index(q)
    if given:  # the rover at the path's end is there, not at an earlier pass that comes as near
        end = np.linalg.norm(q[:, :2] - unb.path[-1, :2], axis=1) <= QUERY_AT_END_M
        idx_q[end] = len(unb.path) - 1
    tree = cKDTree(Pr)
    R0 = Rotation.from_matrix(T[:3, :3]).as_rotvec()

    def model_T(x):  # Rodrigues: scipy's Rotation costs ~25 us a call here, called ~100 times per fit
        return make_transform(exp_so3(x[:3]), x[3:6])

    def apply(x, P, idx):
        return transform_points(model_T(x), unb(P, idx, x[6], x[7]))

    x = np.r_[R0, T[:3, 3], 0.0, 0.0]
    pairs = np.asarray(inl)
    pairs = pairs[known[pairs[:, 0]]]
    if len(pairs) < max(min_inliers, 3):  # the 8 parameters are not determined by what is left
        inf = math.inf
        return BendFit(0.0, inf, 0.0, inf, inf, inf, inf, inf, 0.0, int(len(pairs)), bool(given), source,
                       int(len(inl) - len(pairs)), inf, inf)
    left_out = int(len(inl) - len(pairs))
    prior_sd = (np.array([prior_drift_rad_per_m or math.inf, prior_scale_error or math.inf])
                if (prior_drift_rad_per_m or prior_scale_error) else None)
    chi2_rigid = chi2_bent = 0.0
    first_round = True
    for _ in range(rounds):
        v, r = pairs[:, 0], pairs[:, 1]
        used = len(pairs)

        def resid(xx):
            geo = ((apply(xx, Pv[v], idx_all[v]) - Pr[r]) / sigma_axis_m).ravel()
            return np.r_[geo, xx[6:8] / prior_sd] if prior_sd is not None else geo

        sol = least_squares(resid, x, x_scale=np.r_[np.full(3, 1e-3), np.full(3, 1e-2), 1e-4, 1e-3], method="lm",
                            max_nfev=200)
        if first_round:  # on the rigid fit's own inliers
            chi2_rigid, chi2_bent = float(np.sum(resid(x) ** 2)), float(np.sum(sol.fun**2))
            first_round = False
        x = sol.x
        d, j = tree.query(apply(x, Pv, idx_all), distance_upper_bound=radius_m)
        ok = np.flatnonzero(np.isfinite(d))
        order = ok[np.argsort(d[ok])]
        _, first = np.unique(j[order], return_index=True)
        new = np.stack([order[first], j[order[first]]], axis=1)
        new = new[known[new[:, 0]]]
        if len(new) <= len(pairs):
            break
        pairs = new
    J = sol.jac
    n_prior = 0 if prior_sd is None else 2
    geo = slice(0, J.shape[0] - n_prior)
    dof = max(J.shape[0] - n_prior - 8, 1)
    # residuals noisier than the stated sigma widen the data's part of the covariance (not the prior's)
    s2 = max(1.0, float(np.sum(sol.fun[geo] ** 2)) / dof)
    J = J.copy()
    J[geo] /= math.sqrt(s2)  # the geometric rows at the noise they show; from here on C = (J^T J)^-1
    try:
        C = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        C = np.full((8, 8), np.inf)

    def at_query(xx):  # positions (3 per query point), then the map's local heading at each
        R = model_T(xx)[:3, :3]
        h = unb.heading(idx_q, xx[6])  # yaw_of(R @ rot_z(h)) for every h at once
        c, s = np.cos(h), np.sin(h)
        return np.r_[apply(xx, q, idx_q).ravel(), np.arctan2(R[1, 0] * c + R[1, 1] * s, R[0, 0] * c + R[0, 1] * s)]

    f0 = at_query(x)
    Jq = np.empty((len(f0), 8))
    for i in range(8):
        h = 1e-6 if i == 6 else 1e-5
        dx = np.zeros(8)
        dx[i] = h
        Jq[:, i] = (at_query(x + dx) - at_query(x - dx)) / (2 * h)
    n = len(q)
    var = np.einsum("ij,jk,ik->i", Jq, C, Jq) if np.all(np.isfinite(C)) else np.full(len(f0), np.inf)
    # The bent model's uncertainty at the query points holds the rigid pose's own, which the
    # predicted error counts once as the registration's: only the increase over the rigid
    # model fitted to the same residuals is the bend's. For nested least squares that is the
    # variance of the difference between the two models' predictions.
    if np.all(np.isfinite(var)):
        try:
            C6 = np.linalg.inv(J[:, :6].T @ J[:, :6])
            var = np.maximum(var - np.einsum("ij,jk,ik->i", Jq[:, :6], C6, Jq[:, :6]), 0.0)
        except np.linalg.LinAlgError:
            pass
    # Real maps bend and stretch a little beyond what their noise says (measured floors): the
    # floors' effect at the query points with the rigid part re-fitted to the inliers (what the
    # inliers absorb of a bend does not move the pose). A 1-sigma spread, kept apart, under the
    # prior too (without it, bent maps were claimed wrong: see fitted_predicted_error).
    floor = np.array([math.radians(DRIFT_FLOOR_DEG_PER_M), SCALE_FLOOR]) ** 2
    try:
        G = Jq[:, 6:] - Jq[:, :6] @ np.linalg.solve(J[:, :6].T @ J[:, :6], J[:, :6].T @ J[:, 6:])
        var_floor = G**2 @ floor
    except np.linalg.LinAlgError:
        var_floor = np.full(len(var), np.inf)
    pos_var = var[: 3 * n].reshape(-1, 3).sum(axis=1)
    pos_floor = var_floor[: 3 * n].reshape(-1, 3).sum(axis=1)
    shift = np.linalg.norm(f0[: 3 * n].reshape(-1, 3) - transform_points(T, q), axis=1)
    dyaw = np.abs((f0[3 * n:] - yaw_of(T[:3, :3]) + math.pi) % (2 * math.pi) - math.pi)
    return BendFit(
        drift_rad_per_m=float(x[6]), drift_se=float(math.sqrt(max(C[6, 6], 0.0))), scale_error=float(x[7]),
        scale_se=float(math.sqrt(max(C[7, 7], 0.0))), shift_m=float(shift.max()),
        sigma_m=float(math.sqrt(max(pos_var.max(), 0.0))), rotation_shift_deg=math.degrees(float(dyaw.max())),
        rotation_sigma_deg=math.degrees(math.sqrt(max(float(var[3 * n:].max()), 0.0))), chi2_drop=chi2_rigid - chi2_bent,
        inliers=int(used), path_given=bool(given), placement=source, left_out=left_out,
        floor_sigma_m=float(math.sqrt(max(pos_floor.max(), 0.0))),
        rotation_floor_sigma_deg=math.degrees(math.sqrt(max(float(var_floor[3 * n:].max()), 0.0))),
    )


#: A bend the maps alone fit this many sigma (their standard error and the prior's combined) away
#: from the prior's zero is one real odometry does not make: the prior is not applied. Shrunk
#: towards the prior, a 0.1 deg/m map was claimed 14 cm off (tests/test_sighting_arcs.py), and
#: at 2 sigma pair 10-14 (0.05 deg/m, 30 m window, 1.9 sigma) 10.9 cm off (docs/verification.md)
PRIOR_CONFLICT_SIGMAS = 1.0


def prior_conflict(bend: "BendFit", prior_drift_rad_per_m: float | None, prior_scale_error: float | None) -> float:
    """How far, in sigmas, the bend fitted from the maps alone lies from the zero-mean odometry
    prior: the larger of drift and scale, each over the root sum of squares of its standard
    error and the prior's sigma (a parameter without a prior does not count). Infinite when the
    fit is not finite."""
    out = 0.0
    for est, se, sd in ((bend.drift_rad_per_m, bend.drift_se, prior_drift_rad_per_m),
                        (bend.scale_error, bend.scale_se, prior_scale_error)):
        if sd is None:
            continue
        if not (math.isfinite(est) and math.isfinite(se)):
            return math.inf
        out = max(out, abs(est) / math.sqrt(se**2 + sd**2))
    return out


def fitted_predicted_error(bend: BendFit, cfg: "LocalizationConfig", registration_m: np.ndarray,
                           registration_rot_deg: float) -> tuple[np.ndarray, float]:
    """Predicted 1-sigma position error (m, per query point) and rotation error (deg) when no
    odometry bounds are stated and the distortion is fitted from the maps: the fitted bend's
    shift (a bias) plus the random part, the registration's sigma and `distortion_fit_sigmas`
    times the bend's own sigma (the bend the data cannot exclude), and the measured floor on
    real maps' apparent distortion (`BendFit.floor_sigma_m`, a calibrated 1-sigma spread)
    combined in quadrature. The
    two are independent: `BendFit.sigma_m` is the bent model's uncertainty beyond the rigid
    one's, and the difference of two nested least-squares predictions is uncorrelated with the
    smaller model's. Adding the bent model's whole sigma linearly counted the registration two
    more times, and refused every compact map against a LAC grid (docs/verification.md); that
    margin had hidden a wrong bend model (landmarks placed at their nearest path point, where
    the path passed them twice), now placed where they were seen from (:func:`bending_fit`).
    The shift counts even when the bend is not significant: gating it on a chi-square test let
    a 2.3-sigma bend through (pair 4-9, 0.025 deg/m, 60 m window: 10.3 cm / 1.03 deg off,
    predicted 5.5 cm). Infinite when the fit is not finite."""
    # counted `distortion_fit_sigmas` times, under the prior too: the fit's standard errors run
    # small on real maps (DRIFT_FLOOR_DEG_PER_M), and at 1 sigma under the prior, with no floor,
    # bent maps the inliers could not see (0.05-0.1 deg/m, 11 inliers, 30 m windows: pairs 4-14,
    # 7-15) were claimed 21-24 cm off with 6.5-8.4 cm predicted
    k = cfg.distortion_fit_sigmas
    reg = np.asarray(registration_m, float)
    if not all(map(math.isfinite, (bend.shift_m, bend.sigma_m, bend.rotation_shift_deg, bend.rotation_sigma_deg,
                                   bend.floor_sigma_m, bend.rotation_floor_sigma_deg, registration_rot_deg))):
        return np.full(reg.shape, math.inf), math.inf
    pos = bend.shift_m + np.sqrt(reg**2 + (k * bend.sigma_m) ** 2 + bend.floor_sigma_m**2)
    rot = bend.rotation_shift_deg + math.sqrt(registration_rot_deg**2 + (k * bend.rotation_sigma_deg) ** 2
                                              + bend.rotation_floor_sigma_deg**2)
    return pos, rot


def near_miss_excess(T, Pv, Pr, inlier_veh: np.ndarray, inner_m: float, outer_m: float,
                     density_radius_m: float = 1.5) -> tuple[int, float]:
    """(observed, expected by chance) number of non-inlier vehicle landmarks whose nearest
    reference landmark under T lies between `inner_m` and `outer_m`.

    Under a right pose of a rigid map a landmark either has its rock within the noise
    (an inlier) or nothing nearby but chance neighbours; the chance count follows the local
    reference density lambda (rocks within `density_radius_m`): the nearest neighbour is in
    the band with probability exp(-lambda pi r_in^2) (1 - exp(-lambda pi (r_out^2 - r_in^2))).
    A map that is scaled or bent away from its inliers puts its true rocks a little further
    off, in the band: an excess there is the signature of a non-rigid map."""
    Pt = transform_points(T, Pv)
    rest = np.ones(len(Pt), dtype=bool)
    rest[np.asarray(inlier_veh, dtype=np.int64)] = False
    if not np.any(rest):
        return 0, 0.0
    tree = cKDTree(Pr)
    d, _ = tree.query(Pt[rest])
    observed = int(np.sum((d > inner_m) & (d < outer_m)))
    return observed, float(_chance_in_band(tree, Pt[rest], inner_m, outer_m, density_radius_m).sum())


def _chance_in_band(tree: cKDTree, points: np.ndarray, inner_m: float, outer_m: float,
                    density_radius_m: float = 1.5) -> np.ndarray:
    """Probability that the nearest reference landmark of each point lies between inner_m
    and outer_m by chance, from the local reference density (rocks within
    `density_radius_m`, a horizontal Poisson model)."""
    counts = tree.query_ball_point(points, density_radius_m, return_length=True)
    lam = np.asarray(counts, float) / (math.pi * density_radius_m**2)
    return np.exp(-lam * math.pi * inner_m**2) * (1 - np.exp(-lam * math.pi * (outer_m**2 - inner_m**2)))


def chance_refined(T, Pv, Pr, core_veh: np.ndarray, radius_m: float) -> float:
    """Expected number of vehicle landmarks outside the consistent core that refinement
    pairs with a reference landmark within `radius_m` by chance under T: the refined
    inlier count exceeds the core by about this much even for unrelated maps."""
    rest = np.ones(len(Pv), dtype=bool)
    rest[np.asarray(core_veh, dtype=np.int64)] = False
    if not np.any(rest):
        return 0.0
    return float(_chance_in_band(cKDTree(Pr), transform_points(T, Pv[rest]), 0.0, radius_m).sum())


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


def _nan_T() -> np.ndarray:
    return np.full((4, 4), np.nan)


# --------------------------------------------------------------------------- verification


@dataclass(frozen=True)
class Check:
    """One acceptance test of :func:`verify`: ``value`` must be ``relation`` (``"<="`` or
    ``">="``) ``limit``. ``detail`` is one line: the reason of the refusal when it fails,
    what was tested when it passes."""

    name: str
    value: float
    limit: float
    passed: bool
    relation: str = "<="
    detail: str = ""

    def to_dict(self) -> dict:
        def clean(x):
            return None if not math.isfinite(x) else float(x)

        return {"name": self.name, "value": clean(float(self.value)), "relation": self.relation,
                "limit": clean(float(self.limit)), "passed": bool(self.passed), "detail": self.detail}


def _at_most(name: str, value: float, limit: float, fail: str, ok: str) -> Check:
    passed = not (value > limit)  # NaN passes: a quantity that could not be measured refuses nothing here
    return Check(name, float(value), float(limit), passed, "<=", ok if passed else fail)


def _at_least(name: str, value: float, limit: float, fail: str, ok: str) -> Check:
    passed = not (value < limit)
    return Check(name, float(value), float(limit), passed, ">=", ok if passed else fail)


@dataclass
class Evidence:
    """What :func:`verify` judges: the quantities measured on the winning hypothesis.
    ``tilt_deg`` / ``handedness`` are None outside the gravity-aware mode (not tested)."""

    inliers: int
    rmse_m: float
    rmse_limit_m: float
    sigma_h_m: float
    sigma_z_m: float
    extent_m: float
    planarity: float
    tilt_deg: float | None
    handedness: float | None
    scale_error: float
    scale_se: float
    near_misses: int
    near_misses_expected: float
    near_inner_m: float
    near_outer_m: float
    predicted_error_m: float
    distortion_error_m: float
    predicted_rotation_deg: float
    distortion_rotation_deg: float
    inliers_beyond_chance: float
    required_inliers: int
    chance_inliers: float
    num_associations: int
    competitor: int
    distortion_fitted: bool = False  # the distortion allowance was fitted from the maps, not from stated bounds


def verify(ev: Evidence, cfg: LocalizationConfig) -> list[Check]:
    """The acceptance tests of a hypothesis as a table of named checks, in the order their
    reasons are reported (the first failing check is the reason of a refusal). Every check is
    evaluated, so the table shows all that fail, not only the first. A pose is trusted only
    when every check passes."""
    out = [
        _at_most("residual_rmse", ev.rmse_m, ev.rmse_limit_m,
                 f"residual RMSE {ev.rmse_m * 100:.1f} cm exceeds {ev.rmse_limit_m * 100:.1f} cm (what landmarks of "
                 f"{ev.sigma_h_m * 100:.1f} cm horizontal / {ev.sigma_z_m * 100:.1f} cm vertical uncertainty allow)",
                 f"chi-square test of the inlier residuals at {cfg.rmse_confidence:g} confidence"),
        _at_least("extent", ev.extent_m, cfg.min_extent_m,
                  f"inliers are clustered (extent {ev.extent_m:.2f} m < {cfg.min_extent_m} m)",
                  "inliers spread (2 x largest principal std, m)"),
        _at_least("planarity", ev.planarity, cfg.min_planarity,
                  "inliers are nearly collinear: rotation about their line is poorly fixed",
                  "inliers not collinear (second / first principal std)"),
    ]
    if ev.tilt_deg is not None:
        lim = cfg.max_tilt_deg + 0.5
        out.append(_at_most("tilt", ev.tilt_deg, lim,
                            f"fitted tilt {ev.tilt_deg:.2f} deg exceeds the allowed {cfg.max_tilt_deg} deg "
                            "(mirror or wrong match)", "fitted tilt of the levelled map (deg)"))
    if ev.handedness is not None:
        out.append(_at_least("handedness", ev.handedness, cfg.min_handedness,
                             "inliers are a mirror image of the reference (triangle orientations disagree)",
                             "share of inlier triangles with the reference's orientation"))
    scale_lim = max(cfg.max_scale_error, cfg.scale_sigmas * ev.scale_se)
    out.append(_at_most("scale", abs(ev.scale_error), scale_lim,
                        f"vehicle map is not rigid: its inliers are {ev.scale_error * 100:+.1f} % larger than the "
                        f"reference (+-{ev.scale_se * 100:.1f} %), as odometry scale drift makes them",
                        "relative scale of the inliers against the reference"))
    near_z = (ev.near_misses - ev.near_misses_expected) / math.sqrt(max(ev.near_misses_expected, 1.0))
    near_ok = not (ev.near_misses >= cfg.min_near_misses and near_z > cfg.max_near_miss_z)
    out.append(Check(
        "near_misses", near_z, cfg.max_near_miss_z, near_ok, "<=",
        "excess of landmarks just outside the inlier radius over chance (standard deviations; "
        f"{ev.near_misses} seen, {ev.near_misses_expected:.1f} expected)" if near_ok else
        f"vehicle map is not rigid: {ev.near_misses} of its landmarks land {ev.near_inner_m * 100:.0f}-"
        f"{ev.near_outer_m * 100:.0f} cm from a reference rock where chance gives {ev.near_misses_expected:.1f} "
        "(scaled or bent by odometry drift away from the inliers)"))
    source = "fitted from the maps, no odometry bounds stated" if ev.distortion_fitted else "from the odometry bounds"
    out.append(_at_most(
        "predicted_error", cfg.predicted_error_sigmas * ev.predicted_error_m, cfg.max_predicted_error_m,
        f"pose too uncertain where it is used: predicted error up to {cfg.predicted_error_sigmas:g} x "
        f"{ev.predicted_error_m * 100:.1f} cm (allowed {cfg.max_predicted_error_m * 100:.0f} cm"
        f"{'' if ev.distortion_error_m == 0 else f'; odometry distortion up to {ev.distortion_error_m * 100:.1f} cm, {source}'})"
        + (": the maps cannot show the odometry beyond the rocks they share; state its bounds (0 for a map built "
           "from ground-truth poses) to judge with them" if ev.distortion_fitted and ev.distortion_error_m > 0 else ""),
        "predicted position error where the pose is used (m)"))
    out.append(_at_most(
        "predicted_rotation", cfg.predicted_error_sigmas * ev.predicted_rotation_deg, cfg.max_predicted_rotation_deg,
        f"heading too uncertain: predicted rotation error {cfg.predicted_error_sigmas:g} x "
        f"{ev.predicted_rotation_deg:.2f} deg (allowed {cfg.max_predicted_rotation_deg:g} deg; odometry heading "
        f"drift up to {ev.distortion_rotation_deg:.2f} deg, {source})",
        "predicted rotation error (deg)"))
    out.append(_at_least(
        "inliers_vs_chance", ev.inliers_beyond_chance, ev.required_inliers,
        f"{ev.inliers} inliers ({ev.inliers_beyond_chance:.1f} when refinement's chance matches are discounted) is "
        f"too few to beat chance at {ev.num_associations} associations (need {ev.required_inliers}; "
        f"unrelated maps of this size give up to ~{ev.chance_inliers:.0f})",
        "inliers (refinement's chance matches discounted) against the chance envelope plus margin"))
    out.append(_at_least(
        "winner_margin", ev.inliers, cfg.competitor_ratio * ev.competitor,
        f"ambiguous: {ev.inliers} inliers vs a competing hypothesis with {ev.competitor}",
        f"inliers against {cfg.competitor_ratio:g} x the best competing hypothesis"))
    return out


# --------------------------------------------------------------------------- main entry


def localize(
    reference: LandmarkMap, vehicle: LandmarkMap, config: LocalizationConfig | None = None,
    query_xyz: np.ndarray | None = None, path_xyz: np.ndarray | None = None,
) -> LocalizationResult:
    """Find ``T_ref_veh`` aligning `vehicle` to `reference`, or say why it can't be trusted.

    `query_xyz` (k, 3), vehicle frame: where the pose will be used (e.g. the rover's current
    position); the predicted error is judged there. Default: every vehicle landmark.
    `path_xyz` (F, 3), vehicle frame: the odometry path that built the vehicle map, to
    measure how far the rover travelled between the inliers and the query points (heading
    drift accumulates with it; see :func:`distortion_allowance`).

    Raises InputError / DegenerateGeometryError for unusable input (empty maps, fewer
    than 3 landmarks, coincident or collinear landmarks). A failed localization is not
    an error: it returns ``success=False`` with a reason.
    """
    # 1. the maps and the settings for them (a map without heights: 2D + yaw)
    reference, vehicle, cfg = _prepare(reference, vehicle, config)
    P = _Problem(reference, vehicle, cfg, timings={})
    # 2. all-to-all putative associations, and the inliers chance alone would give
    P.associate()
    if P.num_associations == 0:
        return P.refused("associations", 0, 1, ">=", "no putative associations (size pruning removed all)")
    # 3. the densest consistent set (one sparse graph per yaw bin in gravity mode)
    screen = P.search()
    if screen is not None and not screen.passed:
        return P.refused("screen", screen.score, screen.needed, ">=", _screen_reason(screen, cfg, P.required))
    if len(P.best) < 3:
        return P.refused("consistent_set", len(P.best), 3, ">=",
                         f"no consistent set of 3 or more associations (largest: {len(P.best)})")
    # 4. Arun's SVD on the set, refinement, robust re-weighting
    why = P.register()
    if why is not None:
        return P.refused("registration", float("nan"), float("nan"), "<=", why, inliers=P.inl)
    # 5. the error budget where the pose is used: registration, odometry distortion, chance
    budget = P.error_budget(query_xyz, path_xyz)
    # 6. the competing hypothesis and the table of named checks
    return P.verify(budget, screen)


def _prepare(reference, vehicle, config):
    """The maps and the config localize() works with: a config of the right type, maps
    without heights (a rock catalogue from above) flattened to 2D + yaw, the per-map settings."""
    if config is not None:
        from lunarloc.core.validate import instance

        instance(config, "config", LocalizationConfig, "lunarloc.LocalizationConfig")
    prepare_kernels()  # first call of a process: compile or load the kernels before any stage timer starts
    if isinstance(reference, LandmarkMap) and isinstance(vehicle, LandmarkMap) and not (
        reference.has_heights and vehicle.has_heights
    ):
        # a map without heights (a rock catalogue from above): associate and register in
        # 2D + yaw; the pose's height, roll and pitch are not determined (left 0)
        reference, vehicle = _flattened(reference), _flattened(vehicle)
        config = replace(config or LocalizationConfig(), mode=Mode.GRAVITY, registration=Registration.YAW)
    _check_map(reference, "reference")
    _check_map(vehicle, "vehicle")
    return reference, vehicle, (config or LocalizationConfig()).for_maps(reference, vehicle)


def _screen_reason(screen, cfg, required: int) -> str:
    return (f"no consistent set large enough: the best of {screen.candidates} candidate poses voted by the "
            f"reference's rock triangles has {screen.score:.1f} inliers beyond chance ({screen.inliers} in all), "
            f"under {cfg.screen_fraction:g} x the {required} acceptance needs; the exhaustive search "
            f"(~{screen.incidences:.2g} graph edges) was not run")


@dataclass
class _Budget:
    """What :meth:`_Problem.error_budget` found at the query points."""

    query: np.ndarray
    C_c: np.ndarray
    centre_ref: np.ndarray
    pred_fit: np.ndarray
    pred: np.ndarray
    distortion: np.ndarray
    distortion_rot: np.ndarray
    pred_rot_deg: float
    bend: object
    k_chance: float
    near: int
    near_exp: float
    near_outer: float
    dscale: float
    scale_se: float


class _Problem:
    """One localize() call's state, step by step (each step one method)."""

    def __init__(self, reference: LandmarkMap, vehicle: LandmarkMap, cfg: LocalizationConfig, timings: dict):
        self.reference, self.vehicle, self.cfg, self.timings = reference, vehicle, cfg, timings
        self.Pr, self.Pv = reference.positions_xyz, vehicle.positions_xyz
        self.sigma_h, self.sigma_z = combined_sigma(reference, vehicle, cfg)
        self.built_from_detections = sum(m.sightings is not None for m in (reference, vehicle))  # 0, 1 or 2 maps
        self.required, self.num_associations, self.num_edges = 0, 0, 0
        self.best, self.inl = [], np.zeros((0, 2), int)

    def base(self) -> dict:
        """The result fields every outcome after the association step carries."""
        return dict(required_inliers=self.required, num_associations=self.num_associations,
                    num_edges=self.num_edges, timings=self.timings)  # fmt: skip

    def refused(self, name, value, limit, op, why, inliers=None) -> LocalizationResult:
        """A result that says why not: one failed check, no pose."""
        fields = self.base() if name != "associations" else dict(required_inliers=self.required, timings=self.timings)
        if name == "screen":
            fields.pop("num_edges")
        if name in ("consistent_set", "registration"):
            fields["clique_size"] = len(self.best)
        return LocalizationResult(False, _nan_T(), np.zeros((0, 2), int) if inliers is None else inliers,
                                  float("nan"), why, checks=[Check(name, value, limit, False, op, why)], **fields)

    def associate(self) -> None:
        cfg, t0 = self.cfg, time.perf_counter()
        self.assoc, self.node_of = putative_associations(
            len(self.Pv), len(self.Pr), self.vehicle.sizes, self.reference.sizes, cfg.max_size_ratio
        )
        self.num_associations = m = len(self.assoc)
        self.timings["associations"] = time.perf_counter() - t0
        self.chance = chance_clique_size(m, cfg.mode, cfg.epsilon_m, cfg.epsilon_z_m)
        self.required = max(cfg.min_inliers, int(math.ceil(self.chance + cfg.chance_margin)))

    def search(self):
        """The densest consistent set and its competitor; the screen's verdict (None: not run)."""
        cfg, t0 = self.cfg, time.perf_counter()
        if cfg.mode is Mode.GRAVITY:
            report: dict = {}
            self.best, self.competitor, self.best_yaw, self.num_edges = _search_yaw_bins(
                self.Pv, self.Pr, self.node_of, cfg, self.required, report)
        else:
            self.best, self.competitor, self.num_edges = _search_3d(self.Pv, self.Pr, self.node_of, self.assoc, cfg)
            self.best_yaw, report = None, {}
        screen = report.get("screen")
        if screen is not None:
            self.timings["screen"] = report["screen_s"]
            if not screen.passed:
                return screen
        self.timings["search"] = time.perf_counter() - t0 - self.timings.get("screen", 0.0)
        return screen

    def register(self) -> str | None:
        """T and the inliers (None), or why the set cannot be registered."""
        cfg, Pv, Pr = self.cfg, self.Pv, self.Pr
        self.t_register = time.perf_counter()
        self.inl = inl = self.assoc[self.best]
        try:
            T = _register(Pv[inl[:, 0]], Pr[inl[:, 1]], cfg)
        except DegenerateGeometryError as exc:
            self.timings["registration"] = time.perf_counter() - self.t_register
            return f"inliers are degenerate: {exc}"
        if cfg.refine:
            T, inl = _refine(T, Pv, Pr, inl, cfg)
        try:
            T_w, w = _register_robust(Pv[inl[:, 0]], Pr[inl[:, 1]], cfg, T) if cfg.refine else (T, np.ones(len(inl)))
            T = T_w
        except DegenerateGeometryError:
            w = np.ones(len(inl))
        self.T, self.inl, self.w = T, inl, w
        return None

    def error_budget(self, query_xyz, path_xyz) -> _Budget:
        """The predicted error at the query points: the registration's covariance, the
        odometry's distortion (stated bounds, or fitted from the maps with a prior), chance."""
        cfg, T, Pv, Pr, inl, w = self.cfg, self.T, self.Pv, self.Pr, self.inl, self.w
        query = Pv if query_xyz is None else as_points(query_xyz, "query points")
        C_c, centre_ref = pose_covariance(T, Pv[inl[:, 0]], Pr[inl[:, 1]], w, cfg.registration_sigma_floor_m)
        # plus the error the inliers share and their residuals cannot show (CENTRE_BIAS_M): each map
        # built from detections (sightings given) brings its own centre bias, measured for two
        C_c = C_c + self.built_from_detections / 2 * shared_bias_covariance(cfg.centre_bias_m, cfg.centre_bias_yaw_deg)
        pred_fit = error_at(C_c, centre_ref, T, query)
        path = None if path_xyz is None else as_points(path_xyz, "vehicle path")
        bend = None
        if cfg.odometry_bounds_stated:
            distortion, distortion_rot = distortion_allowance(
                query, Pv[inl[:, 0]], w, cfg.odometry_scale_error or 0.0,
                math.radians(cfg.odometry_heading_drift_deg_per_m or 0.0), path,
            )
        else:  # no bounds stated: what the maps show of a bend or scale error, and how unsure that is
            distortion, distortion_rot = np.array([math.inf]), np.array([math.inf])
            if len(inl) >= cfg.min_inliers_distortion_fit:
                bend = self._fitted_bend(query, path)
        pred = pred_fit + distortion  # the distortion is a bound (a bias), not a random error: added, not in quadrature
        rot_sigma = math.sqrt(max(float(np.max(np.linalg.eigvalsh(C_c[3:, 3:]))), 0.0)) if np.all(np.isfinite(C_c)) else math.inf
        pred_rot_deg = math.degrees(rot_sigma + float(distortion_rot.max()))
        if bend is not None:  # the registration counted once, with the bend's own uncertainty
            pred, pred_rot_deg = fitted_predicted_error(bend, cfg, pred_fit, math.degrees(rot_sigma))
            distortion, distortion_rot = pred - pred_fit, np.array([math.radians(pred_rot_deg) - rot_sigma])
        # the chance envelope was measured on consistent cores: refinement's chance additions
        # (more of them with a wider refinement radius) do not count towards beating it
        core = len(self.best)
        chance_gain = chance_refined(T, Pv, Pr, self.assoc[self.best][:, 0], cfg.refine_radius_m) if cfg.refine else 0.0
        k_chance = min(len(inl), core + max(0.0, len(inl) - core - chance_gain))
        near_outer = max(cfg.near_miss_outer_m, 3 * cfg.refine_radius_m)
        near, near_exp = near_miss_excess(T, Pv, Pr, inl[:, 0], cfg.refine_radius_m, near_outer)
        dscale, scale_se = scale_check(T, Pv[inl[:, 0]], Pr[inl[:, 1]], w, cfg.registration_sigma_floor_m)
        self.timings["registration"] = time.perf_counter() - self.t_register
        return _Budget(query, C_c, centre_ref, pred_fit, pred, distortion, distortion_rot, pred_rot_deg, bend,
                       k_chance, near, near_exp, near_outer, dscale, scale_se)  # fmt: skip

    def _fitted_bend(self, query, path):
        """The bend fitted from the maps alone, then with the odometry prior where the maps agree."""
        cfg, vehicle = self.cfg, self.vehicle
        arcs = ((vehicle.sighting_arc_m, vehicle.sighting_arc_min_m, vehicle.sighting_arc_max_m)
                if vehicle.has_sighting_arcs else None)
        fit_args = (self.T, self.Pv, self.Pr, self.inl, query, path,
                    math.sqrt((2 * self.sigma_h**2 + self.sigma_z**2) / 3),
                    cfg.refine_radius_m, cfg.distortion_fit_rounds, arcs, cfg.max_sighting_span_m,
                    cfg.min_inliers_distortion_fit)
        bend = bending_fit(*fit_args)  # from the maps alone
        prior = (None if cfg.odometry_prior_drift_deg_per_m is None else math.radians(cfg.odometry_prior_drift_deg_per_m),
                 cfg.odometry_prior_scale_error)
        # the prior is per metre of the odometry's path: without the path (a straight stand-in)
        # there is no distance travelled for it to describe. It also narrowed a 6 m map against
        # a LAC grid below its quantisation's error (tests/test_sighting_arcs.py)
        if path is not None and any(v is not None for v in prior):
            conflict = prior_conflict(bend, *prior)
            if conflict <= PRIOR_CONFLICT_SIGMAS:
                bend = bending_fit(*fit_args, *prior)
                bend.prior = "applied"
            else:  # the maps show a bend real odometry does not make: the prior does not describe them
                bend.prior = f"rejected: the maps' bend is {conflict:.1f} sigma from the prior"
        return bend

    def verify(self, b: _Budget, screen) -> LocalizationResult:
        """The competing hypothesis, the result, and the table of named checks deciding it."""
        cfg, T, Pv, Pr, inl = self.cfg, self.T, self.Pv, self.Pr, self.inl
        # competitor in 6-DoF mode: best set among associations the winner does not explain
        t0 = time.perf_counter()
        if cfg.mode is Mode.SIX_DOF:
            competitor = _competitor_3d(T, Pv, Pr, self.node_of, self.assoc, cfg)
        else:
            competitor = max(self.competitor, _competitor_same_yaw(T, Pv, Pr, self.node_of, self.assoc, cfg,
                                                                   self.best_yaw, self.competitor))  # fmt: skip
        self.timings["verification"] = time.perf_counter() - t0

        res = _residuals(T, Pv[inl[:, 0]], Pr[inl[:, 1]])
        rmse = float(np.sqrt(np.mean(res**2)))
        R = T[:3, :3]
        out = LocalizationResult(
            False, T, inl, rmse, "", clique_size=len(self.best), competitor_size=int(competitor),
            predicted_error_m=float(b.pred.max()), scale_error=b.dscale,
            yaw_deg=math.degrees(yaw_of(R)), tilt_deg=math.degrees(tilt_angle(R)),
            distortion_error_m=float(b.distortion.max()), predicted_rotation_deg=b.pred_rot_deg,
            near_misses=b.near, near_misses_expected=b.near_exp,
            covariance=covariance_at_origin(b.C_c, b.centre_ref) + distortion_covariance(
                transform_points(T, b.query[int(np.argmax(b.pred_fit + b.distortion))][None])[0],
                float(b.distortion.max()), float(b.distortion_rot.max())),
            distortion_fit={} if b.bend is None else asdict(b.bend), **self.base(),
        )
        Q = Pr[inl[:, 1]]
        s = np.linalg.svd(Q - Q.mean(axis=0), compute_uv=False) / math.sqrt(len(Q))
        k = len(inl)
        gravity = cfg.mode is Mode.GRAVITY
        ev = Evidence(
            inliers=k, rmse_m=rmse, rmse_limit_m=rmse_limit(cfg, self.sigma_h, self.sigma_z, k),
            sigma_h_m=self.sigma_h, sigma_z_m=self.sigma_z,
            extent_m=2 * s[0], planarity=s[1] / max(s[0], 1e-12),
            tilt_deg=out.tilt_deg if gravity else None,
            handedness=_handedness(Pv[inl[:, 0]], Q, np.random.default_rng(0)) if gravity else None,
            scale_error=b.dscale, scale_se=b.scale_se, near_misses=b.near, near_misses_expected=b.near_exp,
            near_inner_m=cfg.refine_radius_m, near_outer_m=b.near_outer,
            predicted_error_m=float(b.pred.max()), distortion_error_m=float(b.distortion.max()),
            predicted_rotation_deg=b.pred_rot_deg, distortion_rotation_deg=math.degrees(float(b.distortion_rot.max())),
            inliers_beyond_chance=b.k_chance, required_inliers=self.required, chance_inliers=self.chance,
            num_associations=self.num_associations, competitor=int(competitor), distortion_fitted=b.bend is not None,
        )
        out.checks = verify(ev, cfg)
        if screen is not None:  # it passed: shown first, as a check that refuses nothing further
            out.checks.insert(0, Check("screen", screen.score, screen.needed, True, ">=",
                                       "inliers beyond chance at the best pose voted by the reference's rock triangles"))
        failed = [c for c in out.checks if not c.passed]
        out.success = not failed
        out.reason = failed[0].detail if failed else "ok"
        log.info("localize: %s (%d inliers, rmse %.3f m)", out.reason, k, rmse)
        return out


def _search_3d(Pv, Pr, node_of, assoc, cfg):
    g = graph_3d(Pv, Pr, node_of, cfg.epsilon_m, cfg.sigma, cfg.max_edges)
    if g is None:
        raise InputError(
            f"the 6-DoF consistency graph of {len(assoc)} associations exceeds {cfg.max_edges} edges; "
            "use the gravity-aware mode, a smaller epsilon, size pruning, or raise max_edges"
        )
    eu, ev, ew = g
    best = _solve(cfg.solver, len(assoc), eu, ev, ew, 0, cfg.seed)
    return best, 0, len(eu)


def _explained(T, Pv, Pr, assoc, radius):
    """Associations consistent with T (their landmarks land within `radius`)."""
    d = np.linalg.norm(transform_points(T, Pv)[assoc[:, 0]] - Pr[assoc[:, 1]], axis=1)  # each landmark moved once
    return d < radius


def _competitor_3d(T, Pv, Pr, node_of, assoc, cfg):
    explained = _explained(T, Pv, Pr, assoc, 3 * cfg.epsilon_m)
    node2 = node_of.copy()
    node2[assoc[explained, 0], assoc[explained, 1]] = -1
    keep = node2[assoc[:, 0], assoc[:, 1]] >= 0
    g = graph_3d(Pv, Pr, node2, cfg.epsilon_m, cfg.sigma, cfg.max_edges)
    if g is None or not np.any(keep):
        return 0
    eu, ev, ew = g
    return len(_solve(cfg.solver, len(assoc), eu, ev, ew, 0, cfg.seed))


def _n_bins(cfg) -> int:
    return max(1, int(round(360.0 / cfg.yaw_step_deg)))


def _sweep(Pv, Pr, node_of, cfg, visit, bin_start: int = 0, bin_count: int | None = None) -> int:
    """Run `visit(bin, theta, eu, ev, ew)` on the consistency graph of every yaw bin."""
    n_bins = _n_bins(cfg)
    return sweep_yaw_bins(
        vehicle_pairs(Pv), _ref_index(Pr, cfg), node_of, n_bins, _chunk_bins(cfg), *_graph_args(cfg), visit,
        weights=cfg.solver is Solver.CLIPPER, bin_start=bin_start, bin_count=bin_count, workers=cfg.threads,
    )


def _chunk_bins(cfg) -> int:
    return max(1, _n_bins(cfg) // 8)


def _graph_args(cfg) -> tuple:
    """(eps_h, eps_z, tan_tilt, k_yaw, sigma) of the yaw-bin consistency graphs."""
    return (cfg.epsilon_m, cfg.epsilon_z_m, math.tan(math.radians(cfg.max_tilt_deg)), cfg.yaw_noise_factor, cfg.sigma)


_PARALLEL_MIN_WORK = 2e8  # vehicle pairs x reference pairs below which a sweep runs on the calling thread


def _workers(cfg, vp, index: RefPairIndex, share: float = 1.0) -> int:
    """Threads for a sweep over `share` of the yaw circle: one when the work is small
    (handing chunks to other threads then costs more than it saves)."""
    return cfg.threads if len(vp[0]) * len(index.a) * share >= _PARALLEL_MIN_WORK else 1


def _ref_index(Pr, cfg) -> RefPairIndex:
    return RefPairIndex(Pr, dist_cell_m=max(cfg.epsilon_m / 2, 0.01), angle_cell_rad=math.radians(1.0))


class _Scratch(threading.local):
    """Per-thread scratch array for the clique solver (int32, filled with -1)."""

    def __init__(self, n: int):
        self.arr = np.full(n, -1, dtype=np.int32)


# Bin bounds: the vehicle landmarks are split into groups (round robin) and the graphs of
# the pairs inside each group are built for every yaw bin (1/groups of the work); a clique
# of the whole graph splits into cliques of the group graphs, so the sum over the groups of
# (degeneracy + 1) bounds each bin's maximum clique. More groups cost less but bound less
# tightly; measured on the 136 real pairs (benchmarks/pair_speed.py), by association count:
_BOUND_GROUPS = ((2_500, 1), (10_000, 2), (50_000, 4))  # (fewer associations than, groups); else 8


def _bound_groups(n_assoc: int) -> int:
    for limit, groups in _BOUND_GROUPS:
        if n_assoc < limit:
            return groups
    return 8


def _bin_bounds(Pv, vp, index, node_of, cfg) -> tuple[np.ndarray, np.ndarray, int]:
    """(upper, lower) bound on the maximum clique of every yaw bin's consistency graph, and
    the edges generated to find them. Upper: sum over groups of vehicle landmarks of the
    group graph's degeneracy + 1 (any clique of the bin puts at most that many of its
    members in each group); lower: the largest greedy clique of a group graph (a clique of
    the bin's graph too). Without groups (small vehicle maps): (inf, 0)."""
    n_bins = _n_bins(cfg)
    groups = min(_bound_groups(int(np.count_nonzero(node_of >= 0))), max(1, len(Pv) // 8))
    if groups == 1:
        return np.full(n_bins, np.iinfo(np.int64).max, dtype=np.int64), np.zeros(n_bins, dtype=np.int64), 0
    upper = np.zeros(n_bins, dtype=np.int64)
    lower = np.ones(n_bins, dtype=np.int64)
    scratch = _Scratch(int(node_of.size))
    lock = threading.Lock()
    chunks = yaw_bin_chunks(n_bins, _chunk_bins(cfg), range(n_bins))
    pi, pj = vp[0], vp[1]
    # threads by the bounds' whole work (every group's pairs against the reference pairs), as
    # the groups run one after another: many small group sweeps add up to one large one
    workers = _workers(cfg, vp, index, 1.0 / groups)
    edges = 0
    for g in range(groups):
        sel = (pi % groups == g) & (pj % groups == g)
        vpg = tuple(x[sel] for x in vp)

        def visit_chunk(bins, ptr, su, sv, _sw):
            ub, lb = bin_clique_bounds(ptr, su, sv, scratch.arr)
            with lock:
                upper[bins] += np.maximum(ub, 1)  # a group with no edge in a bin still holds one member
                np.maximum.at(lower, bins, lb)

        edges += sweep_bin_chunks(vpg, index, node_of, n_bins, chunks, *_graph_args(cfg), visit_chunk,
                                  weights=False, workers=workers)
    return upper, lower, edges


class _BestYaw(float):
    """The winning relative yaw (rad), carrying what the search learnt (reference pair index,
    per-bin clique bounds, winning size) so that the same-yaw competitor search reuses it."""

    index: RefPairIndex
    upper: np.ndarray
    best_size: int
    edges: dict | None  # bin -> (eu, ev) of the bins the search built (exact solver, up to _EDGE_CACHE_MAX)


_EDGE_CACHE_MAX = 8_000_000
"""Edges (8 bytes each) of the built bins the search keeps for the same-yaw competitor
search, which needs the graphs of the bins around the winner again (13-15: 1.4 million
edges in all); beyond it the competitor rebuilds the bins it needs."""


def _far_pairs_floor(values: np.ndarray, n_bins: int, sep_bins: float) -> int:
    """Largest min(v_x, v_y) over bins x, y more than 2 * sep apart: whatever the winning
    yaw, one of the two is more than sep from it, so the competitor is at least this."""
    far = _far_mask(n_bins, 2 * sep_bins)
    if not far.any():
        return 0
    return int(np.minimum(values[:, None], values[None, :])[far].max())


@functools.lru_cache(maxsize=8)
def _far_mask(n_bins: int, min_sep_bins: float) -> np.ndarray:
    """Boolean (n_bins, n_bins): bins more than `min_sep_bins` apart around the circle."""
    b = np.arange(n_bins)
    d = np.abs(b[:, None] - b[None, :])
    return np.minimum(d, n_bins - d) > min_sep_bins


def _search_yaw_bins(Pv, Pr, node_of, cfg, required: int | None = None, report: dict | None = None):
    """Max consistent set over relative-yaw bins; also the best set whose yaw differs
    by more than competitor_yaw_sep_deg (the competing hypothesis).

    Exact, bin by bin, but only where a bin can matter: cheap per-bin clique bounds
    (:func:`_bin_bounds`) order the bins; the most promising bin is solved first, and
    then only bins whose bound exceeds ``lb = max(floor(best / competitor_ratio), known
    competitor floor)`` are built and searched, each for a clique larger than lb. Hence:
    the winner is the largest clique of any bin (ties: smallest yaw), found exactly; the
    competitor is exact whenever it exceeds best / competitor_ratio (when it can decide
    the ambiguity test, as the inlier count is at least the clique size), otherwise a
    lower bound on it (a clique found in a far bin).

    With `required` (the inliers acceptance needs), a search that would be large is screened
    first (:func:`_screen`, its outcome in ``report["screen"]``); when the screen refuses,
    nothing is built and no set is returned."""
    n_assoc = int(node_of.size)
    n_bins = _n_bins(cfg)
    step = 2 * math.pi / n_bins
    sep_bins = math.radians(cfg.competitor_yaw_sep_deg) / step
    index = _ref_index(Pr, cfg)
    vp = vehicle_pairs(Pv)
    if required is not None:
        t0 = time.perf_counter()
        screen = _screen(Pv, Pr, cfg, required, vp, index)
        if report is not None and screen is not None:
            report["screen"], report["screen_s"] = screen, time.perf_counter() - t0
        if screen is not None and not screen.passed:
            return np.empty(0, dtype=np.int32), 0, None, 0
    upper, lower, total_edges = _bin_bounds(Pv, vp, index, node_of, cfg)
    found: dict[int, np.ndarray] = {}
    state = {"best": 0, "floor": _far_pairs_floor(lower, n_bins, sep_bins)}
    lock = threading.Lock()
    scratch = _Scratch(n_assoc)

    def lb_now() -> int:
        return max(int(state["best"] // cfg.competitor_ratio), state["floor"])

    edges = {} if cfg.solver is Solver.EXACT else None  # clique sizes do not depend on edge order
    kept = [0]

    def visit_chunk(bins, ptr, su, sv, sw):
        if edges is not None:
            with lock:
                if kept[0] + len(su) <= _EDGE_CACHE_MAX:
                    kept[0] += len(su)
                    for t, b in enumerate(bins):
                        edges[b] = (su[ptr[t]:ptr[t + 1]], sv[ptr[t]:ptr[t + 1]])
        for t in sorted(range(len(bins)), key=lambda t: -upper[bins[t]]):
            b = bins[t]
            with lock:
                lb = lb_now()
            if upper[b] <= lb or ptr[t + 1] - ptr[t] < lb * (lb + 1) // 2:
                continue
            sl = slice(ptr[t], ptr[t + 1])
            c = _solve(cfg.solver, n_assoc, su[sl], sv[sl], sw[sl], lb, cfg.seed, scratch.arr)
            if len(c) == 0:
                continue
            with lock:
                found[b] = c
                state["best"] = max(state["best"], len(c))
                for b2, c2 in found.items():
                    d = abs(b - b2)
                    if min(d, n_bins - d) > 2 * sep_bins:
                        state["floor"] = max(state["floor"], min(len(c), len(c2)))

    def sweep(bins) -> int:
        chunks = yaw_bin_chunks(n_bins, _chunk_bins(cfg), bins)
        chunks.sort(key=lambda c: -int(upper[c[0] + c[1]: c[0] + c[2] + 1].max()))
        share = sum(c[2] - c[1] + 1 for c in chunks) / n_bins
        return sweep_bin_chunks(vp, index, node_of, n_bins, chunks, *_graph_args(cfg), visit_chunk,
                                weights=cfg.solver is Solver.CLIPPER, workers=_workers(cfg, vp, index, share))

    top = int(np.argmax(upper))
    if upper[top] < np.iinfo(np.int64).max:
        total_edges += sweep([top])  # the most promising bin first: its clique raises lb for the rest
    lb = lb_now()
    rest = [b for b in np.flatnonzero(upper > lb).tolist() if b not in found]
    total_edges += sweep(rest)

    if not found:
        return np.empty(0, dtype=np.int32), 0, None, total_edges
    size = max(len(c) for c in found.values())
    b_best = min(b for b, c in found.items() if len(c) == size)

    far = _far_mask(n_bins, sep_bins)[b_best]
    second = max([state["floor"], int(lower[far].max(initial=0))] + [len(c) for b, c in found.items() if far[b]])
    best_yaw = _BestYaw(-math.pi + (b_best + 0.5) * step)
    best_yaw.index, best_yaw.upper, best_yaw.best_size, best_yaw.edges = index, upper, size, edges
    return found[b_best], int(second), best_yaw, total_edges


def _competitor_same_yaw(T, Pv, Pr, node_of, assoc, cfg, best_yaw, floor: int = 0):
    """Best set near the winner's yaw among associations the winner does not explain
    (a shifted copy of the pattern at the same heading). Like the main search, exact when
    it exceeds best / competitor_ratio (or `floor`), otherwise `floor` is returned."""
    if best_yaw is None:
        return 0
    explained = _explained(T, Pv, Pr, assoc, 3 * cfg.epsilon_m)
    node2 = node_of.copy()
    node2[assoc[explained, 0], assoc[explained, 1]] = -1
    n_bins = _n_bins(cfg)
    step = 2 * math.pi / n_bins
    centre = int(math.floor((best_yaw + math.pi) / step))
    reach = int(math.ceil(math.radians(cfg.competitor_yaw_sep_deg) / step))
    bins = [(centre + t) % n_bins for t in range(-reach, reach + 1)]
    lb0 = floor
    index = None
    if isinstance(best_yaw, _BestYaw):  # reuse the main search's index and bounds
        index = best_yaw.index
        lb0 = max(floor, int(best_yaw.best_size // cfg.competitor_ratio))
        bins = [b for b in bins if best_yaw.upper[b] > lb0]  # removing associations only lowers the bound
    if not bins:
        return floor
    state = {"best": lb0}  # only a set larger than this can matter
    lock = threading.Lock()
    scratch = _Scratch(int(node_of.size))
    n_assoc = int(node_of.size)

    def visit_chunk(bins_, ptr, su, sv, sw):
        for t in range(len(bins_)):
            if ptr[t + 1] > ptr[t]:
                sl = slice(ptr[t], ptr[t + 1])
                c = _solve(cfg.solver, n_assoc, su[sl], sv[sl], sw[sl], state["best"], cfg.seed, scratch.arr)
                with lock:
                    state["best"] = max(state["best"], len(c))

    cached = best_yaw.edges if isinstance(best_yaw, _BestYaw) and best_yaw.edges is not None else {}
    if any(b in cached for b in bins):
        # a bin the search built: its graph without the explained associations is its edges
        # minus those touching them (the same edges the rebuild below would give, in
        # another order: the maximum clique's size, all that is kept, is the same)
        removed = np.zeros(n_assoc, dtype=bool)
        removed[node_of[assoc[explained, 0], assoc[explained, 1]]] = True
        for b in [b for b in bins if b in cached]:
            eu, ev = cached[b]
            keep = ~(removed[eu] | removed[ev])
            if keep.any():
                eu, ev = eu[keep], ev[keep]
                c = _solve(cfg.solver, n_assoc, eu, ev, eu, state["best"], cfg.seed, scratch.arr)
                state["best"] = max(state["best"], len(c))
        bins = [b for b in bins if b not in cached]
        if not bins:
            return state["best"] if state["best"] > lb0 else floor
    vp = vehicle_pairs(Pv)
    index = index if index is not None else _ref_index(Pr, cfg)
    sweep_bin_chunks(vp, index, node2, n_bins, yaw_bin_chunks(n_bins, _chunk_bins(cfg), bins), *_graph_args(cfg),
                     visit_chunk, weights=cfg.solver is Solver.CLIPPER,
                     workers=_workers(cfg, vp, index, len(bins) / n_bins))
    return state["best"] if state["best"] > lb0 else floor


# --------------------------------------------------------------------------- screen


def predicted_incidences(Pv: np.ndarray, Pr: np.ndarray, cfg: LocalizationConfig, vp=None,
                          index: RefPairIndex | None = None) -> float:
    """Estimated size of the gravity-aware search's yaw-bin consistency graphs: edge
    incidences summed over the bins, before the height test (so an over-estimate).

    A vehicle pair of horizontal distance d meets the ordered reference pairs within
    epsilon of d (counted from the distance rows of the search's :class:`RefPairIndex`,
    interpolated within a row), and such a match lands in the ``2 tol / step`` bins around
    its yaw (tol: the generator's yaw tolerance). O(vehicle pairs) given the search's own
    `vp` and `index`. Measured on the 600-rock overhead benchmark at 15 cm: about 1.5x the
    real incidences (``tests/test_screen.py`` checks it stays within 3x)."""
    eps = cfg.epsilon_m
    vp = vehicle_pairs(Pv) if vp is None else vp
    index = _ref_index(Pr, cfg) if index is None else index
    dh, dz = vp[2], vp[4]
    if len(dh) == 0:
        return 0.0
    cum = index.row_ptr.astype(float)  # ordered pairs closer than each distance cell's start
    cells = np.arange(len(cum)) * index.dist_cell
    within = np.interp(dh + eps, cells, cum) - np.interp(np.maximum(dh - eps, 0.0), cells, cum)
    step = 2 * math.pi / _n_bins(cfg)
    dmin = dh - eps
    k_eps = cfg.yaw_noise_factor * eps
    tan_tilt = math.tan(math.radians(cfg.max_tilt_deg))
    with np.errstate(divide="ignore", invalid="ignore"):
        tol = np.where(dmin > k_eps, 0.5 * step + np.arcsin(np.minimum(k_eps / dmin, 1.0))
                       + tan_tilt * np.abs(dz) / dmin, math.pi)
    bins = np.minimum(np.maximum(2 * tol / step, 1.0), _n_bins(cfg))
    return float(np.sum(within * bins))


_SCREEN_TRIANGLES = 800
"""Vehicle triangles the screen votes with at most: the vote's cost grows with them (a
150-landmark map at 15 cm: 6300 triangles, 117 000 matches, 0.3 s); the true pose keeps its
share of the votes in a sample."""


@dataclass
class Screen:
    """Outcome of :func:`_screen`: the best candidate pose's inliers beyond chance
    (``score``), what passing needs (``needed``), how many candidates were refined, and
    the predicted graph size that made the screen run."""

    passed: bool
    score: float
    needed: float
    candidates: int
    incidences: float
    inliers: int = 0


def _screen(Pv: np.ndarray, Pr: np.ndarray, cfg: LocalizationConfig, required: int, vp=None,
            index: RefPairIndex | None = None) -> Screen | None:
    """Cheap refusal before an exhaustive search that would be large.

    Runs only when the yaw-bin graphs would hold at least ``screen_min_incidences``
    edge incidences (:func:`predicted_incidences`; a 600-rock overhead map at 15 cm holds
    about 70 million, 5-10 s of CPU), else returns None. The reference's rock triangles
    (:class:`~lunarloc.association.index.ReferenceIndex`, at the search's own tolerance)
    vote for poses; each of the ``screen_candidates`` best-voted poses is refined as the
    final hypothesis is (:func:`_refine`, mutual nearest neighbours within the refinement
    radius), and scored by its inliers less the matches chance gives at that pose
    (:func:`chance_refined`). The screen passes when a score reaches ``screen_fraction``
    of the inliers acceptance requires; then the exhaustive search runs as without the
    screen, so the screen can only refuse, never accept, and whatever is accepted is what
    the exact search and verification accept. A vehicle map without a matching triangle
    gives no candidate: the screen passes (it cannot judge) and the exact search decides."""
    if not cfg.screen_min_incidences > 0:
        return None
    incidences = predicted_incidences(Pv, Pr, cfg, vp, index)
    if incidences < cfg.screen_min_incidences:
        return None
    from lunarloc.association.index import IndexConfig, ReferenceIndex

    needed = cfg.screen_fraction * required
    tri = ReferenceIndex(Pr, cfg.epsilon_m, IndexConfig(max_candidates=cfg.screen_candidates))  # rock triangles
    votes = tri.vote(Pv, cfg.epsilon_z_m, math.tan(math.radians(cfg.max_tilt_deg)), _SCREEN_TRIANGLES)
    if not votes.candidates:
        return Screen(True, float("nan"), needed, 0, incidences)
    best, best_inliers = 0.0, 0  # inliers beyond chance: none until a candidate shows some
    for cand in votes.candidates:
        x, y, yaw = _vote_mode(votes.votes_xy_yaw, cand.x_m, cand.y_m, cand.yaw_rad)
        c, s = math.cos(yaw), math.sin(yaw)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = np.array([x, y]) - T[:2, :2] @ votes.centre_xy
        Pt = transform_points(T, Pv)
        d, j = tri.tree_xy.query(Pt[:, :2])  # the vote fixes x, y and yaw; the height from the nearest rocks
        near = d < cfg.refine_radius_m
        if near.sum() < 3:  # nothing to refine from: no more than chance here
            continue
        T[2, 3] = float(np.median((Pr[j, 2] - Pt[:, 2])[near]))
        try:
            T, inl = _refine(T, Pv, Pr, np.zeros((0, 2), np.int64), cfg)
        except (DegenerateGeometryError, InputError):  # fewer than 3 (or collinear) mutual neighbours in 3D
            continue
        score = len(inl) - chance_refined(T, Pv, Pr, np.zeros(0, np.int64), cfg.refine_radius_m)
        if score > best:
            best, best_inliers = score, len(inl)
        if best >= needed:
            break
    return Screen(best >= needed, best, needed, len(votes.candidates), incidences, best_inliers)


def _vote_mode(votes: np.ndarray, x: float, y: float, yaw: float,
               windows=((1.0, 10.0), (0.5, 5.0), (0.25, 2.5), (0.25, 2.5))) -> tuple[float, float, float]:
    """The densest place of the triangle votes (x, y, yaw rad) near a candidate: the median
    of the votes within a window around the estimate, the window shrinking (metres,
    degrees). A candidate is the median of a 6 m x 30 deg neighbourhood that chance votes
    share: 0.4 m and 4 degrees off the true pose on the 600-rock benchmark, too far for
    refinement to lock on; the true votes agree within centimetres."""
    for half_m, half_deg in windows:
        dyaw = (votes[:, 2] - yaw + math.pi) % (2 * math.pi) - math.pi
        near = (np.abs(votes[:, 0] - x) < half_m) & (np.abs(votes[:, 1] - y) < half_m) & (
            np.abs(dyaw) < math.radians(half_deg))
        if near.sum() < 3:
            break
        x, y = float(np.median(votes[near, 0])), float(np.median(votes[near, 1]))
        yaw = float(yaw + np.median(dyaw[near]))
    return x, y, yaw


# --------------------------------------------------------------------------- kernels at first use

_WARM: bool | str = False


def warm_kernels(force: bool = False, jit: bool = False) -> float:
    """Compile (or load from the cache) every association kernel, in every mode and solver.
    Returns the seconds it took (0.0 once done in this process). Public as
    :func:`lunarloc.localization.warmup.warm_up`.

    Where the ahead-of-time kernels are built (:mod:`lunarloc.association.aot`) this only
    loads them; ``jit=True`` runs numba's JIT path even then, compiling into numba's cache
    (``lunarloc warm-up``: the fallback for argument types the build does not hold)."""
    global _WARM
    if _WARM in (("jit", True) if jit else ("jit", "aot", True)) and not force:
        return 0.0
    import contextlib

    from lunarloc.association.aot import exercising, jit_only
    from lunarloc.core.geometry import euler_to_rotation, make_transform, transform_points

    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    # 80 x 40 = 3,200 associations: large enough for the search's per-bin bounds (their
    # kernels compile too), small enough to take a moment once compiled
    ref_xyz = np.c_[rng.uniform(-8, 8, (80, 2)), rng.normal(0, 0.2, 80)]
    T = make_transform(euler_to_rotation(0.0, 0.0, 0.7), np.array([3.0, -2.0, 0.1]))
    veh_xyz = transform_points(np.linalg.inv(T), ref_xyz[:40]) + rng.normal(0, 0.005, (40, 3))
    ref, veh = LandmarkMap(ref_xyz, frame="ref"), LandmarkMap(veh_xyz, frame="veh")
    with exercising(), (jit_only() if jit else contextlib.nullcontext()):
        for mode in Mode:
            for solver in Solver:
                localize(ref, veh, LocalizationConfig(mode=mode, solver=solver))
    _WARM = "jit" if jit else (_WARM or "aot")
    return time.perf_counter() - t0


def prepare_kernels():
    """Once a process: the kernels ready before any stage timer starts (loaded ahead of time,
    from numba's cache, or compiled, announced on the log); see
    :func:`lunarloc.association.aot.prepare_kernels`."""
    from lunarloc.association.aot import prepare_kernels as prepare

    return prepare(warm_kernels)
