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
from dataclasses import dataclass, field

import numpy as np

from lunarloc.core.errors import ConfigError, InputError, import_cv2
from lunarloc.perception.images import ImageNormalization, normalize_image
from lunarloc.perception.camera import IPEX_STEREO_BASELINE_M, PinholeCamera

__all__ = [
    "StereoConfig",
    "StereoMatcher",
    "max_num_disparities",
    "depth_at",
    "to_gray_u8",
    "GroundConfig",
    "HeightMap",
    "ground_height_map",
    "fill_ground_heights",
    "first_ground_row",
    "refine_disparity",
    "mask_disparity_fullres",
    "SGBM_MODES",
    "sgbm_mode_flag",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

SGBM_MODES = ("3way", "sgbm", "hh4", "hh")
"""OpenCV's SGBM modes by name: ``3way`` (cv2.STEREO_SGBM_MODE_SGBM_3WAY: the cost aggregated
along 3 directions, left to right and top down only), ``sgbm`` (5 directions), ``hh4`` (4
directions, HH4: both ways along the rows and the columns) and ``hh`` (the full 8 directions).
The directions that run only downwards bias the disparity of surfaces whose disparity changes
down the image (docs/lac-map.md, "The detections' range")."""


def sgbm_mode_flag(name: str) -> int:
    """The cv2 ``STEREO_SGBM_MODE_*`` flag of a mode named in :data:`SGBM_MODES`."""
    cv2 = import_cv2()
    flags = {
        "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
        "hh4": cv2.STEREO_SGBM_MODE_HH4,
        "hh": cv2.STEREO_SGBM_MODE_HH,
    }
    if name not in flags:
        raise ConfigError(f"SGBM mode {name!r}: choose one of {', '.join(SGBM_MODES)}")
    return flags[name]


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
    # Smoothness penalties; None = p1_per_block_px2 * block_size^2 and p2_per_block_px2 *
    # block_size^2 (the reference agent's 8*3*b^2 and 32*3*b^2: 8 and 32 per channel, 3 channels).
    p1: int | None = None
    p2: int | None = None
    p1_per_block_px2: int = 24
    p2_per_block_px2: int = 96
    # Smallest disparity in pixels accepted as valid (rejects far, noisy matches).
    min_valid_disparity_px: float = 1.0
    # Work at 1/downscale resolution (1 = full). 2 is ~4-6x faster; disparities are
    # rescaled to full-resolution pixels.
    downscale: int = 1
    # OpenCV's 3-way SGBM (fewer paths, ~1.2-1.5x faster, about as accurate on the
    # simulated imagery); False = the reference agent's 5-path mode.
    three_way: bool = False
    # Match the full image width: both images are padded on the left by the search
    # range (black), so the leftmost num_disparities columns, which OpenCV leaves
    # unmatched, get disparities wherever their match lies inside the right image
    # (a point at column u with disparity d <= u). Costs (W + nd) / W of the time.
    full_width: bool = False
    # What the images go through before the low-resolution match (disparity_lowres;
    # visual odometry's ImageNormalization). SGBM's smoothness penalties are fixed in grey
    # levels: with the raw lamp-lit images at night a rock's disparity spreads over the
    # unlit ground above its top and its lower flanks take the ground's, so its height
    # blob is a strip rejected as elongated. `lift` brightens regions darker than
    # normalization_gain grey levels to it and leaves brighter ones as they are (the
    # height map's matcher uses it; see docs/perception-history.md, "Fourth pass").
    # `local-contrast` divides out every slow brightness change (shadows included).
    # The sky mask is always taken from the raw image.
    normalization: ImageNormalization = ImageNormalization.NONE
    # Gaussian local mean of this standard deviation (fraction of the matched image's
    # width; large against a rock, small against the lamps' fall-off); lift: the target
    # grey level, local-contrast: grey levels per unit of relative contrast.
    normalization_sigma_frac: float = 0.05
    normalization_gain: float = 100.0

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "normalization", ImageNormalization(self.normalization))
        except ValueError:
            raise ConfigError(
                f"normalization={self.normalization!r}: choose one of "
                f"{', '.join(m.value for m in ImageNormalization)}"
            ) from None
        if not 0 < self.normalization_sigma_frac < 0.5:
            raise ConfigError(
                f"normalization_sigma_frac={self.normalization_sigma_frac}: must be in (0, 0.5)"
            )
        if not 0 < self.normalization_gain < 1e4:
            raise ConfigError(f"normalization_gain={self.normalization_gain}: must be in (0, 1e4)")
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise ConfigError("num_disparities must be a positive multiple of 16")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ConfigError("block_size must be odd and >= 1")
        if self.downscale < 1:
            raise ConfigError("downscale must be >= 1")
        if not 1 <= self.p1_per_block_px2 < self.p2_per_block_px2:
            raise ConfigError(
                f"p1_per_block_px2={self.p1_per_block_px2}, "
                f"p2_per_block_px2={self.p2_per_block_px2}: need 1 <= p1_per_block_px2 < "
                "p2_per_block_px2 (SGBM wants P2 > P1)"
            )

    @property
    def P1(self) -> int:
        return self.p1 if self.p1 is not None else self.p1_per_block_px2 * self.block_size**2

    @property
    def P2(self) -> int:
        return self.p2 if self.p2 is not None else self.p2_per_block_px2 * self.block_size**2


def max_num_disparities(width: int, block_size: int) -> int:
    """Largest SGBM search range (a multiple of 16, pixels) OpenCV can run on images
    `width` pixels wide with a `block_size` block: ``(width - block_size) // 16 * 16``.

    Measured with OpenCV 5.0: a larger range fails with an out-of-memory error of
    absurd size (or crashes) once it approaches the width. Below 16 no range works.
    """
    return max(int(width) - int(block_size), 0) // 16 * 16


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Grayscale uint8 view of an image (H, W), (H, W, 1) or (H, W, 3/4 RGB[A]).

    Float images are taken to be in [0, 1] when their maximum is <= 1, else [0, 255].
    """
    cv2 = import_cv2()
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
        self.config = config or StereoConfig()
        self.camera = camera or PinholeCamera()
        if not baseline_m > 0:
            raise ConfigError("baseline_m must be > 0")
        self.baseline_m = float(baseline_m)
        c = self.config
        nd = c.num_disparities
        if c.downscale > 1:
            nd = max(16, int(np.ceil(nd / c.downscale / 16.0)) * 16)
        # The search range cannot exceed the matched image's width (OpenCV then fails
        # with an absurd allocation, or crashes): clamp it to the camera's width.
        w = self.camera.width // c.downscale
        nd_max = max_num_disparities(w, c.block_size)
        if nd_max < 16:
            raise InputError(
                f"images of {self.camera.width}x{self.camera.height} px are too small for stereo "
                f"matching: SGBM needs a matched width of at least {16 + c.block_size} px (block "
                f"{c.block_size}, downscale {c.downscale}), got {w} px"
            )
        if nd > nd_max:
            logger.info(
                "SGBM numDisparities %d clamped to %d for %dx%d images (downscale %d)",
                nd,
                nd_max,
                self.camera.width,
                self.camera.height,
                c.downscale,
            )
            nd = nd_max
        self.num_disparities_lowres = nd
        self._matchers: dict[int, object] = {}
        self._sgbm = self._matcher(nd)

    def _matcher(self, num_disparities: int):
        """The OpenCV SGBM object for a search range (cached)."""
        m = self._matchers.get(num_disparities)
        if m is None:
            cv2 = import_cv2()
            c = self.config
            m = cv2.StereoSGBM_create(
                minDisparity=0,
                numDisparities=num_disparities,
                blockSize=c.block_size,
                P1=c.P1,
                P2=c.P2,
                disp12MaxDiff=c.disp12_max_diff,
                uniquenessRatio=c.uniqueness_ratio,
                speckleWindowSize=c.speckle_window_size,
                speckleRange=c.speckle_range,
                mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY if c.three_way else cv2.STEREO_SGBM_MODE_SGBM,
            )
            self._matchers[num_disparities] = m
        return m

    def _compute(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Raw SGBM disparity (int16, x16) of a pair at the matching resolution; the
        search range is narrowed for images narrower than the camera's."""
        h, w = left.shape
        nd = self.num_disparities_lowres
        nd_max = max_num_disparities(w, self.config.block_size)
        if nd > nd_max:
            if nd_max < 16:
                raise InputError(
                    f"a {w}x{h} px image (at matching resolution) is too small for stereo "
                    f"matching: SGBM needs a width of at least {16 + self.config.block_size} px "
                    f"(block {self.config.block_size})"
                )
            nd = nd_max
        return self._matcher(nd).compute(left, right)

    def _compute_full_width(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """Disparity (float32 pixels, NaN invalid) of every column: the pair is padded
        on the left by the search range, so columns u < nd are matched too; a disparity
        larger than u (the match would lie in the padding) is invalid."""
        cv2 = import_cv2()
        nd = self.num_disparities_lowres

        def pad(im):
            return cv2.copyMakeBorder(im, 0, 0, nd, 0, cv2.BORDER_CONSTANT, value=0)

        d = self._compute(pad(left), pad(right))[:, nd:].astype(np.float32) / 16.0
        u = np.arange(d.shape[1], dtype=np.float32)[None, :]
        d[(d <= 0) | (d > u - self.config.block_size // 2)] = np.nan
        return d

    def disparity(
        self, left: np.ndarray, right: np.ndarray, rows: tuple[int, int] | None = None
    ) -> np.ndarray:
        """Disparity of the left image in full-resolution pixels (float32, NaN = invalid).

        rows : optional (v0, v1) band of image rows that is needed; matching then runs
            on that band plus a margin (SGBM cost is proportional to the rows matched)
            and rows outside the band are NaN.
        """
        cv2 = import_cv2()
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
            d = self._compute(Ls, Rs).astype(np.float32) / 16.0
            d[d <= 0] = np.nan
            d = cv2.resize(d, (L.shape[1], L.shape[0]), interpolation=cv2.INTER_NEAREST) * k
        else:
            d = self._compute(L, R).astype(np.float32) / 16.0
        d[~(d >= self.config.min_valid_disparity_px)] = np.nan
        return d

    def disparity_lowres(
        self, left: np.ndarray, right: np.ndarray, v_start: int = 0, sky_level: int | None = None
    ) -> np.ndarray:
        """Disparity at 1/downscale resolution, in low-resolution pixels (float32, NaN = invalid).

        v_start : full-resolution rows above this (sky) are not matched and are NaN.
        sky_level : if given, pixels whose (downscaled) left intensity is below it are
            NaN (black sky: SGBM smears foreground disparities into it).
        The returned array has shape (H // k, W // k); low-resolution pixel (i, j)
        covers full-resolution pixels (k*i .. k*i+k-1, k*j .. k*j+k-1).
        """
        cv2 = import_cv2()
        L, R = to_gray_u8(left), to_gray_u8(right)
        if L.shape != R.shape:
            raise InputError(f"left and right images differ in shape: {L.shape} vs {R.shape}")
        k = self.config.downscale
        h, w = L.shape[0] // k, L.shape[1] // k
        out = np.full((h, w), np.nan, np.float32)
        r0 = min(max(int(v_start) // k - self.config.block_size, 0), h)
        if h - r0 < 2 * self.config.block_size:
            return out
        if k > 1:
            Ls = cv2.resize(L, (w, h), interpolation=cv2.INTER_AREA)[r0:]
            Rs = cv2.resize(R, (w, h), interpolation=cv2.INTER_AREA)[r0:]
        else:
            Ls, Rs = L[r0:], R[r0:]
        Lm, Rm = self._normalized(Ls, sky_level), self._normalized(Rs, sky_level)
        d = (
            self._compute_full_width(Lm, Rm)
            if self.config.full_width
            else self._compute(Lm, Rm).astype(np.float32) / 16.0
        )
        d[~(d >= self.config.min_valid_disparity_px / k)] = np.nan
        if sky_level is not None:
            d[Ls < sky_level] = np.nan
        out[r0:] = d
        return out

    def _normalized(self, image: np.ndarray, sky_level: int | None) -> np.ndarray:
        """`image` (uint8, at matching resolution) after config.normalization; pixels
        darker than `sky_level` in the raw image stay black (sky)."""
        c = self.config
        if c.normalization is ImageNormalization.NONE:
            return image
        sigma = c.normalization_sigma_frac * image.shape[1]
        # the local mean on an image reduced so that its Gaussian keeps >= 4 pixels
        out = normalize_image(
            image, c.normalization, sigma, c.normalization_gain, mean_shrink=int(sigma // 4)
        )
        if sky_level is not None:
            out[image < sky_level] = 0
        return out

    def depth_from_disparity(self, disparity: np.ndarray) -> np.ndarray:
        """z = fx * baseline / d (metres, NaN where d is invalid)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return (self.camera.fx * self.baseline_m / disparity).astype(np.float32)

    def depth(
        self, left: np.ndarray, right: np.ndarray, rows: tuple[int, int] | None = None
    ) -> np.ndarray:
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


def first_ground_row(image: np.ndarray, sky_level: int = 6, min_pixels: int = 8) -> int:
    """First image row with at least `min_pixels` pixels brighter than `sky_level`
    (the lunar sky is black), 0 when even the top row has some; H when none has."""
    g = to_gray_u8(image)
    rows = np.flatnonzero(np.count_nonzero(g[:, ::4] > sky_level, axis=1) * 4 >= min_pixels)
    return int(rows[0]) if rows.size else int(g.shape[0])


@dataclass(frozen=True)
class GroundConfig:
    """Local ground surface from stereo points, and heights above it.

    The camera sits ~0.33 m above the ground, so rays meet the ground at grazing
    angles and height is well conditioned: a disparity error dd gives a height error
    of about h_cam * dd / d (3 mm at 5 m for dd = 0.25 px), while depth errors there
    are centimetres. Rocks stick up; shadows and albedo texture do not.
    """

    # Points farther than this (optical depth, metres) are ignored: past ~10 m the
    # ground is a few rows near the horizon and disparities are a few pixels.
    max_range_m: float = 10.0
    # Side of the square cells (rover x-y plane, metres) of the ground height grid.
    # Several times the footprint of a target rock (radius 0.1-0.4 m) so the median
    # of a cell is ground, small enough to follow craters and the terrain's roll.
    cell_m: float = 0.35
    # Quantile of the heights in a cell taken as its ground level (0.5 = median;
    # rock points are outliers above it).
    quantile: float = 0.5
    # Cells with fewer points are filled from their neighbours.
    min_points: int = 4
    # The ground grid is fitted on every fit_stride-th point (heights are still
    # computed for all): halves the sort, the grid median barely changes.
    fit_stride: int = 2
    # Extrapolate the ground linearly beyond the outer cell centres (False: constant).
    extrapolate_edges: bool = True
    # Weight each point of a cell's quantile by the ground length it covers along the view
    # (how far its horizontal range moves per row towards the points footprint_span_px
    # low-resolution rows above and below, the smaller of the two; clipped to
    # [0, footprint_cap] x that of level ground at its depth): a rock's face, seen square-on,
    # covers many pixels and little ground, while the ground beyond 3 m, seen at a grazing
    # angle, covers few pixels; one point per pixel (False, the default) lets a rock of
    # r >= 0.1 m at 4-5 m fill a 0.35 m cell's median and lift the ground under itself by
    # 4-16 cm. Off by default: it raises recall and precision on LAC-look sites but moves the
    # blobs of rocks that were found already (repeatability of r >= 0.1 m on sites 300-301:
    # median 2.0 -> 2.4 cm); docs/perception-status.md, "Recall of r >= 0.1 m".
    footprint_weights: bool = False
    footprint_span_px: int = 2
    footprint_cap: float = 2.0
    # With footprint_weights: a cell takes the weighted level only where it lies more than
    # this (metres) under the plain quantile, else the plain one (0: the weighted level in
    # every cell). The weights alone move ordinary cells' levels by millimetres, and with them
    # the blobs of near rocks too; 0.02 keeps the repeatability (2.0 cm) but not the weights'
    # precision gain, and gains little recall (docs/perception-status.md).
    footprint_min_drop_m: float = 0.0
    # Cells whose centre lies at least far_range_m (horizontal, from the camera) away take
    # far_quantile instead of quantile (0: off, one quantile everywhere). Beyond ~3 m a rock's
    # face fills much of a cell's pixels and lifts its median under the rock; a lower quantile
    # there lets partly hidden rocks reach the seed while the near ground, and the near
    # blobs, stay as they are (docs/perception-status.md, "The lower ground").
    far_quantile: float = 0.0
    far_range_m: float = 3.0

    def __post_init__(self) -> None:
        if not (self.max_range_m > 0 and self.cell_m > 0):
            raise ConfigError("max_range_m and cell_m must be > 0")
        if not 0.0 < self.quantile < 1.0:
            raise ConfigError("quantile must be in (0, 1)")
        if not (0.0 <= self.far_quantile < 1.0 and self.far_range_m >= 0):
            raise ConfigError(
                f"far_quantile={self.far_quantile} must be in [0, 1) (0: off) and "
                f"far_range_m={self.far_range_m} >= 0"
            )
        if self.min_points < 1:
            raise ConfigError("min_points must be >= 1")
        if not self.footprint_min_drop_m >= 0:
            raise ConfigError(f"footprint_min_drop_m={self.footprint_min_drop_m} must be >= 0")
        if not (1 <= self.footprint_span_px <= 16 and self.footprint_cap > 0):
            raise ConfigError(
                f"footprint_span_px={self.footprint_span_px} must be in [1, 16] and "
                f"footprint_cap={self.footprint_cap} > 0"
            )


@dataclass
class HeightMap:
    """Stereo geometry of one left image at 1/scale resolution (arrays (h, w)).

    disparity : low-resolution pixels, NaN invalid; depth : optical z, metres;
    points_rover : (h, w, 3) points in the rover frame; height : metres above the
    local ground surface (NaN where invalid); scale : full-res pixels per low-res
    pixel; valid_u0 : first full-resolution column where disparities can exist
    (SGBM cannot match the leftmost num_disparities columns).
    """

    disparity: np.ndarray
    depth: np.ndarray
    points_rover: np.ndarray
    height: np.ndarray
    scale: int
    valid_u0: int
    T_rover_optical: np.ndarray
    # the levelling rotation (4x4) when the map was built in a frame levelled on the ground
    # plane fitted to the stereo points (DetectorConfig.level_from_stereo): points_rover and
    # T_rover_optical are then in that frame; None = the rover frame itself
    T_level_rover: np.ndarray | None = None
    # the view's ground normal (unit, pointing up) in the map's frame, when the detector fitted
    # one (small_rocks.ground_plane); None = not fitted
    up_rover: np.ndarray | None = None
    # ground_height_map(heights=False)'s valid pixels and points, for fill_ground_heights
    _lifted: tuple | None = field(default=None, repr=False, compare=False)

    def lowres_index(self, mask) -> tuple[np.ndarray, np.ndarray]:
        """Unique low-resolution (rows, cols) covered by a full-resolution InstanceMask."""
        crop = np.asarray(mask.crop, bool)
        k = self.scale
        h, w = self.height.shape
        if k > 1:
            # the crop pooled onto the low-resolution grid (any pixel of a k x k cell): the
            # cells in row-major order, as the sorted unique cell keys of its pixels
            a, b = mask.v0 % k, mask.u0 % k
            ch, cw = crop.shape
            hh, ww = -(-(a + ch) // k), -(-(b + cw) // k)
            grid = np.zeros((hh * k, ww * k), bool)
            grid[a : a + ch, b : b + cw] = crop
            crop = grid.reshape(hh, k, ww, k).any(axis=(1, 3))
        lv, lu = np.nonzero(crop)
        lv += mask.v0 // k
        lu += mask.u0 // k
        ok = (lv < h) & (lu < w)
        return lv[ok].astype(np.int64), lu[ok].astype(np.int64)


_BLOCK = 16384
"""Points per block in ground_height_map's per-point arithmetic."""


def _bilinear(grid: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """float32 `grid` interpolated bilinearly at (gx, gy) (column, row) positions, all within
    [0, shape - 1). Exact weights: cv2.remap's INTER_LINEAR rounds positions to 1/32 pixel in
    OpenCV 4.x (exact in 5.x), which moved heights by millimetres between OpenCV releases and
    flipped borderline masks; this costs ~1 ms more than cv2.remap at 640x360."""
    x0, y0 = gx.astype(np.int32), gy.astype(np.int32)  # non-negative: truncation is floor
    fx, fy = gx - x0.astype(np.float32), gy - y0.astype(np.float32)
    w = grid.shape[1]
    i = y0 * np.int32(w) + x0
    flat = grid.ravel()
    a, b, c, d = flat.take(i), flat.take(i + 1), flat.take(i + w), flat.take(i + w + 1)
    top = a + fx * (b - a)
    return top + fy * (c + fx * (d - c) - top)


def ground_height_map(
    disparity: np.ndarray,
    scale: int,
    camera: PinholeCamera,
    baseline_m: float,
    T_rover_optical: np.ndarray,
    config: GroundConfig | None = None,
    max_disparity: float | None = None,
    *,
    heights: bool = True,
) -> HeightMap:
    """Heights above the local ground of every stereo point of a low-resolution disparity.

    Points are lifted to the rover frame (z up); the ground is the per-cell quantile
    of z over a horizontal grid, holes filled from neighbours, interpolated
    bilinearly between cell centres; height = z - ground(x, y).
    max_disparity : disparities at or above it (saturated near the search limit) are dropped.
    heights : False = the depths and points only (height all NaN, valid_u0 0) until
    :func:`fill_ground_heights` computes them (a map that may be rebuilt in another frame
    first, as the detector's levelling does, skips the ground grid).
    """
    cfg = config or GroundConfig()
    D = np.asarray(disparity, np.float32)
    h, w = D.shape
    k = int(scale)
    fx = camera.fx / k
    # low-res pixel (j, i) centre in full-res pixel units is k*j + (k-1)/2
    cx = (camera.cx - (k - 1) / 2.0) / k
    cy = (camera.cy - (k - 1) / 2.0) / k
    fb = fx * float(baseline_m)
    with np.errstate(invalid="ignore"):
        ok = D > fb / cfg.max_range_m  # NaN compares False
        if max_disparity is not None:
            ok &= D < max_disparity
    # every per-point quantity is computed at the valid pixels only (about 40 % of the map on
    # the real LAC frames: sky and far field are not), as 1-D arrays, and scattered into the
    # map's NaN-filled arrays; the arithmetic per point is the dense form's, so the values are
    # bit-identical to it (and the map's large temporaries, which cost page faults, are few)
    depth = np.full((h, w), np.nan, np.float32)
    T = np.asarray(T_rover_optical, float)
    out = HeightMap(
        D,
        depth,
        np.full((h, w, 3), np.nan, np.float32),
        np.full((h, w), np.nan, np.float32),
        k,
        0,
        T,
    )
    flat = np.flatnonzero(ok)
    n = flat.size
    if n < cfg.min_points:
        return out
    # in blocks of _BLOCK points: the temporaries stay small (cache-resident, and reused by
    # the allocator instead of fresh pages, which cost about as much as the arithmetic)
    blocks = [slice(i, min(i + _BLOCK, n)) for i in range(0, n, _BLOCK)]
    ru_all = ((np.arange(w) - cx) / fx).astype(np.float32)
    rv_all = ((np.arange(h) - cy) / fx).astype(np.float32)
    xyz = np.empty((3, n), np.float32)
    cols_ok = np.empty(n, np.int64)
    depth_flat, pts_flat = depth.ravel(), out.points_rover.reshape(-1, 3)
    for b in blocks:
        f = flat[b]
        rows, cols_ok[b] = np.divmod(f, w)
        z_ok = np.float32(fb) / D.ravel()[f]
        depth_flat[f] = z_ok
        ru, rv = ru_all[cols_ok[b]], rv_all[rows]
        for i in range(3):  # rover = R @ (ru z, rv z, z) + t, one coordinate at a time
            ray = np.float32(T[i, 0]) * ru + np.float32(T[i, 1]) * rv + np.float32(T[i, 2])
            p = xyz[i, b]
            np.multiply(z_ok, ray, out=p)
            p += np.float32(T[i, 3])
        pts_flat[f] = xyz[:, b].T
    out._lifted = (flat, xyz, cols_ok, cfg, 1.0 / fx)
    if heights:
        fill_ground_heights(out)
    return out


def fill_ground_heights(hm: HeightMap) -> HeightMap:
    """The heights (and valid_u0) of a map that :func:`ground_height_map` built with
    heights=False, in place (the same values as heights=True gives); `hm` itself. A map whose
    heights are already computed is returned as it is."""
    if hm._lifted is None:
        return hm
    flat, xyz, cols_ok, cfg, rad_per_px = hm._lifted
    hm._lifted = None
    cv2 = import_cv2()
    out, k, n = hm, hm.scale, flat.size
    blocks = [slice(i, min(i + _BLOCK, n)) for i in range(0, n, _BLOCK)]
    Xv, Yv, Zv = xyz
    st = max(int(cfg.fit_stride), 1)
    fit = cols_ok % st == 0 if st > 1 else slice(None)
    X, Y, Z = Xv[fit], Yv[fit], Zv[fit]
    if Z.size < cfg.min_points:
        return out
    x_lo, y_lo = float(Xv.min()), float(Yv.min())
    c = cfg.cell_m
    nx = int((float(Xv.max()) - x_lo) / c) + 1
    ny = int((float(Yv.max()) - y_lo) / c) + 1
    idx_f = ((Y - y_lo) / c).astype(np.int64) * nx + ((X - x_lo) / c).astype(np.int64)
    cnt = np.bincount(idx_f, minlength=nx * ny)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    # one sort of (cell, height in mm) keys gives every cell's sorted heights
    z_lo = float(Z.min())
    zq = np.minimum(np.rint((Z - z_lo) * 1000.0).astype(np.int64), (1 << 24) - 1)
    # keys cell * zs + height, ordered as (cell, height); 32-bit when they fit (a faster sort)
    zs = int(zq.max()) + 1
    keys = idx_f * zs + zq
    keys = keys.astype(np.int32) if nx * ny * zs < 1 << 31 else keys
    good = cnt >= cfg.min_points
    g = np.zeros(nx * ny, np.float32)
    q = cfg.quantile
    if cfg.far_quantile > 0:
        # per cell: far_quantile where the cell's centre lies far_range_m or more from the camera
        cam = np.asarray(hm.T_rover_optical, float)[:3, 3]
        cxs = x_lo + (np.arange(nx) + 0.5) * c - cam[0]
        cys = y_lo + (np.arange(ny) + 0.5) * c - cam[1]
        far = np.hypot(cxs[None, :], cys[:, None]).ravel() >= cfg.far_range_m
        q = np.where(far, cfg.far_quantile, cfg.quantile)
    if cfg.footprint_weights:
        wts = _range_footprints(hm, flat[fit], X, Y, Z, cfg, rad_per_px).astype(np.float64)
        # the keys sorted with each point's index packed below them (one sort, no argsort)
        bits = max(int(keys.size).bit_length(), 1)
        if int(keys.max(initial=0)) < 1 << (62 - bits):
            packed = np.sort((keys.astype(np.int64) << bits) | np.arange(keys.size))
            order, keys = packed & ((1 << bits) - 1), packed >> bits
        else:
            order = np.argsort(keys, kind="stable")
            keys = keys[order]
        cw = np.cumsum(wts[order])
        total = np.bincount(idx_f, wts, minlength=nx * ny)
        before = np.where(start > 0, cw[np.maximum(start - 1, 0)], 0.0)
        # first point of the cell whose cumulative weight reaches the quantile's share; a cell
        # without weight (a face seen square-on, no ground) takes the unweighted quantile
        pos = np.searchsorted(cw, before + q * total, side="left")
        plain = start + (cnt * q).astype(np.int64)
        pos = np.where(total > 0, np.clip(pos, start, start + np.maximum(cnt - 1, 0)), plain)
        sel = keys[pos[good]]
        if cfg.footprint_min_drop_m > 0:
            # the weighted level only where it lies well under the plain one (a cell whose
            # plain quantile sits on a rock's face); elsewhere the plain level
            sel_p = keys[plain[good]]
            drop_mm = (sel_p % zs) - (sel % zs)
            sel = np.where(drop_mm > cfg.footprint_min_drop_m * 1000.0, sel, sel_p)
    else:
        keys = np.sort(keys)
        qg = q[good] if cfg.far_quantile > 0 else q
        sel = keys[start[good] + (cnt[good] * qg).astype(np.int64)]
    g[good] = (sel % zs).astype(np.float32) / 1000.0 + z_lo
    G = g.reshape(ny, nx)
    W = good.reshape(ny, nx).astype(np.float32)
    if not good.all():
        # normalized convolution fills holes from their neighbours (repeated for wide holes)
        for _ in range(3):
            Gs = cv2.blur(G * W, (3, 3), borderType=cv2.BORDER_CONSTANT)
            Ws = cv2.blur(W, (3, 3), borderType=cv2.BORDER_CONSTANT)
            fill = (W == 0) & (Ws > 0)
            if not fill.any():
                break
            G = np.where(fill, Gs / np.maximum(Ws, 1e-6), G)
            W = np.where(fill, 1.0, W).astype(np.float32)
    # bilinear interpolation between cell centres
    Gp = np.pad(G, 1, mode="edge")
    if cfg.extrapolate_edges and nx > 1 and ny > 1:
        # linear extrapolation past the outer cell centres (the grid's edge cells are
        # where the near field lies: a constant edge biases heights on slopes)
        Gp[1:-1, 0], Gp[1:-1, -1] = 2 * G[:, 0] - G[:, 1], 2 * G[:, -1] - G[:, -2]
        Gp[0, :], Gp[-1, :] = 2 * Gp[1, :] - Gp[2, :], 2 * Gp[-2, :] - Gp[-3, :]
    # bilinear interpolation of the padded grid at every pixel's cell coordinates
    Gp = Gp.astype(np.float32)
    height_flat = out.height.ravel()
    for b in blocks:
        gx = np.clip(
            (Xv[b] - np.float32(x_lo)) * np.float32(1.0 / c) + np.float32(0.5), 0.0, nx + 0.999
        )
        gy = np.clip(
            (Yv[b] - np.float32(y_lo)) * np.float32(1.0 / c) + np.float32(0.5), 0.0, ny + 0.999
        )
        height_flat[flat[b]] = Zv[b] - _bilinear(Gp, gx, gy)
    out.valid_u0 = int(cols_ok.min()) * k
    return out


def _range_footprints(
    hm: HeightMap, pix: np.ndarray, X: np.ndarray, Y: np.ndarray, Z: np.ndarray, cfg, rad_per_px
) -> np.ndarray:
    """Ground length along the view that each point covers (GroundConfig.footprint_weights;
    `pix`: the points' flat indices in the map, X, Y, Z their coordinates): how far the
    horizontal range moves per row towards the point cfg.footprint_span_px rows above and
    towards the one as many rows below, the smaller of the two (the one there is where the
    other has no stereo, 0 where neither has), clipped to [0, cfg.footprint_cap] x that of
    level ground at the point's range and height under the camera."""
    h, w = hm.height.shape
    cam = np.asarray(hm.T_rover_optical, float)[:3, 3]
    cx, cy = np.float32(cam[0]), np.float32(cam[1])
    rho = np.hypot(X - cx, Y - cy)
    s = int(cfg.footprint_span_px)
    # the points' ranges on the map's grid, padded by s rows above and below (NaN: no point;
    # the fit's columns are every fit_stride-th, so a point's neighbours in its column are in)
    pad = s * w
    grid = np.full(h * w + 2 * pad, np.nan, np.float32)
    grid[pix + pad] = rho
    # the smaller of the two one-sided drops: at an occluding edge (a rock's top against the
    # ground far behind it) one side jumps by metres, the other is the surface's own
    a = (grid.take(pix) - rho) / np.float32(s)
    b = (rho - grid.take(pix + 2 * pad)) / np.float32(s)
    d = np.where(np.isfinite(a) & np.isfinite(b), np.minimum(a, b), np.where(np.isfinite(a), a, b))
    drop = np.maximum(np.float32(cam[2]) - Z, np.float32(0.05))
    level = rho * rho * np.float32(rad_per_px) / drop
    return np.clip(np.nan_to_num(d, nan=0.0), 0.0, np.float32(cfg.footprint_cap) * level)


def refine_disparity(
    left: np.ndarray,
    right: np.ndarray,
    crop: np.ndarray,
    u0: int,
    v0: int,
    d0: float,
    search_px: int = 3,
    erode_px: int = 1,
) -> float:
    """Sub-pixel disparity of one mask at full resolution by masked template matching.

    The whole mask (a boolean `crop` whose top-left pixel is (u0, v0) in the left
    image, eroded by `erode_px` so that background pixels at the silhouette do not
    vote) is matched along the same rows of the right image for disparities within
    `search_px` of the initial guess `d0` (full-resolution pixels, e.g. from the
    low-resolution SGBM); a parabola through the squared-difference minimum gives
    the sub-pixel value. One template averages the texture of hundreds of pixels, so
    the disparity of the rock's visible surface is found to ~0.1 px where per-pixel
    low-resolution SGBM is noisy. Returns NaN when the mask is too small, the search
    leaves the image, or the minimum lies on the search boundary.
    """
    cv2 = import_cv2()
    L, R = to_gray_u8(left), to_gray_u8(right)
    m = np.asarray(crop, np.uint8)
    if erode_px > 0:
        k = 2 * erode_px + 1
        m_e = cv2.erode(m, np.ones((k, k), np.uint8))
        if np.count_nonzero(m_e) >= 20:
            m = m_e
    if np.count_nonzero(m) < 20 or not np.isfinite(d0):
        return float("nan")
    h, w = m.shape
    H, W = L.shape
    di = int(round(d0))
    a = u0 - di - search_px
    b = u0 + w - di + search_px
    if a < 0 or b > W or v0 < 0 or v0 + h > H or u0 + w > W:
        return float("nan")
    tpl = L[v0 : v0 + h, u0 : u0 + w].astype(np.float32)
    strip = R[v0 : v0 + h, a:b].astype(np.float32)
    res = cv2.matchTemplate(strip, tpl, cv2.TM_SQDIFF, mask=m.astype(np.float32))[0]
    i = int(np.argmin(res))
    if i == 0 or i == res.size - 1:
        return float("nan")
    c0, c1, c2 = float(res[i - 1]), float(res[i]), float(res[i + 1])
    den = c0 - 2.0 * c1 + c2
    off = 0.5 * (c0 - c2) / den if den > 0 else 0.0
    # column a + i of the right image matches column u0 of the left: d = u0 - (a + i)
    return float(u0 - (a + i + off))


def mask_disparity_fullres(
    left: np.ndarray,
    right: np.ndarray,
    crop: np.ndarray,
    u0: int,
    v0: int,
    d0: float,
    span_px: int = 16,
    block_size: int = 5,
    pad_px: int = 8,
    p1_per_block_px2: int = 8,
    p2_per_block_px2: int = 32,
    mode: str = "hh4",
) -> np.ndarray | None:
    """Full-resolution SGBM disparity over one mask's bounding box, searched only in a
    narrow band around an initial guess.

    `crop` is a boolean mask whose top-left pixel is (u0, v0) in the left image; `d0`
    is its disparity in full-resolution pixels (e.g. the median of the low-resolution
    SGBM). SGBM runs on the box (plus `pad_px`) with disparities in
    [floor(d0) - span_px / 2, floor(d0) + span_px / 2): the right image is shifted by the
    band's start so a 16-wide search costs little (about a millisecond per mask) while
    keeping SGBM's 1/16 px sub-pixel resolution at full image resolution, where the
    half-resolution map quantises depth. Returns the (h, w) disparity of the crop's box
    in full-resolution pixels (NaN invalid or at the band's edges), or None when the
    band leaves the image. SGBM's smoothness penalties are ``p1_per_block_px2`` and
    ``p2_per_block_px2`` times the block's area (one grayscale channel). `mode`: the SGBM
    mode (:data:`SGBM_MODES`); ``hh4`` aggregates both ways along rows and columns, where
    ``3way``'s top-down-only pass lags behind a disparity that grows down the image and put
    rocks' points too far (measured against ray-cast truth: docs/lac-map.md, "The detections'
    range").
    """
    cv2 = import_cv2()
    L, R = to_gray_u8(left), to_gray_u8(right)
    h, w = np.asarray(crop).shape
    H, W = L.shape
    if not np.isfinite(d0) or h == 0 or w == 0:
        return None
    nd = max(16, int(span_px) // 16 * 16)
    bs = int(block_size) | 1
    dmin = max(int(np.floor(d0)) - nd // 2, 0)
    b = min(u0 + w + pad_px, W)
    la = u0 - pad_px - nd - bs  # SGBM leaves the first nd columns unmatched
    if b <= u0 or u0 - dmin < 0:
        return None
    r0, r1 = max(v0 - pad_px, 0), min(v0 + h + pad_px, H)
    # columns left of the image (near the left edge) are black padding
    Lc = _columns(L, r0, r1, la, b)
    Rc = _columns(R, r0, r1, la - dmin, b - dmin)
    m = cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=nd,
        blockSize=bs,
        P1=p1_per_block_px2 * bs * bs,
        P2=p2_per_block_px2 * bs * bs,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=0,
        mode=sgbm_mode_flag(mode),
    )
    d = m.compute(Lc, Rc).astype(np.float32)[v0 - r0 : v0 - r0 + h, u0 - la : u0 - la + w] / 16.0
    d[(d <= 0) | (d >= nd - 1)] = np.nan
    return d + dmin


def _columns(image: np.ndarray, r0: int, r1: int, a: int, b: int) -> np.ndarray:
    """Contiguous copy of image[r0:r1, a:b], black where a < 0 (left of the image)."""
    if a >= 0:
        return np.ascontiguousarray(image[r0:r1, a:b])
    out = np.zeros((r1 - r0, b - a), image.dtype)
    out[:, -a:] = image[r0:r1, 0:b]
    return out
