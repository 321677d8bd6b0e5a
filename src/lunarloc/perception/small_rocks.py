"""Small rocks near the rover: appearance candidates checked by full-resolution stereo height.

The height-map segmenter (``segment.py``) sees a rock when its half-resolution stereo heights
stand 2.5-3.5 cm above a ground grid of 0.35 m cells. A rock 3-7 cm wide stands 1.5-3 cm
high and covers 5-20 pixels at 1-6 m: the half-resolution match (a 10-pixel block) smooths it
into the ground, and the real LAC terrain has undulations of that height, so the thresholds
cannot come down. This stage finds such rocks in two steps:

1. **Candidates from appearance.** A small rock's lit face is brighter than the regolith
   around it; seen against the sun, its unlit side and the shadow it casts are darker.
   Blobs of a difference of Gaussians on the half-resolution left image, scaled by the local
   contrast of the image (textured and flat regolith alike), whose size at the range the
   height map gives lies in [min_width_m, max_width_m], are candidates: the strongest
   ``max_candidates`` bright ones, then (``dark_contrast_z`` > 0) the strongest
   ``max_dark_candidates`` dark ones. By default (``net_candidates`` 10; 0 turns it off) the
   peaks of a tiny rock-segmentation network's probability (``rock_net.py``, trained on the
   simulator's labelled images) are candidates too, measured and judged as the bright ones
   (in smaller windows, ``net_window_margin``).
2. **Height from full-resolution stereo, against a local plane.** SGBM at full resolution
   runs on a window around each candidate (a 32-disparity band around the height map's
   disparity). A plane is fitted (least squares, once more without outliers beyond 3 MADs)
   to the window's points outside the dilated blob, and the blob's height is the 90th
   percentile of its points' distances from that plane, on the camera's side. The plane is
   local, so the test needs neither the rover's roll and pitch nor a level ground: a rover
   tilted on a crater rim sees the same heights. A candidate is a rock when its height is at
   least ``min_top_m`` and ``min_snr`` times the plane's residual spread (rough or
   mismatched surroundings raise it), at most ``max_top_per_width`` times its width plus
   ``top_margin_m`` (a taller thin blob is an edge, a post or a mismatch), and the local plane
   is within ``max_tilt_deg`` of the ground plane fitted to all near stereo points (the
   lander's panels and a boulder's face are not ground). A dark blob is mostly a shadow, flat
   ground beside the rock that cast it: it is judged by the raised part of its window next to
   it (the largest connected patch standing ``min_snr`` noises high within one blob size),
   which must stand ``dark_min_snr`` noises high over ``dark_min_points`` pixels.
3. **A learned judge** (``judge_min_score`` > 0; on by default at 0.92: trained on sunlit and
   lamp-lit sites; 0 turns it off and the hand verdict of step 2 decides). The hand
   thresholds of step 2 cannot separate a 1-4 cm rock top from ring noise of 0.5-3.5 cm; with
   the judge on, step 2 keeps only floors (``judge_min_top_m``, ``judge_min_snr``,
   ``judge_dark_min_points``) and a small network (``small_rock_judge.npz`` beside this
   module: the height-map verifier's :class:`~lunarloc.perception.verifier.BlobVerifier`
   format, plain arrays, numpy inference)
   scores each candidate above them from :func:`judge_features`: what the stage measured and
   the appearance of the left image around the blob (the verifier's ``appearance_features``). A
   candidate scoring under ``judge_min_score`` is no rock (``reason`` ``"judged"``).
   ``benchmarks/train_small_rocks.py`` trains it on rendered sites labelled by the simulator.

The ground plane of the whole view (:func:`ground_plane`) is also what replaces the level-rover
assumption where one is needed: fitted to the height map's points within ``ground_range_m``,
it gives the "up" direction from stereo alone.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from lunarloc.core.configs import check_settings, setting
from lunarloc.core.errors import ConfigError
from lunarloc.core.stats import median as _median
from lunarloc.perception.masks import InstanceMask
from lunarloc.perception.rock_net import (
    CONTRAST_SIGMA_PX,
    DOG_SIGMA_PX,
    NET_WIDTH_PX,
    local_contrast,
    rock_net_at,
)
from lunarloc.perception.verifier import (
    APPEARANCE_FEATURES,
    BlobVerifier,
    appearance_features,
)

__all__ = [
    "JUDGE_FEATURES",
    "JUDGE_PATH",
    "SmallRock",
    "SmallRockConfig",
    "default_judge",
    "detect_small_rocks",
    "ground_plane",
    "judge_features",
    "load_judge",
    "small_rock_candidates",
]

#: The packaged learned judge (benchmarks/train_small_rocks.py writes it).
JUDGE_PATH = Path(__file__).with_name("small_rock_judge.npz")
#: The stage's own measures of a candidate that reaches the judge, in the model's order.
_STAGE_FEATURES = (
    "top_m",  # the judged blob's top above the local ground (90th percentile)
    "noise_m",  # the ring's residual spread
    "top_snr",  # top_m / noise_m
    "median_snr",  # the blob's median height / noise_m
    "width_m",
    "depth_m",
    "top_per_width",
    "blob_points",  # valid pixels of the judged blob
    "rock_points",  # valid pixels of the rock (the blob and its raised neighbours)
    "box_w_px",  # the candidate's box (full-resolution pixels)
    "box_h_px",
    "aspect",
    "candidate_px",
    "contrast_z",  # the candidate's peak contrast (local contrasts)
    "dark",
    "pair_dist",  # to the nearest candidate of the other polarity, in box sizes (<= 10)
    "row",  # the box's centre row / image height
    "lowres_height_m",  # the height map's highest point around the candidate
    "tilt_cos",  # |cos| of the ring plane's angle to the view's ground plane
)
#: The judge's feature vector: the stage's measures, then the appearance of the left image
#: around the candidate's blob as the height-map verifier measures it (grey statistics of
#: blob and ring, gradients, orientation spread, a 4 x 4 normalised grey patch).
JUDGE_FEATURES: tuple[str, ...] = _STAGE_FEATURES + APPEARANCE_FEATURES
_PAIR_CAP = 10.0


# settings that must come in order: (lower, upper, strictly)
_ORDERED = (
    ("min_range_m", "max_range_m", True),
    ("min_width_m", "max_width_m", True),
    ("band_px", "max_band_px", False),
)


@dataclass(frozen=True)
class SmallRockConfig:
    """Settings of the small-rock stage (see the module's docstring). Pixel sizes are at
    1280x720 (the LAC's cameras); widths and heights in metres. Each setting's range is declared
    beside it and checked once, when the config is built or loaded; why the defaults have their
    values is in docs/perception-status.md ("Small rocks")."""

    # run the stage (after the height-map detections; classical segmenter only)
    enabled: bool = setting(True)

    # -- candidates from appearance (on the left image at 1/candidate_scale resolution)
    # resolution of the candidate search (1 = full, 2 = half); the sigmas are in its pixels
    candidate_scale: int = setting(2, choices=(1, 2, 4))
    # the local background: a Gaussian of this standard deviation (pixels)
    dog_sigma_px: float = setting(2.0, gt=0.0)
    # the local contrast: RMS of the difference of Gaussians over a window this wide (pixels)
    contrast_sigma_px: float = setting(8.0, gt=0.0)
    # a bright candidate stands this many local contrasts above its background
    contrast_z: float = setting(2.0, gt=0.0)
    # a dark candidate (a shadow or a rock's unlit side) lies this many local contrasts below
    # its background (0 = bright candidates only)
    dark_contrast_z: float = setting(2.0, ge=0.0)
    # pixels darker than this are sky (0-255)
    sky_level: int = setting(8, ge=0, le=255)
    # at most this many bright candidates per image (the strongest blobs)
    max_candidates: int = setting(40, ge=0)
    # a candidate's box is at most this many times wider than tall
    max_aspect: float = setting(2.0, gt=0.0)
    # look for candidates inside the height map's rejected blobs too (elongated, too large,
    # duplicate, tentative, ...: a small rock on a hummock or beside a larger blob); its kept
    # detections and the blobs judged no rock or on the lander stay excluded
    inside_rejected: bool = setting(False)
    # ... and inside its detections still to be confirmed across frames (tentative ones, and
    # those on a crest): a small-rock detection there is firm and displaces them
    inside_tentative: bool = setting(False)
    # max_candidates and max_dark_candidates count only the candidates that get a window: centred
    # outside the height map's blobs (the exclusion) and passing the pre-check
    # (min_lowres_height_m); the others are passed over before they take a place
    count_checked: bool = setting(False)
    # at most this many candidates per image from the height map itself (after those from
    # appearance): its local peaks standing height_candidate_m above its local mean (a rock
    # the image's contrast does not show; 0 = none)
    height_candidates: int = setting(0, ge=0)
    height_candidate_m: float = setting(0.01, gt=0.0)
    # a height candidate (no contrast vouches for it) stands at least this high (m) and this
    # many ring noises (the hand verdict; with the judge on, the judge decides)
    height_min_top_m: float = setting(0.018, gt=0.0)
    height_min_snr: float = setting(4.0, ge=0.0)
    # candidates' range (optical depth from the height map, m)
    min_range_m: float = setting(0.8, gt=0.0)
    max_range_m: float = setting(6.0, gt=0.0)
    # candidates' width (m)
    min_width_m: float = setting(0.012, gt=0.0)
    max_width_m: float = setting(0.15, gt=0.0)

    # -- the full-resolution window
    # the blob's box plus this many box sizes each side ...
    window_margin: float = setting(1.5, gt=0.0)
    # ... and at least this many pixels
    window_min_margin_px: int = setting(8, ge=0)
    # SGBM block (pixels, odd)
    block_size: int = setting(5, ge=1, le=15)
    # disparity band searched around the height map's disparities (pixels) ...
    band_px: int = setting(16, ge=16, multiple_of=16)
    # ... widened to hold the window's disparities, up to this
    max_band_px: int = setting(64, ge=16, multiple_of=16)

    # -- the verdict (height above the local ground fitted to the window's ring)
    # a rock stands at least this high (m) ...
    min_top_m: float = setting(0.01, gt=0.0)
    # ... and this many times the ring's residual spread
    min_snr: float = setting(3.0, ge=0.0)
    # ... and, lower than confident_top_m (m), low_top_snr times it
    confident_top_m: float = setting(0.018, gt=0.0)
    low_top_snr: float = setting(4.0, gt=0.0)
    # the blob's median height stands this many times the ring noise over sqrt(its pixels /
    # block_size^2), the noise of a mean over its independent pixels (0 = off)
    min_median_snr: float = setting(0.0, ge=0.0)
    # a rock stands at most max_top_per_width x its width + top_margin_m (m)
    max_top_per_width: float = setting(1.5, gt=0.0)
    top_margin_m: float = setting(0.02, ge=0.0)
    # the ring's plane lies within this angle of the view's ground plane (degrees)
    max_tilt_deg: float = setting(35.0, gt=0.0, le=90.0)
    # fit a quadric (in the plane's coordinates) rather than a plane to the ring
    quadric: bool = setting(True)
    # judge a candidate on the ground fitted to the ring points within this many rock sizes of the
    # rock (its blob and the raised pixels next to it; 0 = the whole window's ring)
    refine_margin: float = setting(0.0, ge=0.0)
    # the fewest valid ring points, and the most used by the fit
    min_ring_points: int = setting(30, ge=6)
    max_ring_points: int = setting(400, ge=12)
    # the height map must stand this high (m) somewhere around a candidate, else no window match
    min_lowres_height_m: float = setting(0.01, ge=0.0)
    # the fewest valid points on the blob
    min_blob_points: int = setting(3, ge=1)
    # at most this many dark candidates per image (after the bright ones)
    max_dark_candidates: int = setting(20, ge=0)
    # the raised part beside a dark candidate stands this many ring noises ...
    dark_min_snr: float = setting(5.0, ge=0.0)
    # ... over at least this many valid pixels
    dark_min_points: int = setting(60, ge=1)
    # the view's ground plane: the height map's points within this optical depth (m)
    ground_range_m: float = setting(6.0, gt=0.0)

    # -- the learned judge (small_rock_judge.npz beside this module; see the module's docstring)
    # a candidate that passes the judge's floors below is a rock when the judge scores it at
    # least this (0.92, the default; 0 = off: the hand verdict above decides;
    # docs/perception-status.md, "Small rocks")
    judge_min_score: float = setting(0.92, ge=0.0, le=1.0)
    # with the judge on, these floors replace min_top_m, min_snr (and low_top_snr, dark_min_snr)
    # and dark_min_points (min_median_snr is not applied): what reaches the judge
    judge_min_top_m: float = setting(0.005, gt=0.0)
    judge_min_snr: float = setting(1.5, ge=0.0)
    judge_dark_min_points: int = setting(20, ge=1)
    # the judge's model file (None: the packaged small_rock_judge.npz; else one written by
    # benchmarks/train_small_rocks.py, e.g. a refit compared before it is packaged)
    judge_path: str | None = None

    # -- candidates from the rock network (perception/rock_net.py; on by default)
    # at most this many candidates per image from the network's rock probability (after the
    # appearance candidates; 0 = off): its peaks of at least net_min_score, each blob the
    # pixels above half its peak; judged as bright candidates are
    net_candidates: int = setting(10, ge=0)
    net_min_score: float = setting(0.5, gt=0.0, lt=1.0)
    # the network runs on the rows whose ground lies within this optical depth (m)
    net_max_range_m: float = setting(4.0, gt=0.0)
    # a network candidate's blob (its pixels of at least net_min_score, and of half its peak,
    # connected to the peak) is at most this wide (m)
    net_max_width_m: float = setting(0.1, gt=0.0)
    # a network candidate's full-resolution window: its box plus this many box sizes each side
    # (window_margin for the others; the network's candidates are near and their blobs the
    # whole rock, so their windows would be the largest and costliest)
    net_window_margin: float = setting(0.75, gt=0.0)
    # the network's file (None: the packaged rock_net.npz; else one written by
    # benchmarks/train_rock_net.py)
    net_path: str | None = None

    def __post_init__(self) -> None:
        check_settings(self)
        for lo, hi, strict in _ORDERED:
            a, b = getattr(self, lo), getattr(self, hi)
            if a > b or (strict and a == b):
                raise ConfigError(f"need {lo} {'<' if strict else '<='} {hi} (got {a!r}, {b!r})")
        if self.block_size % 2 == 0:
            raise ConfigError(f"block_size={self.block_size!r} must be odd")


class _Intrinsics(NamedTuple):
    """A pinhole camera's focal length and principal point (pixels)."""

    fx: float
    cx: float
    cy: float


@dataclass
class SmallRock:
    """One verified candidate: its pixels (a boolean crop at (u0, v0)), points (optical
    frame), height above the local ground (m), the ring's residual spread (m), width (m),
    depth (m) and the verdict: ``reason`` None for a rock, else ``"flat"`` (too low for its
    noise), ``"not_ground"`` (the surroundings are no ground), ``"too_tall"``, ``"too_wide"`` or
    ``"judged"`` (the learned judge scored it under ``judge_min_score``)."""

    u0: int
    v0: int
    crop: np.ndarray
    points_optical: np.ndarray
    top_m: float
    noise_m: float
    width_m: float
    depth_m: float
    reason: str | None = None
    # the judged blob's median height (m) and valid pixels
    median_m: float = float("nan")
    blob_points: int = 0
    # with the learned judge on: its features (JUDGE_FEATURES) and score, and the candidate's
    # rank among those of its polarity (0 = the strongest)
    features: np.ndarray | None = None
    score: float = float("nan")
    rank: int = -1


def ground_plane(
    points_rover: np.ndarray, depth: np.ndarray, max_depth_m: float = 6.0, stride: int = 4
) -> np.ndarray | None:
    """Unit normal (rover frame) of the plane fitted to the height map's points within
    `max_depth_m` (least squares, then once more within 3 MADs), pointing up (to the side of
    the rover frame's +z, i.e. the cameras' side of the ground). None when fewer than 50 points.
    `stride`: about one point in `stride` is used (every sqrt(stride)-th row and column of the
    map, so the full map is never indexed)."""
    k = max(round(float(np.sqrt(stride))), 1)
    D = depth[::k, ::k]
    ok = np.isfinite(D) & (D < max_depth_m)
    P = points_rover[::k, ::k][ok].astype(float)
    if not np.isfinite(P).all():
        P = P[np.isfinite(P).all(axis=1)]
    if len(P) < 50:
        return None
    for it in range(2):
        c = np.array([_median(P[:, j]) for j in range(3)])  # np.median(P, axis=0)
        Q = P - c
        # the plane's normal: the scatter matrix's least eigenvector (as the SVD's last right
        # singular vector, without the (N, 3) left factor)
        n = np.linalg.eigh(Q.T @ Q)[1][:, 0]
        a = np.abs(Q @ n)
        if it == 1:
            break  # (the last pass's inliers are not used)
        P = P[a < 3 * (1.4826 * _median(a) + 1e-6)]
        if len(P) < 50:
            break
    return n if n[2] >= 0 else -n


def small_rock_candidates(
    left: np.ndarray,
    disparity_lowres: np.ndarray,
    scale: int,
    fx: float,
    baseline_m: float,
    cfg: SmallRockConfig,
    exclude: np.ndarray | None = None,
    height_lowres: np.ndarray | None = None,
) -> list[tuple[int, int, np.ndarray, float, bool]]:
    """Blobs of the left image sized like small rocks at their range: (u0, v0, crop, d0,
    dark) with `crop` a full-resolution boolean mask at (u0, v0), d0 the height map's
    disparity there (full-resolution pixels) and `dark` whether the blob is darker than its
    surroundings (a shadow or an unlit side; only with dark_contrast_z > 0); the bright blobs
    first, each kind strongest first. With cfg.count_checked, `exclude` ((H, W) bool) and
    `height_lowres` (the height map's heights, its grid) pass over the candidates the stage
    would not match (see SmallRockConfig.count_checked)."""
    return [
        c[:5]
        for c in _candidates(
            left, disparity_lowres, scale, fx, baseline_m, cfg, exclude, height_lowres
        )
    ]


def _candidates(
    left, disparity_lowres, scale, fx, baseline_m, cfg, exclude=None, height_lowres=None, marks=None
) -> list:
    """small_rock_candidates' blobs, each with its peak contrast (local contrasts) last.
    `marks` (a dict, if given) gets "net": the index of the network's first candidate."""
    import cv2

    H, W = left.shape
    k = int(cfg.candidate_scale)
    kd = int(scale)
    D = np.asarray(disparity_lowres, np.float32)
    # only the rows that hold ground within the range searched (and a margin)
    with np.errstate(invalid="ignore"):
        Dk = D * kd
        near = (Dk >= fx * baseline_m / cfg.max_range_m) & (Dk <= fx * baseline_m / cfg.min_range_m)
        del Dk  # (freed at once, as the two temporaries it replaces were)
    rows = np.flatnonzero(near.any(axis=1))  # (NaN compares False)
    if rows.size == 0:
        return []
    r0 = max(int(rows[0]) * kd - 32, 0) // k * k
    r1 = min((int(rows[-1]) + 1) * kd + 32, H)
    h, w = (r1 - r0) // k, W // k
    roi = left[r0 : r0 + h * k]
    small = (cv2.resize(roi, (w, h), interpolation=cv2.INTER_AREA) if k > 1 else roi).astype(
        np.float32
    )
    z = local_contrast(small, cfg.dog_sigma_px, cfg.contrast_sigma_px)
    sky = small <= cfg.sky_level
    grid = _Grid(D, kd, k, r0, fx, fx * baseline_m)
    if cfg.count_checked:
        grid.exclude, grid.height = exclude, height_lowres
    out = _blobs(z, sky, grid, cfg, cfg.contrast_z, cfg.max_candidates, False)
    if cfg.dark_contrast_z > 0:
        out += _blobs(-z, sky, grid, cfg, cfg.dark_contrast_z, cfg.max_dark_candidates, True)
    if marks is not None:
        marks["net"] = len(out)
    if cfg.net_candidates > 0:
        out += _net_candidates(roi, small, z, sky, grid, cfg, D * kd, out)
    return out


def _net_candidates(roi, small, z, sky, grid: _Grid, cfg, Dfull, cands) -> list:
    """Candidates from the rock network's probability (see SmallRockConfig.net_candidates) on
    the search image's rows a fifth of whose height-map pixels lie within net_max_range_m:
    bright candidates whose peak contrast is the contrast image's highest value on the blob;
    those centred in an earlier candidate's box are dropped (that rock is measured already)."""
    import cv2

    k = grid.k
    with np.errstate(invalid="ignore"):  # rows a fifth of which lies within the range
        near = np.count_nonzero(Dfull >= grid.fb / cfg.net_max_range_m, axis=1)
    rows = np.flatnonzero(near >= 0.2 * Dfull.shape[1])
    if rows.size == 0:
        return []
    h, w = z.shape
    a = min(max(int(rows[0]) * grid.kd - grid.r0, 0) // k, h)
    if h - a < 8:
        return []
    net = rock_net_at(cfg.net_path)
    if w == NET_WIDTH_PX:  # the search image is the network's (1280 wide at half resolution);
        # its contrast too with the default sigmas
        same = cfg.dog_sigma_px == DOG_SIGMA_PX and cfg.contrast_sigma_px == CONTRAST_SIGMA_PX
        p = net.probability(small[a:], z[a:] if same else None)
    else:  # the image at the network's scale (a 640-wide image as it is)
        sub = roi[a * k :]
        f = NET_WIDTH_PX / sub.shape[1]
        size = (NET_WIDTH_PX, max(round(sub.shape[0] * f), 4))
        p = net.probability(sub if f == 1 else cv2.resize(sub, size, interpolation=cv2.INTER_AREA))
    prob = p if p.shape == (h - a, w) else cv2.resize(p, (w, h - a))
    # the search image's rows from a (the blobs' full-resolution rows from r0 + a k)
    sub = replace(grid, r0=grid.r0 + a * k)
    boxes = [(u, v, u + c.shape[1], v + c.shape[0]) for u, v, c, *_ in cands]
    out = []
    for u0, v0, crop, d0, _, _ in _blobs(
        prob,
        sky[a:],
        sub,
        cfg,
        cfg.net_min_score,
        cfg.net_candidates,
        False,
        floor=1.0,
        max_width_m=min(cfg.net_max_width_m, cfg.max_width_m),
    ):
        cu, cv_ = u0 + crop.shape[1] // 2, v0 + crop.shape[0] // 2
        if any(x0 <= cu < x1 and y0 <= cv_ < y1 for x0, y0, x1, y1 in boxes):
            continue
        ys, xs = (v0 - grid.r0) // k, u0 // k
        cz = crop[::k, ::k]
        zz = z[ys : ys + cz.shape[0], xs : xs + cz.shape[1]][cz[: h - ys, : w - xs]]
        out.append((u0, v0, crop, d0, False, float(zz.max()) if zz.size else 0.0))
    return out


@dataclass
class _Grid:
    """The candidate search's image (1/k of full resolution, rows from r0) against the
    height map's disparity D (1/kd of full resolution); fx (pixels), fb = fx x baseline."""

    D: np.ndarray
    kd: int
    k: int
    r0: int
    fx: float
    fb: float
    pad: np.ndarray | None = None  # D padded by 2 NaN pixels each side (made on first use)
    # with count_checked: the excluded pixels (full resolution) and the height map's heights
    exclude: np.ndarray | None = None
    height: np.ndarray | None = None

    def checked(self, u0: int, v0: int, bh: int, bw: int, min_height_m: float) -> bool:
        """Whether a candidate box (full resolution) would get a window: its centre not
        excluded, the height map min_height_m high somewhere around it (the tests of
        detect_small_rocks)."""
        if self.exclude is not None and _centre_in(self.exclude, u0, v0, bh, bw):
            return False
        if self.height is not None:
            hh = _heights_around(self.height, self.kd, u0, v0, bh, bw)
            return bool(np.any(hh >= min_height_m))  # NaN compares False
        return True

    def depth(self, pv: np.ndarray, pu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The height map's disparity (full-resolution pixels; median over 5x5 low-resolution
        pixels) and depth (m) at the search image's pixels (pv, pu)."""
        hd, wd = self.D.shape
        cu = np.clip((pu * self.k) // self.kd, 0, wd - 1)
        cv = np.clip((pv * self.k + self.r0) // self.kd, 0, hd - 1)
        if self.pad is None:  # padded once per image, for both polarities (np.pad costs more)
            self.pad = np.full((hd + 4, wd + 4), np.nan, self.D.dtype)
            self.pad[2:-2, 2:-2] = self.D
        # the 5 x 5 pixels around each (row by row) by one take of the padded map
        wp = wd + 4
        off = (np.arange(5)[:, None] * wp + np.arange(5)[None, :]).ravel()
        win = self.pad.ravel().take((cv * wp + cu)[:, None] + off[None, :])
        d0 = _nanmedian_rows(win) * self.kd
        with np.errstate(divide="ignore", invalid="ignore"):
            return d0, self.fb / d0


def _nanmedian_rows(a: np.ndarray) -> np.ndarray:
    """``np.nanmedian(a, axis=1)`` of a 2-D float array, value for value (NaN for a row without
    a finite value), by one sort (numpy's masked-array path costs ten times more)."""
    s = np.sort(a, axis=1)  # NaN sorts last
    n = np.count_nonzero(~np.isnan(a), axis=1)
    i = np.arange(len(a))
    hi = s[i, n // 2]
    lo = s[i, np.maximum(n - 1, 0) // 2]
    two = a.dtype.type(2)
    with np.errstate(invalid="ignore"):
        out = np.where(n % 2 == 1, hi, (lo + hi) / two)
    return np.where(n == 0, a.dtype.type(np.nan), out).astype(a.dtype, copy=False)


def _blobs(
    z,
    sky,
    grid: _Grid,
    cfg,
    z_min: float,
    n_max: int,
    dark: bool,
    floor: float = 0.6,
    max_width_m: float | None = None,
) -> list:
    """The strongest n_max blobs of the contrast image `z` (see small_rock_candidates); a
    blob's level is at least `floor` x z_min, its width at most max_width_m (None:
    cfg.max_width_m)."""
    import cv2

    h, w = z.shape
    k = grid.k
    # peaks of the contrast (local maxima over 5x5) above z_min; each peak's blob is the part of
    # the window around it above half its peak contrast and connected to it (a lit face
    # touching lit regolith does not merge with it)
    peak = (z >= cv2.dilate(z, np.ones((5, 5), np.uint8))) & (z > z_min) & ~sky
    pv, pu = np.nonzero(peak)
    if pv.size == 0 or n_max == 0:
        return []
    # strongest first by the contrast summed around the peak (a rock's lit face, a few pixels
    # across, before the single bright speckles of the regolith's texture); the height map's
    # range only for the strongest (a median per peak)
    zs = cv2.GaussianBlur(np.maximum(z, 0), (0, 0), 1.5)
    order = np.argsort(-zs[pv, pu], kind="stable")[: 8 * n_max]
    pv, pu = pv[order], pu[order]
    d0, Z = grid.depth(pv, pu)
    inr = np.flatnonzero(np.isfinite(Z) & (Z >= cfg.min_range_m) & (Z <= cfg.max_range_m))
    checked = grid.exclude is not None or grid.height is not None
    if not checked:
        inr = inr[: 3 * n_max]  # the strongest peaks only
    # per peak: the window's half size (a rock of max_width_m at its range, plus a margin; 3-40
    # pixels; float64) and the blob's level (half the peak's contrast, at least 0.6 z_min;
    # float32, as the image it is compared with)
    Zi = np.asarray(Z[inr], np.float64)  # float64 as the scalars were with any numpy
    halves = np.minimum(np.maximum(cfg.max_width_m * grid.fx / Zi / k, 3.0), 40.0)
    zpk = z[pv[inr], pu[inr]]
    levels = np.maximum(0.5 * zpk, floor * z_min)
    wmax = cfg.max_width_m if max_width_m is None else max_width_m
    out = []
    claimed = np.zeros(z.shape, bool)
    for y, x, half, level, j in zip(
        pv[inr].tolist(),
        pu[inr].tolist(),
        halves.astype(int).tolist(),
        levels.tolist(),
        range(inr.size),
    ):
        if len(out) >= n_max:
            break
        if claimed[y, x]:
            continue
        ya, yb, xa, xb = (
            max(y - half, 0),
            min(y + half + 1, h),
            max(x - half, 0),
            min(x + half + 1, w),
        )
        sub = np.greater(z[ya:yb, xa:xb], level).view(np.uint8)
        # the peak's 8-connected blob (a flood fill costs what the blob costs, not the window)
        area, _, _, (bx0, by0, bw, bh) = cv2.floodFill(sub, None, (x - xa, y - ya), 2, flags=8)
        c = sub[by0 : by0 + bh, bx0 : bx0 + bw] == 2
        claimed[ya + by0 : ya + by0 + bh, xa + bx0 : xa + bx0 + bw] |= c
        if area < 2 or bw > cfg.max_aspect * bh:
            continue
        width = max(bw, bh) * k * Zi[j] / grid.fx
        if not cfg.min_width_m <= width <= wmax:
            continue
        full = c.repeat(k, axis=0).repeat(k, axis=1) if k > 1 else c
        u0, v0 = (xa + bx0) * k, (ya + by0) * k + grid.r0
        if checked and not grid.checked(u0, v0, *full.shape, cfg.min_lowres_height_m):
            continue
        out.append((u0, v0, full, float(d0[inr[j]]), dark, float(zpk[j])))
    return out


def _centre_in(mask: np.ndarray, u0: int, v0: int, bh: int, bw: int) -> bool:
    """Whether the centre of a candidate box (full resolution, at (u0, v0), bh x bw) lies on
    `mask` ((H, W) bool)."""
    H, W = mask.shape
    return bool(mask[min(v0 + bh // 2, H - 1), min(u0 + bw // 2, W - 1)])


def _heights_around(height: np.ndarray, kd: int, u0: int, v0: int, bh: int, bw: int):
    """The height map's heights (its grid, 1/kd of full resolution) under a candidate box and
    one cell around it."""
    return height[
        max(v0 // kd - 1, 0) : (v0 + bh) // kd + 2, max(u0 // kd - 1, 0) : (u0 + bw) // kd + 2
    ]


def _height_candidates(height, D, kd, fx, fb, cfg, exclude, cands) -> list:
    """Candidates (as _candidates') from the height map's heights `height` (its grid, 1/kd of
    full resolution): its local peaks (5 x 5) standing cfg.height_candidate_m above the map's
    local mean (a Gaussian of 3 cells, over its valid cells), within the candidates' range,
    centred on no `exclude` pixel nor in another candidate's box, most prominent first; each
    one's blob the cells around it above half its prominence and connected to it, sized as a
    small rock at its range."""
    import cv2

    H, W = exclude.shape
    h = np.asarray(height, np.float32)
    ok = np.isfinite(h)
    h0 = np.where(ok, h, 0).astype(np.float32)
    wsum = cv2.GaussianBlur(ok.astype(np.float32), (0, 0), 3.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        prom = np.where(ok, h0 - cv2.GaussianBlur(h0, (0, 0), 3.0) / wsum, -1.0)
    prom = prom.astype(np.float32)
    peak = (prom >= cv2.dilate(prom, np.ones((5, 5), np.uint8))) & (prom >= cfg.height_candidate_m)
    pv, pu = np.nonzero(peak)
    if pv.size == 0:
        return []
    order = np.argsort(-prom[pv, pu], kind="stable")
    boxes = [(u, v, u + c.shape[1], v + c.shape[0]) for u, v, c, *_ in cands]
    out = []
    for i in order[: 8 * cfg.height_candidates]:
        if len(out) >= cfg.height_candidates:
            break
        y, x = int(pv[i]), int(pu[i])
        d = float(D[y, x]) * kd
        if not np.isfinite(d) or d <= 0:
            continue
        Z = fb / d
        if not cfg.min_range_m <= Z <= cfg.max_range_m:
            continue
        cy_, cx_ = min(y * kd + kd // 2, H - 1), min(x * kd + kd // 2, W - 1)
        if exclude[cy_, cx_] or any(a <= cx_ < c and b <= cy_ < e for a, b, c, e in boxes):
            continue
        half = int(np.clip(cfg.max_width_m * fx / Z / kd, 2, 20))
        ya, yb = max(y - half, 0), min(y + half + 1, h.shape[0])
        xa, xb = max(x - half, 0), min(x + half + 1, h.shape[1])
        sub = (prom[ya:yb, xa:xb] > 0.5 * prom[y, x]).astype(np.uint8)
        _, _, _, (bx0, by0, bw, bh) = cv2.floodFill(sub, None, (x - xa, y - ya), 2, flags=8)
        c = sub[by0 : by0 + bh, bx0 : bx0 + bw] == 2
        width = max(bw, bh) * kd * Z / fx
        if not cfg.min_width_m <= width <= cfg.max_width_m:
            continue
        full = np.repeat(np.repeat(c, kd, axis=0), kd, axis=1)
        u0, v0 = (xa + bx0) * kd, (ya + by0) * kd
        full = full[: H - v0, : W - u0]
        out.append((u0, v0, full, d, False, 0.0))
        boxes.append((u0, v0, u0 + full.shape[1], v0 + full.shape[0]))
    return out


class _Matcher:
    """Cached OpenCV SGBM objects for the windows' band matches, one per band width."""

    def __init__(self, block_size: int, band_px: int, max_band_px: int = 64) -> None:
        self.bs, self.nd, self.max_nd = block_size, band_px, max(band_px, max_band_px)
        self._m: dict[int, object] = {}

    def _sgbm(self, nd: int):
        m = self._m.get(nd)
        if m is None:
            import cv2

            bs = self.bs
            m = cv2.StereoSGBM_create(
                minDisparity=0,
                numDisparities=nd,
                blockSize=bs,
                P1=8 * bs * bs,
                P2=32 * bs * bs,
                disp12MaxDiff=1,
                uniquenessRatio=10,
                speckleWindowSize=0,
                mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
            )
            self._m[nd] = m
        return m

    def window(
        self,
        L: np.ndarray,
        R: np.ndarray,
        u0: int,
        v0: int,
        u1: int,
        v1: int,
        d_lo: float,
        d_hi: float,
    ):
        """Full-resolution disparity of L[v0:v1, u0:u1] (NaN invalid) searched over a band that
        holds [d_lo, d_hi] (the window's disparities from the height map; near the rover the
        ground's disparity changes by tens of pixels over a window) with a margin of half the
        configured band each side, at most max_band_px wide."""
        nd, bs = self.nd, self.bs
        span = (d_hi - d_lo) + nd
        nd = int(min(np.ceil(span / 16.0) * 16, self.max_nd))
        dmin = max(int(np.floor(0.5 * (d_lo + d_hi))) - nd // 2, 0)
        la = u0 - nd - bs
        if u0 - dmin < 0 or u1 <= u0 or v1 <= v0:
            return None

        def cols(img, a, b):
            if a >= 0:
                return np.ascontiguousarray(img[v0:v1, a:b])
            o = np.zeros((v1 - v0, b - a), img.dtype)
            o[:, -a:] = img[v0:v1, 0:b]
            return o

        d = self._sgbm(nd).compute(cols(L, la, u1), cols(R, la - dmin, u1 - dmin))[:, u0 - la :]
        d = d.astype(np.float32)
        d *= np.float32(1 / 16)  # fixed point (4 fractional bits): exact
        d[(d <= 0) | (d >= nd - 1)] = np.nan
        d += np.float32(dmin)
        return d


def _quantile(x: np.ndarray, q: float) -> float:
    """np.quantile(x, q) (linear interpolation) of a non-empty 1-D array, by one partition
    (np.quantile's and np.median's own overheads were most of this stage's time)."""
    n = x.size
    f = q * (n - 1)
    lo = int(f)
    hi = min(lo + 1, n - 1)
    p = np.partition(x, (lo, hi)) if hi != lo else np.partition(x, lo)
    return float(p[lo] + (f - lo) * (p[hi] - p[lo]))


def _quantiles(x: np.ndarray, q0: float, q1: float) -> tuple[float, float]:
    """(_quantile(x, q0), _quantile(x, q1)) by one partition."""
    n = x.size
    f0, f1 = q0 * (n - 1), q1 * (n - 1)
    i0, i1 = int(f0), int(f1)
    j0, j1 = min(i0 + 1, n - 1), min(i1 + 1, n - 1)
    p = np.partition(x, sorted({i0, j0, i1, j1}))
    return (
        float(p[i0] + (f0 - i0) * (p[j0] - p[i0])),
        float(p[i1] + (f1 - i1) * (p[j1] - p[i1])),
    )


def _robust_spread(r: np.ndarray) -> tuple[float, float]:
    """Median of `r` and 1.4826 x its median absolute deviation (plus 0.1 mm); `r` is a 1-D
    float64 array (not modified)."""
    m = _median64(r.copy())
    return m, 1.4826 * _median64(np.abs(r - m)) + 1e-4


def _median64(x: np.ndarray) -> float:
    """_quantile(x, 0.5) of a non-empty 1-D float64 array that may be reordered (partitioned in
    place, no copy; the interpolation in Python floats, which for float64 is numpy's)."""
    n = x.size
    lo = (n - 1) // 2
    if n % 2:
        x.partition(lo)
        return float(x[lo])
    x.partition((lo, lo + 1))
    a = float(x[lo])
    return a + 0.5 * (float(x[lo + 1]) - a)


def _fit_plane(P: np.ndarray):
    """Least-squares plane of (N, 3) points: centroid, unit normal towards the optical origin
    and the points less the centroid."""
    c = np.add.reduce(P, axis=0) / len(P)  # P.mean(axis=0), without its wrapper
    Q = P - c
    n = np.linalg.eigh(Q.T @ Q)[1][:, 0]
    if n @ c > 0:  # the camera (origin) lies on the normal's side
        n = -n
    return c, n, Q


@dataclass
class _Window:
    """The full-resolution match around one candidate: the window's corner (a0, b0), the
    blob (uint8, window-sized), valid pixels `ok`, their points `P` (left optical frame, in
    the order of `vv, uu`), `idx` (window pixel -> row of P, -1 invalid) and the heights
    `hall` (m, NaN invalid) above the local ground fitted to the ring around the blob, with
    that fit's residual spread `noise` and plane normal `n`."""

    a0: int
    b0: int
    blob: np.ndarray
    ok: np.ndarray
    P: np.ndarray
    idx: np.ndarray
    hall: np.ndarray
    noise: float
    n: np.ndarray
    # the ring's subsampled points and their window pixels (rows, columns)
    ring_P: np.ndarray
    ring_v: np.ndarray
    ring_u: np.ndarray


def _local_heights(
    L, R, disparity_lowres, scale, camera, fb, cfg, mt, u0, v0, crop, d0, dark=False, margin=None
):
    """A :class:`_Window` around the candidate blob `crop` at (u0, v0), or None when the window
    cannot be matched or holds too few valid ring or blob points. Heights and points are
    computed for the ring's (subsampled) pixels and the core inside it (the blob and its
    surroundings up to the ring; for a dark blob, up to two blob sizes around it, where the
    rock that cast it stands) only."""
    import cv2

    H, W = L.shape
    fx, cx, cy = camera.fx, camera.cx, camera.cy
    bh, bw = crop.shape
    margin = cfg.window_margin if margin is None else margin
    M = int(max(cfg.window_min_margin_px, margin * max(bw, bh)))
    a0, b0 = max(u0 - M, 0), max(v0 - M, 0)
    a1, b1 = min(u0 + bw + M, W), min(v0 + bh + M, H)
    # the height map's disparities over the window (full-resolution pixels)
    wd = disparity_lowres[b0 // scale : (b1 - 1) // scale + 1, a0 // scale : (a1 - 1) // scale + 1]
    wd = wd[np.isfinite(wd)] * scale
    lo, hi = _quantiles(wd, 0.05, 0.95) if wd.size >= 8 else (d0, d0)
    d = mt.window(L, R, a0, b0, a1, b1, min(lo, d0), max(hi, d0))
    if d is None:
        return None
    blob = np.zeros(d.shape, np.uint8)
    blob[v0 - b0 : v0 - b0 + bh, u0 - a0 : u0 - a0 + bw] = crop
    g = max(3, int(0.5 * max(bw, bh)))
    core = cv2.dilate(blob, _ones(2 * g + 1)) > 0
    ok = np.isfinite(d)
    gr = ok > core  # ok and not core
    if (
        np.count_nonzero(gr) < cfg.min_ring_points
        or np.count_nonzero((cv2.dilate(blob, _ones(3)) > 0) & ok) < cfg.min_blob_points
    ):
        return None
    if dark:
        gd = 2 * (max(3, max(bw, bh)) + 3) + 1
        core = cv2.dilate(blob, _ones(gd)) > 0
    rv, ru = np.nonzero(gr)
    if rv.size > cfg.max_ring_points:  # an even subsample: the fit needs no more
        step = -(-rv.size // cfg.max_ring_points)
        rv, ru = rv[::step], ru[::step]
    core &= ok
    cv_, cu_ = np.nonzero(core)
    n_ring = rv.size
    vv, uu = np.concatenate([rv, cv_]), np.concatenate([ru, cu_])
    # points (left optical frame): the ring's, then the core's
    Z = fb / d[vv, uu]
    P = Pr = np.empty((vv.size, 3))
    np.divide((uu + a0 - cx) * Z, fx, out=P[:, 0])
    np.divide((vv + b0 - cy) * Z, fx, out=P[:, 1])
    P[:, 2] = Z
    hP, s, n = _ground_heights(P[:n_ring], P[n_ring:], cfg)
    P = P[n_ring:]
    idx = np.full(d.shape, -1, np.int64)
    idx[cv_, cu_] = np.arange(cv_.size)
    hall = np.full(d.shape, np.nan, np.float32)
    hall[cv_, cu_] = hP
    return _Window(a0, b0, blob, core, P, idx, hall, float(s), n, Pr[:n_ring], rv, ru)


@lru_cache(maxsize=64)
def _ones(size: int) -> np.ndarray:
    """A square structuring element of ones (uint8), size x size (made once)."""
    return np.ones((size, size), np.uint8)


def _ground_heights(Q: np.ndarray, P: np.ndarray, cfg):
    """Heights of the points `P` above the local ground fitted to the ring points `Q` (a plane,
    once more without the points beyond 3 MADs, then, with cfg.quadric, a quadric in the
    plane's coordinates), the fit's residual spread and the plane's normal."""
    c, n, Qc = _fit_plane(Q)
    r = Qc @ n
    med, s = _robust_spread(r)
    keep = np.abs(r - med) < 3 * s
    n_keep = int(np.count_nonzero(keep))
    if n_keep >= cfg.min_ring_points // 2:
        c, n, Qc = _fit_plane(Q[keep])
        _, s = _robust_spread(Qc @ n)
    if not (cfg.quadric and n_keep >= 12):
        return (P - c) @ n, s, n
    return _quadric_heights(Q, P, c, n, s) + (n,)


def _refit(w: _Window, region: np.ndarray, cfg) -> _Window | None:
    """`w` with its heights refitted to the ring points within cfg.refine_margin region sizes
    of `region` (uint8, window-sized) and outside it (dilated by half its size): a ring close
    to the rock holds less of the terrain's relief. None when too few ring points remain."""
    import cv2

    ys, xs = np.nonzero(region)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    size = max(y1 - y0, x1 - x0)
    m = max(cfg.refine_margin * size, 4)
    g = max(3, size // 2)
    out = cv2.dilate(region, np.ones((2 * g + 1, 2 * g + 1), np.uint8)) > 0
    sel = (
        (w.ring_u >= x0 - m) & (w.ring_u < x1 + m) & (w.ring_v >= y0 - m) & (w.ring_v < y1 + m)
    ) & ~out[w.ring_v, w.ring_u]
    if np.count_nonzero(sel) < cfg.min_ring_points:
        return None
    # heights where the verdict and the rock's outline look: the region and 3 pixels around it
    near = (cv2.dilate(region, np.ones((7, 7), np.uint8)) > 0) & (w.idx >= 0)
    vv, uu = np.nonzero(near)
    hP, s, n = _ground_heights(w.ring_P[sel], w.P[w.idx[vv, uu]], cfg)
    hall = np.full(w.hall.shape, np.nan, np.float32)
    hall[vv, uu] = hP
    return replace(w, blob=region, hall=hall, noise=float(s), n=n, ok=w.ok & near)


def _quadric_heights(Q, P, c, n, s):
    """Heights of the points `P` above a quadric (in the plane (c, n)'s coordinates) fitted to
    the ring's points `Q` (twice, the second time without those beyond 3 MADs) and the fit's
    residual spread (`s` when the fit fails)."""
    e1 = np.array([n[1], -n[0], 0.0])  # n x (0, 0, 1)
    e1 /= np.sqrt(e1 @ e1) + 1e-12
    e2 = np.array(
        [n[1] * e1[2] - n[2] * e1[1], n[2] * e1[0] - n[0] * e1[2], n[0] * e1[1] - n[1] * e1[0]]
    )

    def design(X):
        X = X - c
        a1, a2 = X @ e1, X @ e2
        A = np.empty((len(X), 6))  # the columns 1, a1, a2, a1^2, a1 a2, a2^2
        A[:, 0] = 1.0
        A[:, 1] = a1
        A[:, 2] = a2
        np.multiply(a1, a1, out=A[:, 3])
        np.multiply(a1, a2, out=A[:, 4])
        np.multiply(a2, a2, out=A[:, 5])
        return X @ n, A

    hQ, A = design(Q)
    As, hs = A, hQ  # all the ring's points first, then those within 3 MADs
    coef = np.zeros(6)
    for it in range(2):
        try:  # normal equations: a 6x6 solve (lstsq's SVD costs far more here)
            coef = np.linalg.solve(As.T @ As + _EYE6_1E9, As.T @ hs)
        except np.linalg.LinAlgError:
            break
        res = hQ - A @ coef
        mr, s = _robust_spread(res)
        if it == 1:
            break
        sel = np.flatnonzero(np.abs(res - mr) < 3 * s)
        if sel.size < 12:
            break
        As, hs = A[sel], hQ[sel]
    hP, AP = design(P)
    return hP - AP @ coef, s


_EYE6_1E9 = 1e-9 * np.eye(6)


def _verdict(cfg, top: float, noise: float, width: float, tilt_ok: bool) -> str | None:
    """None for a rock, else why not (see SmallRock)."""
    if not tilt_ok:
        return "not_ground"  # the surroundings are a wall, the lander, a boulder's face
    if (
        top < cfg.min_top_m
        or top < cfg.min_snr * noise
        or (top < cfg.confident_top_m and top < cfg.low_top_snr * noise)
    ):
        return "flat"
    if top > cfg.max_top_per_width * width + cfg.top_margin_m:
        return "too_tall"
    return None


def _shadowed_blob(w: _Window, cfg, bw: int, bh: int) -> np.ndarray | None:
    """For a dark candidate (a shadow, or a rock's unlit side): the raised part of its window
    next to it (the rock that cast the shadow), as a uint8 window-sized blob, or None. Raised:
    higher than min_snr noises and half of min_top_m above the local ground, within one
    blob size of the dark blob; the component touching the dark blob with the most raised
    pixels."""
    import cv2

    with np.errstate(invalid="ignore"):
        raised = w.hall > max(cfg.min_snr * w.noise, 0.5 * cfg.min_top_m)
    g = max(3, int(max(bw, bh)))
    near = cv2.dilate(w.blob, _ones(2 * g + 1)) > 0
    cand = (raised & near).astype(np.uint8)
    n_lab, lab, stats, _ = cv2.connectedComponentsWithStats(cand, connectivity=8)
    if n_lab <= 1:
        return None
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    if stats[best, cv2.CC_STAT_AREA] < cfg.min_blob_points:
        return None
    return (lab == best).astype(np.uint8)


def detect_small_rocks(
    left: np.ndarray,
    right: np.ndarray,
    disparity_lowres: np.ndarray,
    scale: int,
    camera,
    baseline_m: float,
    cfg: SmallRockConfig,
    up_optical: np.ndarray | None = None,
    exclude: np.ndarray | None = None,
    matcher: _Matcher | None = None,
    trace: list | None = None,
    keep_rejected: bool = False,
    height_lowres: np.ndarray | None = None,
    judge=None,
) -> list[SmallRock]:
    """Small rocks of one rectified pair (see the module's docstring).

    disparity_lowres, scale : the height map's disparity (low-resolution pixels) and its scale.
    camera : PinholeCamera (fx, cx, cy). up_optical : the ground plane's normal in the left
    optical frame (pointing up), or None (no tilt test). exclude : (H, W) bool, pixels already
    explained (kept detections): candidates centred there are skipped. trace : if a list, gets
    one dict of the measured features per verified candidate (for diagnosis). keep_rejected :
    also return the candidates judged no rock (their ``reason`` set), for the miss tooling.
    height_lowres : the height map's heights above its ground (metres, same grid as
    disparity_lowres); when given, a candidate whose neighbourhood there stands nowhere
    min_lowres_height_m high is dropped before its full-resolution match (the half-resolution
    heights smooth a small rock, but not to nothing).
    judge : the learned judge (a BlobVerifier over JUDGE_FEATURES); None: the packaged one
    (:func:`default_judge`, or the one at cfg.judge_path), used only when cfg.judge_min_score > 0.
    """
    H, W = left.shape
    fx = camera.fx
    intr = _Intrinsics(fx, camera.cx, camera.cy)  # the camera's properties, computed once
    fb = fx * baseline_m
    mt = matcher or _Matcher(cfg.block_size, cfg.band_px, cfg.max_band_px)
    cos_tilt = np.cos(np.radians(cfg.max_tilt_deg))
    out: list[SmallRock] = []
    taken = np.zeros((H, W), bool) if exclude is None else exclude.copy()
    marks: dict = {}
    cands = _candidates(
        left, disparity_lowres, scale, camera.fx, baseline_m, cfg, taken, height_lowres, marks
    )
    n_appearance = len(cands)
    n_net = marks.get("net", n_appearance)  # the network's candidates: n_net..n_appearance - 1
    if cfg.height_candidates > 0 and height_lowres is not None:
        cands += _height_candidates(
            height_lowres, disparity_lowres, int(scale), camera.fx, fb, cfg, taken, cands
        )
    use_judge = cfg.judge_min_score > 0
    floors = cfg
    height_floors = floors
    if n_appearance < len(cands):  # a height candidate's hand verdict (no contrast vouches)
        height_floors = replace(
            cfg,
            min_top_m=max(cfg.min_top_m, cfg.height_min_top_m),
            min_snr=max(cfg.min_snr, cfg.height_min_snr),
        )
    if use_judge:
        if judge is None:
            judge = default_judge() if cfg.judge_path is None else _judge_at(cfg.judge_path)
        floors = _judge_floors(cfg)
        pair = _pair_distances(cands)
        rank = _ranks(cands)
    for i, (u0, v0, crop, d0, dark, zpk) in enumerate(cands):
        bh, bw = crop.shape
        if _centre_in(taken, u0, v0, bh, bw):
            continue
        low_m = 0.0
        if height_lowres is not None:
            hh = _heights_around(height_lowres, int(scale), u0, v0, bh, bw)
            if not np.any(hh >= cfg.min_lowres_height_m):  # NaN compares False
                continue
            if use_judge:
                low_m = float(np.fmax.reduce(hh, axis=None))  # np.nanmax (hh has a number)
        margin = cfg.net_window_margin if n_net <= i < n_appearance else cfg.window_margin
        w = _local_heights(
            left, right, disparity_lowres, scale, intr, fb, cfg, mt, u0, v0, crop, d0, dark, margin
        )
        if w is None:
            continue
        cos_n = 1.0 if up_optical is None else abs(float(w.n @ up_optical))
        tilt_ok = cos_n >= cos_tilt
        hand = height_floors if i >= n_appearance and not use_judge else floors
        rock = _judge(w, hand, fx, dark, tilt_ok, trace)
        # (rock is _judge's own new SmallRock: it is completed in place)
        if rock.reason is not None:
            if (
                keep_rejected and rock.depth_m > 0
            ):  # a dark blob with nothing raised beside it: none
                rock.u0, rock.v0, rock.crop = u0, v0, crop.copy()
                out.append(rock)
            continue
        if rock.width_m > cfg.max_width_m:
            if keep_rejected:
                rock.u0, rock.v0, rock.crop, rock.reason = u0, v0, crop.copy(), "too_wide"
                out.append(rock)
            continue
        if use_judge:
            x = judge_features(
                rock, left, u0, v0, crop, dark, zpk, pair[i], low_m, cos_n, float(rock.noise_m)
            )
            p = float(judge.score(x))
            rock.features, rock.score, rock.rank = x, p, int(rank[i])
            if p < cfg.judge_min_score:
                if keep_rejected:
                    rock.reason = "judged"
                    out.append(rock)
                continue
        out.append(rock)
        # the rock and one rock width around it: other fragments of it are not rocks again
        g2 = max(rock.crop.shape)
        y0, x0 = rock.v0, rock.u0
        taken[
            max(y0 - g2, 0) : y0 + rock.crop.shape[0] + g2,
            max(x0 - g2, 0) : x0 + rock.crop.shape[1] + g2,
        ] = True
    return out


def _judge(w: _Window, cfg, fx: float, dark: bool, tilt_ok: bool, trace) -> SmallRock:
    """The verdict on one window's candidate (a SmallRock in window-independent, full-image
    pixels; ``reason`` None for a rock). A bright blob is judged as it is; a dark one by the
    raised part of its window beside it (:func:`_shadowed_blob`)."""
    import cv2

    blob = w.blob
    if dark:
        blob = _shadowed_blob(w, cfg, *_box_size(w.blob))
        if blob is None:
            return SmallRock(
                w.a0, w.b0, w.blob > 0, np.zeros((0, 3)), 0.0, w.noise, 0.0, 0.0, "flat"
            )
    if cfg.refine_margin > 0:
        # the rock as the blob and the raised pixels next to it, its ground from a closer ring
        region = blob if dark else _grown(w, blob, max(cfg.min_snr * w.noise, 0.5 * cfg.min_top_m))
        w2 = _refit(w, region, cfg)
        if w2 is not None:
            w, blob = w2, region
    bw, bh = _box_size(blob)
    bl = (cv2.dilate(blob, _ones(3)) > 0) & w.ok
    n_bl = int(np.count_nonzero(bl))
    if n_bl < cfg.min_blob_points:
        return SmallRock(w.a0, w.b0, blob > 0, np.zeros((0, 3)), 0.0, w.noise, 0.0, 0.0, "flat")
    h_bl = w.hall[bl]
    top = _quantile(h_bl, 0.9)
    depth = _quantile(w.P[w.idx[bl], 2], 0.5)
    width = max(bw, bh) * depth / fx
    if trace is not None:
        ys, xs = np.nonzero(blob)
        trace.append(
            {
                "box": (
                    w.a0 + int(xs.min()),
                    w.b0 + int(ys.min()),
                    w.a0 + int(xs.max()) + 1,
                    w.b0 + int(ys.max()) + 1,
                ),
                "top": top,
                "noise": w.noise,
                "width": width,
                "depth": depth,
                "aspect": bw / max(bh, 1),
                "tilt_ok": tilt_ok,
                "dark": dark,
            }
        )
    reason = _verdict(cfg, top, w.noise, width, tilt_ok)
    # the blob's median height against the noise of a mean over its independent pixels (one per
    # SGBM block): a lit patch of flat regolith has a noisy top but no raised middle
    n_ind = max(n_bl / cfg.block_size**2, 1.0)
    med = _quantile(h_bl, 0.5) if reason is None else float("nan")
    if reason is None and med * np.sqrt(n_ind) < cfg.min_median_snr * w.noise:
        reason = "flat"
    if dark and reason is None and (top < cfg.dark_min_snr * w.noise or n_bl < cfg.dark_min_points):
        reason = "flat"  # a raised patch beside a shadow needs more evidence than a lit face
    if reason is not None:
        return SmallRock(w.a0, w.b0, blob > 0, w.P[w.idx[bl]], top, w.noise, width, depth, reason)
    # the rock: the blob and the raised pixels next to it (its unlit side)
    rock = _grown(w, blob, max(0.5 * top, 0.5 * cfg.min_top_m)).view(bool)
    sel = w.idx[rock & w.ok]
    if sel.size < cfg.min_blob_points:
        return SmallRock(w.a0, w.b0, blob > 0, w.P[w.idx[bl]], top, w.noise, width, depth, "flat")
    x0, y0, x1, y1 = cv2.boundingRect(rock.view(np.uint8))
    x1, y1 = x0 + x1, y0 + y1
    return SmallRock(
        w.a0 + x0,
        w.b0 + y0,
        rock[y0:y1, x0:x1].copy(),
        w.P[sel],
        top,
        w.noise,
        (x1 - x0) * depth / fx,
        depth,
        median_m=med,
        blob_points=n_bl,
    )


def _judge_floors(cfg: SmallRockConfig) -> SmallRockConfig:
    """The hand verdict's settings with the judge's floors (what reaches the judge)."""
    return replace(
        cfg,
        min_top_m=cfg.judge_min_top_m,
        min_snr=cfg.judge_min_snr,
        low_top_snr=max(cfg.judge_min_snr, 1e-6),
        confident_top_m=cfg.judge_min_top_m,
        min_median_snr=0.0,
        dark_min_snr=cfg.judge_min_snr,
        dark_min_points=cfg.judge_dark_min_points,
    )


def _pair_distances(cands: list) -> np.ndarray:
    """Per candidate: the distance from its box's centre to the nearest centre of a candidate
    of the other polarity, in its box sizes (a lit face with its shadow), at most _PAIR_CAP."""
    n = len(cands)
    out = np.full(n, _PAIR_CAP)
    if n == 0:
        return out
    c = np.array([(u + cr.shape[1] / 2, v + cr.shape[0] / 2) for u, v, cr, *_ in cands], float)
    size = np.array([max(cr.shape) for _, _, cr, *_ in cands], float)
    dark = np.array([bool(x[4]) for x in cands])
    if dark.all() or not dark.any():
        return out
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    d[dark[:, None] == dark[None]] = np.inf
    return np.minimum(d.min(axis=1) / np.maximum(size, 1.0), _PAIR_CAP)


def _ranks(cands: list) -> np.ndarray:
    """Each candidate's rank among those of its polarity (the lists come strongest first)."""
    dark = np.array([bool(x[4]) for x in cands], bool)
    r = np.zeros(len(cands), int)
    for pol in (False, True):
        i = np.flatnonzero(dark == pol)
        r[i] = np.arange(i.size)
    return r


def judge_features(
    rock: SmallRock,
    left: np.ndarray,
    u0: int,
    v0: int,
    crop: np.ndarray,
    dark: bool,
    contrast_z: float,
    pair_dist: float,
    lowres_height_m: float,
    tilt_cos: float,
    noise_m: float,
) -> np.ndarray:
    """The judge's feature vector (JUDGE_FEATURES, float64) of one candidate that passed the
    floors: `rock` is the stage's verdict on it, (u0, v0, crop) the candidate's appearance
    blob in the left image `left` (H, W; uint8)."""
    bh, bw = crop.shape
    top, med = float(rock.top_m), float(rock.median_m)
    n = max(noise_m, 1e-4)
    width = max(float(rock.width_m), 1e-3)
    stage = [
        top,
        noise_m,
        top / n,
        (med if np.isfinite(med) else 0.0) / n,
        width,
        float(rock.depth_m),
        top / width,
        float(rock.blob_points),
        float(len(rock.points_optical)),
        float(bw),
        float(bh),
        bw / max(bh, 1),
        float(np.count_nonzero(crop)),
        float(contrast_z),
        1.0 if dark else 0.0,
        float(pair_dist),
        (v0 + bh / 2) / left.shape[0],
        lowres_height_m if np.isfinite(lowres_height_m) else 0.0,
        tilt_cos,
    ]
    # the appearance features of the height-map verifier
    app = appearance_features(left, InstanceMask(int(u0), int(v0), np.asarray(crop, bool)))
    x = np.concatenate([np.asarray(stage, float), app])
    return np.where(np.isfinite(x), x, 0.0)


def load_judge(path: Path) -> BlobVerifier:
    """Read a judge written by ``BlobVerifier.save`` (plain arrays, no pickle) over
    JUDGE_FEATURES."""
    return BlobVerifier.load(
        path, JUDGE_FEATURES, "small-rock judge", "benchmarks/train_small_rocks.py"
    )


@lru_cache(maxsize=1)
def default_judge() -> BlobVerifier:
    """The packaged judge (read once)."""
    return load_judge(JUDGE_PATH)


@lru_cache(maxsize=4)
def _judge_at(path: str) -> BlobVerifier:
    """The judge at SmallRockConfig.judge_path (read once)."""
    return load_judge(Path(path))


def _grown(w: _Window, blob: np.ndarray, level_m: float) -> np.ndarray:
    """`blob` (uint8) and the pixels higher than `level_m` within two pixels of it and connected
    to it (a lit face and the rest of its rock)."""
    import cv2

    with np.errstate(invalid="ignore"):
        raised = w.hall > level_m
    grown = cv2.dilate(blob, _ones(5)) > 0
    rock = ((raised & grown) | (blob > 0)).astype(np.uint8)
    return _touching(rock, blob).view(np.uint8)


def _touching(region: np.ndarray, blob: np.ndarray) -> np.ndarray:
    """The 8-connected components of `region` (uint8) that hold a pixel of `blob` (bool)."""
    import cv2

    n_lab, lab = cv2.connectedComponents(region, connectivity=8)
    keep = np.zeros(n_lab, bool)
    keep[lab[blob > 0]] = True
    keep[0] = False
    return keep[lab]


def _box_size(blob: np.ndarray) -> tuple[int, int]:
    """Width and height (pixels) of the bounding box of a blob's nonzero pixels (uint8, not
    empty)."""
    import cv2

    _, _, bw, bh = cv2.boundingRect(blob)
    return int(bw), int(bh)
