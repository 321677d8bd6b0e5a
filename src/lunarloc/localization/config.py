"""Localization settings: the search modes, solvers and registration, and their config."""

from __future__ import annotations

import enum
import math
import os
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from lunarloc.core.configs import check_settings, setting
from lunarloc.core.errors import ConfigError
from lunarloc.io.maps import LandmarkMap


class Mode(str, enum.Enum):
    """Which invariants the consistency graph uses."""

    GRAVITY = (
        "gravity"  # horizontal distance + height difference + common yaw (rover maps, IMU-levelled)
    )
    SIX_DOF = "6dof"  # 3D distance only: any relative rotation


class Registration(str, enum.Enum):
    """Which rigid transform is fitted to the inliers."""

    SE3 = "se3"  # Arun's SVD, full rotation (allows the residual tilt of an IMU-levelled map)
    YAW = "yaw"  # 4-DoF: rotation about the vertical only (maps levelled exactly)


class Solver(str, enum.Enum):
    """How the densest consistent set is found."""

    EXACT = "exact"  # exact maximum clique (robust; default)
    CLIPPER = "clipper"  # CLIPPER relaxation + rounding (the paper's solver)


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
    epsilon_m: float = setting(
        0.05, gt=0.0
    )  # max disagreement of a pairwise (horizontal) distance for consistency
    sigma_m: float | None = setting(
        None, gt=0.0
    )  # CLIPPER weight scale exp(-c^2/2sigma^2); None -> epsilon/2
    epsilon_z_m: float = setting(
        0.05, gt=0.0
    )  # gravity: max disagreement of a height difference (plus tilt allowance)
    max_tilt_deg: float = setting(
        1.5, ge=0.0, lt=45.0
    )  # gravity: residual tilt of the vehicle map after IMU levelling
    yaw_step_deg: float = setting(2.0, gt=0.0)  # gravity: spacing of the relative-yaw bins
    yaw_noise_factor: float = 1.5  # gravity: yaw tolerance of a pair at distance d is asin(k*eps/d)
    max_size_ratio: float | None = setting(
        None, ge=1.0
    )  # prune associations whose size ratio exceeds this (needs sizes)
    max_edges: int = 30_000_000  # 6-DoF memory bound on the consistency graph
    refine: bool = True  # re-fit with mutual nearest neighbours under the estimate
    refine_radius_m: float = setting(
        0.10, gt=0.0
    )  # max residual of a nearest-neighbour pair kept by refinement
    robust_scale_m: float = 0.02  # Cauchy scale of the robust (IRLS) re-weighting in refinement
    irls_rounds: int = setting(5, ge=1, le=100)  # re-weighting rounds of the robust registration
    refine_rounds: int = setting(
        3, ge=1, le=100
    )  # mutual-nearest-neighbour re-fits of refinement (fewer when the inliers settle)
    registration_sigma_floor_m: float = setting(
        0.005, gt=0.0
    )  # floor on the residual noise scale in the covariance, predicted error and scale check
    # --- acceptance (verification) ---
    min_inliers: int = setting(6, ge=3)  # absolute floor on the inlier count
    chance_margin: float = (
        2.5  # inliers must exceed the chance envelope at this map size by this many
    )
    max_rmse_m: float = setting(0.05, gt=0.0)  # residual RMSE of the inliers after registration
    min_extent_m: float = 1.0  # inliers must spread at least this far (largest principal std x 2)
    min_planarity: float = 0.05  # second/first principal std of the inliers (0 = collinear)
    min_handedness: float = 0.9  # gravity: share of inlier triangles with matching orientation
    max_predicted_error_m: float = (
        0.10  # predicted 1-sigma error (x predicted_error_sigmas) at the query points
    )
    predicted_error_sigmas: float = 1.0
    max_predicted_rotation_deg: float = (
        1.0  # predicted 1-sigma rotation error (x predicted_error_sigmas)
    )
    max_scale_error: float = (
        0.005  # a rigid map's inliers match the reference's scale within 0.5 % ...
    )
    scale_sigmas: float = 3.0  # ... or within this many standard errors of the fitted scale
    # --- uncertainty of the maps (tolerances above are floors; the maps' own sigma raises them) ---
    landmark_sigma_m: float = setting(
        0.0083, gt=0.0
    )  # horizontal 1-sigma per axis of a landmark whose map states none; added in quadrature to stated ones
    landmark_sigma_z_m: float = setting(0.0083, gt=0.0)  # vertical, likewise
    rmse_confidence: float = (
        0.999  # chi-square acceptance of the inlier residuals at this confidence
    )
    search_sigmas: float = setting(
        2.0, ge=0.0
    )  # search tolerances >= this many sigma of a pairwise difference (sqrt(2) x combined sigma)
    # --- screen before an exhaustive search that would be large (:func:`_screen`) ---
    screen_min_incidences: float = setting(
        3e7, ge=0.0
    )  # predicted yaw-bin graph size from which the screen runs first (0: never)
    screen_fraction: float = setting(
        0.5, gt=0.0, le=1.0
    )  # a candidate pose passes with this share of the required inliers beyond chance
    screen_candidates: int = setting(
        8, ge=1
    )  # candidate poses of the triangle vote refined by the screen
    # --- distortion (non-rigid vehicle maps: odometry scale error, heading drift) ---
    near_miss_outer_m: float = setting(
        0.30, gt=0.0
    )  # vehicle landmarks landing refine_radius_m..this far from a reference rock are "near misses"
    max_near_miss_z: float = (
        3.0  # refuse when near misses exceed chance by this many standard deviations ...
    )
    min_near_misses: int = 5  # ... and there are at least this many of them
    # Bounds on the distortion of the odometry that built the vehicle map (its specification):
    # relative scale error and heading drift. None (both): not stated, the distortion is fitted
    # from the maps (:func:`bending_fit`) and its effect where the pose is used is added to the
    # predicted error. 0 states a rigid map (e.g. built from ground-truth poses).
    odometry_scale_error: float | None = setting(None, ge=0.0)
    odometry_heading_drift_deg_per_m: float | None = setting(None, ge=0.0)
    distortion_fit_sigmas: float = (
        2.0  # no bounds stated: allowance = fitted bend's shift + this many sigmas
    )
    # no bounds stated: 1-sigma prior on the odometry's heading drift (deg/m) and scale error that
    # regularises the bend fit (None: unconstrained, the fit from the maps alone). Defaults: what
    # real rover odometry shows (PRIOR_DRIFT_DEG_PER_M, PRIOR_SCALE_ERROR; docs/verification.md)
    odometry_prior_drift_deg_per_m: float | None = setting(PRIOR_DRIFT_DEG_PER_M, gt=0.0)
    odometry_prior_scale_error: float | None = setting(PRIOR_SCALE_ERROR, gt=0.0)
    distortion_fit_rounds: int = setting(
        3, ge=1, le=100
    )  # bent-model fits, inliers gathered again under the model between them
    min_inliers_distortion_fit: int = (
        6  # fewer inliers cannot fix the 8 parameters of the bent model: no allowance, refused
    )
    max_sighting_span_m: float = setting(
        10.0, gt=0.0
    )  # a landmark seen over more path than this (passed twice) is left out of the bent-model fit
    competitor_ratio: float = 1.5  # best must be this many times the best competing hypothesis
    competitor_yaw_sep_deg: float = 10.0  # hypotheses whose yaws differ more than this compete
    seed: int = 0  # CLIPPER initialisation
    threads: int = field(
        default_factory=lambda: min(4, os.cpu_count() or 1)
    )  # graph-building threads
    # landmark-centre bias shared by the inliers (1 sigma; added to the registration's covariance about
    # their centroid, not averaged down by their number; CENTRE_BIAS_M, docs/calibration.md):
    centre_bias_m: float = setting(CENTRE_BIAS_M, ge=0.0)  # horizontal translation, m per axis
    centre_bias_yaw_deg: float = setting(
        CENTRE_BIAS_YAW_DEG, ge=0.0
    )  # yaw about the inliers' centroid, deg

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
        return (
            self.odometry_scale_error is not None
            or self.odometry_heading_drift_deg_per_m is not None
        )

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
            self,
            refine_radius_m=refine,
            robust_scale_m=max(self.robust_scale_m, sr),
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


def landmark_sigmas(m: LandmarkMap, cfg: "LocalizationConfig") -> tuple[np.ndarray, np.ndarray]:
    """Per-landmark (horizontal per axis, vertical) 1-sigma of a map: its stated sigma with
    the configured landmark sigma added in quadrature (unmodelled session-to-session error),
    or the configured sigma alone where the map states none."""
    n = len(m)
    h = np.zeros(n) if m.sigma_xy_m is None else m.sigma_xy_m
    z = np.zeros(n) if m.sigma_z_m is None else m.sigma_z_m
    return np.hypot(h, cfg.landmark_sigma_m), np.hypot(z, cfg.landmark_sigma_z_m)


def combined_sigma(
    reference: LandmarkMap, vehicle: LandmarkMap, cfg: "LocalizationConfig"
) -> tuple[float, float]:
    """1-sigma per axis of the offset between a vehicle landmark and its reference landmark
    (horizontal, vertical): the maps' median landmark sigmas combined in quadrature."""
    rh, rz = landmark_sigmas(reference, cfg)
    vh, vz = landmark_sigmas(vehicle, cfg)
    return float(np.hypot(np.median(rh), np.median(vh))), float(
        np.hypot(np.median(rz), np.median(vz))
    )
