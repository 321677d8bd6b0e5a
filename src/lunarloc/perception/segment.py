"""Instance segmentation of rocks in a grayscale image: interface, backends, factory.

Backends (:class:`SegmenterKind`):

* ``classical`` (default, weight-free, real time on a CPU): local-contrast
  thresholding of the shading structure of rocks under a low sun. See
  :class:`ClassicalSegmenter`.
* ``fastsam``: FastSAM through ultralytics, prompted by a uniform 32x32 point grid
  as in LunarLoc (optional extra; see :mod:`lunarloc.perception.fastsam`).

Every backend returns :class:`~lunarloc.perception.masks.InstanceMasks` in the
pixel frame of the input image.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import Enum
from typing import Protocol, runtime_checkable

import numpy as np

from lunarloc.core.errors import ConfigError, InputError, import_cv2
from lunarloc.perception.masks import InstanceMask, InstanceMasks
from lunarloc.perception.stereo import HeightMap, to_gray_u8

__all__ = [
    "SegmenterKind",
    "Segmenter",
    "ClassicalConfig",
    "ClassicalSegmenter",
    "make_segmenter",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())


class SegmenterKind(str, Enum):
    """Which segmentation backend to use."""

    CLASSICAL = "classical"
    FASTSAM = "fastsam"


@runtime_checkable
class Segmenter(Protocol):
    """Anything that turns a grayscale (H, W) uint8 image into instance masks."""

    def segment(self, image: np.ndarray) -> InstanceMasks:  # pragma: no cover - protocol
        ...


@dataclass(frozen=True)
class ClassicalConfig:
    """Parameters of the classical segmenter (tuned on simulated site seed 0).

    Intensities are relative to a robust local background level ``bg`` (a median over
    ``bg_median_px`` pixels) and to the robust spread ``sigma`` of ground pixels
    around it (MAD), so they do not depend on exposure.
    """

    # Pixels darker than this (0-255) are sky / void (the sky is black on the Moon).
    sky_level: int = 6
    # The background is a median over a window of about this many pixels (computed
    # on a 1/8-scale image): several times the size of the rocks to be found.
    bg_median_px: int = 120
    # Seed threshold: a lit rock face has pixels brighter than bg + hi * sigma.
    bright_hi_sigma: float = 3.0
    # Region threshold (hysteresis): the rock region grows over pixels brighter than
    # bg + lo * sigma that are connected to a seed.
    bright_lo_sigma: float = 1.5
    # Shadow level: pixels darker than dark_ratio * bg are in shadow (self-shadowed
    # rock sides and cast shadows; the ambient term is a few percent of the sun).
    dark_ratio: float = 0.45
    # A lit region absorbs adjacent shadow pixels up to grow * its equivalent radius
    # away (the rock's own dark side); cast shadows reach further and are cut.
    grow: float = 0.8
    # Shadow regions not attached to a lit region are candidates too (rocks seen
    # against the sun); False keeps lit regions only.
    dark_candidates: bool = True
    # Smallest region kept, pixels (smaller ones are texture noise).
    min_area_px: int = 40
    # Shadow regions are opened with a disc of this radius (pixels) before becoming
    # candidates: thin cast-shadow strips and rims vanish, round shadowed rock sides stay.
    dark_open_px: int = 0
    # Keep opened shadow regions even when they touch a lit region (a rock seen
    # against the sun: a thin lit rim beside a large shadowed body).
    dark_touching: bool = False
    # --- stereo height cue (used when the caller passes a HeightMap; see
    # lunarloc.perception.stereo.ground_height_map). Rocks stick up from the ground;
    # cast shadows and albedo texture do not. The shading cues above are the
    # fallback when no stereo is given.
    # Use the height cue when a HeightMap is given (False: shading only).
    use_height: bool = True
    # Seed threshold, metres above the local ground: the visible top of a rock of
    # radius >= 0.1 m stands >= ~5 cm above the ground (burial <= 55 % of its
    # height, vertical semi-axis >= 0.55 R); ground height noise is ~1 cm to 5 m.
    # 0.035 (was 0.04): small rocks near the rover (tuned on simulated site seed 0).
    height_seed_m: float = 0.035
    # Region threshold (hysteresis), metres: the blob grows over connected pixels
    # higher than this (rock flanks down to near the ground line). 0.025 (was 0.015):
    # real LAC terrain has 2-3 cm undulations finer than the ground cells, which a
    # lower threshold floods (seen on the real LAC frame, kept on site seed 0).
    height_region_m: float = 0.025
    # Smallest blob kept, in low-resolution (height-map) pixels.
    height_min_area_px: int = 10
    # Blobs whose stereo points are farther than this (median optical depth, metres)
    # are dropped: stereo heights and shapes degrade with range^2.
    height_max_range_m: float = 8.0
    # Blobs that the mask filters would reject as elongated (eigenvalue ratio of the
    # pixel covariance above height_split_eig_ratio, the height masks' tau_elong) or as
    # cut by the image border are split at their height saddles instead: the blob is
    # thresholded at height_split_step_m steps above height_region_m until it falls into
    # two or more parts of at least height_min_area_px, and every pixel goes to the part
    # it is nearest to. Parts that stand apart become masks of their own (a rock merged
    # with a raised streak running to the border, two rocks touching along a crest);
    # a blob without a saddle is left whole. 0 = off. 0.01, the default, goes with the learned
    # verifier (rules.verifier_min_score, on by default): it removes most of the terrain parts
    # the split makes; docs/perception-status.md, "The learned blob verifier".
    height_split_step_m: float = 0.01
    height_split_eig_ratio: float = 20.0
    # Split parts take back the blob's pixels within this many (height-map) pixels of
    # them, the rock's flanks below the split level; the blob's other pixels are dropped.
    height_split_grow_px: float = 3.0

    def __post_init__(self) -> None:
        if not self.bright_hi_sigma >= self.bright_lo_sigma > 0:
            raise ConfigError("need bright_hi_sigma >= bright_lo_sigma > 0")
        if not 0 < self.dark_ratio < 1:
            raise ConfigError("dark_ratio must be in (0, 1)")
        if self.bg_median_px < 16:
            raise ConfigError("bg_median_px must be >= 16")
        if self.grow < 0 or self.min_area_px < 1:
            raise ConfigError("grow must be >= 0 and min_area_px >= 1")
        if not (
            0 <= self.height_split_step_m < 1
            and self.height_split_eig_ratio >= 1
            and 0 <= self.height_split_grow_px < 1e3
        ):
            raise ConfigError(
                f"height_split_step_m={self.height_split_step_m} must be in [0, 1), "
                f"height_split_eig_ratio={self.height_split_eig_ratio} >= 1 and "
                f"height_split_grow_px={self.height_split_grow_px} in [0, 1000)"
            )


class ClassicalSegmenter:
    """Weight-free rock segmentation from shading and shadow under a low sun.

    1. Background level: median of a 1/8-scale image over ~``bg_median_px`` pixels,
       upsampled; the ground spread ``sigma`` is the MAD of the residual.
    2. Lit rock faces: hysteresis threshold of the residual (seeds above
       ``hi * sigma``, regions above ``lo * sigma``), connected components.
    3. Each lit region absorbs the shadow pixels (below ``dark_ratio * bg``) within
       ``grow`` x its equivalent radius: the rock's self-shadowed side.
    4. Shadow regions that touch no lit region become candidates of their own.

    The mask filters (size, elongation, border) are applied by the detector.
    """

    def __init__(self, config: ClassicalConfig | None = None) -> None:
        self.config = config or ClassicalConfig()

    @property
    def uses_stereo(self) -> bool:
        """True when :meth:`segment` wants a HeightMap (the detector then computes one)."""
        return self.config.use_height

    def height_labels(self, height: HeightMap) -> np.ndarray:
        """(h, w) int32 labels of blobs standing above the local ground, low resolution."""
        cv2 = import_cv2()
        c = self.config
        H = np.nan_to_num(height.height, nan=-1.0)
        region = (H > c.height_region_m).astype(np.uint8)
        # 2x2 opening drops one-pixel streaks (mismatches along image rows); the
        # erosion and the dilation use opposite anchors so the blob does not shift.
        k2 = np.ones((2, 2), np.uint8)
        region = cv2.dilate(cv2.erode(region, k2, anchor=(0, 0)), k2, anchor=(1, 1))
        n, lab, st = _components(region)
        if n <= 1:
            return np.zeros(H.shape, np.int32)
        if c.height_split_step_m > 0:
            lab, n = split_at_saddles(H, lab, st, c)
            st = _component_stats(lab, n)
        seeds = np.bincount(lab[H > c.height_seed_m], minlength=n) > 0
        keep = seeds & (st[:, cv2.CC_STAT_AREA] >= c.height_min_area_px)
        # blobs cut by the columns where SGBM cannot match are not fully visible
        u_min = height.valid_u0 // height.scale + 1
        keep &= st[:, cv2.CC_STAT_LEFT] > u_min
        if c.height_max_range_m > 0:
            # the blobs' pixels only (the background's mean is not used): the same sums, in the
            # same order, as over the whole image
            inb = np.flatnonzero(lab)
            z = height.depth.ravel()[inb]
            fin = np.isfinite(z)
            lb = lab.ravel()[inb][fin]
            cnt = np.bincount(lb, minlength=n)
            mean_z = np.bincount(lb, z[fin].astype(float), minlength=n) / np.maximum(cnt, 1)
            keep &= mean_z <= c.height_max_range_m
        keep[0] = False
        return np.where(keep, np.arange(n), 0).astype(np.int32)[lab]

    def labels(self, image: np.ndarray) -> np.ndarray:
        """(H, W) int32 label image: 0 background, 1..N regions."""
        cv2 = import_cv2()
        c = self.config
        I8 = to_gray_u8(image)
        H, W = I8.shape
        if H < 16 or W < 16:
            raise InputError(f"image too small to segment: {I8.shape}")
        If = I8.astype(np.float32)
        sky = I8 < c.sky_level
        k = 8
        small = cv2.resize(I8, (max(W // k, 1), max(H // k, 1)), interpolation=cv2.INTER_AREA)
        ksize = max(3, int(round(c.bg_median_px / k)) | 1)
        bg = cv2.resize(
            cv2.medianBlur(small, ksize), (W, H), interpolation=cv2.INTER_LINEAR
        ).astype(np.float32)
        dark = (If < c.dark_ratio * bg) & ~sky
        ground = ~sky & ~dark
        resid = (If - bg)[ground][::7]
        if resid.size == 0:
            return np.zeros((H, W), np.int32)
        sigma = 1.4826 * float(np.median(np.abs(resid - np.median(resid)))) + 1.0
        hi = (If > bg + c.bright_hi_sigma * sigma) & ~sky
        lo = ((If > bg + c.bright_lo_sigma * sigma) & ~sky).astype(np.uint8)
        lo = cv2.morphologyEx(lo, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        n, lab, st, _ = cv2.connectedComponentsWithStats(lo, connectivity=8)
        keep = np.bincount(lab[hi], minlength=n) > 0
        keep &= st[:, cv2.CC_STAT_AREA] >= c.min_area_px
        keep[0] = False
        lab = np.where(keep[lab], lab, 0).astype(np.int32)
        if c.grow > 0 and keep.any():
            # nearest lit pixel of every pixel (Voronoi labels of the lit pixels)
            dist, vor = cv2.distanceTransformWithLabels(
                (lab == 0).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
            )
            lit = lab.ravel()[np.flatnonzero(lab.ravel())]
            lut = np.zeros(int(vor.max()) + 1, np.int32)
            lut[1 : lit.size + 1] = lit
            nearest = lut[vor]
            radius = np.sqrt(st[:, cv2.CC_STAT_AREA] / np.pi).astype(np.float32)
            add = dark & (nearest > 0) & (dist <= c.grow * radius[nearest])
            lab = np.where(add, nearest, lab)
        if c.dark_candidates:
            dk = (dark & (lab == 0)).astype(np.uint8)
            r = max(1, int(c.dark_open_px))
            kern = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            dk = cv2.morphologyEx(dk, cv2.MORPH_OPEN, kern)
            nd, labd = cv2.connectedComponents(dk, connectivity=8)
            if nd > 1:
                bad = np.zeros(nd, bool)
                if not c.dark_touching:
                    touch = cv2.dilate((lab > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
                    bad = np.bincount(labd[touch], minlength=nd) > 0
                bad[0] = True
                labd = np.where(bad[labd], 0, labd + int(lab.max()))
                lab = np.where(labd > 0, labd, lab)
        return lab

    def segment(self, image: np.ndarray, height: HeightMap | None = None) -> InstanceMasks:
        """Instance masks of the rocks in a grayscale image (H, W).

        height : optional stereo height map of this image (low resolution); when given
        (and ``use_height``), rocks are the blobs standing above the local ground.
        """
        from scipy import ndimage

        if height is not None and self.config.use_height:
            I8 = to_gray_u8(image)
            if I8.shape[0] < 16 or I8.shape[1] < 16:
                raise InputError(f"image too small to segment: {I8.shape}")
            return self._segment_height(I8.shape, height)
        lab = self.labels(image)
        out = InstanceMasks((int(lab.shape[0]), int(lab.shape[1])))
        for idx, sl in enumerate(ndimage.find_objects(lab), start=1):
            if sl is None:
                continue
            crop = lab[sl] == idx
            if np.count_nonzero(crop) < self.config.min_area_px:
                continue
            out.masks.append(InstanceMask(int(sl[1].start), int(sl[0].start), crop))
        return out

    def _segment_height(self, shape: tuple[int, int], height: HeightMap) -> InstanceMasks:
        cv2 = import_cv2()
        from scipy import ndimage

        lab = self.height_labels(height)
        k = height.scale
        out = InstanceMasks((int(shape[0]), int(shape[1])))
        for idx, sl in enumerate(ndimage.find_objects(lab), start=1):
            if sl is None:
                continue
            crop = (lab[sl] == idx).astype(np.uint8)
            if k > 1:
                crop = cv2.resize(
                    crop, (crop.shape[1] * k, crop.shape[0] * k), interpolation=cv2.INTER_NEAREST
                )
            out.masks.append(
                InstanceMask(int(sl[1].start) * k, int(sl[0].start) * k, crop.astype(bool))
            )
        return out


def _components(region: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """cv2.connectedComponentsWithStats(region, connectivity=8)'s (count, labels, stats) of a
    uint8 image, matched over the band of rows that holds its nonzero pixels only (a height
    map's sky and far rows hold none), the band starting on an even row: OpenCV's 8-connected
    labelling scans blocks of two rows and numbers the components in that scan's order, so
    the labels and the stats are the whole image's."""
    cv2 = import_cv2()
    rows = np.flatnonzero(region.any(axis=1))
    h, w = region.shape
    a = int(rows[0]) // 2 * 2 if rows.size else 0
    b = int(rows[-1]) + 1 if rows.size else h
    if a == 0 and b == h:
        n, lab, st, _ = cv2.connectedComponentsWithStats(region, connectivity=8)
        return n, lab, st
    n, band, st, _ = cv2.connectedComponentsWithStats(region[a:b], connectivity=8)
    lab = np.zeros((h, w), band.dtype)
    lab[a:b] = band
    st[1:, cv2.CC_STAT_TOP] += a
    # the background: every column (a row outside the band is all background), the rows
    # from the first to the last that hold a background pixel
    bg = np.flatnonzero((band == 0).any(axis=1)) + a
    top = 0 if a > 0 else int(bg[0]) if bg.size else b
    bottom = h - 1 if b < h else int(bg[-1]) if bg.size else a - 1
    st[0, :4] = (0, top, w, bottom - top + 1)
    st[0, cv2.CC_STAT_AREA] = h * w - int(st[1:, cv2.CC_STAT_AREA].sum())
    return n, lab, st


def _component_stats(lab: np.ndarray, n: int) -> np.ndarray:
    """(n, 5) OpenCV-style stats (left, top, width, height, area) of labels 0..n-1."""
    cv2 = import_cv2()
    st = np.zeros((n, 5), np.int32)
    st[:, cv2.CC_STAT_LEFT] = lab.shape[1]
    st[:, cv2.CC_STAT_TOP] = lab.shape[0]
    st[:, cv2.CC_STAT_AREA] = np.bincount(lab.ravel(), minlength=n)[:n]
    if not lab.any():
        return st
    vv, uu = np.nonzero(lab)
    ll = lab[vv, uu]
    left = np.full(n, lab.shape[1])
    top = np.full(n, lab.shape[0])  # noqa: E702
    right = np.zeros(n, np.int64)
    bottom = np.zeros(n, np.int64)  # noqa: E702
    np.minimum.at(left, ll, uu)
    np.minimum.at(top, ll, vv)  # noqa: E702
    np.maximum.at(right, ll, uu)
    np.maximum.at(bottom, ll, vv)  # noqa: E702
    has = st[:, cv2.CC_STAT_AREA] > 0
    st[has, cv2.CC_STAT_LEFT], st[has, cv2.CC_STAT_TOP] = left[has], top[has]
    st[has, cv2.CC_STAT_WIDTH] = right[has] - left[has] + 1
    st[has, cv2.CC_STAT_HEIGHT] = bottom[has] - top[has] + 1
    return st


def _eig_ratio(mask: np.ndarray) -> float:
    """lambda_max / lambda_min of a binary mask's pixel covariance (as masks.mask_stats)."""
    cv2 = import_cv2()
    mo = cv2.moments(mask.astype(np.uint8), binaryImage=True)
    n = mo["m00"]
    if n <= 0:
        return 1.0
    a, b, d = mo["mu20"] / n + 1 / 12, mo["mu11"] / n, mo["mu02"] / n + 1 / 12
    disc = np.sqrt(max((a - d) ** 2 / 4 + b * b, 0.0))
    lo = (a + d) / 2 - disc
    return float(((a + d) / 2 + disc) / lo) if lo > 1e-12 else float("inf")


def split_at_saddles(
    H: np.ndarray, lab: np.ndarray, st: np.ndarray, c: ClassicalConfig
) -> tuple[np.ndarray, int]:
    """Split the blobs of a label image that the mask filters would reject (elongated
    beyond ``c.height_split_eig_ratio``, or touching the image border) at their height
    saddles: each such blob is thresholded at ``c.height_split_step_m`` steps above
    ``c.height_region_m`` until it falls into >= 2 parts of >= ``c.height_min_area_px``
    pixels (a blob cut by the border: or into one part clear of the border); blob pixels
    within ``c.height_split_grow_px`` of a part then join the nearest part, the others
    are dropped. Returns the new labels and
    their count (background 0 included). H: (h, w) heights above the ground, metres
    (no NaN); lab / st: cv2.connectedComponentsWithStats' labels and stats."""
    cv2 = import_cv2()
    h, w = lab.shape
    n = int(st.shape[0])
    out = lab
    for i in range(1, st.shape[0]):
        x, y, bw, bh, area = (int(v) for v in st[i, :5])
        if area < 2 * c.height_min_area_px:
            continue
        sub = lab[y : y + bh, x : x + bw] == i
        border = x == 0 or y == 0 or x + bw >= w or y + bh >= h
        if not border and _eig_ratio(sub) <= c.height_split_eig_ratio:
            continue
        Hs = np.where(sub, H[y : y + bh, x : x + bw], -1.0)
        peak = float(Hs.max())
        level = c.height_region_m + c.height_split_step_m
        big = np.zeros(0, int)
        while level < peak:
            _, parts, pst, _ = cv2.connectedComponentsWithStats(
                (Hs > level).astype(np.uint8), connectivity=8
            )
            big = np.flatnonzero(pst[1:, cv2.CC_STAT_AREA] >= c.height_min_area_px) + 1
            if big.size >= 2:
                break
            if big.size == 1 and border:
                # one part left that stands apart from the border: the rest was low ground
                # (a raised streak) that joined it to the edge
                px, py, pw, ph = (int(v) for v in pst[big[0], :4])
                if not (x + px == 0 or y + py == 0 or x + px + pw >= w or y + py + ph >= h):
                    break
            if big.size == 0:
                break
            level += c.height_split_step_m
        else:
            continue
        if big.size == 0 or (big.size == 1 and not border):
            continue
        # every blob pixel within height_split_grow_px of a part joins the nearest part
        # (Voronoi labels of the parts' pixels; the rock's flanks below the split level);
        # the rest of the blob (the streak, a saddle's middle) is dropped
        seeds = np.isin(parts, big)
        dist, vor = cv2.distanceTransformWithLabels(
            (~seeds).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
        )
        vv, uu = np.nonzero(seeds)
        lut = np.zeros(int(vor.max()) + 1, np.int64)
        lut[vor[vv, uu]] = parts[vv, uu]
        owner = np.where(dist <= c.height_split_grow_px, lut[vor], 0)
        if out is lab:
            out = lab.copy()
        view = out[y : y + bh, x : x + bw]
        view[sub & (owner == 0)] = 0
        for j, part in enumerate(big):
            if j == 0:
                continue  # the first part keeps the blob's label
            view[sub & (owner == part)] = n
            n += 1
    return out, n


def make_segmenter(
    kind: SegmenterKind | str = SegmenterKind.CLASSICAL,
    *,
    weights: str | None = None,
    classical: ClassicalConfig | None = None,
    **fastsam_kwargs,
) -> Segmenter:
    """Build a segmenter by kind. `weights` is required (and must exist) for fastsam."""
    try:
        kind = SegmenterKind(kind)
    except ValueError:
        raise ConfigError(
            f"unknown segmenter {kind!r}; choose one of {[k.value for k in SegmenterKind]}"
        ) from None
    if kind is SegmenterKind.CLASSICAL:
        return ClassicalSegmenter(classical)
    from lunarloc.perception.fastsam import FastSamSegmenter

    if weights is None:
        raise ConfigError("the fastsam segmenter needs a weights file (--weights PATH)")
    return FastSamSegmenter(weights, **fastsam_kwargs)
