"""The online loop's state, fed frame by frame: map, localize, fuse.

:class:`LoopState` is the per-frame core shared by :func:`lunarloc.pipeline.runner.run` (whole
traverses) and :class:`lunarloc.online.component.OnlineLocalizer` (the per-tick component). Each
``step`` gives a frame's odometry pose; keyframes also give their rock detections (rover
frame). Then:

1. **mapping**: every ``localize_every_m`` metres (or ``localize_every_s`` seconds) the
   detections of the last ``window_m`` metres are placed with the current pose estimates
   and aggregated into a local landmark map;
2. **association**: the local map is localized in the reference map
   (:func:`lunarloc.localization.localize.localize`, gravity-aware), the reference cropped to the
   region the predicted pose allows;
3. **fusion**: a successful localization becomes a fix of the newest keyframe; fixes that
   pass the chi-square gate enter the pose graph (:mod:`lunarloc.fusion.posegraph`), which is
   re-solved and also calibrates the odometry scale and heading bias.

Frames: ``map`` (the reference map's frame, where ground truth lives), ``odo`` (the
drifting odometry frame; equals ``map`` at the start), ``rover`` (body: x forward, y left,
z up). Metres, radians, seconds.
"""

from __future__ import annotations

import enum
import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from lunarloc.core.metrics import ate, path_length
from lunarloc.core.errors import ConfigError, InputError, LunarLocError
from lunarloc.fusion.factors import wrap_angle
from lunarloc.fusion.posegraph import FusionConfig, Keyframe, PoseGraph
from lunarloc.core.geometry import matrix_to_pose, pose_to_matrix, transform_points, yaw_of
from lunarloc.localization.config import LocalizationConfig
from lunarloc.localization.localize import localize
from lunarloc.io.maps import AggregationConfig, LandmarkMap, aggregate_detections, detection_arcs_m
from lunarloc.online.presets import load_preset

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = [
    "FixKind",
    "CropSigma",
    "LoopConfig",
    "IMAGE_WINDOW_M",
    "image_localization_config",
    "image_loop_config",
    "Attempt",
    "LoopResult",
    "LoopState",
    "interpolate_corrections",
    "gate_fix",
]


# --------------------------------------------------------------------------- configuration


class FixKind(str, enum.Enum):
    """How an accepted localization enters the pose graph."""

    LANDMARKS = (
        "landmarks"  # each detection of an inlier rock is tied to its reference landmark (default)
    )
    POSE = "pose"  # one pose fix of the newest keyframe (extrapolates the rigid fit to the rover)


class WindowBounds(str, enum.Enum):
    """How the loop states its windows' odometry distortion to the localizer (the
    ``odometry_scale_error`` / ``odometry_heading_drift_deg_per_m`` of the
    :class:`~lunarloc.localization.config.LocalizationConfig` each attempt runs with), when the
    localization settings state none themselves."""

    # the bounds of the odometry source in use (LoopConfig.odometry_bounds), added to the predicted
    # error
    SOURCE = "source"
    # none stated: localize() fits each window's bend (and the measured floor) from its inliers
    FITTED = "fitted"
    RIGID = "rigid"  # bounds 0: no distortion term (over-confident under drifting odometry)


class CropSigma(str, enum.Enum):
    """Which position sigma sizes the reference crop of an attempt (``LoopConfig.crop_sigma``).
    The crop is chosen from the prediction alone, never from the data, so the chance test at the
    crop's association count stays valid whatever its size; a crop too small only loses fixes."""

    # the pose graph's gate drift model (5 % of the distance since the last fix and a heading random
    # walk)
    GATE = "gate"
    # the odometry bounds the window states (scale error and heading drift per metre, grown over the
    # distance since the last fix, from the gate's base sigmas); the gate's model where the window
    # states none or states them 0 (fitted, rigid)
    SOURCE = "source"


@dataclass(frozen=True)
class OdometryBounds:
    """Bounds on an odometry's distortion over a window: relative scale error and heading
    drift per metre of path (what :func:`lunarloc.localization.uncertainty.distortion_allowance`
    takes)."""

    scale_error: float = 0.0
    heading_drift_deg_per_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("scale_error", "heading_drift_deg_per_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and 0 <= v < math.inf):
                raise ConfigError(f"{name}={v!r} must be >= 0 and finite")

    def localization_overrides(self) -> dict:
        return {
            "odometry_scale_error": float(self.scale_error),
            "odometry_heading_drift_deg_per_m": float(self.heading_drift_deg_per_m),
        }


@dataclass(frozen=True)
class SourceBounds:
    """Per odometry source (:class:`lunarloc.odometry.source.OdometrySource`), the bounds the loop
    states for a window of its poses (``window_bounds = "source"``); None: none stated, the
    window's bend is fitted. Traverse-CSV runs (the real dataset's detections) state their
    simulated drift (``odometry.scale_error``, ``heading_drift_deg_per_m``) exactly; a source
    not listed (replayed poses, a caller's own odometry) is fitted. What the defaults were
    chosen on: docs/online-component.md, "Window distortion"."""

    # stereo VO at 640x360-1280x720: 8 m windows distort by 0.2-0.9 % and up to 0.06-0.08 deg/m
    visual: OdometryBounds | None = field(default_factory=lambda: OdometryBounds(0.01, 0.06))
    # the simulator's drifting record (3 % scale, gyro bias ~0.1 deg/m) stated honestly refuses
    # every
    # fix before the pose graph has calibrated it, so none ever comes: stated rigid by default
    record: OdometryBounds | None = field(default_factory=OdometryBounds)
    imu: OdometryBounds | None = None  # not measured per window: fitted
    ground_truth: OdometryBounds | None = field(default_factory=OdometryBounds)

    def for_source(self, label: str) -> OdometryBounds | None:
        """The bounds of the odometry source named `label` (``visual``, ``record:NAME``,
        ``imu``, ``ground-truth``, as :attr:`lunarloc.odometry.source.OdometryTrajectory.label`
        writes it); None for any other, or one whose bounds are None (fitted)."""
        head = str(label).split(":")[0].split(" ")[0].strip().lower()
        return {
            "visual": self.visual,
            "imu": self.imu,
            "record": self.record,
            "ground-truth": self.ground_truth,
        }.get(head)


@dataclass(frozen=True)
class LoopConfig:
    """Parameters of the online loop (distances in metres, times in seconds). The
    localization it runs is configured apart
    (:class:`~lunarloc.localization.config.LocalizationConfig`,
    the ``localization`` section of a :class:`~lunarloc.config.run.RunConfig`)."""

    localize_every_m: float = 1.5  # attempt a localization after this much odometry travel ...
    localize_every_s: float = 20.0  # ... or this much time, whichever comes first
    window_m: float = 12.0  # the local map holds detections of the last window_m metres of travel
    # adaptive window (:meth:`LoopState.local_map`): a local map of fewer than
    # window_target_landmarks
    # landmarks grows back along the path in steps of window_m / 2, up to window_max_m (<= window_m
    # or
    # a target of 0: fixed window)
    window_target_landmarks: int = 0
    window_max_m: float = 0.0
    min_window_landmarks: int = 6  # fewer landmarks than this: no attempt (recorded as skipped)
    crop_reference: bool = True  # localize against the reference near the predicted window only
    crop_sigmas: float = 3.0  # crop radius = window radius + crop_sigmas x predicted sigma ...
    crop_margin_m: float = 2.0  # ... + this margin
    # the predicted sigma the crop is sized by: the gate's model or the window's odometry bounds
    crop_sigma: CropSigma = CropSigma.GATE
    fix_sigma_fallback_m: float = 0.05  # a fix's sigma when the localizer predicts none
    fix_kind: FixKind = FixKind.LANDMARKS  # how fixes enter the pose graph
    active_window_m: float = (
        40.0  # each solve re-optimises keyframes of the last active_window_m metres
    )
    keyframe_every_s: float = (
        0.5  # traverse-CSV source: keyframe period (frames with detections) ...
    )
    keyframe_max_interval_s: float = 2.0  # ... and a keyframe at least this often
    aggregation: AggregationConfig = field(
        default_factory=lambda: AggregationConfig(min_sightings=2, min_frames=2)
    )
    fusion: FusionConfig = field(default_factory=FusionConfig)
    # how each window's odometry distortion is stated to the localizer (when the localization
    # settings state no odometry bounds): the source's bounds (odometry_bounds), fitted, or rigid
    window_bounds: WindowBounds = WindowBounds.SOURCE
    calibrated_after_fixes: int = (
        0  # > 0: after this many fixes the source's bounds give way to a fitted bend
    )
    odometry_bounds: SourceBounds = field(default_factory=SourceBounds)
    # the covariance a fix is stated with (Attempt.fix_covariance_xyz, where OnlineLocalizer's
    # covariance restarts; not what localize() decides with, the gate or the pose graph):
    # localize()'s registration covariance at the rover, its window distortion allowance (a
    # bound) counted as fix_distortion_sigmas sigmas, and the centre bias a window's few
    # neighbouring rocks share (per axis: horizontal, vertical; for two maps built from
    # detections, half the variance for one): docs/calibration.md, "The online loop's uncertainty".
    # The heading likewise (Attempt.fix_sigma_yaw_rad): the window's heading-drift allowance
    # counted as fix_heading_drift_sigmas sigmas, and the turn of a centre bias that differs by
    # fix_centre_bias_spread_m across the window's inliers (over their rms radius).
    # fix_centre_bias_along_m: a horizontal part along the fix's heading only (image detections
    # sit on the rocks' faces turned to the camera, nearer than their centres)
    fix_distortion_sigmas: float = 1.0
    fix_centre_bias_m: float = 0.0
    fix_centre_bias_along_m: float = 0.0
    fix_centre_bias_z_m: float = 0.0
    fix_heading_drift_sigmas: float = 1.0
    fix_centre_bias_spread_m: float = 0.0
    # the heading rate error (rad/s) the pose graph carries past its last accepted fix: the
    # window is placed with the graph's poses and its registration aligns their average, so a
    # fix keeps the heading error the graph's prediction grew at the keyframe since that fix
    fix_heading_rate_sigma_rad_s: float = 0.0
    # the heading the graph's estimated bias turned its prediction by since its last solve
    # (PoseGraph.bias_turn_since_solve) counted as an error of fix_heading_turn_factor times it:
    # a bias per second of motion carried through a slow stretch turns the prediction where the
    # odometry's drift (per metre) did not
    fix_heading_turn_factor: float = 0.0
    # the odometry's scale error (fraction, one sigma) over the path its prediction alone carried
    # the window's inlier sightings to the rover (Attempt.fix_carried_path_m: the sightings from
    # keyframes after the pose graph's last accepted fix, all of them before a first fix), along
    # the fix's heading: the graph corrects the keyframes up to that fix, not the odometry's
    # scale after it (docs/calibration.md, "The image loop's fixes on LAC-look sites")
    fix_odometry_scale_sigma: float = 0.0

    def __post_init__(self) -> None:
        for name in (
            "localize_every_m",
            "localize_every_s",
            "window_m",
            "crop_sigmas",
            "fix_sigma_fallback_m",
            "keyframe_every_s",
            "keyframe_max_interval_s",
            "fix_distortion_sigmas",
            "fix_heading_drift_sigmas",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v < math.inf):
                raise ConfigError(f"{name}={v!r} must be positive and finite")
        for name in (
            "crop_margin_m",
            "fix_centre_bias_m",
            "fix_centre_bias_along_m",
            "fix_centre_bias_z_m",
            "fix_centre_bias_spread_m",
            "fix_heading_rate_sigma_rad_s",
            "fix_heading_turn_factor",
            "fix_odometry_scale_sigma",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v < math.inf):
                raise ConfigError(f"{name}={v!r} must be >= 0 and finite")
        try:
            object.__setattr__(self, "fix_kind", FixKind(self.fix_kind))
        except ValueError:
            raise ConfigError(
                f"fix_kind={self.fix_kind!r}: use one of {', '.join(k.value for k in FixKind)}"
            ) from None
        try:
            object.__setattr__(self, "crop_sigma", CropSigma(self.crop_sigma))
        except ValueError:
            raise ConfigError(
                f"crop_sigma={self.crop_sigma!r}: use one of "
                f"{', '.join(k.value for k in CropSigma)}"
            ) from None
        try:
            object.__setattr__(self, "window_bounds", WindowBounds(self.window_bounds))
        except ValueError:
            raise ConfigError(
                f"window_bounds={self.window_bounds!r}: use one of "
                f"{', '.join(k.value for k in WindowBounds)}"
            ) from None
        if not isinstance(self.min_window_landmarks, int) or self.min_window_landmarks < 3:
            raise ConfigError(
                f"min_window_landmarks={self.min_window_landmarks!r} must be an integer >= 3"
            )
        c = self.calibrated_after_fixes
        if not isinstance(c, int) or isinstance(c, bool) or c < 0:
            raise ConfigError(
                f"calibrated_after_fixes={c!r} must be an integer >= 0 (0: the source's bounds "
                "throughout)"
            )
        t = self.window_target_landmarks
        if not isinstance(t, int) or isinstance(t, bool) or t < 0:
            raise ConfigError(
                f"window_target_landmarks={t!r} must be an integer >= 0 (0: fixed window)"
            )
        w = self.window_max_m
        if not (isinstance(w, (int, float)) and not isinstance(w, bool) and 0 <= w < math.inf):
            raise ConfigError(
                f"window_max_m={w!r} must be >= 0 and finite (at most window_m: fixed window)"
            )

    def to_dict(self) -> dict:
        from lunarloc.core.configs import config_to_dict

        return config_to_dict(self)


RIGID_WINDOW = {"odometry_scale_error": 0.0, "odometry_heading_drift_deg_per_m": 0.0}
"""Odometry bounds 0: a window stated rigid (``window_bounds = "rigid"``)."""


def loop_localization_config(**overrides) -> LocalizationConfig:
    """The default localization for the loop's windows (real-dataset detections), the preset
    ``loop_localization`` (:mod:`lunarloc.online.presets`): the bend fit the windows were
    measured with, without the one-shot's odometry prior (a calibrated window's drift is what
    the pose graph left, not raw odometry's; docs/online-component.md). It states no odometry
    bounds: each window's are the loop's to state (``LoopConfig.window_bounds``)."""
    return load_preset(LocalizationConfig, "loop_localization", **overrides)


def image_localization_config(**overrides) -> LocalizationConfig:
    """Localization settings for detections from simulated stereo images (noisier than the
    real dataset's), the preset ``image_localization``: 8 cm consistency tolerance and residual
    RMSE, refinement radius 16 cm, predicted error up to 15 cm, the loop's bend fit. No
    odometry bounds: the loop states each window's."""
    return load_preset(LocalizationConfig, "image_localization", **overrides)


def image_loop_config(**overrides) -> LoopConfig:
    """The loop for detections from stereo images (``RunConfig()``, ``OnlineConfig()``), the
    preset ``image_loop``: an 8 m window (:data:`IMAGE_WINDOW_M`) that grows to 12 m while it
    holds fewer than 20 landmarks (not when stated rigid, :meth:`LoopState.local_map`), and a
    reference crop sized by the window's odometry bounds (``crop_sigma = "source"``). Measured
    on the multi-session sites: docs/online-component.md (multi-session runs without a fix)."""
    return load_preset(LoopConfig, "image_loop", **overrides)


IMAGE_WINDOW_M: float = image_loop_config().window_m
"""Local-map window for detections from simulated stereo images: less odometry distortion
inside it before the first fix than the real dataset's 12 m (the ``image_loop`` preset's)."""


def stated_window_bounds(localization: LocalizationConfig) -> tuple[float, float] | None:
    """The odometry bounds a window's localization states, (scale error, heading drift deg/m),
    a bound not given counting 0; None where it states none (the bend is fitted)."""
    if not localization.odometry_bounds_stated:
        return None
    return (
        float(localization.distortion.scale_error or 0.0),
        float(localization.distortion.heading_drift_deg_per_m or 0.0),
    )


def window_localization(
    localization: LocalizationConfig, loop: LoopConfig, source_bounds: OdometryBounds | None
) -> LocalizationConfig:
    """The localization a loop window is judged with: `localization` as given when it states
    odometry bounds itself (a run configuration of its own, ``bench loop --odometry-bounds``);
    else the loop's ``window_bounds``: ``source`` states `source_bounds` (the odometry source's,
    :meth:`SourceBounds.for_source`; None, a source not known, leaves them to be fitted),
    ``fitted`` none, ``rigid`` 0."""
    if localization.odometry_bounds_stated or loop.window_bounds is WindowBounds.FITTED:
        return localization
    if loop.window_bounds is WindowBounds.RIGID:
        return replace(localization, **RIGID_WINDOW)
    return (
        localization
        if source_bounds is None
        else replace(localization, **source_bounds.localization_overrides())
    )


# --------------------------------------------------------------------------- results


@dataclass
class Attempt:
    """One localization attempt of the local map (see module docstring for frames)."""

    frame: int
    time_s: float
    keyframe: int
    landmarks: int  # local-map landmarks
    reference_landmarks: int  # reference landmarks after cropping
    success: bool  # localize() trusted its answer
    accepted: bool  # ... and the fix passed the gate
    inliers: int = 0
    reason: str = ""
    correction_m: float = float("nan")  # |translation| of the fix relative to the prediction
    correction_yaw_deg: float = float("nan")
    gate_d2: float = float("nan")
    predicted_error_m: float = float("nan")
    fix_error_m: float = float("nan")  # |fix - ground truth| at the keyframe (evaluation only)
    fix_xyz: list | None = None
    fix_yaw_rad: float = float("nan")  # the fix's heading (map frame, rad)
    inlier_vehicle_xyz: list | None = None  # inlier landmarks in the estimate frame, before the fix
    inlier_reference_xyz: list | None = None
    # the fix's position error (fix - truth, map frame, m; evaluation only) and the 3x3 position
    # covariance localize() states for it at the rover (m^2): what a NEES of the fixes needs
    fix_error_xyz: list | None = None
    fix_covariance_xyz: list | None = None
    # the yaw sigma stated for the fix: localize()'s with the loop's model (fix_stated_yaw_variance)
    fix_sigma_yaw_rad: float = float("nan")
    fix_error_yaw_rad: float = float("nan")  # fix - ground truth yaw (evaluation only)
    fix_distortion_m: float = float("nan")  # localize()'s distortion allowance at the rover (m)
    fix_distortion_yaw_rad: float = float("nan")  # ... and its rotation part (rad, one sigma)
    fix_maps_from_detections: int = 0  # of the two maps, those built from detections (sightings)
    fix_since_fix_s: float = float("nan")  # time since the last accepted fix (s; NaN before one)
    # the heading error (rad^2) the pose graph's prediction grew since its last solve, from its
    # heading bias's marginal and from its process noise (PoseGraph.predicted_heading_variance)
    fix_graph_yaw_var_bias_rad2: float = float("nan")
    fix_graph_yaw_var_process_rad2: float = float("nan")
    # the heading the graph's bias estimate turned its prediction by since that solve (rad), and
    # the odometry path since the last accepted fix (m)
    fix_graph_bias_turn_rad: float = float("nan")
    fix_since_fix_m: float = float("nan")
    # the inliers' viewing geometry: the mean over inlier rocks of the mean horizontal ray
    # (map frame, m) from the keyframes that detected them to the detections, and the mean
    # horizontal range (m) of those detections (window_ray_geometry)
    fix_ray_xy_m: list | None = None
    fix_range_m: float = float("nan")
    # the path (m) the odometry's prediction alone carried the inliers' sightings to the rover:
    # per inlier rock the mean over its detections from keyframes after the last accepted fix
    # (all before a first fix) of the path from that keyframe to the rover (0 for the others),
    # averaged over the rocks (window_carried_path_m)
    fix_carried_path_m: float = float("nan")
    time_mapping_s: float = 0.0
    time_association_s: float = 0.0
    # window length used: window_m, or longer where the adaptive window grew
    window_m: float = float("nan")

    def row(self) -> dict:
        d = asdict(self)
        for k in (
            "inlier_vehicle_xyz",
            "inlier_reference_xyz",
            "fix_xyz",
            "fix_error_xyz",
            "fix_covariance_xyz",
            "fix_ray_xy_m",
        ):
            d.pop(k)
        return d


@dataclass
class LoopResult:
    """Everything a run produced. Trajectories are (F, 4, 4) transforms, one per frame; the
    run folder's TUM files hold them as positions and quaternions
    (:func:`lunarloc.io.runs.write_run`)."""

    frames: np.ndarray
    times: np.ndarray
    T_odo_rover: np.ndarray  # odometry (odo == map at the start)
    T_map_rover_online: np.ndarray  # causal estimate: what the rover knew at each frame
    T_map_rover: np.ndarray  # corrected: pose-graph estimate at the end of the run (continuous)
    T_map_rover_true: np.ndarray | None  # ground truth
    attempts: list[Attempt]
    vehicle_map: LandmarkMap  # all detections placed with the corrected poses
    vehicle_map_odometry: LandmarkMap  # ... and with the raw odometry poses
    reference: LandmarkMap
    timings_s: dict[str, float]
    num_image_frames: int
    config: dict
    scale: float = 1.0
    rocks: np.ndarray | None = None
    example: dict | None = None  # one camera frame: image + detections (for the figure)
    source: str = ""

    @property
    def duration_s(self) -> float:
        return float(self.times[-1] - self.times[0]) if len(self.times) > 1 else 0.0

    @staticmethod
    def attempt_columns() -> list[str]:
        """The columns of a run folder's ``attempts.csv`` (one :class:`Attempt` per row)."""
        return list(Attempt(0, 0.0, 0, 0, 0, False, False).row().keys())

    def summary(self) -> dict:
        out: dict = {
            "source": self.source,
            "frames": int(len(self.frames)),
            "image_frames": int(self.num_image_frames),
            "duration_s": round(self.duration_s, 3),
            "path_length_m": round(
                path_length(
                    (
                        self.T_map_rover_true
                        if self.T_map_rover_true is not None
                        else self.T_odo_rover
                    )[:, :3, 3]
                ),
                3,
            ),
            "reference_landmarks": len(self.reference),
            "vehicle_landmarks": len(self.vehicle_map),
            "attempts": len(self.attempts),
            "localized": sum(a.success for a in self.attempts),
            "fixes": sum(a.accepted for a in self.attempts),
            "rejected_by_gate": sum(a.success and not a.accepted for a in self.attempts),
            "odometry_scale_estimate": round(self.scale, 5),
        }
        acc = [a.fix_error_m for a in self.attempts if a.accepted and math.isfinite(a.fix_error_m)]
        out["max_accepted_fix_error_m"] = round(max(acc), 4) if acc else None
        if self.T_map_rover_true is not None:
            gt = self.T_map_rover_true[:, :3, 3]
            for name, T in (
                ("odometry", self.T_odo_rover),
                ("corrected", self.T_map_rover),
                ("online", self.T_map_rover_online),
            ):
                out[f"ate_{name}"] = ate(T[:, :3, 3], gt)
            out["final_error_odometry_m"] = round(
                float(np.linalg.norm(self.T_odo_rover[-1, :3, 3] - gt[-1])), 4
            )
            out["final_error_corrected_m"] = round(
                float(np.linalg.norm(self.T_map_rover[-1, :3, 3] - gt[-1])), 4
            )
        total = sum(self.timings_s.values())
        n = max(self.num_image_frames, 1)
        out["time_total_s"] = round(total, 3)
        out["time_per_image_frame_ms"] = {
            k: round(1000 * v / n, 2) for k, v in self.timings_s.items()
        }
        out["time_stage_total_s"] = {k: round(v, 3) for k, v in self.timings_s.items()}
        out["real_time_fraction"] = (
            round(total / self.duration_s, 4) if self.duration_s > 0 else None
        )
        return out


# --------------------------------------------------------------------------- the loop


class LoopState:
    """The loop's state, fed frame by frame (see module docstring); the per-tick component an
    agent calls is :class:`lunarloc.online.component.OnlineLocalizer`, built on this class.

    ``step(frame, t, T_odo_rover, detections_rover=None, T_map_rover_true=None)``: every frame
    gives its odometry pose (4x4); keyframes (image frames) also give their detections in the rover
    frame, (N, 3). Ground truth, when given, is only used to score fixes.

    ``reference=None``: no reference map (a rover that only localizes in other rovers' maps,
    :mod:`lunarloc.pipeline.multirover`). Attempts are still made on schedule (their local map is
    what a caller can localize elsewhere) and end with the reason "no reference map".
    """

    def __init__(
        self,
        reference: LandmarkMap | None,
        config: LoopConfig | None = None,
        localization: LocalizationConfig | None = None,
        odometry: str | OdometryBounds | None = None,
    ):
        from lunarloc.localization.warmup import warm_up

        warm_up()  # compile before any stage timer starts: compile time is not run time
        if reference is not None and not isinstance(reference, LandmarkMap):
            raise InputError("reference must be a LandmarkMap or None")
        if reference is not None and len(reference) < 3:
            raise InputError(
                f"reference map has {len(reference)} landmark(s); at least 3 are needed"
            )
        self.has_reference = reference is not None
        self.reference = (
            reference if reference is not None else LandmarkMap(np.zeros((0, 3)), frame="map")
        )
        self.config = config or LoopConfig()
        self._localization = localization or loop_localization_config()
        self.set_odometry(odometry)
        # per reference landmark (horizontal per axis, vertical) 1-sigma as the map states it
        # (0 where it states none): the error its ties share (fusion.ReferenceErrorModel)
        self.reference_sigmas = stated_sigmas(self.reference)
        self.graph = PoseGraph(self.config.fusion)
        self.frames: list[int] = []
        self.times: list[float] = []
        # per frame, 4x4: odometry, causal estimate (T_map_odo @ T_odo_rover), ground truth or None
        self.T_odo_rover: list[np.ndarray] = []
        self.T_map_rover_online: list[np.ndarray] = []
        self.T_map_rover_true: list[np.ndarray | None] = []
        self._q_prev: np.ndarray | None = (
            None  # the previous frame's odometry (x, y, z, roll, pitch, yaw)
        )
        self.attempts: list[Attempt] = []
        self.timings = {"detection": 0.0, "mapping": 0.0, "association": 0.0, "fusion": 0.0}
        self._dist = 0.0
        self._moving_since_kf = 0.0
        self._step_var = 0.0  # the odometry's stated step variances since the last keyframe (m^2)
        self._last_attempt_dist = 0.0
        self._last_attempt_t = None
        self.T_map_odo = np.eye(4)  # the latest keyframe's correction

    def set_odometry(self, odometry: str | OdometryBounds | None) -> None:
        """Name the odometry that feeds :meth:`step` (a source label, ``visual``,
        ``record:odometry``, ...; or its bounds directly; None: not known), whose bounds the
        windows state under ``window_bounds = "source"`` (:func:`window_localization`)."""
        if odometry is not None and not isinstance(odometry, (str, OdometryBounds)):
            raise InputError(
                f"odometry must be a source name or OdometryBounds, got {type(odometry).__name__}"
            )
        self.odometry = odometry
        bounds = (
            odometry
            if not isinstance(odometry, str)
            else self.config.odometry_bounds.for_source(odometry)
        )
        self.localization = window_localization(self._localization, self.config, bounds)
        # the source's bounds describe the raw odometry: once the pose graph has calibrated it
        # (calibrated_after_fixes accepted fixes), what is left of a window's bend is fitted
        from_source = (
            self.config.window_bounds is WindowBounds.SOURCE
            and bounds is not None
            and not self._localization.odometry_bounds_stated
        )
        self._calibrated_localization = (
            replace(
                self.localization, odometry_scale_error=None, odometry_heading_drift_deg_per_m=None
            )
            if from_source
            else self.localization
        )

    def window_localization(self) -> LocalizationConfig:
        """The localization the next window is judged with: :attr:`localization`, or once
        ``calibrated_after_fixes`` fixes are in the pose graph (> 0) and the bounds are the
        source's, none stated (the calibrated window's bend is fitted)."""
        n = self.config.calibrated_after_fixes
        if n > 0 and sum(a.accepted for a in self.attempts) >= n:
            return self._calibrated_localization
        return self.localization

    @property
    def keyframes(self) -> list[Keyframe]:
        """The keyframes (:class:`lunarloc.fusion.posegraph.Keyframe`: the one record the loop and
        the
        pose graph share: frame, time, odometry pose, roll/pitch, detections, path length,
        current estimate)."""
        return self.graph.keyframes

    # -------------------------------------------------------------- per frame
    def step(
        self,
        frame: int,
        t: float,
        T_odo_rover: np.ndarray,
        detections_rover: np.ndarray | None = None,
        T_map_rover_true: np.ndarray | None = None,
        keyframe: bool | None = None,
        odometry_step_sigma_m: float | None = None,
    ) -> Attempt | None:
        """Feed one frame (its odometry pose, 4x4); returns the localization attempt made at it,
        if any. The frame's odometry, online estimate and ground truth are kept as 4x4
        transforms. `odometry_step_sigma_m`: the odometry's own 1-sigma (m) of its step ending
        at this frame (the visual odometry's, ``OdometryTrajectory.step_sigma_m``), None or NaN
        where it states none. A keyframe's odometry edge gets the root sum of squares of those
        stated since the previous keyframe when the keyframe's own frame states one
        (:attr:`lunarloc.fusion.posegraph.Keyframe.step_sigma_m`), else none."""
        T_odo_rover = np.array(T_odo_rover, float)
        s = odometry_step_sigma_m
        try:
            s = math.nan if s is None else float(s)
        except (TypeError, ValueError):
            raise InputError(f"odometry_step_sigma_m={s!r} must be a number or None") from None
        own = math.isfinite(s)
        if own and s < 0:
            raise InputError(f"odometry_step_sigma_m={s!r} must be >= 0")
        q = np.asarray(matrix_to_pose(T_odo_rover), float)
        if own:
            self._step_var += s * s
        if self._q_prev is not None:
            step = float(np.linalg.norm(q[:3] - self._q_prev[:3]))
            if step > 1e-6 or abs(float(wrap_angle(q[5] - self._q_prev[5]))) > 1e-6:
                self._moving_since_kf += t - self.times[-1]
            self._dist += step
        self._q_prev = q
        self.frames.append(int(frame))
        self.times.append(float(t))
        self.T_odo_rover.append(T_odo_rover)
        self.T_map_rover_true.append(
            None if T_map_rover_true is None else np.array(T_map_rover_true, float)
        )
        is_kf = (detections_rover is not None) if keyframe is None else keyframe
        attempt = None
        if is_kf or not self.graph.keyframes:
            attempt = self._keyframe(
                frame,
                t,
                q,
                np.zeros((0, 3)) if detections_rover is None else detections_rover,
                math.sqrt(self._step_var) if own else None,
            )
            self._step_var = 0.0
        self.T_map_rover_online.append(self.T_map_odo @ T_odo_rover)
        return attempt

    def _keyframe(self, frame, t, q, det, step_sigma_m=None) -> Attempt | None:
        t0 = time.perf_counter()
        k = self.graph.add_keyframe(
            t,
            (q[0], q[1], q[2], q[5]),
            self._moving_since_kf if self.graph.keyframes else None,
            frame=int(frame),
            roll_pitch_rad=(float(q[3]), float(q[4])),
            detections_rover=det,
            path_m=self._dist,
            step_sigma_m=step_sigma_m,
        )
        self._moving_since_kf = 0.0
        self.timings["fusion"] += time.perf_counter() - t0
        if self._last_attempt_t is None:
            self._last_attempt_t = t
        attempt = None
        cfg = self.config
        if (
            self._dist - self._last_attempt_dist >= cfg.localize_every_m
            or t - self._last_attempt_t >= cfg.localize_every_s
        ):
            self._last_attempt_dist, self._last_attempt_t = self._dist, t
            attempt = self._attempt(k, frame, t)
            self.attempts.append(attempt)
        self.T_map_odo = self._correction(k)
        return attempt

    def _correction(self, k: int) -> np.ndarray:
        return self.graph.keyframes[k].T_map_odo

    def window(self, k: int, length_m: float | None = None) -> np.ndarray:
        """Indices of the keyframes whose detections form keyframe k's local map: those of the
        last `length_m` (default ``window_m``) metres of odometry path up to it (and any after
        it)."""
        path = np.array([kf.path_m for kf in self.graph.keyframes])
        return np.flatnonzero(
            path >= path[k] - (self.config.window_m if length_m is None else length_m)
        )

    def local_map(self, k: int, poses4: np.ndarray):
        """Keyframe k's local map, its detections placed with `poses4`: (window keyframes,
        points, keyframe of each, index of each within its keyframe, the aggregated
        LandmarkMap, window length m). The window is the last ``window_m`` metres of path; an
        adaptive window (``window_target_landmarks`` > 0, ``window_max_m`` > ``window_m``)
        whose map holds fewer landmarks than the target grows back along the path by
        ``window_m / 2`` at a time, up to ``window_max_m`` or the first keyframe (the longest
        is used when none reaches the target)."""
        cfg = self.config
        length = cfg.window_m
        # a window stated rigid (bounds 0) does not grow: its odometry's bend, larger over a longer
        # path, would be kept out of the predicted error (a 12 m window of the drifting record gave
        # a
        # fix 11.0 cm off at 2.7 cm predicted, docs/multi-session-images.md)
        grows = stated_window_bounds(self.window_localization()) != (0.0, 0.0)
        while True:
            win = self.window(k, length)
            P, F, I = self.window_points(win, poses4, with_index=True)
            # arcs along the window's path
            veh = (
                aggregate_detections(
                    P,
                    F,
                    cfg.aggregation,
                    frame="estimate",
                    detection_arc_m=detection_arcs_m(poses4[win, :3], win, F),
                )
                if len(P)
                else LandmarkMap(np.zeros((0, 3)))
            )
            if (
                len(veh) >= cfg.window_target_landmarks
                or length >= cfg.window_max_m
                or win[0] == 0
                or not grows
            ):
                return win, P, F, I, veh, length
            length = min(length + cfg.window_m / 2, cfg.window_max_m)

    def window_points(
        self, keyframes: np.ndarray, poses4: np.ndarray | None, with_index: bool = False
    ):
        """Detections of `keyframes` placed with `poses4` (estimate) or odometry (None):
        (points (N, 3), keyframe of each (N,)[, index of each within its keyframe (N,)])."""
        pts, fr, ix = [], [], []
        for k in keyframes:
            kf = self.graph.keyframes[k]
            D = kf.detections_rover
            if len(D) == 0:
                continue
            if poses4 is None:
                T = kf.T_odo_rover
            else:
                roll, pitch = kf.roll_pitch_rad
                x, y, z, yaw = poses4[k]
                T = pose_to_matrix(x, y, z, roll, pitch, yaw)
            pts.append(transform_points(T, D))
            fr.append(np.full(len(D), k))
            ix.append(np.arange(len(D)))
        if not pts:
            out = (np.zeros((0, 3)), np.zeros(0, int), np.zeros(0, int))
        else:
            out = (np.concatenate(pts), np.concatenate(fr), np.concatenate(ix))
        return out if with_index else out[:2]

    def crop_sigma_m(self, k: int) -> float:
        """The position sigma (m) of keyframe k's prediction that sizes its attempt's reference
        crop (``crop_sigma``): the gate's drift model, or the bounds the window states (scale error
        s, heading drift d per metre) over the distance D since the last fix, from the gate's base
        sigmas b (m) and b_yaw: sqrt(b^2 + (s D)^2 + (yaw D / 2)^2), yaw = hypot(b_yaw, d D) - the
        gate's own form with the odometry's bounds for its rates."""
        gate_m, _ = self.graph.predicted_sigma(k)
        bounds = stated_window_bounds(self.window_localization())
        if self.config.crop_sigma is CropSigma.GATE or bounds is None or bounds == (0.0, 0.0):
            return gate_m  # none stated (fitted) or stated rigid: nothing to size it by
        scale, drift_deg = bounds
        g = self.config.fusion.gate
        dd = self.graph.distance_since_fix(k)
        yaw = math.hypot(math.radians(g.base_sigma_yaw_deg), math.radians(drift_deg) * dd)
        return min(gate_m, math.sqrt(g.base_sigma_m**2 + (scale * dd) ** 2 + (0.5 * yaw * dd) ** 2))

    def _attempt(self, k: int, frame: int, t: float) -> Attempt:
        cfg = self.config
        t0 = time.perf_counter()
        poses = self.graph.poses()
        win, P, F, I, veh, length = self.local_map(k, poses)
        att = Attempt(frame, t, k, len(veh), 0, False, False, window_m=float(length))
        ref, ref_index = self.reference, np.arange(len(self.reference))
        if cfg.crop_reference and len(veh):
            c = veh.positions_xyz[:, :2].mean(axis=0)
            radius = float(np.max(np.linalg.norm(veh.positions_xyz[:, :2] - c, axis=1)))
            R = radius + cfg.crop_sigmas * self.crop_sigma_m(k) + cfg.crop_margin_m
            near = np.linalg.norm(ref.positions_xyz[:, :2] - c, axis=1) <= R
            ref_index = np.flatnonzero(near)
            ref = ref.subset(ref_index)
        att.reference_landmarks = len(ref)
        att.time_mapping_s = time.perf_counter() - t0
        self.timings["mapping"] += att.time_mapping_s
        if len(veh) < cfg.min_window_landmarks:
            att.reason = f"too few local landmarks ({len(veh)} < {cfg.min_window_landmarks})"
            return att
        if not self.has_reference:
            att.reason = "no reference map"
            return att
        if len(ref) < 3:
            att.reason = f"reference has {len(ref)} landmarks near the predicted position"
            return att
        t0 = time.perf_counter()
        try:
            # the pose is judged where it is used (the rover now, keyframe k) and the distance
            # travelled between inliers and rover is measured along the window's path
            res = localize(
                ref,
                veh,
                self.window_localization(),
                query_xyz=poses[k : k + 1, :3],
                path_xyz=poses[win, :3],
            )
        except LunarLocError as exc:
            att.time_association_s = time.perf_counter() - t0
            self.timings["association"] += att.time_association_s
            att.reason = f"{type(exc).__name__}: {exc}"
            return att
        att.time_association_s = time.perf_counter() - t0
        self.timings["association"] += att.time_association_s
        att.inliers, att.reason, att.success = res.num_inliers, res.reason, bool(res.success)
        att.predicted_error_m = float(res.predicted_error_m)
        if not res.success:
            return att
        t0 = time.perf_counter()
        x, y, z, yaw = poses[k]
        roll, pitch = self.graph.keyframes[k].roll_pitch_rad
        T_est = pose_to_matrix(x, y, z, roll, pitch, yaw)
        T_fix = res.T_ref_veh @ T_est
        fix4 = np.array([T_fix[0, 3], T_fix[1, 3], T_fix[2, 3], yaw_of(T_fix[:3, :3])])
        inl = res.inliers
        Vp = veh.positions_xyz[inl[:, 0]]
        extent = max(float(np.max(np.linalg.norm(Vp[:, :2] - Vp[:, :2].mean(axis=0), axis=1))), 1.0)
        sig_m = (
            float(res.predicted_error_m)
            if math.isfinite(res.predicted_error_m)
            else cfg.fix_sigma_fallback_m
        )
        g = gate_fix(self.graph, att, k, fix4, sig_m, sig_m / extent)
        att.correction_yaw_deg = math.degrees(float(g.innovation[3]))
        att.fix_xyz = fix4[:3].tolist()
        att.fix_yaw_rad = float(fix4[3])
        att.inlier_vehicle_xyz = Vp.round(4).tolist()
        att.inlier_reference_xyz = ref.positions_xyz[inl[:, 1]].round(4).tolist()
        att.fix_distortion_m = float(res.distortion_error_m)
        att.fix_maps_from_detections = sum(m.sightings is not None for m in (ref, veh))
        last = next((a for a in reversed(self.attempts) if a.accepted), None)
        path = np.array([kf.path_m for kf in self.graph.keyframes], float)
        att.fix_carried_path_m = window_carried_path_m(
            Vp,
            P,
            path[F] if len(F) else np.zeros(0),
            F > (last.keyframe if last is not None else -1),
            float(path[k]),
            self.config.aggregation.radius_m,
        )
        att.fix_covariance_xyz = fix_stated_covariance(
            res, fix4[:3], att.fix_maps_from_detections, cfg, fix4[3], att.fix_carried_path_m
        ).tolist()
        att.fix_distortion_yaw_rad = math.radians(float(res.distortion_rotation_deg))
        att.fix_since_fix_s = t - last.time_s if last is not None else math.nan
        if last is not None:
            gb, gp = self.graph.predicted_heading_variance(k)
            att.fix_graph_yaw_var_bias_rad2, att.fix_graph_yaw_var_process_rad2 = gb, gp
            att.fix_graph_bias_turn_rad = self.graph.bias_turn_since_solve(k)
            kfs = self.graph.keyframes
            att.fix_since_fix_m = float(kfs[k].path_m - kfs[last.keyframe].path_m)
        ray, rng = window_ray_geometry(
            veh.positions_xyz[inl[:, 0]], P, poses[F, :3], self.config.aggregation.radius_m
        )
        att.fix_ray_xy_m, att.fix_range_m = ray.tolist(), rng
        att.fix_sigma_yaw_rad = math.sqrt(
            fix_stated_yaw_variance(
                res,
                Vp,
                att.fix_maps_from_detections,
                cfg,
                att.fix_since_fix_s,
                att.fix_graph_bias_turn_rad,
            )
        )
        T_true = self.T_map_rover_true[-1]
        if T_true is not None:
            att.fix_error_m = float(np.linalg.norm(fix4[:3] - T_true[:3, 3]))
            att.fix_error_xyz = (fix4[:3] - T_true[:3, 3]).tolist()
            att.fix_error_yaw_rad = float(wrap_angle(fix4[3] - yaw_of(T_true[:3, :3])))
        if g.accepted:
            if cfg.fix_kind is FixKind.POSE:
                self.graph.add_fix(k, fix4, sig_m, sig_m / extent)
            else:
                self._add_observations(veh, inl, ref, P, F, I, ref_index)
            self.graph.solve(cfg.active_window_m)
            att.accepted = True
        self.timings["fusion"] += time.perf_counter() - t0
        return att

    def _add_observations(
        self,
        veh: LandmarkMap,
        inl: np.ndarray,
        ref: LandmarkMap,
        P,
        F,
        I,
        ref_index: np.ndarray | None = None,
    ) -> None:
        """Tie every window detection of an inlier vehicle landmark to its reference landmark
        (`ref_index`: the index of each of `ref`'s landmarks in the full reference, which names
        the landmark whose error its ties share; its sigma is the one the reference states,
        :attr:`reference_sigmas`)."""
        from scipy.spatial import cKDTree

        V = veh.positions_xyz[inl[:, 0]]
        d, j = cKDTree(V).query(P, distance_upper_bound=self.config.aggregation.radius_m)
        ok = np.isfinite(d)
        if not np.any(ok):
            return
        kf, idx, lm = F[ok], I[ok], j[ok]
        targets = ref.positions_xyz[inl[lm, 1]]
        kfs = self.graph.keyframes
        p_rover = np.array([kfs[k].detections_rover[i] for k, i in zip(kf, idx)])
        rp = np.array([kfs[k].roll_pitch_rad for k in kf])
        keys = list(zip(kf.tolist(), idx.tolist()))
        rock = (np.arange(len(ref)) if ref_index is None else np.asarray(ref_index))[inl[lm, 1]]
        sig_xy, sig_z = self.reference_sigmas
        sig = np.column_stack([sig_xy[rock], sig_xy[rock], sig_z[rock]])
        self.graph.add_landmark_observations(
            keys,
            kf,
            p_rover,
            rp,
            targets,
            self.config.fusion.observation_sigma_m,
            rock.tolist(),
            sig,
        )

    # -------------------------------------------------------------- end of run
    def finish(
        self,
        num_image_frames: int,
        source: str = "",
        rocks=None,
        example=None,
        config: dict | None = None,
    ) -> LoopResult:
        """Final pose-graph solve and the smoothed (continuous) trajectory. `config`: the
        run's full configuration as written to its run folder."""
        t0 = time.perf_counter()
        self.graph.solve()
        T_kf = self.graph.correction_transforms()
        self.timings["fusion"] += time.perf_counter() - t0
        frames = np.asarray(self.frames)
        times = np.asarray(self.times)
        T_odo = np.asarray(self.T_odo_rover).reshape(-1, 4, 4)
        kf_t = np.array([kf.t_s for kf in self.graph.keyframes])
        corrected = interpolate_corrections(T_kf, kf_t, times, T_odo)
        poses = self.graph.poses()
        all_kf = np.arange(len(self.graph.keyframes))
        P, F = self.window_points(all_kf, poses)
        Po, Fo = self.window_points(all_kf, None)
        agg = self.config.aggregation
        vmap = (
            aggregate_detections(P, F, agg, frame="map")
            if len(P)
            else LandmarkMap(np.zeros((0, 3)), frame="map")
        )
        vodo = (
            aggregate_detections(Po, Fo, agg, frame="odometry")
            if len(Po)
            else LandmarkMap(np.zeros((0, 3)), frame="odometry")
        )
        gt = (
            None
            if any(g is None for g in self.T_map_rover_true)
            else np.asarray(self.T_map_rover_true).reshape(-1, 4, 4)
        )
        return LoopResult(
            frames,
            times,
            T_odo,
            np.asarray(self.T_map_rover_online).reshape(-1, 4, 4),
            corrected,
            gt,
            self.attempts,
            vmap,
            vodo,
            self.reference,
            dict(self.timings),
            num_image_frames,
            config or {},
            self.graph.scale,
            rocks,
            example,
            source,
        )


def gate_fix(graph, att: Attempt, k: int, fix4, sigma_m: float, sigma_yaw_rad: float):
    """The pose graph's gate on a fix at keyframe `k`, recorded on `att`: its Mahalanobis d2, the
    correction it would make (m) and, when it fails, the refusal reason. Returns the gate."""
    g = graph.gate(k, fix4, sigma_m, sigma_yaw_rad)
    att.gate_d2, att.correction_m = g.d2, float(np.linalg.norm(g.innovation[:3]))
    if not g.accepted:
        att.reason = (
            f"fix rejected by the gate (d2 {g.d2:.1f} > {g.threshold:.1f}; "
            f"correction {att.correction_m:.2f} m)"
        )
    return g


def interpolate_corrections(
    T_kf: np.ndarray, kf_t: np.ndarray, times: np.ndarray, T_odo_rover: np.ndarray
) -> np.ndarray:
    """Apply per-keyframe corrections T_map_odo (K, 4, 4), linearly interpolated in time
    (translation and yaw), to every frame's odometry pose (F, 4, 4): a continuous trajectory
    T_map_rover (F, 4, 4)."""
    yaw = np.unwrap(np.arctan2(T_kf[:, 1, 0], T_kf[:, 0, 0]))
    tx = [np.interp(times, kf_t, T_kf[:, i, 3]) for i in range(3)]
    ya = np.interp(times, kf_t, yaw)
    out = np.empty((len(times), 4, 4))
    for n in range(len(times)):
        c, s = math.cos(ya[n]), math.sin(ya[n])
        T = np.array(
            [[c, -s, 0, tx[0][n]], [s, c, 0, tx[1][n]], [0, 0, 1, tx[2][n]], [0, 0, 0, 1.0]]
        )
        out[n] = T @ T_odo_rover[n]
    return out


def fix_position_covariance(covariance: np.ndarray, point_xyz) -> np.ndarray:
    """3x3 position covariance (m^2) at map-frame point `point_xyz` of a localization's 6x6
    pose-error covariance about the map origin (``T_true = exp(xi) T``, ``xi = (rho, phi)``: a
    point p is off by ``rho + phi x p``, so ``A C A^T`` with ``A = [I, -[p]x]``)."""
    x, y, z = np.asarray(point_xyz, float).reshape(3)
    A = np.hstack([np.eye(3), np.array([[0.0, z, -y], [-z, 0.0, x], [y, -x, 0.0]])])
    return A @ np.asarray(covariance, float) @ A.T


def window_centre_bias_covariance(
    maps_from_detections: int, config: LoopConfig, heading_yaw_rad: float = math.nan
) -> np.ndarray:
    """The centre bias a window's few neighbouring rocks share (3x3, m^2): ``fix_centre_bias_m``
    per horizontal axis, ``fix_centre_bias_along_m`` along the heading `heading_yaw_rad` (map
    frame, rad; that part is left out where it is not finite) and ``fix_centre_bias_z_m``
    vertical, for each map built from detections (half the variance where one of the two maps
    is). No number of inliers averages it, so neither localize()'s residuals nor the pose
    graph's per-rock bias show it."""
    f = maps_from_detections / 2
    b, bz = config.fix_centre_bias_m, config.fix_centre_bias_z_m
    B = np.diag([f * b * b, f * b * b, f * bz * bz])
    ba = config.fix_centre_bias_along_m
    h = float(heading_yaw_rad)
    if ba > 0 and math.isfinite(h):
        u = np.array([math.cos(h), math.sin(h), 0.0])
        B = B + f * ba * ba * np.outer(u, u)
    return B


def fix_model_terms(
    distortion_m: float,
    maps_from_detections: int,
    config: LoopConfig,
    heading_yaw_rad: float = math.nan,
    carried_path_m: float = math.nan,
) -> np.ndarray:
    """What :func:`fix_stated_covariance` adds to localize()'s covariance at the rover (3x3,
    m^2): the distortion allowance re-counted in ``fix_distortion_sigmas`` sigmas, the
    window's centre bias (:func:`window_centre_bias_covariance`, along `heading_yaw_rad`) and
    the odometry's scale error ``fix_odometry_scale_sigma`` over `carried_path_m`, the path its
    prediction alone carried the inliers' sightings (along the heading; none where either is
    not finite)."""
    d = float(distortion_m)
    k = 1.0 / config.fix_distortion_sigmas**2 - 1.0
    dd = k * d * d / 2 if math.isfinite(d) and d > 0 else 0.0
    out = np.diag([dd, dd, 0.0]) + window_centre_bias_covariance(
        maps_from_detections, config, heading_yaw_rad
    )
    s, c, h = config.fix_odometry_scale_sigma, float(carried_path_m), float(heading_yaw_rad)
    if s > 0 and math.isfinite(c) and c > 0 and math.isfinite(h):
        u = np.array([math.cos(h), math.sin(h), 0.0])
        out = out + (s * c) ** 2 * np.outer(u, u)
    return out


def fix_stated_covariance(
    res,
    point_xyz,
    maps_from_detections: int,
    config: LoopConfig,
    heading_yaw_rad=math.nan,
    carried_path_m=math.nan,
) -> np.ndarray:
    """The 3x3 position covariance (m^2) a loop fix is stated with at the rover (map-frame
    `point_xyz`, heading `heading_yaw_rad`): localize()'s covariance there
    (:func:`fix_position_covariance`) with its distortion allowance (``res.distortion_error_m``,
    split over x and y at the rover) counted as ``config.fix_distortion_sigmas`` sigmas instead
    of one, plus the window's shared centre bias (``fix_centre_bias_m`` per horizontal axis,
    ``fix_centre_bias_along_m`` along the heading, ``fix_centre_bias_z_m`` vertical) times half
    the number of the two maps built from detections, and the odometry's scale error over the
    path its prediction carried the inliers' sightings, `carried_path_m`
    (:func:`fix_model_terms`)."""
    C = fix_position_covariance(res.covariance, point_xyz)
    return C + fix_model_terms(
        res.distortion_error_m, maps_from_detections, config, heading_yaw_rad, carried_path_m
    )


def window_yaw_bias_variance(inliers_xyz, maps_from_detections: int, config: LoopConfig) -> float:
    """The turn of a window's shared centre bias (rad^2): a bias that differs by
    ``fix_centre_bias_spread_m`` from one side of the inliers to the other turns the fit by
    about that over their rms horizontal radius about their centroid (a compact window turns
    most), for each map built from detections (half the variance where one is). Infinite when
    the inliers coincide horizontally; 0 without a spread."""
    b = config.fix_centre_bias_spread_m
    if not b > 0 or not maps_from_detections:
        return 0.0
    r = inlier_radius_m(inliers_xyz)
    return maps_from_detections / 2 * b * b / (r * r) if r > 0 else math.inf


def window_ray_geometry(
    inliers_xyz, points_xyz, viewpoints_xyz, radius_m: float
) -> tuple[np.ndarray, float]:
    """How a window's inlier rocks (n, 3) were seen: each window detection (`points_xyz` (N,
    3), taken from `viewpoints_xyz` (N, 3), the rover at its keyframe) within `radius_m` of an
    inlier belongs to it; per rock the mean horizontal ray (viewpoint to detection) and the
    mean horizontal range; returned: the mean ray over the rocks (2,) (m, map frame) and the
    mean range (m). NaN where no detection belongs to an inlier."""
    from scipy.spatial import cKDTree

    V = np.asarray(inliers_xyz, float).reshape(-1, 3)
    P = np.asarray(points_xyz, float).reshape(-1, 3)
    if not len(V) or not len(P):
        return np.full(2, np.nan), math.nan
    d, j = cKDTree(V).query(P, distance_upper_bound=radius_m)
    ok = np.isfinite(d)
    if not np.any(ok):
        return np.full(2, np.nan), math.nan
    ray = P[ok, :2] - np.asarray(viewpoints_xyz, float).reshape(-1, 3)[ok, :2]
    rocks = np.unique(j[ok])
    per_ray = np.array([ray[j[ok] == r].mean(axis=0) for r in rocks])
    rng = np.linalg.norm(ray, axis=1)
    per_rng = np.array([rng[j[ok] == r].mean() for r in rocks])
    return per_ray.mean(axis=0), float(per_rng.mean())


def window_carried_path_m(
    inliers_xyz, points_xyz, path_m, carried, rover_path_m: float, radius_m: float
) -> float:
    """The path (m) the odometry's prediction alone carried a window's inlier sightings to the
    rover: each window detection (`points_xyz` (N, 3)) within `radius_m` of an inlier (`inliers_xyz`
    (n, 3)) belongs to it; a detection from a keyframe the odometry carried (`carried` (N,),
    bool: after the pose graph's last accepted fix) counts the path from its keyframe
    (`path_m` (N,), the odometry path at it) to the rover (`rover_path_m`), the others 0; the
    mean per rock, averaged over the rocks. NaN where no detection belongs to an inlier."""
    from scipy.spatial import cKDTree

    V = np.asarray(inliers_xyz, float).reshape(-1, 3)
    P = np.asarray(points_xyz, float).reshape(-1, 3)
    if not len(V) or not len(P):
        return math.nan
    d, j = cKDTree(V).query(P, distance_upper_bound=radius_m)
    ok = np.isfinite(d)
    if not np.any(ok):
        return math.nan
    back = np.where(
        np.asarray(carried, bool), float(rover_path_m) - np.asarray(path_m, float), 0.0
    )[ok]
    rocks = j[ok]
    return float(np.mean([back[rocks == r].mean() for r in np.unique(rocks)]))


def inlier_radius_m(inliers_xyz) -> float:
    """The rms horizontal distance (m) of points (n, 3) from their centroid; NaN for none."""
    P = np.asarray(inliers_xyz, float).reshape(-1, 3)[:, :2]
    if not len(P):
        return math.nan
    return math.sqrt(float(np.mean(np.sum((P - P.mean(axis=0)) ** 2, axis=1))))


def fix_model_yaw_variance(
    distortion_yaw_rad: float,
    inliers_xyz,
    maps_from_detections: int,
    config: LoopConfig,
    since_fix_s: float = math.nan,
    bias_turn_rad: float = math.nan,
) -> float:
    """What :func:`fix_stated_yaw_variance` adds to localize()'s yaw variance (rad^2, may be
    negative): the window's heading-drift allowance re-counted in ``fix_heading_drift_sigmas``
    sigmas, the turn of the window's centre bias (:func:`window_yaw_bias_variance`) and the
    heading error the pose graph's prediction grew since its last accepted fix,
    ``fix_heading_rate_sigma_rad_s`` times `since_fix_s` (none where that is not finite: no
    fix yet, the window placed with the odometry) and ``fix_heading_turn_factor`` times the turn
    its heading bias carried into the prediction since its last solve, `bias_turn_rad` (none
    where not finite)."""
    d = float(distortion_yaw_rad)
    k = 1.0 / config.fix_heading_drift_sigmas**2 - 1.0
    dd = k * d * d if math.isfinite(d) and d > 0 else 0.0
    dt = float(since_fix_s)
    grown = (config.fix_heading_rate_sigma_rad_s * dt) ** 2 if math.isfinite(dt) else 0.0
    turn = float(bias_turn_rad)
    if math.isfinite(turn):
        grown += (config.fix_heading_turn_factor * turn) ** 2
    return dd + grown + window_yaw_bias_variance(inliers_xyz, maps_from_detections, config)


def fix_stated_yaw_variance(
    res,
    inliers_xyz,
    maps_from_detections: int,
    config: LoopConfig,
    since_fix_s=math.nan,
    bias_turn_rad=math.nan,
) -> float:
    """The yaw variance (rad^2) a loop fix is stated with: localize()'s (``covariance[5, 5]``:
    the registration's, the whole maps' shared bias and the window's heading-drift allowance
    ``res.distortion_rotation_deg`` as one sigma) with that allowance counted as
    ``config.fix_heading_drift_sigmas`` sigmas, plus the turn of the window's shared centre
    bias over its inliers `inliers_xyz` (n, 3) and the pose graph's heading error grown over
    `since_fix_s` seconds since its last accepted fix (:func:`fix_model_yaw_variance`)."""
    v = float(res.covariance[5, 5])
    d = math.radians(float(res.distortion_rotation_deg))
    # localize() adds no allowance where it is not finite (distortion_covariance)
    if not (math.isfinite(d) and math.isfinite(float(res.distortion_error_m))):
        d = 0.0
    v += fix_model_yaw_variance(
        d, inliers_xyz, maps_from_detections, config, since_fix_s, bias_turn_rad
    )
    return max(v, 0.0)


def stated_sigmas(m: LandmarkMap) -> tuple[np.ndarray, np.ndarray]:
    """A map's per-landmark (horizontal per axis, vertical) 1-sigma as it states them, 0 where
    it states none (a catalogue without sigmas, a simulated site's exact ``rocks.csv``)."""
    n = len(m)
    return (
        np.zeros(n) if m.sigma_xy_m is None else m.sigma_xy_m.copy(),
        np.zeros(n) if m.sigma_z_m is None else m.sigma_z_m.copy(),
    )
