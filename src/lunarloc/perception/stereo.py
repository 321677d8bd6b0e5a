"""Stereo depth with OpenCV semi-global block matching (SGBM).

Defaults are those of the Lunar Autonomy Challenge reference agent (numDisparities
128, blockSize 11, uniquenessRatio 10, speckleWindowSize 100, speckleRange 32,
disp12MaxDiff 1, P1 = 8*3*11^2, P2 = 32*3*11^2).

Images are rectified (the IPEx pairs are ideal pinholes with parallel axes), left is
the reference view; depth is z in the left camera's optical frame, metres:
``z = fx * baseline / disparity``. Invalid pixels are NaN.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lunarloc.errors import ConfigError, InputError
from lunarloc.perception.camera import IPEX_STEREO_BASELINE_M, PinholeCamera

__all__ = ["StereoConfig", "StereoMatcher", "depth_at", "to_gray_u8"]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())


@dataclass(frozen=True)
class StereoConfig:
    """OpenCV StereoSGBM parameters (LAC reference agent values) and depth limits."""

    # Disparity search range in pixels (multiple of 16). 128 px at fx ~ 914 px and a
    # 0.162 m baseline means the nearest measurable depth is ~1.16 m.
    num_disparities: int = 128
    # Matching block size in pixels (odd).
    block_size: int = 11
    # Margin (percent) by which the best cost must beat the second best.
    uniqueness_ratio: int = 10
    # Largest size (pixels) of smooth disparity regions treated as speckle noise.
    speckle_window_size: int = 100
    # Maximum disparity variation (x16 units in OpenCV) inside a connected component.
    speckle_range: int = 32
    # Maximum left-right consistency difference in pixels.
    disp12_max_diff: int = 1
    # Smoothness penalties; None = the reference agent's 8*3*b^2 and 32*3*b^2.
    p1: int | None = None
    p2: int | None = None
    # Smallest disparity in pixels accepted as valid (rejects far, noisy matches).
    min_valid_disparity_px: float = 1.0
    # Work at 1/downscale resolution (1 = full). 2 is ~4-6x faster; disparities are
    # rescaled to full-resolution pixels.
    downscale: int = 1

    def __post_init__(self) -> None:
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise ConfigError("num_disparities must be a positive multiple of 16")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ConfigError("block_size must be odd and >= 1")
        if self.downscale < 1:
            raise ConfigError("downscale must be >= 1")

    @property
    def P1(self) -> int:
        return self.p1 if self.p1 is not None else 8 * 3 * self.block_size**2

    @property
    def P2(self) -> int:
        return self.p2 if self.p2 is not None else 32 * 3 * self.block_size**2


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Grayscale uint8 view of an image (H, W), (H, W, 1) or (H, W, 3/4 RGB[A]).

    Float images are taken to be in [0, 1] when their maximum is <= 1, else [0, 255].
    """
    import cv2

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(np.ascontiguousarray(img[:, :, :3]), cv2.COLOR_RGB2GRAY)
    if img.ndim != 2:
        raise InputError(f"expected a grayscale or RGB image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return img
    if np.issubdtype(img.dtype, np.floating):
        scale = 255.0 if np.nanmax(img) <= 1.0 else 1.0
        return np.clip(np.nan_to_num(img) * scale, 0, 255).astype(np.uint8)
    if img.dtype == np.uint16:
        return (img >> 8).astype(np.uint8)
    return np.clip(img, 0, 255).astype(np.uint8)


class StereoMatcher:
    """Dense depth for one rectified stereo pair geometry (camera + baseline)."""

    def __init__(
        self,
        config: StereoConfig | None = None,
        camera: PinholeCamera | None = None,
        baseline_m: float = IPEX_STEREO_BASELINE_M,
    ) -> None:
        import cv2

        self.config = config or StereoConfig()
        self.camera = camera or PinholeCamera()
        if not baseline_m > 0:
            raise ConfigError("baseline_m must be > 0")
        self.baseline_m = float(baseline_m)
        c = self.config
        nd = c.num_disparities
        if c.downscale > 1:
            nd = max(16, int(np.ceil(nd / c.downscale / 16.0)) * 16)
        self._sgbm = cv2.StereoSGBM_create(
            minDisparity=0,
            numDisparities=nd,
            blockSize=c.block_size,
            P1=c.P1,
            P2=c.P2,
            disp12MaxDiff=c.disp12_max_diff,
            uniquenessRatio=c.uniqueness_ratio,
            speckleWindowSize=c.speckle_window_size,
            speckleRange=c.speckle_range,
        )

    def disparity(
        self, left: np.ndarray, right: np.ndarray, rows: tuple[int, int] | None = None
    ) -> np.ndarray:
        """Disparity of the left image in full-resolution pixels (float32, NaN = invalid).

        rows : optional (v0, v1) band of image rows that is needed; matching then runs
            on that band plus a margin (SGBM cost is proportional to the rows matched)
            and rows outside the band are NaN.
        """
        import cv2

        L, R = to_gray_u8(left), to_gray_u8(right)
        if L.shape != R.shape:
            raise InputError(f"left and right images differ in shape: {L.shape} vs {R.shape}")
        if rows is not None:
            H = L.shape[0]
            margin = 2 * self.config.block_size + 8 * self.config.downscale
            v0 = max(int(rows[0]) - margin, 0)
            v1 = min(int(rows[1]) + margin, H)
            if v1 <= v0:
                return np.full(L.shape, np.nan, np.float32)
            out = np.full(L.shape, np.nan, np.float32)
            out[v0:v1] = self.disparity(L[v0:v1], R[v0:v1])
            return out
        k = self.config.downscale
        if k > 1:
            size = (L.shape[1] // k, L.shape[0] // k)
            Ls = cv2.resize(L, size, interpolation=cv2.INTER_AREA)
            Rs = cv2.resize(R, size, interpolation=cv2.INTER_AREA)
            d = self._sgbm.compute(Ls, Rs).astype(np.float32) / 16.0
            d[d <= 0] = np.nan
            d = cv2.resize(d, (L.shape[1], L.shape[0]), interpolation=cv2.INTER_NEAREST) * k
        else:
            d = self._sgbm.compute(L, R).astype(np.float32) / 16.0
        d[~(d >= self.config.min_valid_disparity_px)] = np.nan
        return d

    def depth_from_disparity(self, disparity: np.ndarray) -> np.ndarray:
        """z = fx * baseline / d (metres, NaN where d is invalid)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return (self.camera.fx * self.baseline_m / disparity).astype(np.float32)

    def depth(self, left: np.ndarray, right: np.ndarray, rows: tuple[int, int] | None = None) -> np.ndarray:
        """(H, W) float32 depth z of the left image's optical frame, metres; NaN = invalid.

        rows : optional band of needed rows, as in :meth:`disparity`.
        """
        return self.depth_from_disparity(self.disparity(left, right, rows))


def depth_at(
    depth: np.ndarray,
    u: float,
    v: float,
    half_window: int = 3,
    mask: np.ndarray | None = None,
    min_valid: int = 3,
) -> float:
    """Median of the valid depths in a (2*half_window+1)^2 window around pixel (u, v).

    If `mask` (full-size boolean) is given and at least `min_valid` valid pixels of the
    window lie in it, only those are used (so a window at a rock's edge does not mix
    rock and background). Returns NaN when fewer than `min_valid` valid depths exist.
    """
    H, W = depth.shape
    ui, vi = int(round(u)), int(round(v))
    u0, u1 = max(ui - half_window, 0), min(ui + half_window + 1, W)
    v0, v1 = max(vi - half_window, 0), min(vi + half_window + 1, H)
    if u0 >= u1 or v0 >= v1:
        return float("nan")
    win = depth[v0:v1, u0:u1]
    valid = np.isfinite(win) & (win > 0)
    if mask is not None:
        inside = valid & mask[v0:v1, u0:u1]
        if np.count_nonzero(inside) >= min_valid:
            valid = inside
    if np.count_nonzero(valid) < min_valid:
        return float("nan")
    return float(np.median(win[valid]))
