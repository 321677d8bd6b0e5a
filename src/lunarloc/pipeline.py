"""Online localization over a whole traverse: detect, map, localize, fuse.

``run_online(archive, reference)`` reads like its table of contents:

1. play the `.lac` archive frame by frame through :class:`~lunarloc.data.playback.PlaybackAgent`
   (odometry from :func:`lunarloc.odometry.archive_odometry`: visual, IMU or a record;
   ground truth only for evaluation);
2. **detection**: on frames with stereo images, rocks in the rover frame
   (:class:`~lunarloc.perception.detector.Detector`); each image frame is a keyframe of
   the pose graph;
3. **mapping**: every ``localize_every_m`` metres (or ``localize_every_s`` seconds) the
   detections of the last ``window_m`` metres are placed with the current pose estimates
   and aggregated into a local landmark map;
4. **association**: the local map is localized in the reference map
   (:func:`lunarloc.localize.localize`, gravity-aware), the reference cropped to the
   region the predicted pose allows;
5. **fusion**: a successful localization becomes a fix of the newest keyframe; fixes that
   pass the chi-square gate enter the pose graph (:mod:`lunarloc.fusion`), which is
   re-solved and also calibrates the odometry scale and heading bias.

``run_traverse_csv`` runs the same loop on a traverse CSV (world-frame detections, no
images, as in the LunarLoc dataset) with simulated odometry drift.

Frames: ``ref`` (reference map / world frame, where ground truth lives), ``odo`` (the
drifting odometry frame; equals ``ref`` at the start), ``rover`` (body: x forward, y left,
z up). Metres, radians, seconds.
"""

from __future__ import annotations

import csv
import enum
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from lunarloc.errors import FileFormatError, InputError, LunarLocError
from lunarloc.fusion import FusionConfig, PoseGraph, wrap_angle
from lunarloc.geometry import matrix_to_pose, pose_to_matrix, transform_points, yaw_of
from lunarloc.localize import LocalizationConfig, localize
from lunarloc.maps import AggregationConfig, LandmarkMap, aggregate_detections, load_map

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = [
    "FixKind",
    "LoopConfig",
    "Attempt",
    "LoopResult",
    "LoopState",
    "rocks_to_reference",
    "load_reference",
    "scaled_detector_config",
    "build_reference_map",
    "run_online",
    "run_traverse_csv",
    "write_outputs",
    "ate",
]

ROCK_COLUMNS = ["id", "x", "y", "z", "radius"]


# --------------------------------------------------------------------------- configuration


class FixKind(str, enum.Enum):
    """How an accepted localization enters the pose graph."""

    LANDMARKS = "landmarks"  # each detection of an inlier rock is tied to its reference landmark (default)
    POSE = "pose"  # one pose fix of the newest keyframe (extrapolates the rigid fit to the rover)


@dataclass(frozen=True)
class LoopConfig:
    """Parameters of the online loop (distances in metres, times in seconds)."""

    localize_every_m: float = 1.5  # attempt a localization after this much odometry travel ...
    localize_every_s: float = 20.0  # ... or this much time, whichever comes first
    window_m: float = 12.0  # the local map holds detections of the last window_m metres of travel
    min_window_landmarks: int = 6  # fewer landmarks than this: no attempt (recorded as skipped)
    crop_reference: bool = True  # localize against the reference near the predicted window only
    crop_margin_m: float = 2.0  # crop radius = window radius + 3 x predicted sigma + this margin
    fix_kind: FixKind = FixKind.LANDMARKS  # how fixes enter the pose graph
    active_window_m: float = 40.0  # each solve re-optimises keyframes of the last active_window_m metres
    keyframe_every_s: float = 0.5  # traverse-CSV variant: keyframe period (frames with detections)
    aggregation: AggregationConfig = field(default_factory=lambda: AggregationConfig(min_sightings=2, min_frames=2))
    # windows stated rigid (odometry bounds 0), as before the fitted distortion: the loop passes
    # no path or rover position to localize() yet, and its pose graph and fix gate model the drift
    localization: LocalizationConfig = field(default_factory=lambda: LocalizationConfig(
        odometry_scale_error=0.0, odometry_heading_drift_deg_per_m=0.0))
    fusion: FusionConfig = field(default_factory=FusionConfig)

    def __post_init__(self) -> None:
        from lunarloc.errors import ConfigError

        if not all(0 < v < math.inf for v in (self.localize_every_m, self.localize_every_s, self.window_m)):
            raise ConfigError("localize_every_m, localize_every_s and window_m must be positive and finite")
        object.__setattr__(self, "fix_kind", FixKind(self.fix_kind))
        if self.min_window_landmarks < 3:
            raise ConfigError("min_window_landmarks must be >= 3")

    @classmethod
    def for_images(cls, **overrides) -> "LoopConfig":
        """Settings for detections from simulated stereo images (noisier than the real
        dataset's): 8 cm consistency tolerance and residual RMSE, an 8 m window (less odometry
        distortion inside it before the first fix), predicted error up to 15 cm."""
        loc = LocalizationConfig(epsilon_m=0.08, epsilon_z_m=0.08, max_rmse_m=0.08, refine_radius_m=0.16,
                                 max_predicted_error_m=0.15, odometry_scale_error=0.0,
                                 odometry_heading_drift_deg_per_m=0.0)  # fmt: skip
        return cls(**{"window_m": 8.0, "localization": loc, **overrides})

    def to_dict(self) -> dict:
        d = asdict(self)
        d["localization"] = self.localization.to_dict()
        d["fix_kind"] = self.fix_kind.value
        return d


# --------------------------------------------------------------------------- reference maps


def rocks_to_reference(rocks: np.ndarray, min_radius_m: float = 0.05, top_offset: float = 0.1) -> LandmarkMap:
    """Reference landmark map from a ground-truth rock list ``(N, 5) id, x, y, z, radius``.

    A vision detection of a rock lands on the centre of its *visible* part: horizontally
    the rock's centre (the detector shifts the surface centroid back by the estimated
    radius), vertically near the centroid of the part above ground, not the (possibly
    buried) ellipsoid centre. Measured on simulated sites, detections sit
    ``+0.1 x radius`` above the ellipsoid centre (median), so landmarks are placed at
    ``z + top_offset * radius``. Rocks smaller than `min_radius_m` are dropped: the
    detector does not see them (its size floor is a radius of about 6 cm), and keeping
    them would only add chance associations.
    """
    r = np.asarray(rocks, float)
    if r.ndim != 2 or r.shape[1] < 5:
        raise InputError(f"rock list must be (N, 5) id,x,y,z,radius; got shape {r.shape}")
    keep = r[:, 4] >= min_radius_m
    r = r[keep]
    pos = r[:, 1:4].copy()
    pos[:, 2] += top_offset * r[:, 4]
    return LandmarkMap(pos, sizes=2 * r[:, 4], frame="rocks")


def _is_rock_csv(path: Path) -> bool:
    from lunarloc.maps import _first_line

    return _first_line(path).split(",")[:5] == ROCK_COLUMNS


def load_reference(path: str | Path, config: AggregationConfig | None = None, min_radius_m: float = 0.05,
                   dem: str | Path | None = None) -> LandmarkMap:
    """A reference map from a landmark CSV/.npz, a traverse CSV, a rock list (``rocks.csv``:
    ``id,x,y,z,radius``, converted by :func:`rocks_to_reference`), a LAC geometric map
    (``.npy``, rocks grouped by :func:`lunarloc.overhead.grid_landmarks`) or a rock catalogue
    (``x,y[,z],radius[,sigma_m]``; heights from the LAC map `dem` when it has no ``z``).
    Raises InputError when empty."""
    from lunarloc import overhead

    from lunarloc.inputs import check_input_file

    path = check_input_file(path, None, "reference map")
    if path.suffix.lower() == ".npy":
        ref = overhead.grid_landmarks(overhead.load_lac_grid(path), frame=path.stem)
    elif path.suffix.lower() == ".csv" and overhead.is_rock_catalogue(path):
        ref = overhead.load_rock_catalogue(path, dem)
    elif path.suffix.lower() == ".csv" and _is_rock_csv(path):
        ref = rocks_to_reference(_load_rock_csv(path), min_radius_m)
    else:
        ref = load_map(path, config)
    if len(ref) < 3:
        raise InputError(f"{path}: reference map has {len(ref)} landmark(s); at least 3 are needed")
    return ref


def _load_rock_csv(path: Path) -> np.ndarray:
    """(N, 5) id, x, y, z, radius from a rock list CSV; FileFormatError naming file and line."""
    from lunarloc.maps import read_numeric_csv

    _, header, table = read_numeric_csv(path, tuple(ROCK_COLUMNS), "rock list CSV")
    return table[:, [header.index(c) for c in ROCK_COLUMNS]]


def scaled_detector_config(width: int, base=None):
    """Detector config for images `width` pixels wide: the pixel-sized parameters of the
    defaults (tuned at 1280 px) scaled to the resolution. Below 1280 px the range cap drops
    to 5 m and the SGBM block shrinks (coarser pixels, larger depth error at range)."""
    from dataclasses import replace

    from lunarloc.perception.detector import DetectorConfig

    base = base or DetectorConfig()
    f = width / 1280.0
    if abs(f - 1.0) < 1e-6:
        return base
    c, fl, st = base.classical, base.filters, base.stereo
    return replace(
        base,
        classical=replace(c, bg_median_px=max(16, int(c.bg_median_px * f)), min_area_px=max(4, int(c.min_area_px * f * f))),
        filters=replace(fl, min_area_px=max(4, int(fl.min_area_px * f * f)), max_range_m=min(fl.max_range_m, 5.0) if f < 1 else fl.max_range_m),
        stereo=replace(st, num_disparities=max(16, int(st.num_disparities * f) // 16 * 16), block_size=7 if f < 1 else st.block_size),
        height_filters=replace(base.height_filters, near_sigma_px=base.height_filters.near_sigma_px * f),
    )  # fmt: skip


def build_reference_map(
    archive_path: str | Path,
    detector_config=None,
    aggregation: AggregationConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> LandmarkMap:
    """Landmark map of an earlier traverse, built from its images with its (ground-truth)
    poses: the "map from a previous session" of LunarLoc (frame ``ref``)."""
    from lunarloc.data.lac import LacArchive
    from lunarloc.perception.detector import Detector, detect_archive

    with LacArchive(archive_path) as ar:
        cam = _camera_of(ar.configured_cameras)
        det = Detector(detector_config or scaled_detector_config(cam.width), cam)
        pts, frames = [], []
        lefts = [l for l, _ in det.config.pairs if l in ar.cameras]
        total = len({int(f) for c in lefts for f in ar.camera_frames(c)["frame"]})
        for n, fd in enumerate(detect_archive(ar, det.config, "ground-truth", detector=det), start=1):
            p = fd.positions_map()
            pts.append(p)
            frames.append(np.full(len(p), fd.frame))
            if progress:
                progress(n, total)
    if not pts:
        raise InputError(f"{archive_path}: no stereo image frames to build a reference map from")
    P = np.concatenate(pts)
    lm = aggregate_detections(P, np.concatenate(frames), aggregation or LoopConfig().aggregation, frame="ref")
    log.info("reference map from %s: %d detections -> %d landmarks", archive_path, len(P), len(lm))
    return lm


def _camera_of(cams: dict):
    from lunarloc.perception.camera import STEREO_PAIRS, PinholeCamera

    for left, _ in STEREO_PAIRS:
        c = cams.get(left)
        if c and c.get("camera_active", True):
            return PinholeCamera(int(c.get("width", 1280)), int(c.get("height", 720)), float(c.get("fov", 70.0)))
    return PinholeCamera()


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
    inlier_vehicle_xyz: list | None = None  # inlier landmarks in the estimate frame, before the fix
    inlier_reference_xyz: list | None = None
    time_mapping_s: float = 0.0
    time_association_s: float = 0.0

    def row(self) -> dict:
        d = asdict(self)
        for k in ("inlier_vehicle_xyz", "inlier_reference_xyz", "fix_xyz"):
            d.pop(k)
        return d


@dataclass
class LoopResult:
    """Everything a run produced (poses (F, 6): x, y, z, roll, pitch, yaw in ``ref``)."""

    frames: np.ndarray
    times: np.ndarray
    odometry: np.ndarray
    online: np.ndarray  # causal estimate: what the rover knew at each frame
    corrected: np.ndarray  # pose-graph estimate at the end of the run (continuous)
    ground_truth: np.ndarray | None
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

    def summary(self) -> dict:
        out: dict = {
            "source": self.source,
            "frames": int(len(self.frames)),
            "image_frames": int(self.num_image_frames),
            "duration_s": round(self.duration_s, 3),
            "path_length_m": round(_path_length(self.ground_truth if self.ground_truth is not None else self.odometry), 3),
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
        if self.ground_truth is not None:
            for name, est in (("odometry", self.odometry), ("corrected", self.corrected), ("online", self.online)):
                out[f"ate_{name}"] = ate(est, self.ground_truth)
            out["final_error_odometry_m"] = round(float(np.linalg.norm(self.odometry[-1, :3] - self.ground_truth[-1, :3])), 4)
            out["final_error_corrected_m"] = round(float(np.linalg.norm(self.corrected[-1, :3] - self.ground_truth[-1, :3])), 4)
        total = sum(self.timings_s.values())
        n = max(self.num_image_frames, 1)
        out["time_total_s"] = round(total, 3)
        out["time_per_image_frame_ms"] = {k: round(1000 * v / n, 2) for k, v in self.timings_s.items()}
        out["time_stage_total_s"] = {k: round(v, 3) for k, v in self.timings_s.items()}
        out["real_time_fraction"] = round(total / self.duration_s, 4) if self.duration_s > 0 else None
        return out


def ate(est: np.ndarray, gt: np.ndarray) -> dict:
    """Absolute trajectory error of positions (no alignment: both are in ``ref``): RMSE and
    max of the 3D error and RMSE of the horizontal error, metres."""
    e = np.linalg.norm(est[:, :3] - gt[:, :3], axis=1)
    eh = np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)
    return {"rmse_m": round(float(np.sqrt(np.mean(e**2))), 4), "max_m": round(float(e.max()), 4),
            "rmse_xy_m": round(float(np.sqrt(np.mean(eh**2))), 4)}  # fmt: skip


def _path_length(P: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(P[:, :3], axis=0), axis=1).sum()) if len(P) > 1 else 0.0


# --------------------------------------------------------------------------- the loop


class LoopState:
    """The loop's state, fed frame by frame (see module docstring); the per-tick component an
    agent calls is :class:`lunarloc.online.OnlineLocalizer`, built on this class.

    ``step(frame, t, odo_pose6, detections_rover=None, gt_pose6=None)``: every frame gives
    its odometry pose; keyframes (image frames) also give their detections in the rover
    frame, (N, 3). Ground truth, when given, is only used to score fixes.
    """

    def __init__(self, reference: LandmarkMap, config: LoopConfig | None = None):
        from lunarloc.warmup import warm_up

        warm_up()  # compile before any stage timer starts: compile time is not run time
        if not isinstance(reference, LandmarkMap):
            raise InputError("reference must be a LandmarkMap")
        if len(reference) < 3:
            raise InputError(f"reference map has {len(reference)} landmark(s); at least 3 are needed")
        self.reference = reference
        self.config = config or LoopConfig()
        self.graph = PoseGraph(self.config.fusion)
        self._ref_xy = None
        self.frames: list[int] = []
        self.times: list[float] = []
        self.odo: list[np.ndarray] = []
        self.online: list[np.ndarray] = []
        self.gt: list[np.ndarray] = []
        self.kf_frame: list[int] = []
        self.kf_rp: list[tuple[float, float]] = []  # odometry roll, pitch at keyframes
        self.kf_det: list[np.ndarray] = []
        self.kf_dist: list[float] = []
        self._kf_odo: list[np.ndarray] = []
        self.attempts: list[Attempt] = []
        self.timings = {"detection": 0.0, "mapping": 0.0, "association": 0.0, "fusion": 0.0}
        self._dist = 0.0
        self._moving_since_kf = 0.0
        self._last_attempt_dist = 0.0
        self._last_attempt_t = None
        self._T_corr = np.eye(4)  # current T_ref_odo (latest keyframe's correction)

    # -------------------------------------------------------------- per frame
    def step(self, frame: int, t: float, odo_pose6, detections_rover: np.ndarray | None = None,
             gt_pose6=None, keyframe: bool | None = None) -> Attempt | None:  # fmt: skip
        """Feed one frame; returns the localization attempt made at it, if any."""
        q = np.asarray(odo_pose6, float).reshape(6)
        if self.odo:
            step = float(np.linalg.norm(q[:3] - self.odo[-1][:3]))
            if step > 1e-6 or abs(float(wrap_angle(q[5] - self.odo[-1][5]))) > 1e-6:
                self._moving_since_kf += t - self.times[-1]
            self._dist += step
        self.frames.append(int(frame))
        self.times.append(float(t))
        self.odo.append(q)
        self.gt.append(None if gt_pose6 is None else np.asarray(gt_pose6, float).reshape(6))
        is_kf = (detections_rover is not None) if keyframe is None else keyframe
        attempt = None
        if is_kf or not self.kf_frame:
            attempt = self._keyframe(frame, t, q, np.zeros((0, 3)) if detections_rover is None else detections_rover)
        self.online.append(_apply_corr(self._T_corr, q))
        return attempt

    def _keyframe(self, frame, t, q, det) -> Attempt | None:
        t0 = time.perf_counter()
        k = self.graph.add_keyframe(t, (q[0], q[1], q[2], q[5]), self._moving_since_kf if self.kf_frame else None)
        self._moving_since_kf = 0.0
        self.timings["fusion"] += time.perf_counter() - t0
        self.kf_frame.append(int(frame))
        self.kf_rp.append((float(q[3]), float(q[4])))
        self._kf_odo.append(q)
        self.kf_det.append(np.asarray(det, float).reshape(-1, 3))
        self.kf_dist.append(self._dist)
        if self._last_attempt_t is None:
            self._last_attempt_t = t
        attempt = None
        cfg = self.config
        if self._dist - self._last_attempt_dist >= cfg.localize_every_m or t - self._last_attempt_t >= cfg.localize_every_s:
            self._last_attempt_dist, self._last_attempt_t = self._dist, t
            attempt = self._attempt(k, frame, t)
            self.attempts.append(attempt)
        self._T_corr = self._correction(k)
        return attempt

    def _correction(self, k: int) -> np.ndarray:
        est = self.graph.pose(k)
        o = self.odo_at_keyframe(k)
        d = float(wrap_angle(est[3] - o[5]))
        c, s = math.cos(d), math.sin(d)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:3, 3] = est[:3] - T[:3, :3] @ o[:3]
        return T

    def odo_at_keyframe(self, k: int) -> np.ndarray:
        """Odometry pose (6,) of keyframe k."""
        return self._kf_odo[k]

    def _window_points(self, keyframes: np.ndarray, poses4: np.ndarray | None, with_index: bool = False):
        """Detections of `keyframes` placed with `poses4` (estimate) or odometry (None):
        (points (N, 3), keyframe of each (N,)[, index of each within its keyframe (N,)])."""
        pts, fr, ix = [], [], []
        for k in keyframes:
            D = self.kf_det[k]
            if len(D) == 0:
                continue
            roll, pitch = self.kf_rp[k]
            if poses4 is None:
                o = self._kf_odo[k]
                T = pose_to_matrix(o[0], o[1], o[2], roll, pitch, o[5])
            else:
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

    def _attempt(self, k: int, frame: int, t: float) -> Attempt:
        cfg = self.config
        t0 = time.perf_counter()
        dist = np.asarray(self.kf_dist)
        win = np.flatnonzero(dist >= dist[k] - cfg.window_m)
        poses = self.graph.poses()
        P, F, I = self._window_points(win, poses, with_index=True)
        veh = aggregate_detections(P, F, cfg.aggregation, frame="estimate") if len(P) else LandmarkMap(np.zeros((0, 3)))
        att = Attempt(frame, t, k, len(veh), 0, False, False)
        ref = self.reference
        if cfg.crop_reference and len(veh):
            c = veh.positions_xyz[:, :2].mean(axis=0)
            radius = float(np.max(np.linalg.norm(veh.positions_xyz[:, :2] - c, axis=1)))
            sig, _ = self.graph.predicted_sigma(k)
            R = radius + 3 * sig + cfg.crop_margin_m
            near = np.linalg.norm(ref.positions_xyz[:, :2] - c, axis=1) <= R
            ref = ref.subset(np.flatnonzero(near))
        att.reference_landmarks = len(ref)
        att.time_mapping_s = time.perf_counter() - t0
        self.timings["mapping"] += att.time_mapping_s
        if len(veh) < cfg.min_window_landmarks:
            att.reason = f"too few local landmarks ({len(veh)} < {cfg.min_window_landmarks})"
            return att
        if len(ref) < 3:
            att.reason = f"reference has {len(ref)} landmarks near the predicted position"
            return att
        t0 = time.perf_counter()
        try:
            res = localize(ref, veh, cfg.localization)
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
        roll, pitch = self.kf_rp[k]
        T_est = pose_to_matrix(x, y, z, roll, pitch, yaw)
        T_fix = res.T_ref_veh @ T_est
        fix4 = np.array([T_fix[0, 3], T_fix[1, 3], T_fix[2, 3], yaw_of(T_fix[:3, :3])])
        inl = res.inliers
        Vp = veh.positions_xyz[inl[:, 0]]
        extent = max(float(np.max(np.linalg.norm(Vp[:, :2] - Vp[:, :2].mean(axis=0), axis=1))), 1.0)
        sig_m = float(res.predicted_error_m) if math.isfinite(res.predicted_error_m) else 0.05
        g = self.graph.gate(k, fix4, sig_m, sig_m / extent)
        att.gate_d2 = g.d2
        att.correction_m = float(np.linalg.norm(g.innovation[:3]))
        att.correction_yaw_deg = math.degrees(float(g.innovation[3]))
        att.fix_xyz = fix4[:3].tolist()
        att.inlier_vehicle_xyz = Vp.round(4).tolist()
        att.inlier_reference_xyz = ref.positions_xyz[inl[:, 1]].round(4).tolist()
        gt = self.gt[-1]
        if gt is not None:
            att.fix_error_m = float(np.linalg.norm(fix4[:3] - gt[:3]))
        if g.accepted:
            if cfg.fix_kind is FixKind.POSE:
                self.graph.add_fix(k, fix4, sig_m, sig_m / extent)
            else:
                self._add_observations(veh, inl, ref, P, F, I)
            self.graph.solve(cfg.active_window_m)
            att.accepted = True
        else:
            att.reason = f"fix rejected by the gate (d2 {g.d2:.1f} > {g.threshold:.1f}; correction {att.correction_m:.2f} m)"
        self.timings["fusion"] += time.perf_counter() - t0
        return att

    def _add_observations(self, veh: LandmarkMap, inl: np.ndarray, ref: LandmarkMap, P, F, I) -> None:
        """Tie every window detection of an inlier vehicle landmark to its reference landmark."""
        from scipy.spatial import cKDTree

        V = veh.positions_xyz[inl[:, 0]]
        d, j = cKDTree(V).query(P, distance_upper_bound=self.config.aggregation.radius_m)
        ok = np.isfinite(d)
        if not np.any(ok):
            return
        kf, idx, lm = F[ok], I[ok], j[ok]
        targets = ref.positions_xyz[inl[lm, 1]]
        p_rover = np.array([self.kf_det[k][i] for k, i in zip(kf, idx)])
        rp = np.array([self.kf_rp[k] for k in kf])
        keys = list(zip(kf.tolist(), idx.tolist()))
        self.graph.add_landmark_observations(keys, kf, p_rover, rp, targets, self.config.fusion.observation_sigma_m)

    # -------------------------------------------------------------- end of run
    def finish(self, num_image_frames: int, source: str = "", rocks=None, example=None,
               config_extra: dict | None = None) -> LoopResult:  # fmt: skip
        """Final pose-graph solve and the smoothed (continuous) trajectory."""
        t0 = time.perf_counter()
        self.graph.solve()
        T_kf = np.stack([self._correction(k) for k in range(len(self.kf_frame))])
        self.timings["fusion"] += time.perf_counter() - t0
        frames = np.asarray(self.frames)
        times = np.asarray(self.times)
        odo = np.asarray(self.odo)
        kf_t = times[np.searchsorted(frames, np.asarray(self.kf_frame))]
        corrected = _interpolate_corrections(T_kf, kf_t, times, odo)
        poses = self.graph.poses()
        all_kf = np.arange(len(self.kf_frame))
        P, F = self._window_points(all_kf, poses)
        Po, Fo = self._window_points(all_kf, None)
        agg = self.config.aggregation
        vmap = aggregate_detections(P, F, agg, frame="ref") if len(P) else LandmarkMap(np.zeros((0, 3)), frame="ref")
        vodo = aggregate_detections(Po, Fo, agg, frame="odometry") if len(Po) else LandmarkMap(np.zeros((0, 3)), frame="odometry")
        gt = None if any(g is None for g in self.gt) else np.asarray(self.gt)
        cfg = {"loop": self.config.to_dict(), **(config_extra or {})}
        return LoopResult(frames, times, odo, np.asarray(self.online), corrected, gt, self.attempts, vmap, vodo,
                          self.reference, dict(self.timings), num_image_frames, cfg, self.graph.scale,
                          rocks, example, source)  # fmt: skip


def _apply_corr(T_ref_odo: np.ndarray, q: np.ndarray) -> np.ndarray:
    T = T_ref_odo @ pose_to_matrix(*q)
    return np.asarray(matrix_to_pose(T), float)


def _interpolate_corrections(T_kf: np.ndarray, kf_t: np.ndarray, times: np.ndarray, odo: np.ndarray) -> np.ndarray:
    """Apply per-keyframe corrections T_ref_odo, linearly interpolated in time (translation and
    yaw), to every frame's odometry pose: a continuous trajectory."""
    yaw = np.unwrap(np.arctan2(T_kf[:, 1, 0], T_kf[:, 0, 0]))
    tx = [np.interp(times, kf_t, T_kf[:, i, 3]) for i in range(3)]
    ya = np.interp(times, kf_t, yaw)
    out = np.empty_like(odo)
    for n in range(len(times)):
        c, s = math.cos(ya[n]), math.sin(ya[n])
        T = np.array([[c, -s, 0, tx[0][n]], [s, c, 0, tx[1][n]], [0, 0, 1, tx[2][n]], [0, 0, 0, 1.0]])
        out[n] = _apply_corr(T, odo[n])
    return out


# --------------------------------------------------------------------------- archives


def run_online(
    archive: str | Path,
    reference: LandmarkMap,
    config: LoopConfig | None = None,
    detector_config=None,
    *,
    max_frames: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    odometry: np.ndarray | None = None,
    odometry_source: str | None = None,
) -> LoopResult:
    """Run the online loop over a `.lac` archive.

    odometry_source : where the odometry comes from (:class:`lunarloc.odometry.OdometrySource`:
        ``visual``, ``imu``, ``record:NAME``, ``ground-truth``); default ``visual`` when the
        archive has front stereo pairs, else ``imu``. The run's config names it.
    odometry : optional (F, 6) odometry poses (x, y, z, roll, pitch, yaw), one per archive
        frame in order, replacing the source (to replay the images with another drift).

    reference : map in the ``ref`` frame (see :func:`load_reference`).
    config : default :meth:`LoopConfig.for_images`.
    detector_config : default scales :class:`DetectorConfig` to the archive's image width.
    """
    from lunarloc.data.lac import LacArchive
    from lunarloc.data.playback import PlaybackAgent
    from lunarloc.perception.camera import CameraMount
    from lunarloc.perception.detector import Detector

    cfg = config or LoopConfig.for_images()
    loop = LoopState(reference, cfg)
    t_io = 0.0
    t0 = time.perf_counter()
    ar = LacArchive(archive)
    with PlaybackAgent(ar) as agent:
        if odometry is not None:
            od_arr = np.asarray(odometry, float)
            if od_arr.shape != (len(ar.frame_numbers), 6):
                raise InputError(f"odometry override must be ({len(ar.frame_numbers)}, 6), got {od_arr.shape}")
            odo = {int(f): r for f, r in zip(ar.frame_numbers, od_arr)}
            odo_label = "override"
        else:
            from lunarloc.odometry import archive_odometry, default_odometry_source

            ta = time.perf_counter()
            t_io += ta - t0
            odo_traj = archive_odometry(ar, odometry_source or default_odometry_source(ar))
            loop.timings["odometry"] = time.perf_counter() - ta
            odo = {int(f): r for f, r in zip(odo_traj.frames, odo_traj.poses6())}
            odo_label = odo_traj.label
            t0 = time.perf_counter()  # the odometry's time is counted apart from I/O
        cam = _camera_of(ar.configured_cameras)
        det_cfg = detector_config or scaled_detector_config(cam.width)
        detector = Detector(det_cfg, cam)
        lefts = [l for l, _ in det_cfg.pairs if l in ar.cameras]
        if not lefts:
            raise FileFormatError(f"{archive}: no left stereo camera recorded images (have: {', '.join(ar.cameras) or 'none'})")
        image_frames = {int(f) for c in lefts for f in ar.camera_frames(c)["frame"]}
        rocks = None
        if "rocks" in ar.custom_records:
            rocks = ar.custom("rocks").to_array(tuple(ROCK_COLUMNS))
        n_total = len(ar.frame_numbers) if max_frames is None else min(max_frames, len(ar.frame_numbers))
        t_io += time.perf_counter() - t0
        n_img = 0
        best_example = None
        for n, frame in enumerate(agent, start=1):
            if n > n_total:
                break
            ta = time.perf_counter()
            if frame not in odo:
                raise FileFormatError(f"{archive}: no odometry pose at frame {frame}")
            gt = agent.get_transform().as_tuple()
            t = agent.get_mission_time()
            det_rover = None
            t_io += time.perf_counter() - ta
            if frame in image_frames:
                ta = time.perf_counter()
                images = {k: v for k, v in agent.input_data().get("Grayscale", {}).items() if v is not None}
                mounts = {name: CameraMount(name, agent.get_camera_position(name).matrix(), cam)
                          for name in images}  # fmt: skip
                t_io += time.perf_counter() - ta
                ta = time.perf_counter()
                fd = detector.detect_frame(images, mounts, None, frame)
                loop.timings["detection"] += time.perf_counter() - ta
                dets = fd.detections
                det_rover = np.array([d.p_rover for d in dets], float).reshape(-1, 3)
                n_img += 1
                if dets and (best_example is None or len(dets) > best_example["n"]):
                    left = fd.pairs[0].camera if fd.pairs else lefts[0]
                    best_example = {
                        "n": len(dets), "frame": int(frame), "camera": left, "image": images[left],
                        "uv": np.array([d.uv for d in dets if d.camera == left], float).reshape(-1, 2),
                        "radius_px": np.array([d.radius_m / d.depth_m * cam.fx for d in dets if d.camera == left]),
                        "depth_m": np.array([d.depth_m for d in dets if d.camera == left]),
                    }  # fmt: skip
            loop.step(frame, t, odo[frame], det_rover, gt, keyframe=frame in image_frames)
            if progress:
                progress(n, n_total)
    ar.close()
    if n_img == 0:
        raise InputError(f"{archive}: no image frames were played; nothing to localize")
    loop.timings["io"] = t_io
    extra = {"archive": str(archive), "odometry_source": odo_label, "detector": det_cfg.to_dict(), "camera": asdict(cam)}
    return loop.finish(n_img, str(archive), rocks, best_example, extra)


# --------------------------------------------------------------------------- traverse CSV (no images)


def run_traverse_csv(
    traverse,
    reference: LandmarkMap,
    drift=None,
    config: LoopConfig | None = None,
    rate_hz: float = 20.0,
) -> LoopResult:
    """The loop on a traverse CSV (world-frame detections, no images) with simulated drift.

    Odometry follows :func:`lunarloc.evaluation.drifted_detections` (scale error and a
    heading error growing with distance). The CSV has no rover heading, so the "rover" frame
    here is world-aligned at the rover's position: its true yaw is 0, its odometry yaw is the
    accumulated heading error, and a detection's rover-frame offset is ``det - rover``.
    Keyframes are frames with detections, at least ``keyframe_every_s`` apart, plus one at
    least every 2 s. Frame time is frame number / `rate_hz`.
    """
    from lunarloc.evaluation import DriftModel, drifted_path
    from lunarloc.maps import Traverse, load_traverse

    trav: Traverse = traverse if isinstance(traverse, Traverse) else load_traverse(traverse)
    drift = drift or DriftModel(0.05, 0.02)
    cfg = config or LoopConfig()
    g = trav.rover_xyz
    o, psi = drifted_path(g, drift)
    order = np.argsort(trav.detection_frame, kind="stable")
    df = trav.detection_frame[order]
    dx = trav.detections_xyz[order]
    loop = LoopState(reference, cfg)
    times = trav.frames.astype(float) / rate_hz
    last_kf_t = -np.inf
    n_kf = 0
    for i, f in enumerate(trav.frames):
        a, b = np.searchsorted(df, f, "left"), np.searchsorted(df, f, "right")
        t = times[i]
        dets = dx[a:b] - g[i] if b > a else None
        is_kf = (dets is not None and t - last_kf_t >= cfg.keyframe_every_s) or t - last_kf_t >= 2.0
        if is_kf:
            last_kf_t = t
            n_kf += 1
            ta = time.perf_counter()
            det_r = np.zeros((0, 3)) if dets is None else dets.copy()
            loop.timings["detection"] += time.perf_counter() - ta
        loop.step(int(f), t, (o[i, 0], o[i, 1], o[i, 2], 0.0, 0.0, psi[i]),
                  det_r if is_kf else None, (g[i, 0], g[i, 1], g[i, 2], 0.0, 0.0, 0.0), keyframe=is_kf)  # fmt: skip
    extra = {"traverse": trav.name, "drift": asdict(drift), "rate_hz": rate_hz}
    return loop.finish(n_kf, trav.name, None, None, extra)


# --------------------------------------------------------------------------- outputs


def _write_tum(path: Path, times: np.ndarray, poses: np.ndarray) -> None:
    from scipy.spatial.transform import Rotation

    from lunarloc.outputs import atomic_open

    q = Rotation.from_euler("ZYX", poses[:, [5, 4, 3]]).as_quat()  # x, y, z, w; R = Rz Ry Rx
    with atomic_open(path, "w") as fh:
        for t, p, qq in zip(times, poses, q):
            fh.write(f"{t:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {qq[0]:.8f} {qq[1]:.8f} {qq[2]:.8f} {qq[3]:.8f}\n")


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(times (F,), poses (F, 6) x, y, z, roll, pitch, yaw) from a TUM file."""
    from scipy.spatial.transform import Rotation

    a = np.loadtxt(path, ndmin=2)
    eul = Rotation.from_quat(a[:, 4:8]).as_euler("ZYX")
    return a[:, 0], np.column_stack([a[:, 1:4], eul[:, 2], eul[:, 1], eul[:, 0]])


def write_outputs(result: LoopResult, outdir: str | Path) -> dict:
    """Write a run to `outdir`; returns the summary. Files:

    ``trajectory.tum`` (corrected, pose graph at the end of the run), ``trajectory_online.tum``
    (causal), ``trajectory_odometry.tum``, ``trajectory_groundtruth.tum`` (if known),
    ``attempts.csv`` and ``attempts.json`` (every localization attempt), ``vehicle_map.csv``
    (corrected frame), ``vehicle_map_odometry.csv``, ``reference_map.csv``, ``rocks.csv`` (if
    known), ``config.json``, ``summary.json``, ``example_frame.npz`` (one camera frame with
    its detections, when images were used).

    Every file is written to a temporary name and renamed (:mod:`lunarloc.outputs`), so an
    interrupted run leaves no truncated file; ``summary.json``, written last, marks a
    complete run.
    """
    from lunarloc.maps import save_map
    from lunarloc.outputs import atomic_open, atomic_path, make_dir, write_text

    out = make_dir(outdir)
    _write_tum(out / "trajectory.tum", result.times, result.corrected)
    _write_tum(out / "trajectory_online.tum", result.times, result.online)
    _write_tum(out / "trajectory_odometry.tum", result.times, result.odometry)
    if result.ground_truth is not None:
        _write_tum(out / "trajectory_groundtruth.tum", result.times, result.ground_truth)
    rows = [a.row() for a in result.attempts]
    keys = list(Attempt(0, 0.0, 0, 0, 0, False, False).row().keys())
    with atomic_open(out / "attempts.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    write_text(out / "attempts.json", json.dumps([_clean(asdict(a)) for a in result.attempts], indent=1))
    save_map(result.vehicle_map, out / "vehicle_map.csv")
    save_map(result.vehicle_map_odometry, out / "vehicle_map_odometry.csv")
    save_map(result.reference, out / "reference_map.csv")
    if result.rocks is not None:
        with atomic_path(out / "rocks.csv") as tmp:
            np.savetxt(tmp, result.rocks, delimiter=",", header=",".join(ROCK_COLUMNS), comments="",
                       fmt=["%d", "%.5f", "%.5f", "%.5f", "%.5f"])  # fmt: skip
    if result.example is not None:
        ex = result.example
        with atomic_path(out / "example_frame.npz") as tmp:
            np.savez_compressed(tmp, image=ex["image"], uv=ex["uv"], radius_px=ex["radius_px"],
                                depth_m=ex["depth_m"], frame=ex["frame"], camera=ex["camera"])  # fmt: skip
    write_text(out / "config.json", json.dumps(_clean(result.config), indent=2, default=str))
    summary = result.summary()
    write_text(out / "summary.json", json.dumps(_clean(summary), indent=2))
    return summary


def _clean(x):
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return _clean(x.item())
    if hasattr(x, "value") and not isinstance(x, (int, float, str)):
        return x.value
    return x
