"""The detector's settings, :class:`DetectorConfig`, in sections.

Each setting's range is declared beside it (:func:`lunarloc.core.configs.setting`) and checked
once, when the config is built or loaded; a setting's line says what it means and its unit.
Why each default has its value (what it was measured on, what it was before) is in
docs/perception-history.md; the reference table is docs/run-configuration.md.

Sections (``DetectorConfig.<section>``):

* ``classical``, ``filters``, ``stereo``, ``height_stereo``, ``height_filters``, ``ground``,
  ``small_rocks``: the segmenter, the mask filters, the two SGBM matches, the ground fit and the
  small-rock stage (their own modules' configs);
* ``level``: levelling the height map by the pair's own ground plane;
* ``depth_split``: cutting height blobs at their depth steps;
* ``centre``: how a kept mask becomes a 3D centre and a radius;
* ``points``: the full-resolution stereo points of a kept mask;
* ``rules``: what is not a rock (the rejection rules, :mod:`lunarloc.perception.rules`);
* ``confirm``, ``tentative``: confirmation of doubtful detections by neighbouring frames;
* ``track_fusion``: a detection's centre from several views.

Files and code from before the sections use flat keys (``fuse_tol_m``, ``centre_estimator``);
they still load: :data:`MOVED_KEYS` maps each to its section.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

from lunarloc.core.configs import check_settings, config_to_dict, moved_keys, setting
from lunarloc.core.errors import ConfigError
from lunarloc.perception.camera import STEREO_PAIRS
from lunarloc.perception.images import ImageNormalization
from lunarloc.perception.masks import MaskFilterConfig
from lunarloc.perception.rules import RULE_NAMES
from lunarloc.perception.segment import ClassicalConfig, SegmenterKind
from lunarloc.perception.small_rocks import SmallRockConfig
from lunarloc.perception.stereo import GroundConfig, StereoConfig

__all__ = [
    "PoseSource",
    "CentreMethod",
    "CentreEstimator",
    "CentreFusion",
    "LevelConfig",
    "DepthSplitConfig",
    "CentreConfig",
    "PointsConfig",
    "RulesConfig",
    "ConfirmConfig",
    "TentativeConfig",
    "TrackFusionConfig",
    "DetectorConfig",
    "MOVED_KEYS",
]


class PoseSource(str, Enum):
    """Which rover pose places detections in the map frame."""

    GROUND_TRUTH = "ground-truth"
    ODOMETRY = "odometry"


class CentreMethod(str, Enum):
    """How a kept mask becomes a 3D rock centre."""

    # Depth at the image centroid, back-projected, then pushed along the viewing ray
    # by the radius estimated from s_i (the paper's spherical-object assumption).
    RAY_SHIFT = "ray-shift"
    # From the mask's stereo points in the rover frame: lateral centre = mean lateral offset;
    # range = median range of the visible surface + range_factor * R; height = visible top -
    # height_factor * R (CentreConfig).
    STEREO_POINTS = "stereo-points"


class CentreEstimator(str, Enum):
    """STEREO_POINTS: how the centre is placed from the mask's stereo points."""

    # Along the viewing ray: median range of the visible surface + range_factor x R;
    # lateral: mean lateral offset; height: visible top - height_factor x R.
    MEDIAN = "median"
    # Along the ray, a blend of that median anchor and a near anchor (a low quantile of the
    # points' range + near_range_factor x R); height from the visible top and the ground
    # fitted in a ring around the blob (excluding it).
    BLEND = "blend"


class CentreFusion(str, Enum):
    """How :func:`~lunarloc.perception.detector.fuse_track_centres` combines the sightings of
    one rock: MEAN (range-weighted mean of the map-frame centres) or MEDIAN (range-weighted
    median, component by component)."""

    MEAN = "mean"
    MEDIAN = "median"


def _height_stereo_default() -> StereoConfig:
    return StereoConfig(
        num_disparities=192,
        block_size=5,
        downscale=2,
        speckle_window_size=50,
        three_way=True,
        p1=8 * 25,
        p2=32 * 25,
        full_width=True,
        normalization=ImageNormalization.LIFT,
    )


def _height_filters_default() -> MaskFilterConfig:
    # 192 full-resolution disparities measure depths down to ~0.77 m, so rocks from 0.9 m on
    # are kept; small rocks near the rover are kept when their masks are large.
    return MaskFilterConfig(tau_elong=20.0, min_range_m=0.9, near_sigma_px=6.0)


@dataclass(frozen=True)
class LevelConfig:
    """Level the height map by the plane fitted to the pair's own stereo points (no level-rover
    assumption: a rover rolled or pitched on a slope sees the same heights as on level ground)."""

    # build the height map in a frame whose z is the fitted ground's normal (false: the rover frame)
    from_stereo: bool = setting(True)
    # ... only when that normal lies more than this far from the rover's z (degrees)
    min_deg: float = setting(8.0, ge=0.0, lt=90.0)

    def __post_init__(self) -> None:
        check_settings(self)


@dataclass(frozen=True)
class DepthSplitConfig:
    """Cut a height blob that joins two bodies at different ranges at its depth steps."""

    # a blob whose 5-95 % depth quantiles differ by more than this (relative) is cut where depth
    # jumps by it (0 = off)
    ratio: float = setting(0.07, ge=0.0, lt=10.0)
    # ... between pixels this many low-resolution pixels apart along rows and columns
    step_px: int = setting(2, ge=1, le=8)

    def __post_init__(self) -> None:
        check_settings(self)


@dataclass(frozen=True)
class CentreConfig:
    """How a kept mask becomes a 3D centre and a radius."""

    # STEREO_POINTS (from the mask's 3D points) or RAY_SHIFT (the centroid's depth, the paper's)
    method: CentreMethod = CentreMethod.STEREO_POINTS
    # STEREO_POINTS: MEDIAN or BLEND (CentreEstimator)
    estimator: CentreEstimator = CentreEstimator.MEDIAN
    # the centre lies this many radii beyond the visible surface's median range (radii)
    range_factor: float = setting(0.5)
    # ... and this many radii below the visible top (MEDIAN; radii)
    height_factor: float = setting(0.6)
    # height quantile of a mask's points taken as its visible top
    top_quantile: float = setting(0.9, gt=0.0, le=1.0)
    # radius from the silhouette's spread (radius_per_size x its horizontal pixel std x depth x
    # alpha) rather than from the spread of its stereo points
    radius_from_silhouette: bool = setting(True)
    # radius R = radius_per_size x s_i (a disc of radius r pixels has sigma r / 2)
    radius_per_size: float = setting(2.0, gt=0.0)
    # BLEND: weight of the near anchor along the ray (0-1)
    near_weight: float = setting(0.3, ge=0.0, le=1.0)
    # BLEND: the near anchor's quantile of the points' range
    near_quantile: float = setting(0.05, gt=0.0, le=0.5)
    # BLEND: the near anchor's radius factor (radii beyond that quantile)
    near_range_factor: float = setting(0.81, ge=0.0)
    # BLEND: height = top - ring_radius_factor x R - ring_exposed_factor x (top - ring ground)
    # (radii)
    ring_radius_factor: float = setting(0.3, ge=0.0)
    # BLEND: see ring_radius_factor (a fraction of the exposed height)
    ring_exposed_factor: float = setting(0.4, ge=0.0)
    # BLEND: the near anchor no nearer than the median range minus this many radii
    near_clamp_radii: float = setting(1.0, ge=0.0)
    # RAY_SHIFT: depth = median of the valid depths in a (2h+1)^2 window at the centroid (h, pixels)
    depth_half_window_px: int = setting(3, ge=0)
    # RAY_SHIFT: too few valid depths in that window: the median over the whole mask
    depth_fallback_mask: bool = setting(True)
    # RAY_SHIFT: move the centroid along the viewing ray by the radius (a sphere's centre)
    correction: bool = setting(True)

    def __post_init__(self) -> None:
        object.__setattr__(self, "method", CentreMethod(self.method))
        object.__setattr__(self, "estimator", CentreEstimator(self.estimator))
        check_settings(self)


@dataclass(frozen=True)
class PointsConfig:
    """STEREO_POINTS: a kept mask's stereo points at full resolution (the half-resolution map
    quantises depth: at 4 m a quarter low-resolution pixel is ~5 cm of range)."""

    # recompute each kept mask's points by SGBM on its box (~1 ms a mask; false: low resolution)
    full_resolution: bool = setting(True)
    # width of the disparity band searched around the low-resolution value (pixels)
    span_px: int = setting(16, ge=1)
    # SGBM block of that match (pixels, odd)
    block_size: int = setting(5, ge=1)
    # its smoothness penalty P1 per pixel of the block (P1 = this x block_size^2)
    p1_per_block_px2: int = setting(8, ge=1)
    # its P2 per pixel of the block (must exceed p1_per_block_px2)
    p2_per_block_px2: int = setting(32, ge=1)
    # its OpenCV SGBM mode (stereo.SGBM_MODES): hh4 aggregates both ways along rows and columns;
    # 3way's top-down-only pass put the rocks' points too far (docs/lac-map.md)
    sgbm_mode: str = setting("hh4", choices=("3way", "sgbm", "hh4", "hh"))
    # pixels eroded from the mask before its points are taken (silhouette pixels mix disparities)
    erode_px: int = setting(2, ge=0)
    # refine the disparity by masked template matching within this many pixels (0 = off)
    refine_disparity_px: int = setting(0, ge=0)
    # pixels eroded from the mask before that match
    refine_erode_px: int = setting(4, ge=0)

    def __post_init__(self) -> None:
        check_settings(self)
        if not self.p1_per_block_px2 < self.p2_per_block_px2:
            raise ConfigError(
                f"p1_per_block_px2={self.p1_per_block_px2}, "
                f"p2_per_block_px2={self.p2_per_block_px2}: need p1 < p2 (SGBM wants P2 > P1)"
            )


@dataclass(frozen=True)
class RulesConfig:
    """What is not a rock: the thresholds of the rejection rules (perception/rules.py), each
    rule also switchable off by name (``off``). STEREO_POINTS only."""

    # names of rules switched off (RULE_NAMES: too_tall, too_wide, perched, framed, rough,
    # featureless,
    # contrast, quadric, crest, strip)
    off: tuple[str, ...] = ()
    # too_tall: nothing whose visible top stands higher above the local ground is a rock (m)
    max_rock_height_m: float = setting(1.0, gt=0.0)
    # too_wide: nothing of larger estimated radius is a rock (m)
    max_rock_radius_m: float = setting(1.2, gt=0.0)
    # perched: a top higher than height_per_radius x R + height_margin_m above the ground in
    # front is a knob on a larger object (radii)
    height_per_radius: float = setting(1.5)
    # perched: the margin of that test, for slopes (m)
    height_margin_m: float = setting(0.25)
    # perched: a top higher than top_per_radius x R + top_noise_m above the local ground (radii)
    top_per_radius: float = setting(2.5, gt=0.0)
    # perched: the noise margin of that test (m)
    top_noise_m: float = setting(0.02, ge=0.0)
    # perched: a blob of at least this estimated radius is never judged perched (m; 0 = all are)
    perched_max_radius_m: float = setting(0.2, ge=0.0)
    # contrast: a top less than this above the upper quartile of the ring around it is a crest (m)
    min_contrast_m: float = setting(0.015)
    # quadric: a top less than this x R above a quadric ground fitted around it is a crest (radii; 0
    # = off)
    quadric_contrast_per_radius: float = setting(0.3, ge=0.0)
    # quadric: ... nor this much (m; blobs standing higher are not judged)
    quadric_contrast_max_m: float = setting(0.05, ge=0.0)
    # framed: more than this share of the depths in the ring's upper half nearer than
    # nearer_depth_ratio x its own depth: it lies on a nearer surface (1 = off)
    max_nearer_ring_fraction: float = setting(0.3, ge=0.0, le=1.0)
    # framed: the depth ratio of that test
    nearer_depth_ratio: float = setting(0.6, gt=0.0, lt=1.0)
    # duplicate: of two detections of one image closer than (R1 + R2) / this, the smaller is
    # dropped (0 = off)
    duplicate_overlap_ratio: float = setting(0.8, ge=0.0)
    # crest: a blob whose height goes on beyond its left and right ends at more than this
    # ratio of its top is a crest (0 = off)
    crest_extension_ratio: float = setting(0.6, ge=0.0)
    # crest: ... and at most this ratio (ground far higher beside it is a larger body)
    crest_extension_max_ratio: float = setting(2.0)
    # crest: only blobs of estimated radius under this are judged (m)
    crest_max_radius_m: float = setting(0.12, ge=0.0)
    # strip: an elongated height blob up to this eigenvalue ratio may be a small rock's flat
    # top at mid range (0 = off)
    strip_max_eig_ratio: float = setting(30.0, ge=0.0)
    # strip: ... kept when its lateral extension ratio is at most this
    strip_max_extension_ratio: float = setting(0.35, ge=0.0)
    # strip: an elongated blob up to this eigenvalue ratio may be a raised strip (a large
    # rock's top at 2.5-5 m; 0 = off)
    raised_strip_max_eig_ratio: float = setting(50.0, ge=0.0)
    # strip: ... with at least this many full-resolution pixels
    raised_strip_min_area_px: int = setting(600, ge=0)
    # strip: ... kept when its top stands at least this high above the quadric ground (m)
    raised_strip_min_quadric_m: float = setting(0.05, ge=0.0)
    # strip: ... and its estimated radius is at most this (m)
    raised_strip_max_radius_m: float = setting(0.5, gt=0.0)
    # rough: more than this share of the full-resolution disparity's second differences above
    # roughness_step_px is stereo noise (1 = off)
    max_disparity_roughness: float = setting(0.15, gt=0.0, le=1.0)
    # rough: the step of that test (full-resolution pixels)
    roughness_step_px: float = setting(1.0, gt=0.0)
    # featureless: a blob whose image gradient (image_gradient: its upper quantile over the mask
    # and its rim) is under this shows no rock in the image (grey levels per pixel, at 1280 px
    # wide; 0 = off, the default; 5 turns it on: docs/perception-status.md gives what it costs)
    min_image_gradient: float = setting(0.0, ge=0.0)
    # featureless: ... when the upper quartile of the heights in the ring around it is at least
    # this (the ground rises with it; m) ...
    featureless_min_ring_m: float = setting(0.01)
    # featureless: ... and it stands less than this above the quadric ground around it (m) ...
    featureless_max_quadric_m: float = setting(0.1, ge=0.0)
    # featureless: ... at a depth of at least this (m)
    featureless_min_depth_m: float = setting(2.0, ge=0.0)
    # featureless: the quantile of the gradient magnitude (over the mask and its rim)
    gradient_quantile: float = setting(0.95, gt=0.0, le=1.0)
    # featureless: the rim around the mask where the gradient is read too (full-resolution px)
    gradient_rim_px: int = setting(3, ge=0, le=32)
    # on the lander: detections within this horizontal distance of its centre are dropped (m)
    lander_radius_m: float = setting(2.2, ge=0.0)
    # the learned blob verifier (perception/verifier.py): a firm blob the rules keep is rejected
    # when its score P(rock) is under this (0 = the verifier off; 0.7, the default, chosen on
    # sites 300-304, goes with classical.height_split_step_m 0.01; trained on sunlit and
    # lamp-lit sites; docs/perception-status.md, "The learned blob verifier", gives what it
    # gains and costs)
    verifier_min_score: float = setting(0.7, ge=0.0, lt=1.0)
    # verifier: ... a blob of estimated radius at least this is judged with
    # verifier_large_min_score instead (a large rock's plain face; the training sites hold few; m)
    verifier_max_radius_m: float = setting(0.3, gt=0.0)
    # verifier: a tentative blob (mid-range, awaiting confirmation by a neighbouring frame) is
    # rejected when its score is under this (0 = tentatives not judged; only while
    # verifier_min_score > 0)
    verifier_tentative_min_score: float = setting(0.5, ge=0.0, lt=1.0)
    # verifier: a blob of estimated radius verifier_max_radius_m or more is rejected when its
    # score is under this (0 = not judged; only while verifier_min_score > 0)
    verifier_large_min_score: float = setting(0.5, ge=0.0, lt=1.0)
    # verifier: a firm blob (radius under verifier_max_radius_m) at a depth of at least this is
    # judged with verifier_far_min_score instead (m; 0 = off; 3.5 with 0.65, the default, chosen
    # on development sites with verifier_confirm_score 0.95, docs/perception-status.md)
    verifier_far_m: float = setting(3.5, ge=0.0)
    # verifier: see verifier_far_m
    verifier_far_min_score: float = setting(0.65, ge=0.0, lt=1.0)
    # verifier: a tentative blob scoring at least this is confirmed when seen again (as any
    # detection) in one neighbouring frame instead of tentative.min_repeats (a rock partly
    # hidden at 2-5 m is often tentative frame after frame, never firm beside it; 0 = off;
    # only while verifier_min_score > 0)
    verifier_confirm_score: float = setting(0.95, ge=0.0, le=1.0)
    # verifier: which packaged model judges the blobs: "default" (verifier_model.npz, fitted on
    # blobs of the median ground) or "low_ground" (verifier_model_low_ground.npz, fitted on
    # blobs of a ground at cell quantile 0.4: goes with ground.quantile 0.4; opt-in,
    # docs/perception-status.md, "The lower ground")
    verifier_model: str = setting("default", choices=("default", "low_ground"))

    def __post_init__(self) -> None:
        object.__setattr__(self, "off", tuple(self.off))
        check_settings(self)
        unknown = [n for n in self.off if n not in RULE_NAMES]
        if unknown:
            raise ConfigError(f"off: unknown rule {unknown[0]!r} (rules: {', '.join(RULE_NAMES)})")
        if not self.crest_extension_max_ratio > self.crest_extension_ratio:
            raise ConfigError(
                f"crest_extension_max_ratio={self.crest_extension_max_ratio!r} must exceed "
                f"crest_extension_ratio={self.crest_extension_ratio!r}"
            )


@dataclass(frozen=True)
class ConfirmConfig:
    """Low crest blobs confirmed by a second view (detect_archive / confirm_across_frames)."""

    # a marked blob is kept when a neighbouring frame's detection lies within this, horizontally (m;
    # 0 = off)
    tol_m: float = setting(0.2, ge=0.0)
    # marked: a visible top under this above the local ground (m) ...
    max_top_m: float = setting(0.06, ge=0.0)
    # ... and a height going on beyond its ends at more than this ratio of its top
    min_extension_ratio: float = setting(0.3, ge=0.0)
    # a neighbouring frame lies at least this far in rover travel (m)
    min_baseline_m: float = setting(0.1, ge=0.0)
    # ... and at most this many frames away
    max_frames: int = setting(10, ge=1)

    def __post_init__(self) -> None:
        check_settings(self)


@dataclass(frozen=True)
class TentativeConfig:
    """Mid-range blobs that a marginal rule rejects, kept as tentative detections until a
    neighbouring frame confirms them (detect_frame drops them unless asked to keep them)."""

    # a blob whose median depth lies in [min_range_m, max_range_m] may be tentative (m; max 0 = off)
    max_range_m: float = setting(5.0, ge=0.0)
    # see max_range_m (m)
    min_range_m: float = setting(2.0, ge=0.0)
    # the most elongated blob (eigenvalue ratio) that may be tentative
    max_eig_ratio: float = setting(60.0, ge=0.0)
    # a tentative is confirmed by a firm detection within max(tol_m, tol_per_radius x R) (m)
    tol_m: float = setting(0.1, gt=0.0)
    # see tol_m (radii; 0 = tol_m alone)
    tol_per_radius: float = setting(0.5, ge=0.0)
    # ... on at least this many sides (earlier, later frames)
    min_views: int = setting(1, choices=(1, 2))
    # frames each way that may confirm (each at least confirm.min_baseline_m away)
    confirm_frames: int = setting(3, ge=1)
    # ... or it is seen again, as any detection, in at least this many of them (0 = off)
    min_repeats: int = setting(3, ge=0)

    def __post_init__(self) -> None:
        check_settings(self)
        if self.max_range_m > 0 and not self.min_range_m < self.max_range_m:
            raise ConfigError(
                f"min_range_m={self.min_range_m!r} must be under max_range_m={self.max_range_m!r}"
            )


@dataclass(frozen=True)
class TrackFusionConfig:
    """A detection's centre from several views (detect_archive, fuse_track_centres)."""

    # a sighting of the same rock in a neighbouring frame lies within this, horizontally (m; 0 =
    # off)
    tol_m: float = setting(0.0, ge=0.0)
    # frames searched on each side
    max_frames: int = setting(10, ge=1)
    # sightings weighted by (1 m / camera range) ** range_power
    range_power: float = setting(0.0, ge=0.0)
    # earlier frames only
    causal: bool = setting(False)
    # MEAN or MEDIAN (CentreFusion)
    estimator: CentreFusion = CentreFusion.MEAN

    def __post_init__(self) -> None:
        object.__setattr__(self, "estimator", CentreFusion(self.estimator))
        check_settings(self)


#: The flat keys of configs saved before the sections: {old key: (section, new key)}.
MOVED_KEYS: dict[str, tuple[str, str]] = {
    "level_from_stereo": ("level", "from_stereo"),
    "level_min_deg": ("level", "min_deg"),
    "depth_split_ratio": ("depth_split", "ratio"),
    "depth_split_step_px": ("depth_split", "step_px"),
    "centre_method": ("centre", "method"),
    "centre_estimator": ("centre", "estimator"),
    "centre_range_factor": ("centre", "range_factor"),
    "centre_height_factor": ("centre", "height_factor"),
    "top_quantile": ("centre", "top_quantile"),
    "radius_from_silhouette": ("centre", "radius_from_silhouette"),
    "radius_per_size": ("centre", "radius_per_size"),
    "centre_near_weight": ("centre", "near_weight"),
    "centre_near_quantile": ("centre", "near_quantile"),
    "centre_near_range_factor": ("centre", "near_range_factor"),
    "centre_ring_radius_factor": ("centre", "ring_radius_factor"),
    "centre_ring_exposed_factor": ("centre", "ring_exposed_factor"),
    "centre_near_clamp_radii": ("centre", "near_clamp_radii"),
    "depth_half_window_px": ("centre", "depth_half_window_px"),
    "depth_fallback_mask": ("centre", "depth_fallback_mask"),
    "centre_correction": ("centre", "correction"),
    "fullres_points": ("points", "full_resolution"),
    "fullres_span_px": ("points", "span_px"),
    "fullres_block_size": ("points", "block_size"),
    "fullres_p1_per_block_px2": ("points", "p1_per_block_px2"),
    "fullres_p2_per_block_px2": ("points", "p2_per_block_px2"),
    "fullres_erode_px": ("points", "erode_px"),
    "refine_disparity_px": ("points", "refine_disparity_px"),
    "refine_erode_px": ("points", "refine_erode_px"),
    **{
        k: ("rules", k)
        for k in (
            "max_rock_height_m",
            "max_rock_radius_m",
            "height_per_radius",
            "height_margin_m",
            "top_per_radius",
            "top_noise_m",
            "perched_max_radius_m",
            "min_contrast_m",
            "quadric_contrast_per_radius",
            "quadric_contrast_max_m",
            "max_nearer_ring_fraction",
            "nearer_depth_ratio",
            "duplicate_overlap_ratio",
            "crest_extension_ratio",
            "crest_extension_max_ratio",
            "crest_max_radius_m",
            "strip_max_eig_ratio",
            "strip_max_extension_ratio",
            "raised_strip_max_eig_ratio",
            "raised_strip_min_area_px",
            "raised_strip_min_quadric_m",
            "raised_strip_max_radius_m",
            "max_disparity_roughness",
            "roughness_step_px",
            "lander_radius_m",
        )
    },
    **{
        f"confirm_{k}": ("confirm", k)
        for k in ("tol_m", "max_top_m", "min_extension_ratio", "min_baseline_m", "max_frames")
    },
    **{
        f"tentative_{k}": ("tentative", k)
        for k in (
            "max_range_m",
            "min_range_m",
            "max_eig_ratio",
            "tol_m",
            "tol_per_radius",
            "min_views",
            "confirm_frames",
            "min_repeats",
        )
    },
    **{
        f"fuse_{k}": ("track_fusion", k)
        for k in ("tol_m", "max_frames", "range_power", "causal", "estimator")
    },
}


@moved_keys(MOVED_KEYS)
@dataclass(frozen=True)
class DetectorConfig:
    """Everything the detector depends on, in sections (module docstring); defaults follow
    the paper's intent where it has one, else what the tuning sites chose
    (docs/perception-history.md)."""

    # segmentation backend: classical (weight-free, stereo heights) or fastsam
    segmenter: SegmenterKind = SegmenterKind.CLASSICAL
    # FastSAM checkpoint path (.pt or .onnx); required with fastsam, never fetched
    weights: str | None = None
    # FastSAM's network input, long side (pixels)
    fastsam_imgsz_px: int = setting(1024, ge=32, le=4096, multiple_of=32)
    # (left, right) camera names processed each frame (front and rear pairs)
    pairs: tuple[tuple[str, str], ...] = STEREO_PAIRS
    # the classical segmenter
    classical: ClassicalConfig = field(default_factory=ClassicalConfig)
    # mask filters of shading and FastSAM masks (size, elongation, border, range)
    filters: MaskFilterConfig = field(default_factory=MaskFilterConfig)
    # full-resolution SGBM (RAY_SHIFT's depth at a mask; the LAC reference agent's)
    stereo: StereoConfig = field(default_factory=StereoConfig)
    # low-resolution SGBM behind the height map
    height_stereo: StereoConfig = field(default_factory=_height_stereo_default)
    # mask filters of height blobs
    height_filters: MaskFilterConfig = field(default_factory=_height_filters_default)
    # the local ground under the height map
    ground: GroundConfig = field(default_factory=GroundConfig)
    # the small-rock stage (perception/small_rocks.py; on by default)
    small_rocks: SmallRockConfig = field(default_factory=SmallRockConfig)
    # levelling the height map
    level: LevelConfig = field(default_factory=LevelConfig)
    # cutting height blobs at depth steps
    depth_split: DepthSplitConfig = field(default_factory=DepthSplitConfig)
    # centre and radius of a kept mask
    centre: CentreConfig = field(default_factory=CentreConfig)
    # full-resolution points of a kept mask
    points: PointsConfig = field(default_factory=PointsConfig)
    # what is not a rock
    rules: RulesConfig = field(default_factory=RulesConfig)
    # low crest blobs confirmed by a second view
    confirm: ConfirmConfig = field(default_factory=ConfirmConfig)
    # tentative mid-range detections
    tentative: TentativeConfig = field(default_factory=TentativeConfig)
    # centre from several views
    track_fusion: TrackFusionConfig = field(default_factory=TrackFusionConfig)

    def __post_init__(self) -> None:
        object.__setattr__(self, "segmenter", SegmenterKind(self.segmenter))
        check_settings(self)
        # the checks that tie two sections together
        t, c = self.tentative, self.confirm
        if t.min_repeats > 2 * c.max_frames:
            raise ConfigError(
                f"tentative.min_repeats={t.min_repeats!r} must be an integer from 0 (off) to "
                f"2 x confirm.max_frames ({2 * c.max_frames})"
            )
        if t.confirm_frames > c.max_frames:
            raise ConfigError(
                f"tentative.confirm_frames={t.confirm_frames!r} must be an integer from 1 to "
                f"confirm.max_frames={c.max_frames!r}"
            )
        if self.segmenter is SegmenterKind.FASTSAM and not self.weights:
            raise ConfigError("the fastsam segmenter needs weights (a FastSAM .pt path)")

    def to_dict(self) -> dict:
        """Plain dict (sections as dicts, Enums as values) to write next to results."""
        return config_to_dict(self)
