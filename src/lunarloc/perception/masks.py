"""Instance masks, their statistics and the paper's mask filters.

A segmenter returns an :class:`InstanceMasks`: a list of :class:`InstanceMask`, each
a boolean crop plus its top-left pixel, so that hundreds of (possibly overlapping)
masks cost memory in proportion to their area, not to the image.

Per mask (LunarLoc, "Open-Set Object-Based Mapping") we compute the image centroid
``c_i``, the 2x2 pixel covariance, the standard deviation ``sigma_i``, the
eigenvalue ratio ``lambda_max / lambda_min`` and whether the mask touches the image
border. :func:`classify_mask` applies the filters of the paper's filtered set
``M~`` (fully visible, ``s_min <= s_i <= s_max``, ``lambda_max/lambda_min <= tau``)
plus a maximum range, each configured in :class:`MaskFilterConfig`.

Pixel conventions are OpenCV's (see :mod:`lunarloc.perception.camera`): ``u`` is the
column, ``v`` the row, pixel centres on integers.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from lunarloc.core.errors import ConfigError, InputError, import_cv2

__all__ = [
    "InstanceMask",
    "InstanceMasks",
    "MaskStats",
    "MaskFilterConfig",
    "RejectReason",
    "mask_stats",
    "masks_from_labels",
    "size_from_sigma",
    "image_reject_reason",
    "classify_mask",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())


@dataclass(frozen=True)
class InstanceMask:
    """One instance mask: a boolean crop whose top-left pixel is (u0, v0) in the image.

    `score` is the segmenter's confidence in [0, 1] where it has one (1.0 otherwise).
    """

    u0: int
    v0: int
    crop: np.ndarray
    score: float = 1.0

    @property
    def area(self) -> int:
        """Number of pixels in the mask."""
        return int(np.count_nonzero(self.crop))

    @property
    def bbox(self) -> tuple[int, int, int, int]:
        """(u0, v0, u1, v1), with u1 / v1 exclusive."""
        h, w = self.crop.shape
        return self.u0, self.v0, self.u0 + w, self.v0 + h

    def to_full(self, shape: tuple[int, int]) -> np.ndarray:
        """The mask as a full (H, W) boolean image."""
        full = np.zeros(shape, dtype=bool)
        u0, v0, u1, v1 = self.bbox
        full[v0:v1, u0:u1] = self.crop
        return full

    @classmethod
    def from_full(cls, mask: np.ndarray, score: float = 1.0) -> InstanceMask:
        """Crop a full-size boolean mask to its bounding box. Raises InputError if empty."""
        m = np.asarray(mask, dtype=bool)
        rows = np.flatnonzero(m.any(axis=1))
        cols = np.flatnonzero(m.any(axis=0))
        if rows.size == 0:
            raise InputError("empty mask")
        v0, v1, u0, u1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        return cls(int(u0), int(v0), m[v0:v1, u0:u1].copy(), float(score))


@dataclass
class InstanceMasks:
    """The masks of one image of shape `image_shape` = (H, W)."""

    image_shape: tuple[int, int]
    masks: list[InstanceMask] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.masks)

    def __iter__(self):
        return iter(self.masks)

    def __getitem__(self, i: int) -> InstanceMask:
        return self.masks[i]


def masks_from_labels(labels: np.ndarray, min_area: int = 1) -> InstanceMasks:
    """Instance masks from a label image (0 = background, 1..N = instances).

    Labels need not be contiguous; instances smaller than `min_area` pixels are dropped.
    """
    from scipy import ndimage

    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise InputError(f"label image must be 2-D, got shape {lab.shape}")
    out = InstanceMasks((int(lab.shape[0]), int(lab.shape[1])))
    if lab.size == 0 or lab.max() <= 0:
        return out
    lab = lab.astype(np.int32, copy=False)
    for idx, sl in enumerate(ndimage.find_objects(lab), start=1):
        if sl is None:
            continue
        crop = lab[sl] == idx
        if np.count_nonzero(crop) < min_area:
            continue
        out.masks.append(InstanceMask(int(sl[1].start), int(sl[0].start), crop))
    return out


@dataclass(frozen=True)
class MaskStats:
    """Statistics of one mask, in pixels of the full image.

    centroid_uv : (u, v) image centroid c_i.
    cov : 2x2 covariance of the mask's pixel coordinates (u, v), pixels^2.
    sigma_px : sigma_i = sqrt(trace(cov) / 2), the RMS standard deviation along the
        image axes (pixels). For a disc of radius r pixels sigma = r / 2.
    eig_ratio : lambda_max / lambda_min of `cov` (1 for a disc; inf for a line).
    area : pixel count.
    touches_border : True when a mask pixel lies within `border_px` of the image edge
        (the mask may be cut by the edge, so the object is not fully visible).
    """

    centroid_uv: tuple[float, float]
    cov: np.ndarray
    sigma_px: float
    eig_ratio: float
    area: int
    touches_border: bool


def mask_stats(mask: InstanceMask, image_shape: tuple[int, int], border_px: int = 1) -> MaskStats:
    """Compute :class:`MaskStats` of `mask` in an image of shape (H, W).

    A one-pixel mask has zero covariance; its covariance gets the variance of a
    uniform pixel (1/12 per axis) so that the eigenvalue ratio stays finite.
    """
    cv2 = import_cv2()
    # image moments of the binary crop (same sums as over the pixel coordinates)
    mo = cv2.moments(np.asarray(mask.crop, np.uint8), binaryImage=True)
    n = int(round(mo["m00"]))
    if n == 0:
        raise InputError("empty mask")
    cu, cv = mo["m10"] / n + mask.u0, mo["m01"] / n + mask.v0
    # Pixel-area correction: each pixel is a unit square (variance 1/12 per axis).
    suu = mo["mu20"] / n + 1.0 / 12.0
    svv = mo["mu02"] / n + 1.0 / 12.0
    suv = mo["mu11"] / n
    cov = np.array([[suu, suv], [suv, svv]])
    tr, det = suu + svv, suu * svv - suv * suv
    disc = np.sqrt(max(tr * tr / 4.0 - det, 0.0))
    lmax, lmin = tr / 2.0 + disc, tr / 2.0 - disc
    ratio = float(lmax / lmin) if lmin > 1e-12 else float("inf")
    H, W = image_shape
    u0, v0, u1, v1 = mask.bbox
    b = int(border_px)
    touches = bool(u0 < b or v0 < b or u1 > W - b or v1 > H - b)
    return MaskStats(
        centroid_uv=(float(cu), float(cv)),
        cov=cov,
        sigma_px=float(np.sqrt(tr / 2.0)),
        eig_ratio=ratio,
        area=int(n),
        touches_border=touches,
    )


def size_from_sigma(sigma_px: float, depth_m: float, alpha: float) -> float:
    """Physical size s_i = sigma_i * D_i * alpha (metres; LunarLoc eq. for s_i).

    sigma_px : mask standard deviation in pixels; depth_m : depth at the centroid in
    metres; alpha : angular resolution in radians per pixel.
    """
    return float(sigma_px) * float(depth_m) * float(alpha)


class RejectReason(str, Enum):
    """Why a mask was dropped (None = kept). Values are stable names for CSV/debug output."""

    TOO_FEW_PIXELS = "too_few_pixels"
    BORDER = "border"
    ELONGATED = "elongated"
    NO_DEPTH = "no_depth"
    TOO_NEAR = "too_near"
    TOO_FAR = "too_far"
    TOO_SMALL = "too_small"
    TOO_LARGE = "too_large"
    # taller or wider than any rock (lander, rover parts, terrain walls)
    NOT_A_ROCK = "not_a_rock"
    # inside the lander's footprint (its pose in the map is known)
    ON_LANDER = "on_lander"
    # overlaps a larger detection of the same image in 3D (two blobs of one rock)
    DUPLICATE = "duplicate"
    # a low blob on a crest that no neighbouring frame saw at the same map place
    UNCONFIRMED = "unconfirmed"
    # a tentative mid-range detection (DetectorConfig.tentative_max_range_m) dropped
    # unconfirmed: detect_frame without keep_tentative, or no neighbouring frame saw it
    TENTATIVE = "tentative"
    # a small-rock candidate (DetectorConfig.small_rocks) standing too low above its local
    # ground for that ground's roughness
    FLAT = "flat"


@dataclass(frozen=True)
class MaskFilterConfig:
    """Thresholds of the mask filters (LunarLoc's filtered set M~ plus a range cap).

    Sizes are the paper's s_i = sigma_i * D_i * alpha, so for a sphere of radius R
    seen whole, s_i is about R / 2 (a disc of radius r pixels has sigma = r / 2).
    """

    # Minimum mask area in pixels: below this the covariance and the centroid are noise.
    min_area_px: int = 30
    # "Fully visible": reject masks with a pixel within this many pixels of the border.
    border_px: int = 2
    # Smallest physical size kept, metres of s_i (~ radius / 2): 0.03 keeps rocks of
    # radius >= ~6 cm, large enough to be re-observed across sessions (tuned on
    # simulated site seed 0: 0.04 loses half-buried domes, whose s_i is small).
    s_min_m: float = 0.03
    # Largest physical size kept, metres of s_i: beyond ~1 m radius a "mask" is more
    # likely a crater wall, a ridge or a merged region than one rock.
    s_max_m: float = 0.5
    # tau_elong: lambda_max / lambda_min of the pixel covariance. A whole sphere gives
    # 1, a half-buried dome seen from a low camera 3-8 (a half disc is 3.5); shadows
    # cast by a low sun and terrain edges are long and thin (ratios of 10-1000).
    tau_elong: float = 8.0
    # Maximum range (depth along the optical axis, metres): stereo depth error grows
    # with range^2 (at 0.162 m baseline, ~0.25 px matching error gives ~4 cm at 5 m).
    max_range_m: float = 6.0
    # Minimum range (metres): SGBM with 128 disparities cannot measure closer than
    # fx * B / 128 ~ 1.16 m, and depths at that limit are clipped, hence wrong.
    min_range_m: float = 1.3
    # Small rocks close by: a mask below s_min_m is still kept when it spans at least
    # near_sigma_px pixels (standard deviation) and s_i >= near_s_min_m. Near the
    # rover a small rock covers hundreds of pixels and stereo measures it well; far
    # away the same size is a handful of noisy pixels. 0 = off.
    near_sigma_px: float = 0.0
    near_s_min_m: float = 0.008

    def __post_init__(self) -> None:
        if self.min_area_px < 1:
            raise ConfigError("min_area_px must be >= 1")
        if self.border_px < 0:
            raise ConfigError("border_px must be >= 0")
        if not (0.0 <= self.s_min_m < self.s_max_m):
            raise ConfigError(f"need 0 <= s_min_m < s_max_m, got {self.s_min_m}, {self.s_max_m}")
        if not self.tau_elong >= 1.0:
            raise ConfigError("tau_elong must be >= 1")
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise ConfigError("need 0 <= min_range_m < max_range_m")


def image_reject_reason(stats: MaskStats, cfg: MaskFilterConfig) -> RejectReason | None:
    """The filters that need no depth (pixel count, border, elongation), in that order."""
    if stats.area < cfg.min_area_px:
        return RejectReason.TOO_FEW_PIXELS
    if stats.touches_border:
        return RejectReason.BORDER
    if stats.eig_ratio > cfg.tau_elong:
        return RejectReason.ELONGATED
    return None


def classify_mask(
    stats: MaskStats, depth_m: float | None, alpha: float, cfg: MaskFilterConfig
) -> tuple[RejectReason | None, float]:
    """Apply the filters to one mask.

    Returns (reason, s_i): reason is None when the mask is kept, otherwise the first
    filter that rejects it, in the order: pixel count, border, elongation, depth
    (missing), range (far, near), size. s_i (metres) is NaN when there is no depth.
    """
    reason = image_reject_reason(stats, cfg)
    if reason is not None:
        return reason, float("nan")
    if depth_m is None or not np.isfinite(depth_m) or depth_m <= 0:
        return RejectReason.NO_DEPTH, float("nan")
    s = size_from_sigma(stats.sigma_px, depth_m, alpha)
    if depth_m > cfg.max_range_m:
        return RejectReason.TOO_FAR, s
    if depth_m < cfg.min_range_m:
        return RejectReason.TOO_NEAR, s
    if s < cfg.s_min_m and not (
        cfg.near_sigma_px > 0 and stats.sigma_px >= cfg.near_sigma_px and s >= cfg.near_s_min_m
    ):
        return RejectReason.TOO_SMALL, s
    if s > cfg.s_max_m:
        return RejectReason.TOO_LARGE, s
    return None, s
