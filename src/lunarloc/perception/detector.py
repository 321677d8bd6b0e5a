"""Frame -> 3D rock detections (LunarLoc "Open-Set Object-Based Mapping").

For each stereo pair (front and rear, same pass): segment the left image, compute
mask statistics, drop masks that fail the image-only filters (pixel count, border,
elongation), compute SGBM depth for the rows the survivors occupy, read the depth
at each centroid (median of valid depths in a small window), apply the size and
range filters (``s_i = sigma_i * D_i * alpha``), back-project the centroid into the
left optical frame, optionally move it from the visible surface to the estimated
centre of the rock (the paper assumes spherical objects), then into the rover frame
(camera pose from the archive's camera table or the IPEx rig) and the map frame
(rover pose: ground truth or odometry, the caller's choice).

With the height map (the classical segmenter, STEREO_POINTS centres) one pair runs as these
named steps (:meth:`Detector._detect_pair_height`): the levelled height map, the blobs cut
at their depth steps, then per blob (:meth:`Detector._judge_mask`) the image filters, depth
and size, the centre and the measures the rejection rules judge (the rule table of
:mod:`lunarloc.perception.rules`, each switchable by ``rules.off``), the lander's footprint;
then the small-rock stage, duplicates and unconfirmed tentatives. The settings are
:class:`~lunarloc.perception.detector_config.DetectorConfig`'s sections.

Frames: ``p_optical`` (OpenCV optical frame of the left camera), ``p_rover`` (rover
body: x forward, y left, z up), ``p_map`` (site / world frame). Metres throughout.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from lunarloc.core.errors import InputError, import_cv2
from lunarloc.core.geometry import invert_transform, pose_to_matrix, transform_points
from lunarloc.core.stats import median as _median
from lunarloc.perception.camera import (
    CameraMount,
    PinholeCamera,
    camera_from_archive,
    ipex_rig,
    mounts_from_archive_row,
)
from lunarloc.perception.detector_config import (
    CentreEstimator,
    CentreFusion,
    CentreMethod,
    DetectorConfig,
    PoseSource,
)
from lunarloc.perception.images import gradient_magnitude
from lunarloc.perception.masks import (
    InstanceMask,
    InstanceMasks,
    MaskFilterConfig,
    MaskStats,
    RejectReason,
    classify_mask,
    image_reject_reason,
    mask_stats,
    size_from_sigma,
)
from lunarloc.perception.rules import (
    TENTATIVE_RULES,
    BlobMeasures,
    fired_rules,
    is_flat_strip,
    is_raised_strip,
)
from lunarloc.perception.segment import (
    Segmenter,
    make_segmenter,
)
from lunarloc.perception.small_rocks import (
    detect_small_rocks,
    ground_plane,
)
from lunarloc.perception.stereo import (
    HeightMap,
    StereoMatcher,
    depth_at,
    fill_ground_heights,
    first_ground_row,
    ground_height_map,
    mask_disparity_fullres,
    refine_disparity,
    to_gray_u8,
)
from lunarloc.perception.verifier import (
    blob_features,
    default_verifier,
    verifier_named,
    verifier_threshold,
)

__all__ = [
    "PoseSource",
    "CentreMethod",
    "CentreEstimator",
    "CentreFusion",
    "DetectorConfig",
    "Detection",
    "MaskRecord",
    "PairResult",
    "FrameDetections",
    "Detector",
    "mounts_from_archive_row",
    "on_lander",
    "overlapping_duplicates",
    "split_at_depth_steps",
    "detect_archive",
    "fuse_track_centres",
    "debug_overlay",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())


@dataclass(frozen=True)
class Detection:
    """One kept mask lifted to 3D.

    camera : left camera name; uv : image centroid (pixels); depth_m : depth z at the
    centroid (optical frame, metres); size_m : s_i; radius_m : estimated rock radius;
    p_optical / p_rover / p_map : (3,) centroid (centre-corrected if configured) in
    each frame; p_map is None when no rover pose was given.
    """

    camera: str
    uv: tuple[float, float]
    depth_m: float
    sigma_px: float
    eig_ratio: float
    area_px: int
    size_m: float
    radius_m: float
    p_optical: np.ndarray
    p_rover: np.ndarray
    p_map: np.ndarray | None
    # its visible top above the local ground, the ground in front of it (NaN when too
    # few points there) and the upper quartile of the heights around it (metres; NaN
    # without stereo points)
    height_m: float = float("nan")
    height_front_m: float = float("nan")
    height_ring_m: float = float("nan")
    # its visible top above a quadric ground surface fitted to the stereo points in the
    # ring around it (metres; NaN when too few)
    height_quadric_m: float = float("nan")
    # fraction of the valid depths in the ring around it nearer than
    # nearer_depth_ratio x its depth (NaN without stereo points)
    nearer_ring_fraction: float = float("nan")
    # median highest height just beyond its left and right ends over its own top
    # (NaN when not measured: blobs of radius >= crest_max_radius_m)
    extension_ratio: float = float("nan")
    # fraction of rough second differences of the full-resolution disparity (see
    # DetectorConfig.rules.max_disparity_roughness); NaN when not measured
    disparity_roughness: float = float("nan")
    # a low blob on a crest, to be confirmed by a neighbouring frame (see
    # DetectorConfig.confirm.tol_m)
    needs_confirmation: bool = False
    # a tentative mid-range detection: the name of the marginal rule that would have
    # rejected it ("" = a firm detection); kept only when a neighbouring frame's firm
    # detection confirms it (see DetectorConfig.tentative.max_range_m)
    tentative: str = ""
    # found by the small-rock stage (DetectorConfig.small_rocks), not by the height map; its
    # local ground's residual spread (metres; NaN for the height map's detections)
    small_rock: bool = False
    ground_noise_m: float = float("nan")
    # upper (DetectorConfig.rules.gradient_quantile) quantile of the image's gradient magnitude
    # over the mask and a rim around it (grey levels per pixel; see image_gradient); NaN when
    # not measured
    image_gradient: float = float("nan")
    # the learned verifier's P(rock) (perception/verifier.py; DetectorConfig.rules.
    # verifier_min_score); NaN when not scored
    verifier_score: float = float("nan")


@dataclass
class MaskRecord:
    """A mask with its statistics and the filter outcome (for debugging and overlays)."""

    mask_index: int
    stats: MaskStats
    depth_m: float
    size_m: float
    reason: RejectReason | None
    # the marginal rules that made its detection tentative (Detection.tentative; "" = firm
    # or never a detection), kept when the detection is later dropped
    tentative: str = ""
    # what judged a NOT_A_ROCK blob no rock: the rules that fired, joined by "+", or
    # "verifier" (the learned blob verifier's score under its threshold); "" otherwise
    rejected_by: str = ""


@dataclass
class PairResult:
    """Everything computed for one stereo pair in one frame."""

    camera: str
    masks: InstanceMasks
    records: list[MaskRecord]
    detections: list[Detection]
    depth: np.ndarray | None
    height: HeightMap | None = None
    # the left camera's pose on the rover (4x4, optical -> rover) the pair was lifted with;
    # None when unknown (fuse_track_centres then leaves p_optical as it was)
    T_rover_optical: np.ndarray | None = None


@dataclass
class FrameDetections:
    """Detections of one frame over all pairs, with per-stage timings (seconds)."""

    frame: int
    T_map_rover: np.ndarray | None
    pairs: list[PairResult] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def detections(self) -> list[Detection]:
        return [d for p in self.pairs for d in p.detections]

    def positions_map(self) -> np.ndarray:
        """(N, 3) map-frame centroids (empty if no pose)."""
        pts = [d.p_map for d in self.detections if d.p_map is not None]
        return np.array(pts, dtype=float).reshape(-1, 3)


@dataclass
class _PairScene:
    """What each mask of one stereo pair is judged against: the images, the height map, the
    frames (levelled when the height map is), the filters of its masks and where it is placed."""

    config: DetectorConfig
    L: np.ndarray
    right: np.ndarray
    hm: HeightMap
    image_shape: tuple[int, int]
    fc: MaskFilterConfig
    T_rover_optical: np.ndarray
    T_map_rover: np.ndarray | None
    camera_name: str
    lander_xy: np.ndarray | None
    _ground_points: np.ndarray | None = None
    _ground_cam_d2: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.T_optical_rover = np.linalg.inv(self.T_rover_optical)

    @property
    def stereo_rules(self) -> bool:
        """Height blobs with STEREO_POINTS centres: the strips, the tentatives and the
        small-rock stage apply."""
        return (
            self.fc is self.config.height_filters
            and self.config.centre.method is CentreMethod.STEREO_POINTS
        )

    @property
    def tentative_on(self) -> bool:
        return self.config.tentative.max_range_m > 0 and self.stereo_rules

    @property
    def ground_points(self) -> np.ndarray:
        """Every 8th valid stereo point of the height map (rover frame): the ground in front
        of a blob is read from these (computed on first use)."""
        if self._ground_points is None:
            # the same points as points_rover[isfinite(depth)][::8], gathering only those kept
            idx = np.flatnonzero(np.isfinite(self.hm.depth).ravel())[::8]
            # column-major: _height_above_surroundings reads them by coordinate
            self._ground_points = np.asfortranarray(self.hm.points_rover.reshape(-1, 3)[idx])
        return self._ground_points

    @property
    def ground_cam_d2(self) -> np.ndarray:
        """Squared horizontal distance (m^2) of each of ground_points from the camera."""
        if self._ground_cam_d2 is None:
            pts, cam = self.ground_points, self.T_rover_optical[:3, 3]
            cx, cy = pts[:, 0] - cam[0], pts[:, 1] - cam[1]
            self._ground_cam_d2 = cx * cx + cy * cy
        return self._ground_cam_d2

    def admitted_elongated(
        self, reason: RejectReason | None, st: MaskStats
    ) -> tuple[bool, bool, bool]:
        """(strip, raised, long): whether a mask the image filters rejected as elongated goes on
        as a flat strip, a raised strip candidate, or a tentative candidate elongated beyond the
        strip limits (perception/rules.py)."""
        r = self.config.rules
        strip = is_flat_strip(reason, st, self.fc, r) and self.stereo_rules
        raised = is_raised_strip(reason, st, self.fc, r) and self.stereo_rules
        long_ = (
            self.tentative_on
            and not (strip or raised)
            and reason is RejectReason.ELONGATED
            and st.eig_ratio <= self.config.tentative.max_eig_ratio
        )
        return strip, raised, long_


def _full_size_depth(hm: HeightMap, shape: tuple[int, int]) -> np.ndarray:
    """The height map's depth (optical z, metres) resized to the image (nearest neighbour)."""
    cv2 = import_cv2()
    return cv2.resize(hm.depth, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)


def _quantile(a: np.ndarray, q) -> np.floating:
    """``np.quantile(a, q)`` bit for bit (method linear), faster for a 1-D float array and a
    Python float `q` (one partition, no array machinery: the detector takes some 80 quantiles
    of small arrays per pair); anything else goes to np.quantile."""
    if type(q) is not float or a.ndim != 1 or a.dtype.kind != "f" or a.size == 0:
        return np.quantile(a, q)
    n = a.size
    v = (n - 1) * q
    lo = max(min(math.floor(v), n - 1), 0)
    hi = min(lo + 1, n - 1)
    p = np.partition(a, (lo, hi) if hi == n - 1 else (lo, hi, n - 1))
    if np.isnan(p[-1]):  # NaN sorts last; np.quantile returns NaN then
        return p.dtype.type(np.nan)
    x, y = p[lo], p[hi]
    g = v - math.floor(v)
    d = y - x
    # numpy's _lerp: from the nearer end
    return y - d * (1 - g) if g >= 0.5 else x + d * g


def _quantiles64(a: np.ndarray, qs: tuple[float, ...]) -> list[float]:
    """``np.quantile(a, list(qs))`` bit for bit (method linear; a float64 result as numpy gives
    for a float32 `a` and a list of quantiles), for a 1-D float array without NaN: one
    partition and the lerp as numpy's ``_lerp`` computes it (the difference in a's dtype, the
    weights in float64)."""
    n = a.size
    idx = []
    for q in qs:
        v = (n - 1) * q
        i = -1 if v >= n - 1 else math.floor(v)
        idx += [i, i + 1 if i >= 0 else -1]
    p = np.partition(a, sorted({i % n for i in idx} | {0, n - 1}))
    out = []
    for k, q in enumerate(qs):
        i, j = idx[2 * k], idx[2 * k + 1]
        x, y = p[i], p[j]
        g = (n - 1) * q - (i if i >= 0 else -1)
        d = y - x
        out.append(float(y) - float(d) * (1 - g) if g >= 0.5 else float(x) + float(d) * g)
    return out


def _drop_kept(
    dets: list[Detection], kept_recs: list[MaskRecord], indices, reason: RejectReason
) -> None:
    """Remove the detections at `indices` (and their records from `kept_recs`), setting the
    records' reason."""
    for k in sorted(indices, reverse=True):
        kept_recs[k].reason = reason
        del dets[k], kept_recs[k]


class Detector:
    """Detect rocks in stereo frames. Build once; call :meth:`detect_frame` per frame.

    Parameters
    ----------
    config : DetectorConfig.
    camera : intrinsics shared by the cameras (LAC: 1280x720, 70 deg HFOV).
    segmenter : an already-built segmenter (overrides ``config.segmenter``).
    """

    def __init__(
        self,
        config: DetectorConfig | None = None,
        camera: PinholeCamera | None = None,
        segmenter: Segmenter | None = None,
    ) -> None:
        self.config = config or DetectorConfig()
        self.camera = camera or PinholeCamera()
        self.segmenter = segmenter or make_segmenter(
            self.config.segmenter,
            weights=self.config.weights,
            classical=self.config.classical,
            imgsz=self.config.fastsam_imgsz_px,
        )
        self.stereo = StereoMatcher(self.config.stereo, self.camera)
        self.height_stereo = StereoMatcher(self.config.height_stereo, self.camera)

    @property
    def uses_height(self) -> bool:
        """True when each pair needs the low-resolution stereo height map."""
        return self.config.centre.method is CentreMethod.STEREO_POINTS or bool(
            getattr(self.segmenter, "uses_stereo", False)
        )

    def height_map(
        self, left: np.ndarray, right: np.ndarray, T_rover_optical: np.ndarray
    ) -> HeightMap:
        """Low-resolution disparity, rover-frame points and heights above the local ground."""
        sky = self.config.classical.sky_level
        v0 = first_ground_row(left, sky)
        disp = self.height_stereo.disparity_lowres(left, right, v_start=v0, sky_level=sky)
        k = self.config.height_stereo.downscale
        nd = self.height_stereo.num_disparities_lowres
        # levelling fits the ground plane to the points first and may rebuild the map in the
        # levelled frame: the heights of this one are computed only when it is kept
        hm = ground_height_map(
            disp,
            k,
            self.camera,
            self.height_stereo.baseline_m,
            T_rover_optical,
            self.config.ground,
            nd - 1.0,
            heights=not self.config.level.from_stereo,
        )
        if self.config.level.from_stereo:
            n = ground_plane(hm.points_rover, hm.depth, self.config.small_rocks.ground_range_m)
            if (
                n is not None
                and np.degrees(np.arccos(np.clip(n[2], -1.0, 1.0))) > self.config.level.min_deg
            ):
                T_level_rover = np.eye(4)
                T_level_rover[:3, :3] = _rotation_onto_z(n)
                hm = ground_height_map(
                    disp,
                    k,
                    self.camera,
                    self.height_stereo.baseline_m,
                    T_level_rover @ T_rover_optical,
                    self.config.ground,
                    nd - 1.0,
                )
                hm.T_level_rover = T_level_rover
                n = T_level_rover[:3, :3] @ n
            else:
                fill_ground_heights(hm)
            hm.up_rover = n
        hm.valid_u0 = 0 if self.config.height_stereo.full_width else nd * k
        return hm

    def _fullres_points(
        self,
        L,
        right,
        m,
        d_lr: float,
        T_rover_optical: np.ndarray,
        min_points: int = 5,
        disparity_out: dict | None = None,
    ):
        """Rover-frame points of a mask from a full-resolution SGBM match in a narrow
        band around its low-resolution disparity `d_lr` (full-res pixels); the mask is
        eroded by points.erode_px first. None when too few pixels match.
        disparity_out : if given, receives "disparity" (the crop's full-resolution
        disparity, NaN invalid) and "mask" (the eroded crop) when the match ran."""
        cv2 = import_cv2()
        cfg = self.config
        d = mask_disparity_fullres(
            L,
            right,
            m.crop,
            m.u0,
            m.v0,
            d_lr,
            cfg.points.span_px,
            cfg.points.block_size,
            p1_per_block_px2=cfg.points.p1_per_block_px2,
            p2_per_block_px2=cfg.points.p2_per_block_px2,
            mode=cfg.points.sgbm_mode,
        )
        if d is None:
            return None
        crop = np.asarray(m.crop, bool)
        if cfg.points.erode_px > 0:
            k = 2 * cfg.points.erode_px + 1
            ce = cv2.erode(crop.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
            if np.count_nonzero(ce) >= 10:
                crop = ce
        if disparity_out is not None:
            disparity_out.update(disparity=d, mask=crop)
        vv, uu = np.nonzero(crop & np.isfinite(d))
        if vv.size < min_points:
            return None
        z = self.stereo.camera.fx * self.height_stereo.baseline_m / d[vv, uu]
        uv = np.stack([uu + m.u0, vv + m.v0], axis=1).astype(float)
        P = self.camera.backproject(uv, z.astype(float))
        return transform_points(T_rover_optical, P)

    def _on_lander(self, det: Detection, lander_xy: np.ndarray | None) -> bool:
        """True when the detection's map position lies in the lander's footprint."""
        if lander_xy is None or det.p_map is None:
            return False
        return bool(
            on_lander(det.p_map[None], np.eye(4), lander_xy, self.config.rules.lander_radius_m)[0]
        )

    # ------------------------------------------------------------------ one pair
    def _lift_centroid(self, cu: float, cv: float, D: float, s: float, T_rover_optical: np.ndarray):
        """Back-project a mask centroid at depth D (m) and, with centre correction, move it
        along the viewing ray by the estimated radius (the paper's spherical-rock model).
        Returns (p_optical, p_rover, radius_m)."""
        p = self.camera.backproject(np.array([[cu, cv]]), np.array([D]))[0]
        R_est = self.config.centre.radius_per_size * s
        if self.config.centre.correction:
            p = p + p / np.linalg.norm(p) * R_est
        return p, transform_points(T_rover_optical, p[None])[0], R_est

    def detect_pair(
        self,
        left: np.ndarray,
        right: np.ndarray | None,
        T_rover_optical: np.ndarray,
        T_map_rover: np.ndarray | None = None,
        camera_name: str = "left",
        *,
        keep_depth: bool = False,
        timings: dict[str, float] | None = None,
        lander_xy: np.ndarray | None = None,
        keep_tentative: bool = False,
    ) -> PairResult:
        """Detections from one rectified stereo pair.

        left / right : (H, W) grayscale images (right may be None: no depth, so every
        mask is rejected as NO_DEPTH). T_rover_optical : 4x4 pose of the left optical
        frame in the rover frame. T_map_rover : 4x4 rover pose in the map, or None.
        lander_xy : (2,) the lander's centre in the map frame (metres), or None;
        detections within config.rules.lander_radius_m of it are rejected (needs T_map_rover).
        keep_tentative : keep tentative detections (Detection.tentative; see
        DetectorConfig.tentative.max_range_m), for confirm_across_frames to judge; by default
        they are dropped (their record's reason TENTATIVE).
        """
        cfg = self.config
        fc = cfg.filters
        tm = timings if timings is not None else {}
        L = to_gray_u8(left)
        if L.shape != (self.camera.height, self.camera.width):
            raise InputError(
                f"{camera_name}: image {L.shape} does not match the camera "
                f"({self.camera.height}, {self.camera.width})"
            )
        if self.uses_height and right is not None:
            return self._detect_pair_height(
                L,
                right,
                T_rover_optical,
                T_map_rover,
                camera_name,
                keep_depth,
                tm,
                lander_xy,
                keep_tentative,
            )
        t0 = time.perf_counter()
        masks = self.segmenter.segment(L)
        t1 = time.perf_counter()
        records: list[MaskRecord] = []
        pending: list[MaskRecord] = []
        for i, m in enumerate(masks):
            st = mask_stats(m, masks.image_shape, border_px=fc.border_px)
            rec = MaskRecord(i, st, float("nan"), float("nan"), None)
            rec.reason = image_reject_reason(st, fc)  # no stereo needed for these
            if rec.reason is None:
                pending.append(rec)
            records.append(rec)
        t2 = time.perf_counter()
        depth = None
        if pending and right is not None:
            v0 = min(masks[r.mask_index].bbox[1] for r in pending)
            v1 = max(masks[r.mask_index].bbox[3] for r in pending)
            depth = self.stereo.depth(L, right, rows=(v0, v1))
        t3 = time.perf_counter()
        dets: list[Detection] = []
        alpha = self.camera.alpha
        for rec in pending:
            m = masks[rec.mask_index]
            cu, cv = rec.stats.centroid_uv
            D = (
                _mask_depth(
                    depth,
                    m,
                    cu,
                    cv,
                    cfg.centre.depth_half_window_px,
                    cfg.centre.depth_fallback_mask,
                )
                if depth is not None
                else float("nan")
            )
            reason, s = classify_mask(rec.stats, D, alpha, fc)
            rec.depth_m, rec.size_m, rec.reason = D, s, reason
            if reason is not None:
                continue
            p, p_rover, R_est = self._lift_centroid(cu, cv, D, s, T_rover_optical)
            det = _detection(camera_name, rec.stats, D, s, R_est, p, p_rover, T_map_rover)
            if self._on_lander(det, lander_xy):
                rec.reason = RejectReason.ON_LANDER
                continue
            rec.tentative = det.tentative
            dets.append(det)
        t4 = time.perf_counter()
        for k, v in (("segment", t1 - t0), ("filter", (t2 - t1) + (t4 - t3)), ("stereo", t3 - t2)):
            tm[k] = tm.get(k, 0.0) + v
        return PairResult(camera_name, masks, records, dets, depth if keep_depth else None)

    def _detect_pair_height(
        self,
        L: np.ndarray,
        right: np.ndarray,
        T_rover_optical: np.ndarray,
        T_map_rover: np.ndarray | None,
        camera_name: str,
        keep_depth: bool,
        tm: dict[str, float],
        lander_xy: np.ndarray | None = None,
        keep_tentative: bool = False,
    ) -> PairResult:
        """detect_pair with the low-resolution stereo height map computed first (it feeds
        the segmenter when it uses stereo, and the centre estimate)."""
        c0 = time.process_time()
        t0 = time.perf_counter()
        hm, T_rover_optical, T_map_rover, T_rover_level = self._levelled_height_map(
            L, right, T_rover_optical, T_map_rover
        )
        t1 = time.perf_counter()
        masks, fc = self._segment_blobs(L, hm)
        t2 = time.perf_counter()
        scene = _PairScene(
            self.config,
            L,
            right,
            hm,
            masks.image_shape,
            fc,
            T_rover_optical,
            T_map_rover,
            camera_name,
            lander_xy,
        )
        records, dets, kept_recs = self._judge_masks(scene, masks)
        if self.config.small_rocks.enabled and scene.stereo_rules and np.isfinite(hm.depth).any():
            # before the duplicate test: a small-rock detection beside a larger one is dropped there
            self._add_small_rocks(
                L,
                right,
                hm,
                masks,
                records,
                dets,
                kept_recs,
                T_rover_optical,
                T_map_rover,
                camera_name,
                lander_xy,
            )
        _drop_kept(
            dets,
            kept_recs,
            _duplicates_firm_first(dets, self.config.rules.duplicate_overlap_ratio),
            RejectReason.DUPLICATE,
        )
        if not keep_tentative:
            _drop_kept(
                dets,
                kept_recs,
                [k for k, d in enumerate(dets) if d.tentative],
                RejectReason.TENTATIVE,
            )
        t3 = time.perf_counter()
        for k, v in (("segment", t2 - t1), ("filter", t3 - t2), ("stereo", t1 - t0)):
            tm[k] = tm.get(k, 0.0) + v
        # process CPU time of all three stages (all threads; less load-sensitive than wall)
        tm["cpu"] = tm.get("cpu", 0.0) + time.process_time() - c0
        if T_rover_level is not None:  # back from the levelled frame to the rover frame
            dets[:] = [
                replace(d, p_rover=transform_points(T_rover_level, d.p_rover[None])[0])
                for d in dets
            ]
        return PairResult(
            camera_name,
            masks,
            records,
            dets,
            _full_size_depth(hm, L.shape) if keep_depth else None,
            hm if keep_depth else None,
        )

    def _judge_masks(self, scene: _PairScene, masks: InstanceMasks):
        """Every mask judged (:meth:`_judge_mask`): (records, detections, the record of each
        detection)."""
        records: list[MaskRecord] = []
        dets: list[Detection] = []
        kept_recs: list[MaskRecord] = []
        for i, m in enumerate(masks):
            rec, det = self._judge_mask(scene, i, m)
            records.append(rec)
            if det is not None:
                dets.append(det)
                kept_recs.append(rec)
        return records, dets, kept_recs

    def _levelled_height_map(
        self, L, right, T_rover_optical: np.ndarray, T_map_rover: np.ndarray | None
    ):
        """The pair's height map, and the frames the pair is worked in: (height map,
        T_rover_optical, T_map_rover, T_rover_level). When the height map is levelled
        (LevelConfig), "rover" is the levelled frame and T_rover_level takes points back to the
        rover frame; else the frames as given and None."""
        hm = self.height_map(L, right, T_rover_optical)
        if hm.T_level_rover is None:
            return hm, T_rover_optical, T_map_rover, None
        T_rover_level = invert_transform(hm.T_level_rover)
        if T_map_rover is not None:
            T_map_rover = T_map_rover @ T_rover_level
        return hm, hm.T_rover_optical, T_map_rover, T_rover_level

    def _segment_blobs(self, L, hm: HeightMap) -> tuple[InstanceMasks, MaskFilterConfig]:
        """The masks of the left image and the filters that judge them: height blobs cut at
        their depth steps and the height filters when the segmenter uses stereo, else its
        masks and the plain filters."""
        cfg = self.config
        if not getattr(self.segmenter, "uses_stereo", False):
            return self.segmenter.segment(L), cfg.filters
        masks = self.segmenter.segment(L, height=hm)
        masks = split_at_depth_steps(
            masks,
            hm,
            cfg.depth_split.ratio,
            cfg.classical.height_min_area_px,
            cfg.classical.height_seed_m,
            cfg.depth_split.step_px,
        )
        return masks, cfg.height_filters

    def _judge_mask(
        self, scene: _PairScene, i: int, m: InstanceMask
    ) -> tuple[MaskRecord, Detection | None]:
        """One mask of a pair: its record and its detection (None when rejected). The steps:
        image filters (elongated strips may go on), depth and size, then, for STEREO_POINTS,
        the centre and the measures the rejection rules judge (perception/rules.py), and last
        the lander's footprint."""
        cfg = self.config
        st = mask_stats(m, scene.image_shape, border_px=scene.fc.border_px)
        rec = MaskRecord(i, st, float("nan"), float("nan"), None)
        rec.reason = image_reject_reason(st, scene.fc)
        strip, raised, long_ = scene.admitted_elongated(rec.reason, st)
        if rec.reason is not None and not (strip or raised or long_):
            return rec, None
        rows, cols = scene.hm.lowres_index(m)
        ok = np.isfinite(scene.hm.depth[rows, cols])
        D, s, mid, tent = self._depth_and_size(
            scene, rec, st, rows, cols, ok, strip or raised or long_, long_
        )
        if rec.reason is not None:
            return rec, None
        if cfg.centre.method is CentreMethod.STEREO_POINTS:
            D, p, p_rover, blob = self._measure_blob(
                scene, rec, m, st, rows, cols, ok, D, strip, raised
            )
            hard, soft = fired_rules(blob, cfg.rules)
            if hard or (soft and not (mid and set(soft) <= TENTATIVE_RULES)):
                rec.reason = RejectReason.NOT_A_ROCK
                rec.rejected_by = "+".join((*hard, *soft))
                return rec, None
            det = replace(
                _detection(
                    scene.camera_name, st, D, s, blob.radius_m, p, p_rover, scene.T_map_rover
                ),
                height_m=blob.top_m,
                height_front_m=blob.front_m,
                height_ring_m=blob.ring_m,
                height_quadric_m=blob.quadric_m,
                nearer_ring_fraction=blob.nearer_fraction,
                extension_ratio=blob.extension_ratio,
                disparity_roughness=blob.roughness,
                image_gradient=blob.image_gradient,
                needs_confirmation=_needs_confirmation(
                    blob.top_m, blob.extension_ratio, scene.hm.height, rows, cols, cfg
                ),
                tentative="+".join(filter(None, (tent, *soft))),
            )
            min_score = verifier_threshold(
                cfg.rules, bool(det.tentative), blob.radius_m, det.depth_m
            )
            if min_score > 0:
                name = cfg.rules.verifier_model
                model = default_verifier() if name == "default" else verifier_named(name)
                score = float(model.score(blob_features(det, scene.L, m)))
                if score < min_score:
                    rec.reason = RejectReason.NOT_A_ROCK
                    rec.rejected_by = "verifier"
                    return rec, None
                det = replace(det, verifier_score=score)
        else:
            p, p_rover, R_est = self._lift_centroid(*st.centroid_uv, D, s, scene.T_rover_optical)
            det = _detection(scene.camera_name, st, D, s, R_est, p, p_rover, scene.T_map_rover)
        if self._on_lander(det, scene.lander_xy):
            rec.reason = RejectReason.ON_LANDER
            return rec, None
        rec.tentative = det.tentative
        return rec, det

    def _depth_and_size(
        self,
        scene: _PairScene,
        rec: MaskRecord,
        st: MaskStats,
        rows,
        cols,
        ok,
        elongated_ok: bool,
        long_: bool,
    ) -> tuple[float, float, bool, str]:
        """A blob's depth (median of its valid low-resolution depths) and size s_i, judged by
        the range and size filters (an elongated blob let through is not judged elongated
        again); sets the record's depth, size and reason. Returns (depth m, s_i m, in the
        tentative range band, the tentative rules so far): a mid-range blob too small becomes
        tentative, an elongated tentative candidate outside the band is rejected."""
        cfg = self.config
        z = scene.hm.depth[rows, cols]
        D = float(_median(z[ok])) if np.count_nonzero(ok) >= 3 else float("nan")
        fc = replace(scene.fc, tau_elong=st.eig_ratio) if elongated_ok else scene.fc
        reason, s = classify_mask(st, D, self.camera.alpha, fc)
        rec.depth_m, rec.size_m, rec.reason = D, s, reason
        mid = bool(
            scene.tentative_on and cfg.tentative.min_range_m <= D <= cfg.tentative.max_range_m
        )
        tent = "elongated" if long_ else ""
        if reason is RejectReason.TOO_SMALL and mid and s > 0:
            tent, rec.reason = "+".join(filter(None, (tent, "too_small"))), None
        elif long_ and reason is None and not mid:
            rec.reason = RejectReason.ELONGATED
        return D, s, mid, tent

    def _measure_blob(
        self,
        scene: _PairScene,
        rec: MaskRecord,
        m: InstanceMask,
        st: MaskStats,
        rows,
        cols,
        ok,
        D: float,
        strip: bool,
        raised: bool,
    ):
        """STEREO_POINTS: a kept blob's stereo points (full resolution when configured), its
        centre and radius, and what the rules judge it by. Returns (depth m, possibly refined;
        p_optical; p_rover; BlobMeasures)."""
        cfg = self.config
        hm, L, right = scene.hm, scene.L, scene.right
        T_rover_optical = scene.T_rover_optical
        P_rov = hm.points_rover[rows[ok], cols[ok]].astype(float)
        if cfg.points.refine_disparity_px > 0:
            # full-resolution masked template match rescales the points' depths
            d_lr = float(_median(hm.disparity[rows[ok], cols[ok]])) * hm.scale
            d_ref = refine_disparity(
                L,
                right,
                m.crop,
                m.u0,
                m.v0,
                d_lr,
                cfg.points.refine_disparity_px,
                cfg.points.refine_erode_px,
            )
            if np.isfinite(d_ref) and d_ref > 0:
                P_opt = transform_points(scene.T_optical_rover, P_rov) * (d_lr / d_ref)
                P_rov = transform_points(T_rover_optical, P_opt)
                D = D * d_lr / d_ref
                rec.depth_m = D
        h_pts = hm.height[rows[ok], cols[ok]]
        fr_disp: dict = {}
        if cfg.points.full_resolution and P_rov.shape[0] >= 3:
            fr = self._fullres_points(
                L,
                right,
                m,
                float(_median(hm.disparity[rows[ok], cols[ok]])) * hm.scale,
                T_rover_optical,
                disparity_out=fr_disp,
            )
            if fr is not None:
                ground = float(_median(P_rov[:, 2] - h_pts))
                P_rov, h_pts = fr, fr[:, 2] - ground
        R_sil = None
        if cfg.centre.radius_from_silhouette:
            # the silhouette's lateral spread: a disc or half-disc of radius R
            # has a horizontal standard deviation of R / 2
            R_sil = (
                cfg.centre.radius_per_size * float(np.sqrt(st.cov[0, 0])) * D * self.camera.alpha
            )
        p_rover, R_est = _centre_for_mask(
            P_rov, h_pts, T_rover_optical[:3, 3], cfg, R_sil, hm.points_rover, rows, cols
        )
        p = transform_points(scene.T_optical_rover, p_rover[None])[0]
        q = cfg.centre.top_quantile
        vis_h = _visible_height(P_rov[:, 2], h_pts, q)
        top = float(_quantile(h_pts, q))
        h_sur = _height_above_surroundings(
            P_rov,
            p_rover,
            R_est,
            scene.ground_points,
            T_rover_optical[:3, 3],
            q,
            cam_d2=scene.ground_cam_d2,
        )
        if np.isfinite(h_sur):
            vis_h = max(vis_h, h_sur)
        ext = (
            _lateral_extension_ratio(hm.height, rows, cols)
            if R_est < cfg.rules.crest_max_radius_m or strip
            else float("nan")
        )
        rough = (
            disparity_roughness(fr_disp["disparity"], fr_disp["mask"], cfg.rules.roughness_step_px)
            if fr_disp and cfg.rules.max_disparity_roughness < 1.0
            else float("nan")
        )
        grad = (
            image_gradient(L, m, cfg.rules.gradient_rim_px, cfg.rules.gradient_quantile)
            if cfg.rules.min_image_gradient > 0
            else float("nan")
        )
        ring = _ring_mask(hm.height.shape, rows, cols, 4, 1)  # the three ring measures' ring
        blob = BlobMeasures(
            radius_m=R_est,
            visible_height_m=vis_h,
            top_m=top,
            front_m=h_sur,
            ring_m=_ring_height(hm.height, rows, cols, ring=ring),
            quadric_m=_height_above_quadric(hm.points_rover, rows, cols, P_rov, q, ring=ring),
            nearer_fraction=_nearer_ring_fraction(
                hm.depth, rows, cols, D, cfg.rules.nearer_depth_ratio, ring=ring
            ),
            extension_ratio=ext,
            roughness=rough,
            strip=strip,
            raised=raised,
            image_gradient=grad,
            depth_m=D,
        )
        return D, p, p_rover, blob

    def _add_small_rocks(
        self,
        L,
        right,
        hm: HeightMap,
        masks: InstanceMasks,
        records: list[MaskRecord],
        dets: list[Detection],
        kept_recs: list[MaskRecord],
        T_rover_optical: np.ndarray,
        T_map_rover: np.ndarray | None,
        camera_name: str,
        lander_xy: np.ndarray | None,
    ) -> None:
        """The small-rock stage (DetectorConfig.small_rocks): its rocks join `dets` (and their
        masks `masks`, with records); candidates it judged no rock get records with the reason
        FLAT (too low above their local ground for its noise) or NOT_A_ROCK."""
        cfg = self.config
        sc = cfg.small_rocks
        H, W = L.shape
        exclude = np.zeros((H, W), bool)
        # pixels the height map already judged: its blobs, kept or rejected, but those too small
        # or too far for it (a small or far rock's top is what it saw of one); with
        # inside_rejected only its kept blobs and those it judged no rock or on the lander
        skip = {RejectReason.FLAT, RejectReason.TOO_SMALL, RejectReason.TOO_FAR}
        if sc.inside_rejected:
            skip = set(RejectReason) - {RejectReason.NOT_A_ROCK, RejectReason.ON_LANDER}
        unsure = set()
        if sc.inside_tentative:
            unsure = {
                r.mask_index for r, d in zip(kept_recs, dets) if d.tentative or d.needs_confirmation
            }
        for r in records:
            if r.reason not in skip and r.mask_index not in unsure:
                m = masks[r.mask_index]
                h, w = m.crop.shape
                exclude[m.v0 : m.v0 + h, m.u0 : m.u0 + w] |= m.crop
        import cv2

        exclude = (
            cv2.dilate(exclude.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        )  # and their edges
        n_up = hm.up_rover  # fitted by height_map (the same fit), else fitted here
        if n_up is None:
            n_up = ground_plane(hm.points_rover, hm.depth, sc.ground_range_m)
        up_optical = T_rover_optical[:3, :3].T @ n_up if n_up is not None else None
        found = detect_small_rocks(
            L,
            to_gray_u8(right),
            hm.disparity,
            hm.scale,
            self.camera,
            self.height_stereo.baseline_m,
            sc,
            up_optical,
            exclude,
            keep_rejected=True,
            height_lowres=hm.height,
        )
        alpha = self.camera.alpha
        ray_to = T_rover_optical[:3, 3]
        for rock in found:
            m = InstanceMask(int(rock.u0), int(rock.v0), np.asarray(rock.crop, bool))
            masks.masks.append(m)
            st = mask_stats(m, masks.image_shape, border_px=cfg.height_filters.border_px)
            D = float(rock.depth_m)
            s = size_from_sigma(st.sigma_px, D, alpha)
            rec = MaskRecord(len(masks.masks) - 1, st, D, s, None)
            records.append(rec)
            if rock.reason is not None:
                rec.reason = RejectReason.FLAT if rock.reason == "flat" else RejectReason.NOT_A_ROCK
                rec.rejected_by = "" if rock.reason == "flat" else f"small-rock {rock.reason}"
                continue
            R_est = 0.5 * float(rock.width_m)
            P_rov = transform_points(T_rover_optical, rock.points_optical)
            # the centre: the visible surface's median, centre.range_factor x R farther along
            # the viewing ray (as STEREO_POINTS' MEDIAN estimator)
            med = np.array([_median(P_rov[:, j]) for j in range(3)])  # np.median(axis=0)
            ray = med - ray_to
            p_rover = med + ray / (np.linalg.norm(ray) + 1e-12) * cfg.centre.range_factor * R_est
            p = transform_points(np.linalg.inv(T_rover_optical), p_rover[None])[0]
            det = replace(
                _detection(camera_name, st, D, s, R_est, p, p_rover, T_map_rover),
                height_m=float(rock.top_m),
                small_rock=True,
                ground_noise_m=float(rock.noise_m),
            )
            if self._on_lander(det, lander_xy):
                rec.reason = RejectReason.ON_LANDER
                continue
            dets.append(det)
            kept_recs.append(rec)

    # ------------------------------------------------------------------ one frame
    def detect_frame(
        self,
        images: Mapping[str, np.ndarray],
        mounts: Mapping[str, CameraMount] | None = None,
        T_map_rover: np.ndarray | None = None,
        frame: int = 0,
        *,
        keep_depth: bool = False,
        lander_xy: np.ndarray | None = None,
        keep_tentative: bool = False,
    ) -> FrameDetections:
        """Detections of all configured pairs whose left image is in `images`.

        mounts : camera name -> CameraMount (defaults to the IPEx rig).
        lander_xy : the lander's centre in the map frame (detections on it are dropped).
        keep_tentative : keep tentative mid-range detections (only confirm_across_frames
        may judge them; detect_archive asks for them). Off by default: a caller without
        cross-frame confirmation (the online loop) never gets one.
        """
        mounts = mounts if mounts is not None else ipex_rig(self.camera)
        out = FrameDetections(frame, T_map_rover)
        for left_name, right_name in self.config.pairs:
            if left_name not in images:
                continue
            if left_name not in mounts:
                raise InputError(f"no camera pose for {left_name}")
            out.pairs.append(
                self.detect_pair(
                    images[left_name],
                    images.get(right_name),
                    mounts[left_name].T_rover_optical,
                    T_map_rover,
                    left_name,
                    keep_depth=keep_depth,
                    timings=out.timings,
                    lander_xy=lander_xy,
                    keep_tentative=keep_tentative,
                )
            )
            out.pairs[-1].T_rover_optical = mounts[left_name].T_rover_optical
        return out


def _rotation_onto_z(n: np.ndarray) -> np.ndarray:
    """The smallest rotation (3x3) taking the unit vector `n` onto +z (Rodrigues)."""
    n = np.asarray(n, float) / np.linalg.norm(n)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(n, z)
    s, c = float(np.linalg.norm(v)), float(np.dot(n, z))
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K * ((1 - c) / s**2)


def on_lander(
    p_rover: np.ndarray,
    T_frame_rover: np.ndarray,
    lander_xy: np.ndarray | None,
    radius_m: float = 2.2,
) -> np.ndarray:
    """(N,) True for the points `p_rover` (N, 3; rover frame) whose horizontal distance
    to the lander's centre `lander_xy` (2,) is at most `radius_m`, with the rover at
    `T_frame_rover` (4x4) in the frame the lander's position is given in: the map
    (ground truth or an estimate) or the odometry frame, where the LAC gives the lander
    relative to the rover's initial pose (``get_initial_lander_position()``). All False
    when `lander_xy` is None. For the online loop, whose detections are in the rover
    frame: ``dets[~on_lander(dets, T_odo_rover, lander_xy_odo)]``."""
    P = np.asarray(p_rover, float).reshape(-1, 3)
    if lander_xy is None or P.shape[0] == 0:
        return np.zeros(P.shape[0], bool)
    T = np.asarray(T_frame_rover, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"T_frame_rover must be a finite 4x4 transform, got shape {T.shape}")
    c = np.asarray(lander_xy, float).reshape(-1)[:2]
    if c.size != 2 or not np.all(np.isfinite(c)):
        raise InputError(f"lander_xy must be two finite numbers, got {lander_xy!r}")
    xy = transform_points(T, P)[:, :2]
    return np.hypot(xy[:, 0] - c[0], xy[:, 1] - c[1]) <= float(radius_m)


def _detection(camera_name, stats, D, s, R_est, p, p_rover, T_map_rover) -> Detection:
    """A Detection from a kept mask's statistics and its lifted centre."""
    p_map = transform_points(T_map_rover, p_rover[None])[0] if T_map_rover is not None else None
    return Detection(
        camera=camera_name,
        uv=tuple(stats.centroid_uv),
        depth_m=D,
        sigma_px=stats.sigma_px,
        eig_ratio=stats.eig_ratio,
        area_px=stats.area,
        size_m=s,
        radius_m=R_est,
        p_optical=p,
        p_rover=p_rover,
        p_map=p_map,
    )


def split_at_depth_steps(
    masks: InstanceMasks,
    height: HeightMap,
    step_ratio: float,
    min_area_px: int,
    seed_m: float,
    step_px: int = 1,
) -> InstanceMasks:
    """Masks cut at their depth steps (see DetectorConfig.depth_split.ratio): each mask of
    `masks` (full resolution, from the low-resolution `height` map) whose valid depths'
    5-95 % quantiles differ by more than `step_ratio` is cut where a pixel lies farther
    than (1 + step_ratio) x the depth of a pixel `step_px` low-resolution pixels above,
    below, left or right of it (DetectorConfig.depth_split.step_px: SGBM spreads a step
    over a pixel or two); when two or more 4-connected parts of
    at least `min_area_px` low-resolution pixels with a height above `seed_m` remain,
    they replace the mask (in its place), otherwise it stays whole. Pixels without a
    depth stay with the part they connect to. `masks` itself when step_ratio is 0."""
    if step_ratio <= 0 or len(masks) == 0:
        return masks
    out = InstanceMasks(masks.image_shape)
    for m in masks:
        parts = _depth_parts(m, height, step_ratio, min_area_px, seed_m, step_px)
        out.masks.extend([m] if parts is None else parts)
    return out


def _depth_parts(
    m, height: HeightMap, step_ratio: float, min_area_px: int, seed_m: float, step_px: int = 1
):
    """The parts of mask `m` between its depth steps (list of InstanceMask), or None when
    it has fewer than two (see split_at_depth_steps)."""
    cv2 = import_cv2()
    rows, cols = height.lowres_index(m)
    z = height.depth[rows, cols]
    ok = np.isfinite(z)
    if np.count_nonzero(ok) < 2 * max(min_area_px, 1):
        return None
    lo, hi = _quantiles64(z[ok], (0.05, 0.95))  # np.quantile(z[ok], [0.05, 0.95])
    f = 1.0 + step_ratio
    if not hi > f * lo:
        return None
    r0, c0 = int(rows.min()), int(cols.min())
    shape = (int(rows.max()) - r0 + 1, int(cols.max()) - c0 + 1)
    Z = np.full(shape, np.nan)
    Z[rows - r0, cols - c0] = z
    blob = np.zeros(shape, bool)
    blob[rows - r0, cols - c0] = True
    far = np.zeros(shape, bool)
    s = int(step_px)
    with np.errstate(invalid="ignore"):
        far[s:] |= Z[s:] > f * Z[:-s]
        far[:-s] |= Z[:-s] > f * Z[s:]
        far[:, s:] |= Z[:, s:] > f * Z[:, :-s]
        far[:, :-s] |= Z[:, :-s] > f * Z[:, s:]
    n, lab = cv2.connectedComponents((blob & ~far).astype(np.uint8), connectivity=4)
    if n <= 2:
        return None
    H = height.height[r0 : r0 + shape[0], c0 : c0 + shape[1]]
    k = height.scale
    parts = []
    for i in range(1, n):
        p = lab == i
        if np.count_nonzero(p) < min_area_px or not np.any(H[p] > seed_m):
            continue
        pr, pc = np.nonzero(p)
        crop = p[pr.min() : pr.max() + 1, pc.min() : pc.max() + 1]
        crop = np.repeat(np.repeat(crop, k, axis=0), k, axis=1) if k > 1 else crop
        parts.append(InstanceMask(int(c0 + pc.min()) * k, int(r0 + pr.min()) * k, crop.copy()))
    return parts if len(parts) >= 2 else None


def _centre_from_points(
    P: np.ndarray,
    h: np.ndarray,
    cam_rover: np.ndarray,
    cfg: DetectorConfig,
    radius_m: float | None = None,
) -> tuple[np.ndarray, float]:
    """Rock centre (rover frame) and radius from the stereo points of its mask.

    P : (n, 3) rover-frame points of the visible surface; h : (n,) their heights above
    the local ground; cam_rover : camera position in the rover frame; radius_m : the
    radius when known otherwise (the silhouette's), else twice the points' lateral
    standard deviation (a disc or half-disc of radius R has a lateral std of R / 2).
    The centre lies centre.range_factor * R beyond the median
    range of the visible points (those within a diameter of the nearest: _on_rock_range)
    and centre.height_factor * R below their top.
    """
    P = np.asarray(P, float)
    fwd, perp, rng, lat = _ray_frame(P, cam_rover)
    R = max(2.0 * float(np.std(lat)) if radius_m is None else float(radius_m), 1e-3)
    ground = float(_median(P[:, 2] - h))
    top = float(_quantile(h, cfg.centre.top_quantile))
    r_c = float(_median(_on_rock_range(rng, R))) + cfg.centre.range_factor * R
    l_c = float(np.mean(lat))
    xy = cam_rover[:2] + fwd * r_c + perp * l_c
    z = ground + top - cfg.centre.height_factor * R
    return np.array([xy[0], xy[1], z]), R


def _on_rock_range(rng: np.ndarray, R: float) -> np.ndarray:
    """The horizontal ranges `rng` (m) of a mask's points that can lie on a rock of radius `R`
    (m). A rock's visible surface spans at most its diameter 2 R along the viewing ray, so with
    the median point on the rock, points more than 2 R in front of the median are not on it,
    nor are points more than 2 R beyond the nearest of the rest (their 5 % quantile); all are
    kept when fewer than 3 remain. What the half-resolution mask holds beyond a rock is mostly
    the ground behind it (10-36 % of a 5-10 cm rock's points at 640x360, 3-15 cm farther, more
    with range: the rock's centre was put 0.3-3.9 cm too far; docs/perception-status.md, "The
    centres' range")."""
    front = rng >= float(_median(rng)) - 2.0 * R
    keep = front & (rng <= float(_quantile(rng[front], 0.05)) + 2.0 * R)
    return rng[keep] if np.count_nonzero(keep) >= 3 else rng


def _ray_frame(P: np.ndarray, cam_rover: np.ndarray):
    """The horizontal viewing ray from the camera `cam_rover` to the median of the
    points P (n, 3; rover frame): (fwd, perp) unit vectors along and across it, and each
    point's horizontal range along it and lateral offset across it."""
    d = np.array([_median(P[:, 0]), _median(P[:, 1])]) - cam_rover[:2]
    n = float(np.hypot(d[0], d[1]))
    fwd = d / n if n > 1e-9 else np.array([1.0, 0.0])
    perp = np.array([-fwd[1], fwd[0]])
    rel = P[:, :2] - cam_rover[:2]
    return fwd, perp, rel @ fwd, rel @ perp


def _centre_for_mask(
    P: np.ndarray,
    h: np.ndarray,
    cam_rover: np.ndarray,
    cfg: DetectorConfig,
    radius_m: float | None,
    points: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
) -> tuple[np.ndarray, float]:
    """Rock centre (rover frame) and radius of a kept mask by cfg.centre.estimator: P, h,
    cam_rover and radius_m as for _centre_from_points; `points` (H, W, 3) the height
    map's rover-frame points and (rows, cols) the blob's low-resolution pixels (BLEND
    fits the ground in a ring around it)."""
    if cfg.centre.estimator is CentreEstimator.BLEND:
        return _centre_blend(P, h, cam_rover, cfg, radius_m, _ring_ground_plane(points, rows, cols))
    return _centre_from_points(P, h, cam_rover, cfg, radius_m)


def _centre_blend(
    P: np.ndarray,
    h: np.ndarray,
    cam_rover: np.ndarray,
    cfg: DetectorConfig,
    radius_m: float | None,
    plane: np.ndarray | None,
) -> tuple[np.ndarray, float]:
    """Rock centre (rover frame) and radius, CentreEstimator.BLEND. Along the viewing
    ray, (1 - w) x (median range + centre.range_factor x R) + w x (near +
    centre.near_range_factor x R), w = centre.near_weight, near = the points' range
    quantile centre.near_quantile but no nearer than the median - centre.near_clamp_radii
    x R: the median of the visible surface moves with how much of the rock's top the
    mask holds, its near edge with the mask's lower part, and their errors are partly
    independent. Lateral: the points' mean lateral offset. Height: top -
    centre.ring_radius_factor x R - centre.ring_exposed_factor x (top - g), g the ground
    `plane` (z = c0 + c1 x + c2 y, rover frame; see _ring_ground_plane) under the centre:
    the exposed height 2 c (1 - burial) carries the vertical semi-axis c, which the
    radius alone fixes to +-0.15 R. Without a plane the height is MEDIAN's."""
    P = np.asarray(P, float)
    fwd, perp, rng, lat = _ray_frame(P, cam_rover)
    R = max(2.0 * float(np.std(lat)) if radius_m is None else float(radius_m), 1e-3)
    w = cfg.centre.near_weight
    med = float(_median(_on_rock_range(rng, R)))
    near = max(
        float(_quantile(rng, cfg.centre.near_quantile)), med - cfg.centre.near_clamp_radii * R
    )
    r_c = (1.0 - w) * (med + cfg.centre.range_factor * R) + w * (
        near + cfg.centre.near_range_factor * R
    )
    xy = cam_rover[:2] + fwd * r_c + perp * float(np.mean(lat))
    top = float(_median(P[:, 2] - h)) + float(_quantile(h, cfg.centre.top_quantile))
    if plane is None:
        z = top - cfg.centre.height_factor * R
    else:
        g = float(plane[0] + plane[1] * xy[0] + plane[2] * xy[1])
        z = top - cfg.centre.ring_radius_factor * R - cfg.centre.ring_exposed_factor * (top - g)
    return np.array([xy[0], xy[1], z]), R


def _ring_ground_plane(
    points: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    width: int = 6,
    gap: int = 2,
    min_points: int = 15,
    max_points: int = 400,
) -> np.ndarray | None:
    """Ground plane z = c0 + c1 x + c2 y (rover frame, metres) under a blob (rows, cols)
    of the low-resolution map, fitted to the valid stereo `points` (H, W, 3) in the ring
    `width` pixels wide that starts `gap` pixels outside it, by least squares repeated
    three times without the points more than 2 MADs above the plane or 4 below it (one-
    sided: the rock's own skirt and neighbouring rocks stand above the ground). Unlike
    the local ground cells it does not rise under a large rock. None when fewer than
    min_points ring points are valid or kept."""
    (r0, r1, c0, c1), ring = _ring_mask(points.shape[:2], rows, cols, width, gap)
    Q = points[r0:r1, c0:c1][ring]
    Q = Q[np.isfinite(Q[:, 2])]
    if Q.shape[0] < min_points:
        return None
    Q = Q[:: -(-Q.shape[0] // max_points)].astype(float)
    A = np.column_stack([np.ones(Q.shape[0]), Q[:, 0], Q[:, 1]])
    keep = np.ones(Q.shape[0], bool)
    c = None
    for _ in range(3):
        c = np.linalg.lstsq(A[keep], Q[keep, 2], rcond=None)[0]
        res = Q[:, 2] - A @ c
        mad = 1.4826 * float(_median(np.abs(res[keep]))) + 2e-3
        keep = (res < 2.0 * mad) & (res > -4.0 * mad)
        if np.count_nonzero(keep) < min_points:
            return None
    return c


def _ring_height(
    height: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    width: int = 4,
    gap: int = 1,
    q: float = 0.75,
    ring=None,
) -> float:
    """Quantile q of the heights above the local ground (low-resolution height map) in
    the ring of pixels `width` wide that starts `gap` pixels outside a blob (rows,
    cols); NaN when none is valid. ring: _ring_mask's result for these (computed when None)."""
    (r0, r1, c0, c1), ring = ring or _ring_mask(height.shape, rows, cols, width, gap)
    vals = height[r0:r1, c0:c1][ring]
    vals = vals[np.isfinite(vals)]
    return float(_quantile(vals, q)) if vals.size else float("nan")


def _ring_mask(shape: tuple[int, int], rows: np.ndarray, cols: np.ndarray, width: int, gap: int):
    """((r0, r1, c0, c1) window, boolean ring of pixels `width` wide starting `gap`
    pixels outside the blob (rows, cols) in that window) of a low-resolution map."""
    cv2 = import_cv2()
    h, w = shape
    r = width + gap
    r0, r1 = max(int(rows.min()) - r, 0), min(int(rows.max()) + r + 1, h)
    c0, c1 = max(int(cols.min()) - r, 0), min(int(cols.max()) + r + 1, w)
    blob = np.zeros((r1 - r0, c1 - c0), np.uint8)
    blob[rows - r0, cols - c0] = 1
    outer = cv2.dilate(blob, np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0
    inner = (
        cv2.dilate(blob, np.ones((2 * gap + 1, 2 * gap + 1), np.uint8)) > 0 if gap > 0 else blob > 0
    )
    return (r0, r1, c0, c1), outer & ~inner


def _height_above_quadric(
    points: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    P: np.ndarray,
    q: float,
    width: int = 4,
    gap: int = 1,
    min_points: int = 12,
    max_points: int = 400,
    ring=None,
) -> float:
    """Visible top (quantile q of the heights of P, the blob's rover-frame points) above
    a quadric surface z(x, y) fitted (least squares, then once more without the points
    beyond 2.5 MADs) to the low-resolution stereo `points` (h, w, 3) in the ring around
    the blob (rows, cols); at most max_points of each are used. A quadric follows a
    crest or a crater rim through the blob, so a stretch of crest stands out of it by
    little; a rock stands out by its height. NaN when fewer than min_points ring points
    are valid. ring: _ring_mask's result for these (computed when None)."""
    (r0, r1, c0, c1), ring = ring or _ring_mask(points.shape[:2], rows, cols, width, gap)
    R = points[r0:r1, c0:c1][ring]
    R = R[np.isfinite(R[:, 2])]
    if R.shape[0] < min_points or P.shape[0] == 0:
        return float("nan")
    R = R[:: -(-R.shape[0] // max_points)].astype(float)
    P = np.asarray(P, float)[:: -(-P.shape[0] // max_points)]
    o = R[:, :2].mean(axis=0)

    def design(xy):
        x, y = xy[:, 0] - o[0], xy[:, 1] - o[1]
        return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)

    A, z = design(R[:, :2]), R[:, 2]
    keep = np.ones(R.shape[0], bool)
    for _ in range(2):
        Ak = A[keep]
        try:
            c = np.linalg.solve(Ak.T @ Ak + 1e-9 * np.eye(6), Ak.T @ z[keep])
        except np.linalg.LinAlgError:
            return float("nan")
        res = z - A @ c
        mad = 1.4826 * float(_median(np.abs(res[keep] - _median(res[keep])))) + 1e-3
        keep = np.abs(res) <= 2.5 * mad
        if np.count_nonzero(keep) < min_points:
            return float("nan")
    return float(_quantile(P[:, 2] - design(P[:, :2]) @ c, q))


def _nearer_ring_fraction(
    depth: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    depth_m: float,
    ratio: float,
    width: int = 4,
    gap: int = 1,
    min_valid: int = 6,
    ring=None,
) -> float:
    """Fraction of the valid depths (low-resolution map `depth`, optical z in metres) in
    the upper half of the ring `width` pixels wide starting `gap` pixels outside the
    blob (rows, cols), i.e. its part above the blob's mean row, that are nearer than
    `ratio` x `depth_m`, the blob's own depth. Above and beside a rock resting on the
    ground lies ground at its own range or farther (below it the ground is nearer, and
    steeply so at grazing angles or when the rover rolls, so that half is not used); a
    blob framed from above by a nearer surface is a stereo mismatch on that surface (a
    boulder's face beside the rover) or a knob seen on it. NaN when fewer than
    `min_valid` of those ring depths are valid. ring: _ring_mask's result for these
    (computed when None; not modified)."""
    if not np.isfinite(depth_m):
        return float("nan")
    (r0, r1, c0, c1), ring = ring or _ring_mask(depth.shape, rows, cols, width, gap)
    ring = ring & (np.arange(r0, r1) < float(np.mean(rows)))[:, None]
    vals = depth[r0:r1, c0:c1][ring]
    vals = vals[np.isfinite(vals)]
    if vals.size < min_valid:
        return float("nan")
    return float(np.count_nonzero(vals < ratio * depth_m)) / vals.size


def _lateral_extension_ratio(
    height: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    q: float = 0.9,
    gap: int = 1,
    min_columns: int = 3,
) -> float:
    """How far a blob (rows, cols) of the low-resolution map `height` (metres above the
    local ground, NaN invalid) goes on beyond its left and right ends: over the columns
    from `gap` + 1 to `gap` + W beyond each end (W = its width in columns, at least 3),
    each column's highest valid height in the blob's rows (one row either side), then
    the median over the columns, divided by the blob's top (quantile q of its heights).
    A rock ends at its silhouette (ground beyond it: about 0); a stretch of crest goes on
    at nearly its height. NaN when fewer than `min_columns` columns hold a valid height
    or the blob's top is not above the ground."""
    h, w = height.shape
    vals = height[rows, cols]
    vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        return float("nan")
    top = float(_quantile(vals, q))
    if top <= 0:
        return float("nan")
    c0, c1 = int(cols.min()), int(cols.max())
    W = max(3, c1 - c0 + 1)
    ext = np.r_[np.arange(c1 + 1 + gap, c1 + 1 + gap + W), np.arange(c0 - gap - W, c0 - gap)]
    ext = ext[(ext >= 0) & (ext < w)]
    win = height[max(int(rows.min()) - 1, 0) : int(rows.max()) + 2][:, ext]
    ok = np.isfinite(win).any(axis=0)
    if np.count_nonzero(ok) < min_columns:
        return float("nan")
    col_max = np.max(np.where(np.isfinite(win[:, ok]), win[:, ok], -np.inf), axis=0)
    return float(_median(col_max)) / top


def _needs_confirmation(
    top: float,
    ext: float,
    height: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    cfg: DetectorConfig,
) -> bool:
    """True for a low blob on a crest (see DetectorConfig.confirm.tol_m): its visible top
    under cfg.confirm.max_top_m and its lateral extension ratio (measured here when the
    crest rule did not measure it) above cfg.confirm.min_extension_ratio."""
    if cfg.confirm.tol_m <= 0 or not top < cfg.confirm.max_top_m:
        return False
    if not np.isfinite(ext):
        ext = _lateral_extension_ratio(height, rows, cols)
    return bool(ext > cfg.confirm.min_extension_ratio)


def _verifier_confirms(d: Detection, config: DetectorConfig) -> bool:
    """Whether the blob verifier is sure enough of tentative detection `d` that one repeat in a
    neighbouring frame confirms it (rules.verifier_confirm_score; a blob it did not score
    never is)."""
    r = config.rules
    return 0 < r.verifier_min_score and 0 < r.verifier_confirm_score <= d.verifier_score


def confirm_across_frames(
    frames: Iterable[FrameDetections], config: DetectorConfig
) -> Iterator[FrameDetections]:
    """Drop the detections marked needs_confirmation that no neighbouring frame confirms
    (see DetectorConfig.confirm.tol_m); frames are yielded in order, each once its
    later neighbour is known (at most config.confirm.max_frames frames of look-ahead).

    For each frame, its neighbours are the nearest earlier and the nearest later frame
    whose rover position lies at least confirm.min_baseline_m away, within
    confirm.max_frames frames. A marked detection is kept when any detection of either
    neighbour lies within confirm.tol_m of it horizontally (map frame), or when neither
    neighbour exists; otherwise it is removed from its pair and its record's reason set
    to UNCONFIRMED. Frames without a map pose (T_map_rover None) pass unchanged. Off
    (a plain pass-through) when confirm.tol_m is 0.

    Tentative detections (Detection.tentative; DetectorConfig.tentative.max_range_m) are
    judged more strictly: one is kept when a firm (not tentative) detection lies
    within max(tentative.tol_m, tentative.tol_per_radius x its radius) of it horizontally
    on config.tentative.min_views sides (1:
    either), a side being its first config.tentative.confirm_frames frames that way at
    least confirm.min_baseline_m away. Failing that, it is kept when any detection (a
    tentative too) lies within the same tolerance in at least
    config.tentative.min_repeats of those frames (0: never; one is enough for a tentative the
    blob verifier scored at least rules.verifier_confirm_score). Otherwise, or with no map
    pose, it is removed (reason TENTATIVE). They are judged even when confirm.tol_m is 0."""
    from collections import deque

    cfg = config
    if cfg.confirm.tol_m <= 0 and cfg.tentative.max_range_m <= 0:
        yield from frames
        return
    past: deque[FrameDetections] = deque(maxlen=cfg.confirm.max_frames)
    pending: list[FrameDetections] = []

    def pos(fd: FrameDetections):
        return None if fd.T_map_rover is None else np.asarray(fd.T_map_rover, float)[:2, 3]

    def far(a: FrameDetections, b: FrameDetections) -> bool:
        pa, pb = pos(a), pos(b)
        return (
            pa is not None
            and pb is not None
            and float(np.hypot(*(pa - pb))) >= cfg.confirm.min_baseline_m
        )

    def near(Q: np.ndarray, p: np.ndarray, tol: float) -> bool:
        return Q.shape[0] > 0 and float(np.min(np.hypot(*(Q - p[:2]).T))) <= tol

    def any_xy(o: FrameDetections) -> np.ndarray:
        return np.asarray(
            [d.p_map[:2] for d in o.detections if d.p_map is not None], float
        ).reshape(-1, 2)

    def firm_xy(o: FrameDetections) -> np.ndarray:
        return np.asarray(
            [d.p_map[:2] for d in o.detections if d.p_map is not None and not d.tentative], float
        ).reshape(-1, 2)

    def resolve(fd: FrameDetections, later: list[FrameDetections]) -> FrameDetections:
        if pos(fd) is None:
            if any(d.tentative for d in fd.detections):
                _drop(fd, lambda d: not d.tentative, RejectReason.TENTATIVE)
            return fd
        K = cfg.tentative.confirm_frames
        befores = [o for o in reversed(past) if far(fd, o)][:K]
        afters = [o for o in later if far(fd, o)][:K]
        views = befores[:1] + afters[:1]  # the crest rule asks the nearest frame each way
        firm = [firm_xy(o) for o in views]  # tentative detections confirm nothing
        Q = np.concatenate(firm) if firm else np.zeros((0, 2))
        # per side, the firm detections of its first K frames (tentatives confirm nothing)
        sides = [np.concatenate([firm_xy(o) for o in side]) for side in (befores, afters) if side]

        def ok(d: Detection) -> bool:
            if d.tentative:
                tol = max(cfg.tentative.tol_m, cfg.tentative.tol_per_radius * d.radius_m)
                seen = sum(d.p_map is not None and near(F, d.p_map, tol) for F in sides)
                if seen >= cfg.tentative.min_views:
                    return True
                # one the blob verifier is sure of needs to be seen again only once
                repeats = 1 if _verifier_confirms(d, cfg) else cfg.tentative.min_repeats
                if repeats <= 0 or d.p_map is None:
                    return False
                # seen again, tentatively or firmly, in enough of the neighbouring frames
                again = sum(near(any_xy(o), d.p_map, tol) for o in (*befores, *afters))
                return again >= repeats
            return (
                not d.needs_confirmation
                or d.p_map is None
                or not views
                or cfg.confirm.tol_m <= 0
                or near(Q, d.p_map, cfg.confirm.tol_m)
            )

        _drop(fd, ok, None)
        return fd

    # frames of look-ahead a frame waits for: the later views that may confirm it
    ahead = cfg.tentative.confirm_frames if cfg.tentative.max_range_m > 0 else 1
    for fd in frames:
        pending.append(fd)
        while pending and (
            len(pending) > cfg.confirm.max_frames
            or sum(far(pending[0], o) for o in pending[1:]) >= ahead
        ):
            head = pending.pop(0)
            out = resolve(head, pending[: cfg.confirm.max_frames])
            past.append(head)
            yield out
    while pending:
        head = pending.pop(0)
        out = resolve(head, pending[: cfg.confirm.max_frames])
        past.append(head)
        yield out


def _drop(fd: FrameDetections, keep, reason: RejectReason | None) -> None:
    """Remove the detections of `fd` for which keep(d) is False from their pairs, setting
    their records' reason (`reason`, or TENTATIVE / UNCONFIRMED by the detection's kind)."""
    for pair in fd.pairs:
        kept = [r for r in pair.records if r.reason is None]
        flags = [bool(keep(d)) for d in pair.detections]
        if len(kept) == len(pair.detections):
            for rec, d, f in zip(kept, pair.detections, flags):
                if not f:
                    rec.reason = reason or (
                        RejectReason.TENTATIVE if d.tentative else RejectReason.UNCONFIRMED
                    )
        pair.detections = [d for d, f in zip(pair.detections, flags) if f]


def fuse_track_centres(
    frames: Iterable[FrameDetections], config: DetectorConfig
) -> Iterator[FrameDetections]:
    """Give each detection the centre of its track: its own map-frame centre combined with
    the sightings of the same rock in neighbouring frames (DetectorConfig.fuse_*); frames
    are yielded in order, each once its track_fusion.max_frames later frames are known (at once
    when track_fusion.causal). Off (a plain pass-through) when track_fusion.tol_m is 0.

    A sighting of detection d (frame i) in frame j (|i - j| <= track_fusion.max_frames, j < i when
    causal) is the detection of j nearest to d horizontally, when within track_fusion.tol_m and
    when d is the nearest of frame i's detections to it (mutual nearest: two rocks side by
    side stay apart). d's new p_map is the range-weighted mean (track_fusion.estimator MEAN) or
    median (MEDIAN, per coordinate) of its own and its sightings' centres as first
    detected (never already fused ones), weight (1 m / camera range) ** track_fusion.range_power;
    p_rover follows from the frame's pose and p_optical from the pair's camera pose
    (PairResult.T_rover_optical). A detection with no sighting, one without p_map and a
    frame without a pose keep their centres."""
    cfg = config
    if cfg.track_fusion.tol_m <= 0:
        yield from frames
        return
    K, causal = cfg.track_fusion.max_frames, cfg.track_fusion.causal
    window: list[
        tuple[FrameDetections, np.ndarray, np.ndarray]
    ] = []  # (frame, centres (n, 3), weights (n,))
    done = 0  # frames of `window` already yielded

    def sightings(fd: FrameDetections):
        dets = fd.detections if fd.T_map_rover is not None else []
        P = np.array(
            [d.p_map if d.p_map is not None else np.full(3, np.nan) for d in dets], float
        ).reshape(-1, 3)
        rng = np.array([max(float(np.linalg.norm(d.p_optical)), 1e-3) for d in dets], float)
        return fd, P, rng**-cfg.track_fusion.range_power

    def fuse(c: int) -> FrameDetections:
        fd, P, w = window[c]
        if not len(P):
            return fd
        others = window[max(c - K, 0) : c] + ([] if causal else window[c + 1 : c + 1 + K])
        pts, wts = [[p] for p in P], [[x] for x in w]
        for _, Q, v in others:
            if not len(Q):
                continue
            D = np.hypot(P[:, None, 0] - Q[None, :, 0], P[:, None, 1] - Q[None, :, 1])
            D[~np.isfinite(D)] = np.inf
            a_best, b_best = D.argmin(axis=1), D.argmin(axis=0)
            for a, b in enumerate(a_best):
                if D[a, b] <= cfg.track_fusion.tol_m and b_best[b] == a:
                    pts[a].append(Q[b])
                    wts[a].append(v[b])
        T_rover_map = invert_transform(np.asarray(fd.T_map_rover, float))
        k = 0
        for pair in fd.pairs:
            new = []
            for d in pair.detections:
                if d.p_map is not None and len(pts[k]) > 1:
                    p_map = _fused_centre(
                        np.asarray(pts[k]), np.asarray(wts[k]), cfg.track_fusion.estimator
                    )
                    p_rover = transform_points(T_rover_map, p_map[None])[0]
                    p_opt = (
                        d.p_optical
                        if pair.T_rover_optical is None
                        else transform_points(
                            invert_transform(pair.T_rover_optical), p_rover[None]
                        )[0]
                    )
                    d = replace(d, p_map=p_map, p_rover=p_rover, p_optical=p_opt)
                new.append(d)
                k += 1
            pair.detections = new
        return fd

    for fd in frames:
        window.append(sightings(fd))
        while done < len(window) and (causal or len(window) - 1 - done >= K):
            yield fuse(done)
            done += 1
        if done > K:  # keep K yielded frames as the past of the next ones
            del window[: done - K]
            done = K
    while done < len(window):
        yield fuse(done)
        done += 1


def _fused_centre(P: np.ndarray, w: np.ndarray, how: CentreFusion) -> np.ndarray:
    """(3,) weighted mean or per-coordinate weighted median of centres P (n, 3), weights w (n,)."""
    w = np.asarray(w, float) / float(np.sum(w))
    if how is CentreFusion.MEAN:
        return w @ P
    out = np.empty(3)
    for i in range(3):
        o = np.argsort(P[:, i], kind="stable")
        cw = np.cumsum(w[o])
        out[i] = P[o[int(np.searchsorted(cw, 0.5))], i]
    return out


def image_gradient(image: np.ndarray, mask: InstanceMask, rim_px: int, q: float) -> float:
    """How much a blob shows in the image: quantile `q` of the gradient magnitude (grey levels
    per pixel; Sobel of the image smoothed with a Gaussian of sigma 1 px) over the mask grown by
    `rim_px` pixels, so that its silhouette's edge is included. A rock shows a lit face, a
    shaded side, its outline against the ground or its shadow; a bump of smooth regolith that
    stereo lifts out of the ground (a hummock, a gentle rim) shows only soft shading. NaN for
    an empty mask."""
    cv2 = import_cv2()
    crop = np.asarray(mask.crop, np.uint8)
    if not crop.any():
        return float("nan")
    H, W = image.shape[:2]
    pad = int(rim_px) + 4  # the rim, and the smoothing and Sobel supports beyond it
    h, w = crop.shape
    v0, v1 = max(mask.v0 - pad, 0), min(mask.v0 + h + pad, H)
    u0, u1 = max(mask.u0 - pad, 0), min(mask.u0 + w + pad, W)
    win = cv2.GaussianBlur(np.asarray(image[v0:v1, u0:u1], np.float32), (0, 0), 1.0)
    gx = cv2.Sobel(win, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(win, cv2.CV_32F, 0, 1, ksize=3)
    mag = gradient_magnitude(cv2, gx, gy) * np.float32(0.125)  # the 3x3 Sobel's gain is 8
    sel = np.zeros(win.shape, np.uint8)
    sel[mask.v0 - v0 : mask.v0 - v0 + h, mask.u0 - u0 : mask.u0 - u0 + w] = crop
    if rim_px > 0:
        k = 2 * int(rim_px) + 1
        sel = cv2.dilate(sel, np.ones((k, k), np.uint8))
    return float(_quantile(mag[sel > 0], q))


def disparity_roughness(
    disparity: np.ndarray, mask: np.ndarray, step_px: float = 1.0, min_triples: int = 10
) -> float:
    """Fraction of the second differences of a full-resolution `disparity` (h, w; pixels,
    NaN invalid) over `mask` (h, w bool) whose magnitude exceeds `step_px`: for every
    three pixels in a row or a column, all in the mask and valid, |d[i-1] - 2 d[i] +
    d[i+1]|. On a smooth surface (a rock, the ground) the disparity's curvature is a small
    fraction of a pixel, so few exceed a pixel; stereo noise in a textureless region
    (a deep shadow) jumps from pixel to pixel. NaN when fewer than `min_triples`
    triples are valid."""
    d = np.where(np.asarray(mask, bool), np.asarray(disparity, float), np.nan)
    if d.ndim != 2:
        raise InputError(f"disparity must be a 2-D array, got shape {d.shape}")
    second = [
        np.abs(d[:, :-2] - 2.0 * d[:, 1:-1] + d[:, 2:]),
        np.abs(d[:-2, :] - 2.0 * d[1:-1, :] + d[2:, :]),
    ]
    vals = np.concatenate([x[np.isfinite(x)] for x in second])
    if vals.size < min_triples:
        return float("nan")
    return float(np.count_nonzero(vals > step_px)) / vals.size


def _duplicates_firm_first(dets: list[Detection], overlap_ratio: float) -> list[int]:
    """overlapping_duplicates over the firm detections of `dets` (exactly its result when
    none is tentative); then each tentative one (largest radius first) that overlaps a
    kept detection (the same test) is dropped too: a tentative never displaces a firm one."""
    firm = [i for i, d in enumerate(dets) if not d.tentative]
    drop = {firm[k] for k in overlapping_duplicates([dets[i] for i in firm], overlap_ratio)}
    tent = sorted((i for i, d in enumerate(dets) if d.tentative), key=lambda i: -dets[i].radius_m)
    if overlap_ratio <= 0 or not tent:
        return sorted(drop)
    kept = [i for i in firm if i not in drop]
    for i in tent:
        d = dets[i]
        if any(
            float(np.linalg.norm(d.p_rover - dets[j].p_rover)) * overlap_ratio
            < d.radius_m + dets[j].radius_m
            for j in kept
        ):
            drop.add(i)
        else:
            kept.append(i)
    return sorted(drop)


def overlapping_duplicates(dets: list[Detection], overlap_ratio: float) -> list[int]:
    """Indices of the detections to drop as duplicates: of two detections whose centres
    (``p_rover``) are closer than (R1 + R2) / overlap_ratio (their spheres overlap for a
    ratio of 1), the smaller radius is dropped (the larger first keeps its place, so a
    chain of overlaps keeps the larger of each pair it meets). [] when overlap_ratio is 0
    or fewer than two detections are given."""
    if overlap_ratio <= 0 or len(dets) < 2:
        return []
    P = np.array([d.p_rover for d in dets], float).reshape(-1, 3)
    R = np.array([d.radius_m for d in dets], float)
    dist = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2)
    close = dist * overlap_ratio < R[:, None] + R[None, :]
    dropped: set[int] = set()
    for i in np.argsort(-R, kind="stable"):
        if i in dropped:
            continue
        for j in np.flatnonzero(close[i]):
            if j != i and j not in dropped and R[j] <= R[i]:
                dropped.add(int(j))
    return sorted(dropped)


def _visible_height(z: np.ndarray, h: np.ndarray, q: float) -> float:
    """How high an object stands (metres): its visible top above the local ground, or
    the vertical extent of its visible surface when larger (a large object fills the
    ground cells it stands on, so the ground fit rises under it). Quantiles q and 1-q
    keep stray silhouette pixels out."""
    top = float(_quantile(h, q))
    extent = float(_quantile(z, q) - _quantile(z, 1.0 - q))
    return max(top, extent)


def _height_above_surroundings(
    P: np.ndarray,
    centre: np.ndarray,
    R: float,
    pts: np.ndarray,
    cam: np.ndarray,
    q: float,
    inner_m: float = 0.3,
    outer_m: float = 1.5,
    min_points: int = 20,
    cam_d2: np.ndarray | None = None,
) -> float:
    """Visible top of an object (rover-frame points P, centre, radius R) above the
    ground in front of it: the lower quartile of the heights of the stereo points `pts`
    in an annulus R + inner_m .. R + outer_m around its centre that are nearer to the
    camera `cam` than it (behind it the ground is hidden). Unlike the local ground fit,
    this does not rise under an object larger than a ground cell (the lander). NaN
    when too few points surround it. cam_d2: the points' squared horizontal distances from
    the camera (computed when None)."""
    dx, dy = pts[:, 0] - centre[0], pts[:, 1] - centre[1]
    d2 = dx * dx + dy * dy
    if cam_d2 is None:
        cx, cy = pts[:, 0] - cam[0], pts[:, 1] - cam[1]
        cam_d2 = cx * cx + cy * cy
    near = cam_d2 < (centre[0] - cam[0]) ** 2 + (centre[1] - cam[1]) ** 2
    sel = (d2 > (R + inner_m) ** 2) & (d2 < (R + outer_m) ** 2) & near
    if np.count_nonzero(sel) < min_points:
        return float("nan")
    return float(_quantile(P[:, 2], q) - _quantile(pts[sel, 2], 0.25))


def _mask_depth(
    depth: np.ndarray, m, cu: float, cv: float, h: int, fallback: bool, min_valid: int = 3
) -> float:
    """Depth of a mask: median of the valid depths in the (2h+1)^2 window at the
    centroid that belong to the mask, when at least `min_valid` are valid; otherwise the
    median of the valid depths of the whole mask (`fallback`) or of the whole window
    (not `fallback`). NaN when too few depths are valid."""
    u0, v0, u1, v1 = m.bbox
    ui, vi = int(round(cu)), int(round(cv))
    a0, a1 = max(ui - h, u0), min(ui + h + 1, u1)
    b0, b1 = max(vi - h, v0), min(vi + h + 1, v1)
    if a0 < a1 and b0 < b1:
        win = depth[b0:b1, a0:a1]
        inside = np.isfinite(win) & m.crop[b0 - v0 : b1 - v0, a0 - u0 : a1 - u0]
        if np.count_nonzero(inside) >= min_valid:
            return float(_median(win[inside]))
    if not fallback:
        return depth_at(depth, cu, cv, h, min_valid=min_valid)
    vals = depth[v0:v1, u0:u1][m.crop]
    vals = vals[np.isfinite(vals)]
    return float(_median(vals)) if vals.size >= max(min_valid, 5) else float("nan")


# ---------------------------------------------------------------------- archives
def detect_archive(
    archive,
    config: DetectorConfig | None = None,
    pose: PoseSource | str = PoseSource.GROUND_TRUTH,
    *,
    detector: Detector | None = None,
    frames: Iterable[int] | None = None,
    keep_depth: bool = False,
    poses: Mapping[int, np.ndarray] | None = None,
    lander_xy: np.ndarray | None = None,
) -> Iterator[FrameDetections]:
    """Run the detector over the frames of a LacArchive that have left images, then
    confirm low crest blobs across neighbouring frames (:func:`confirm_across_frames`,
    DetectorConfig.confirm.tol_m) and, when DetectorConfig.track_fusion.tol_m > 0, give each
    detection its track's centre from several views (:func:`fuse_track_centres`).

    pose : ground truth (frames.csv) or odometry (custom/odometry.csv) for the map frame.
    frames : optional subset of frame numbers.
    poses : optional {frame: T_map_rover (4x4)} placing detections instead of `pose`
        (e.g. :func:`lunarloc.odometry.source.archive_odometry`'s trajectory).
    lander_xy : the lander's centre in the map frame of `pose` (detections on it are
        dropped); default: the archive's (initial.toml ``lander`` is relative to the
        rover's initial pose, composed by :meth:`LacArchive.lander_pose_map`).
    """
    det = detector or Detector(config, camera_from_archive(archive))
    confirmed = confirm_across_frames(
        _detect_archive_frames(archive, det, pose, frames, keep_depth, poses, lander_xy), det.config
    )
    yield from fuse_track_centres(confirmed, det.config)


def _detect_archive_frames(
    archive, det: Detector, pose, frames, keep_depth: bool, poses, lander_xy
):
    """detect_archive's frames, each detected on its own (arguments as detect_archive's)."""
    pose = PoseSource(pose)
    if pose is PoseSource.ODOMETRY and poses is None:
        raise InputError(
            "pose 'odometry' needs the odometry poses (poses=...; lunarloc.pipeline.runner.detect "
            "reads them from the archive)"
        )
    if (
        lander_xy is None
    ):  # the archive knows where the lander stands (initial.toml, rover-relative)
        lander_xy = np.asarray(archive.lander_pose_map()[:2], float)
    wanted = None if frames is None else {int(f) for f in frames}
    lefts = {left for left, _ in det.config.pairs}
    for rec in archive.iter_frames(semantic=False):
        if wanted is not None and rec.frame not in wanted:
            continue
        if not any(c in rec.grayscale for c in lefts):
            continue
        if poses is not None:
            if rec.frame not in poses:
                raise InputError(f"{archive.path}: no rover pose at frame {rec.frame}")
            T = np.asarray(poses[rec.frame], float)
        else:
            s = rec.state
            T = pose_to_matrix(s["x"], s["y"], s["z"], s["roll"], s["pitch"], s["yaw"])
        mounts = mounts_from_archive_row(rec.cameras, det.camera)
        yield det.detect_frame(
            rec.grayscale,
            mounts,
            T,
            rec.frame,
            keep_depth=keep_depth,
            lander_xy=lander_xy,
            keep_tentative=True,
        )


# ---------------------------------------------------------------------- debug output
REASON_COLOURS_BGR = {
    RejectReason.TOO_FEW_PIXELS: (128, 128, 128),
    RejectReason.BORDER: (255, 0, 255),
    RejectReason.ELONGATED: (0, 0, 255),
    RejectReason.NO_DEPTH: (255, 255, 0),
    RejectReason.TOO_NEAR: (255, 128, 128),
    RejectReason.TOO_FAR: (255, 0, 0),
    RejectReason.TOO_SMALL: (0, 255, 255),
    RejectReason.TOO_LARGE: (0, 128, 255),
    RejectReason.NOT_A_ROCK: (128, 0, 128),
    RejectReason.ON_LANDER: (0, 200, 255),
    RejectReason.DUPLICATE: (255, 128, 0),
    RejectReason.UNCONFIRMED: (200, 200, 255),
    RejectReason.TENTATIVE: (255, 200, 200),
    RejectReason.FLAT: (128, 128, 128),
}
KEPT_COLOUR_BGR = (0, 255, 0)


def debug_overlay(image: np.ndarray, pair: PairResult, depth_max_m: float = 10.0) -> np.ndarray:
    """BGR picture: left, the image with kept masks green and rejected masks coloured
    by the rejecting filter (legend drawn in the corner); right, the depth map (near =
    bright, invalid = black), when the pair kept it."""
    cv2 = import_cv2()
    g = to_gray_u8(image)
    vis = cv2.cvtColor(g, cv2.COLOR_GRAY2BGR)
    colour = np.zeros_like(vis)
    painted = np.zeros(g.shape, bool)
    for rec in pair.records:
        m = pair.masks[rec.mask_index]
        u0, v0, u1, v1 = m.bbox
        col = KEPT_COLOUR_BGR if rec.reason is None else REASON_COLOURS_BGR[rec.reason]
        colour[v0:v1, u0:u1][m.crop] = col
        painted[v0:v1, u0:u1] |= m.crop
    vis[painted] = (0.45 * vis[painted] + 0.55 * colour[painted]).astype(np.uint8)
    for d in pair.detections:
        cv2.drawMarker(
            vis,
            (int(round(d.uv[0])), int(round(d.uv[1]))),
            (255, 255, 255),
            cv2.MARKER_CROSS,
            12,
            2,
        )
        cv2.putText(
            vis,
            f"{d.depth_m:.1f}m r{d.radius_m:.2f}",
            (int(d.uv[0]) + 6, int(d.uv[1]) - 6),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
    y = 18
    for name, col in [("kept", KEPT_COLOUR_BGR)] + [
        (r.value, c) for r, c in REASON_COLOURS_BGR.items()
    ]:
        cv2.rectangle(vis, (8, y - 10), (20, y + 2), col, -1)
        cv2.putText(
            vis, name, (26, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA
        )
        y += 18
    if pair.depth is None:
        return vis
    z = pair.depth
    dz = np.where(np.isfinite(z), np.clip(255.0 * (1.0 - z / depth_max_m), 0, 255), 0).astype(
        np.uint8
    )
    dvis = cv2.applyColorMap(dz, cv2.COLORMAP_INFERNO)
    dvis[~np.isfinite(z)] = 0
    cv2.putText(
        dvis,
        f"depth 0-{depth_max_m:g} m",
        (8, 18),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.5,
        (255, 255, 255),
        1,
    )
    return np.hstack([vis, dvis])


def scaled_detector_config(width: int, base=None, tuned_width_px: int = 1280):
    """Detector config for images `width` pixels wide: the pixel-sized parameters of `base`
    (tuned at `tuned_width_px`) scaled to the resolution. Below the tuned width the range cap
    drops to 5 m and the SGBM block shrinks (coarser pixels, larger depth error at range)."""
    base = base or DetectorConfig()
    f = width / float(tuned_width_px)
    if abs(f - 1.0) < 1e-6:
        return base
    c, fl, st = base.classical, base.filters, base.stereo
    return replace(
        base,
        classical=replace(
            c,
            bg_median_px=max(16, int(c.bg_median_px * f)),
            min_area_px=max(4, int(c.min_area_px * f * f)),
        ),
        filters=replace(
            fl,
            min_area_px=max(4, int(fl.min_area_px * f * f)),
            max_range_m=min(fl.max_range_m, 5.0) if f < 1 else fl.max_range_m,
        ),
        stereo=replace(
            st,
            num_disparities=max(16, int(st.num_disparities * f) // 16 * 16),
            block_size=7 if f < 1 else st.block_size,
        ),
        height_filters=replace(
            base.height_filters, near_sigma_px=base.height_filters.near_sigma_px * f
        ),
    )
