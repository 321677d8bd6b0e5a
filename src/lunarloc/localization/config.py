"""Localization settings: the search modes, solvers and registration, and
:class:`LocalizationConfig` in sections.

Each setting's range is declared beside it (:func:`lunarloc.core.configs.setting`) and checked
once, when the config is built or loaded; a setting's line says what it means and its unit.
Why each default has its value: docs/verification.md and docs/calibration.md; the reference
table is docs/run-configuration.md.

Sections (``LocalizationConfig.<section>``), in the order :func:`localize` uses them:

* ``search``: the consistency graph and its densest consistent set (tolerances, yaw bins,
  memory bound, threads);
* ``screen``: the quick screen run before an exhaustive search that would be large;
* ``refinement``: the registration's nearest-neighbour re-fits and robust re-weighting;
* ``uncertainty``: the maps' landmark sigmas, the residual floor and the landmark-centre bias
  behind the covariance and the predicted error;
* ``distortion``: the vehicle map's odometry distortion, stated as bounds or fitted as a bend;
* ``acceptance``: the checks a fix must pass (inliers beyond chance, residuals, spread,
  predicted error, scale, near misses, competing hypotheses).

Code and files from before the sections use flat keys (``epsilon_m``, ``screen_candidates``);
they still load and read: :data:`MOVED_KEYS` maps each to its section.
"""

from __future__ import annotations

import enum
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from lunarloc.core.configs import (
    check_settings,
    config_from_dict,
    config_to_dict,
    moved_keys,
    setting,
)
from lunarloc.core.errors import ConfigError
from lunarloc.io.maps import LandmarkMap

__all__ = [
    "Mode",
    "Registration",
    "Solver",
    "SearchConfig",
    "ScreenConfig",
    "RefinementConfig",
    "UncertaintyConfig",
    "DistortionConfig",
    "AcceptanceConfig",
    "LocalizationConfig",
    "MOVED_KEYS",
    "landmark_sigmas",
    "combined_sigma",
]


class Mode(str, enum.Enum):
    """Which invariants the consistency graph uses."""

    # horizontal distance + height difference + common yaw (rover maps, IMU-levelled)
    GRAVITY = "gravity"
    SIX_DOF = "6dof"  # 3D distance only: any relative rotation


class Registration(str, enum.Enum):
    """Which rigid transform is fitted to the inliers."""

    SE3 = "se3"  # Arun's SVD, full rotation (allows the residual tilt of an IMU-levelled map)
    YAW = "yaw"  # 4-DoF: rotation about the vertical only (maps levelled exactly)


class Solver(str, enum.Enum):
    """How the densest consistent set is found."""

    EXACT = "exact"  # exact maximum clique (robust; default)
    CLIPPER = "clipper"  # CLIPPER relaxation + rounding (the paper's solver)


#: 1-sigma prior on the vehicle map's odometry heading drift (deg/m) and relative scale error
#: when no bounds are stated: what lunarloc's own stereo VO shows on nine simulated traverses
#: (docs/verification.md, "The prior"; docs/odometry-visual.md).
PRIOR_DRIFT_DEG_PER_M = 0.012
PRIOR_SCALE_ERROR = 0.003

#: 1-sigma landmark-centre bias the inliers share for two maps built from detections: a translation
#: (m per horizontal axis), and the bias's difference across the inliers (m), which turns the fit
#: about their centroid by CENTRE_BIAS_SPREAD_M / (the inliers' rms horizontal radius) rad: a
#: compact inlier set cannot hold its yaw against it (measured: docs/calibration.md). A constant
#: yaw (deg) can be added; 0 by default.
CENTRE_BIAS_M = 0.002
CENTRE_BIAS_SPREAD_M = 0.0025
CENTRE_BIAS_YAW_DEG = 0.0


def _default_threads() -> int:
    return min(4, os.cpu_count() or 1)


@dataclass(frozen=True)
class SearchConfig:
    """The consistency graph and the search for its densest consistent set."""

    # max disagreement of a pairwise (horizontal) distance for consistency (m)
    epsilon_m: float = setting(0.05, gt=0.0)
    # gravity: max disagreement of a height difference, plus the tilt allowance (m)
    epsilon_z_m: float = setting(0.05, gt=0.0)
    # CLIPPER weight scale exp(-c^2 / 2 sigma^2) (m; None: epsilon_m / 2)
    sigma_m: float | None = setting(None, gt=0.0)
    # tolerances are at least this many sigma of a pairwise difference (the maps' own sigma)
    sigmas: float = setting(2.0, ge=0.0)
    # gravity: residual tilt of the vehicle map after IMU levelling (deg)
    max_tilt_deg: float = setting(1.5, ge=0.0, lt=45.0)
    # gravity: spacing of the relative-yaw bins (deg)
    yaw_step_deg: float = setting(2.0, gt=0.0)
    # gravity: a pair at distance d tolerates a yaw of asin(k x epsilon / d) (k)
    yaw_noise_factor: float = setting(1.5, ge=0.0)
    # drop associations whose landmark sizes differ by more than this ratio (needs sizes)
    max_size_ratio: float | None = setting(None, ge=1.0)
    # 6-DoF: memory bound on the consistency graph (edges)
    max_edges: int = setting(30_000_000, ge=1)
    # CLIPPER's initialisation seed
    seed: int = setting(0)
    # graph-building threads
    threads: int = setting(default_factory=_default_threads, ge=1)

    def __post_init__(self) -> None:
        check_settings(self)


@dataclass(frozen=True)
class ScreenConfig:
    """A quick screen (triangle vote, candidate poses refined) before an exhaustive search
    that would be large (:func:`lunarloc.localization.search.screen`)."""

    # predicted yaw-bin graph size from which the screen runs first (incidences; 0: never)
    min_incidences: float = setting(3e7, ge=0.0)
    # a candidate pose passes with this share of the required inliers beyond chance
    fraction: float = setting(0.5, gt=0.0, le=1.0)
    # candidate poses of the triangle vote refined by the screen
    candidates: int = setting(8, ge=1)

    def __post_init__(self) -> None:
        check_settings(self)


@dataclass(frozen=True)
class RefinementConfig:
    """The registration's refinement: mutual-nearest-neighbour re-fits under the estimate,
    robustly (Cauchy IRLS) re-weighted."""

    # re-fit with mutual nearest neighbours under the estimate (false: the clique's fit alone)
    enabled: bool = setting(True)
    # max residual of a nearest-neighbour pair kept by refinement (m)
    radius_m: float = setting(0.10, gt=0.0)
    # mutual-nearest-neighbour re-fits (fewer when the inliers settle)
    rounds: int = setting(3, ge=1, le=100)
    # Cauchy scale of the robust re-weighting (m)
    robust_scale_m: float = setting(0.02, gt=0.0)
    # re-weighting rounds of the robust registration
    irls_rounds: int = setting(5, ge=1, le=100)

    def __post_init__(self) -> None:
        check_settings(self)


@dataclass(frozen=True)
class UncertaintyConfig:
    """The maps' uncertainty behind the tolerances, the covariance and the predicted error
    (the fixed tolerances are floors; the maps' own sigma raises them, :meth:`for_maps`)."""

    # horizontal 1-sigma per axis of a landmark whose map states none; added in quadrature to stated
    # ones (m)
    landmark_sigma_m: float = setting(0.0083, gt=0.0)
    # vertical 1-sigma of such a landmark (m)
    landmark_sigma_z_m: float = setting(0.0083, gt=0.0)
    # floor on the residual noise scale in the covariance, predicted error and scale check (m)
    sigma_floor_m: float = setting(0.005, gt=0.0)
    # landmark-centre bias the inliers share, horizontal translation (1 sigma, m per axis)
    centre_bias_m: float = setting(CENTRE_BIAS_M, ge=0.0)
    # ... and a constant yaw about the inliers' centroid (1 sigma, deg)
    centre_bias_yaw_deg: float = setting(CENTRE_BIAS_YAW_DEG, ge=0.0)
    # ... and its difference across the inliers: a yaw of this over their rms radius (1 sigma, m)
    centre_bias_spread_m: float = setting(CENTRE_BIAS_SPREAD_M, ge=0.0)

    def __post_init__(self) -> None:
        check_settings(self)


@dataclass(frozen=True)
class DistortionConfig:
    """The vehicle map's odometry distortion (scale error, heading drift): bounds stated for
    the odometry that built it, or, with none stated, a bend fitted from the maps
    (:func:`lunarloc.localization.bending.bending_fit`) whose effect is added to the
    predicted error."""

    # bound on the odometry's relative scale error (fraction; None: not stated, fitted; 0: rigid)
    scale_error: float | None = setting(None, ge=0.0)
    # bound on its heading drift (deg/m; None: not stated, fitted; 0: rigid)
    heading_drift_deg_per_m: float | None = setting(None, ge=0.0)
    # fitted: 1-sigma prior on the heading drift that regularises the bend fit (deg/m; None: none)
    prior_drift_deg_per_m: float | None = setting(PRIOR_DRIFT_DEG_PER_M, gt=0.0)
    # fitted: 1-sigma prior on the scale error (fraction; None: none)
    prior_scale_error: float | None = setting(PRIOR_SCALE_ERROR, gt=0.0)
    # fitted: allowance = the fitted bend's shift + this many sigma
    fit_sigmas: float = setting(2.0, ge=0.0)
    # fitted: bent-model fits, inliers gathered again under the model between them
    fit_rounds: int = setting(3, ge=1, le=100)
    # fitted: fewer inliers cannot fix the bent model's 8 parameters: refused
    fit_min_inliers: int = setting(6, ge=0)
    # a landmark seen over more path than this (passed twice) is left out of the bend fit (m)
    max_sighting_span_m: float = setting(10.0, gt=0.0)

    def __post_init__(self) -> None:
        check_settings(self)

    @property
    def bounds_stated(self) -> bool:
        """Whether bounds are given (else the bend is fitted from the maps)."""
        return self.scale_error is not None or self.heading_drift_deg_per_m is not None


@dataclass(frozen=True)
class AcceptanceConfig:
    """The checks a localization must pass to be claimed (:mod:`lunarloc.localization.verify`)."""

    # absolute floor on the inlier count
    min_inliers: int = setting(6, ge=3)
    # inliers must exceed the chance envelope at this map size by this many
    chance_margin: float = setting(2.5)
    # inliers' residual RMSE after registration (m; a floor under the chi-square limit)
    max_rmse_m: float = setting(0.05, gt=0.0)
    # chi-square acceptance of the inlier residuals at this confidence
    rmse_confidence: float = setting(0.999, gt=0.0, lt=1.0)
    # inliers spread at least this far (largest principal std x 2, m)
    min_extent_m: float = setting(1.0, ge=0.0)
    # second / first principal std of the inliers (0: collinear)
    min_planarity: float = setting(0.05, ge=0.0, le=1.0)
    # gravity: share of inlier triangles with matching orientation
    min_handedness: float = setting(0.9, ge=0.0, le=1.0)
    # predicted error at the query points, times predicted_error_sigmas, at most this (m)
    max_predicted_error_m: float = setting(0.10, gt=0.0)
    # predicted rotation error, times predicted_error_sigmas, at most this (deg)
    max_predicted_rotation_deg: float = setting(1.0, gt=0.0)
    # the predicted-error limits apply to this many sigma
    predicted_error_sigmas: float = setting(1.0, gt=0.0)
    # a rigid map's inliers match the reference's scale within this fraction ...
    max_scale_error: float = setting(0.005, ge=0.0)
    # ... or within this many standard errors of the fitted scale
    scale_sigmas: float = setting(3.0, ge=0.0)
    # vehicle landmarks landing refinement.radius_m..this far from a reference rock are near misses
    # (m)
    near_miss_outer_m: float = setting(0.30, gt=0.0)
    # refuse when near misses exceed chance by this many standard deviations ...
    max_near_miss_z: float = setting(3.0)
    # ... and number at least this many
    min_near_misses: int = setting(5, ge=0)
    # the best hypothesis must be this many times the best competing one
    competitor_ratio: float = setting(1.5, ge=1.0)
    # hypotheses whose yaws differ more than this compete (deg)
    competitor_yaw_sep_deg: float = setting(10.0, ge=0.0, le=180.0)

    def __post_init__(self) -> None:
        check_settings(self)


_SECTION_KEYS = {
    "search": {
        "epsilon_m": "epsilon_m",
        "epsilon_z_m": "epsilon_z_m",
        "sigma_m": "sigma_m",
        "search_sigmas": "sigmas",
        "max_tilt_deg": "max_tilt_deg",
        "yaw_step_deg": "yaw_step_deg",
        "yaw_noise_factor": "yaw_noise_factor",
        "max_size_ratio": "max_size_ratio",
        "max_edges": "max_edges",
        "seed": "seed",
        "threads": "threads",
    },
    "screen": {
        "screen_min_incidences": "min_incidences",
        "screen_fraction": "fraction",
        "screen_candidates": "candidates",
    },
    "refinement": {
        "refine": "enabled",
        "refine_radius_m": "radius_m",
        "refine_rounds": "rounds",
        "robust_scale_m": "robust_scale_m",
        "irls_rounds": "irls_rounds",
    },
    "uncertainty": {
        "landmark_sigma_m": "landmark_sigma_m",
        "landmark_sigma_z_m": "landmark_sigma_z_m",
        "registration_sigma_floor_m": "sigma_floor_m",
        "centre_bias_m": "centre_bias_m",
        "centre_bias_yaw_deg": "centre_bias_yaw_deg",
        "centre_bias_spread_m": "centre_bias_spread_m",
    },
    "distortion": {
        "odometry_scale_error": "scale_error",
        "odometry_heading_drift_deg_per_m": "heading_drift_deg_per_m",
        "odometry_prior_drift_deg_per_m": "prior_drift_deg_per_m",
        "odometry_prior_scale_error": "prior_scale_error",
        "distortion_fit_sigmas": "fit_sigmas",
        "distortion_fit_rounds": "fit_rounds",
        "min_inliers_distortion_fit": "fit_min_inliers",
        "max_sighting_span_m": "max_sighting_span_m",
    },
    "acceptance": {
        k: k
        for k in (
            "min_inliers",
            "chance_margin",
            "max_rmse_m",
            "rmse_confidence",
            "min_extent_m",
            "min_planarity",
            "min_handedness",
            "max_predicted_error_m",
            "max_predicted_rotation_deg",
            "predicted_error_sigmas",
            "max_scale_error",
            "scale_sigmas",
            "near_miss_outer_m",
            "max_near_miss_z",
            "min_near_misses",
            "competitor_ratio",
            "competitor_yaw_sep_deg",
        )
    },
}

#: The flat keys of configs saved (and code written) before the sections:
#: {old key: (section, new key)}.
MOVED_KEYS: dict[str, tuple[str, str]] = {
    old: (section, new) for section, keys in _SECTION_KEYS.items() for old, new in keys.items()
}


@moved_keys(MOVED_KEYS)
@dataclass(frozen=True)
class LocalizationConfig:
    """Parameters of :func:`~lunarloc.localization.localize.localize`, in sections (module
    docstring). Distances in metres, angles in degrees."""

    # which invariants the consistency graph uses: gravity (IMU-levelled maps) or 6dof
    mode: Mode = Mode.GRAVITY
    # how the densest consistent set is found: exact maximum clique or clipper
    solver: Solver = Solver.EXACT
    # the rigid transform fitted to the inliers: se3 or yaw (needs gravity)
    registration: Registration = Registration.SE3
    # the consistency graph and its search
    search: SearchConfig = field(default_factory=SearchConfig)
    # the quick screen before a large exhaustive search
    screen: ScreenConfig = field(default_factory=ScreenConfig)
    # nearest-neighbour re-fits and robust re-weighting
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    # landmark sigmas, residual floor, shared centre bias
    uncertainty: UncertaintyConfig = field(default_factory=UncertaintyConfig)
    # the vehicle map's odometry distortion: stated bounds or a fitted bend
    distortion: DistortionConfig = field(default_factory=DistortionConfig)
    # the checks a fix must pass
    acceptance: AcceptanceConfig = field(default_factory=AcceptanceConfig)

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", Mode(self.mode))
        object.__setattr__(self, "solver", Solver(self.solver))
        object.__setattr__(self, "registration", Registration(self.registration))
        if self.registration is Registration.YAW and self.mode is not Mode.GRAVITY:
            raise ConfigError("yaw-only registration needs the gravity-aware mode")
        for name, cls in _SECTIONS.items():
            if isinstance(getattr(self, name), Mapping):  # a section as plain values
                object.__setattr__(self, name, config_from_dict(cls, getattr(self, name), name))
            if not isinstance(getattr(self, name), cls):
                raise ConfigError(
                    f"{name}: expected {cls.__name__}, got {type(getattr(self, name)).__name__}"
                )

    @property
    def odometry_bounds_stated(self) -> bool:
        """Whether the odometry's distortion bounds are given (else they are fitted from the
        maps)."""
        return self.distortion.bounds_stated

    @property
    def sigma(self) -> float:
        """CLIPPER's weight scale (m): ``search.sigma_m``, or half of ``search.epsilon_m``."""
        s = self.search
        return s.sigma_m if s.sigma_m is not None else s.epsilon_m / 2.0

    def with_settings(self, **sections) -> "LocalizationConfig":
        """A copy with settings of sections changed: ``with_settings(search={"epsilon_m":
        0.08})`` (each section's other settings kept)."""
        return replace(
            self, **{name: replace(getattr(self, name), **kv) for name, kv in sections.items()}
        )

    def for_maps(self, reference: LandmarkMap, vehicle: LandmarkMap) -> "LocalizationConfig":
        """This config with its refinement and acceptance tolerances raised to what the
        maps' stated uncertainty needs (:func:`combined_sigma`): refinement radius
        ``3 sigma_r`` and robust scale ``sigma_r``, sigma_r = sqrt(2 sigma_h^2 + sigma_z^2)
        the 3D offset of a landmark from its partner; the residual RMSE limit follows from
        a chi-square test (:func:`rmse_limit`). The consistency search tolerances become
        ``search.sigmas`` standard deviations of the difference between a vehicle pair's
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
        s, r = self.search, self.refinement
        radius_m = max(r.radius_m, 3 * sr)
        return self.with_settings(
            refinement={"radius_m": radius_m, "robust_scale_m": max(r.robust_scale_m, sr)},
            acceptance={"near_miss_outer_m": max(self.acceptance.near_miss_outer_m, 3 * radius_m)},
            search={
                "epsilon_m": max(s.epsilon_m, s.sigmas * math.sqrt(2) * sh),
                "epsilon_z_m": max(s.epsilon_z_m, s.sigmas * math.sqrt(2) * sz),
            },
        )

    def to_dict(self) -> dict:
        """Plain dict (sections as dicts, Enums as values) to write next to results."""
        return config_to_dict(self)


_SECTIONS = {
    "search": SearchConfig,
    "screen": ScreenConfig,
    "refinement": RefinementConfig,
    "uncertainty": UncertaintyConfig,
    "distortion": DistortionConfig,
    "acceptance": AcceptanceConfig,
}


def landmark_sigmas(m: LandmarkMap, cfg: "LocalizationConfig") -> tuple[np.ndarray, np.ndarray]:
    """Per-landmark (horizontal per axis, vertical) 1-sigma of a map: its stated sigma with
    the configured landmark sigma added in quadrature (unmodelled session-to-session error),
    or the configured sigma alone where the map states none."""
    n = len(m)
    h = np.zeros(n) if m.sigma_xy_m is None else m.sigma_xy_m
    z = np.zeros(n) if m.sigma_z_m is None else m.sigma_z_m
    u = cfg.uncertainty
    return np.hypot(h, u.landmark_sigma_m), np.hypot(z, u.landmark_sigma_z_m)


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
