"""Small rocks near the rover: appearance candidates checked by full-resolution stereo height.

The height-map segmenter (``segment.py``) sees a rock when its half-resolution stereo heights
stand 2.5-3.5 cm above a ground grid of 0.35 m cells. A rock 3-7 cm wide stands 1.5-3 cm
high and covers 5-20 pixels at 1-6 m: the half-resolution match (a 10-pixel block) smooths it
into the ground, and the real LAC terrain has undulations of that height, so the thresholds
cannot come down. This stage finds such rocks in two steps:

1. **Candidates from appearance.** A small rock's lit face is brighter than the regolith
   around it (the LAC's rocks are lit by the sun or the rover's lamps; their unlit side and
   cast shadow lie beside it). Bright blobs of a difference of Gaussians on the half-
   resolution left image, scaled by the local contrast of the image (textured and flat
   regolith alike), whose size at the range the height map gives lies in
   [min_width_m, max_width_m], are candidates; the strongest ``max_candidates`` are kept.
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
   lander's panels and a boulder's face are not ground).

The ground plane of the whole view (:func:`ground_plane`) is also what replaces the level-rover
assumption where one is needed: fitted to the height map's points within ``ground_range_m``,
it gives the "up" direction from stereo alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lunarloc.core.errors import ConfigError

__all__ = [
    "SmallRock",
    "SmallRockConfig",
    "detect_small_rocks",
    "ground_plane",
    "small_rock_candidates",
]


@dataclass(frozen=True)
class SmallRockConfig:
    """Settings of the small-rock stage (see the module's docstring). Pixel sizes are at
    1280x720 (the LAC's cameras); widths and heights in metres."""

    # Run the stage (Detector: after the height-map detections, classical segmenter only). Off
    # by default: on the real LAC frames it takes recall of the labelled rocks from 0.23 to 0.55
    # at 26 of 27 detections on rocks, but on the simulated sites it costs precision within 5 m
    # (0.98-0.99 -> 0.91-0.95 at sun 5-25 and sun+lamps; lamps 0.98 kept) and 45-60 ms CPU per
    # pair (docs/perception.md, "Thirteenth pass"). Turn it on for LAC imagery.
    enabled: bool = False

    # DoG on the half-resolution left image: Gaussian of this standard deviation
    # (half-resolution pixels) is the local background; the local contrast is the RMS
    # of the difference over a window contrast_sigma_px wide (at 1/8 resolution).
    dog_sigma_px: float = 2.0
    # Resolution of the candidate search (1 = full, 2 = half; sigmas are in its pixels).
    candidate_scale: int = 2
    contrast_sigma_px: float = 8.0
    # A candidate's pixels are brighter than the background by this many local
    # contrasts (the real frames' regolith: 1 % of the pixels exceed 2).
    contrast_z: float = 2.0
    # Pixels darker than this are sky (0-255).
    sky_level: int = 8
    # At most this many candidates per image (the strongest blobs).
    max_candidates: int = 60
    # A candidate's box is at most this many times wider than tall: the regolith's lit
    # ridges and streaks under a low sun run along the rows; a small rock's lit face is
    # compact (a crescent is taller than wide).
    max_aspect: float = 2.0
    # Candidates' range (metres, from the height map) and width (metres).
    min_range_m: float = 0.8
    max_range_m: float = 6.0
    min_width_m: float = 0.012
    max_width_m: float = 0.15
    # Full-resolution window: the blob's box plus this many box sizes each side (at
    # least window_min_margin_px pixels).
    window_margin: float = 1.5
    window_min_margin_px: int = 8
    # SGBM block (odd) and band width (multiple of 16) of the window's match.
    block_size: int = 5
    band_px: int = 16
    # ... widened to hold the height map's disparities over the window, up to max_band_px.
    max_band_px: int = 64
    # The verdict (see the module's docstring).
    min_top_m: float = 0.01
    min_snr: float = 3.0
    # ... and a candidate lower than confident_top_m must stand low_top_snr times the noise:
    # the simulated sites' terrain bumps that passed min_snr stood 1.1-2.0 cm at 3.3-3.6
    # noises (sites 291, 292 at sun 12: 21 false detections within 5 m with 3.0, 9 with 4.0
    # everywhere; the real frames' rocks of 1.8 cm and more passed at 3.0-3.9).
    confident_top_m: float = 0.018
    low_top_snr: float = 4.0
    max_top_per_width: float = 1.5
    top_margin_m: float = 0.02
    max_tilt_deg: float = 35.0
    # Fit a quadric (in the plane's coordinates) rather than a plane to the ring: follows a
    # rim or a swell the window spans.
    quadric: bool = True
    min_ring_points: int = 30
    max_ring_points: int = 400
    # The cheap test first: the half-resolution height map must stand this high somewhere
    # around the candidate (real frames: every candidate on a labelled rock but one of 44 did;
    # 30 % of the others did not), else no full-resolution match is run.
    min_lowres_height_m: float = 0.005
    min_blob_points: int = 3
    # The ground plane of the view: height-map points within this optical depth.
    ground_range_m: float = 6.0

    def __post_init__(self) -> None:
        if not (self.dog_sigma_px > 0 and self.contrast_sigma_px > 0 and self.contrast_z > 0):
            raise ConfigError("dog_sigma_px, contrast_sigma_px and contrast_z must be > 0")
        if not (
            0 < self.min_range_m < self.max_range_m and 0 < self.min_width_m < self.max_width_m
        ):
            raise ConfigError(
                "need 0 < min_range_m < max_range_m and 0 < min_width_m < max_width_m"
            )
        if (
            self.block_size < 1
            or self.block_size % 2 == 0
            or self.band_px < 16
            or self.band_px % 16
        ):
            raise ConfigError("block_size must be odd, band_px a multiple of 16")
        if not (
            self.min_top_m > 0
            and self.min_snr >= 0
            and self.max_top_per_width > 0
            and 0 < self.max_tilt_deg <= 90
        ):
            raise ConfigError(
                "min_top_m and max_top_per_width must be > 0, min_snr >= 0, max_tilt_deg in (0, 90]"
            )
        if self.max_candidates < 0:
            raise ConfigError("max_candidates must be >= 0")
        positive = (
            "max_aspect",
            "window_margin",
            "top_margin_m",
            "confident_top_m",
            "low_top_snr",
            "ground_range_m",
        )
        for name in positive:
            v = getattr(self, name)
            if not (
                isinstance(v, (int, float))
                and np.isfinite(v)
                and v >= 0
                and (v > 0 or name == "top_margin_m")
            ):
                raise ConfigError(f"{name}={v!r} must be a finite number > 0")
        if not (np.isfinite(self.min_lowres_height_m) and self.min_lowres_height_m >= 0):
            raise ConfigError(
                f"min_lowres_height_m={self.min_lowres_height_m!r} must be a finite number >= 0"
            )
        if (
            self.max_band_px < self.band_px
            or self.max_band_px % 16
            or self.min_ring_points < 6
            or self.max_ring_points < 12
        ):
            raise ConfigError(
                "max_band_px must be a multiple of 16 >= band_px, min_ring_points >= 6, max_ring_points >= 12"
            )


@dataclass
class SmallRock:
    """One verified candidate: its pixels (a boolean crop at (u0, v0)), points (optical
    frame), height above the local ground (m), the ring's residual spread (m), width (m),
    depth (m) and the verdict: ``reason`` None for a rock, else ``"flat"`` (too low for its
    noise), ``"not_ground"`` (the surroundings are no ground), ``"too_tall"`` or ``"too_wide"``."""

    u0: int
    v0: int
    crop: np.ndarray
    points_optical: np.ndarray
    top_m: float
    noise_m: float
    width_m: float
    depth_m: float
    reason: str | None = None


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
    P = P[np.isfinite(P).all(axis=1)]
    if len(P) < 50:
        return None
    for _ in range(2):
        c = np.median(P, axis=0)
        Q = P - c
        # the plane's normal: the scatter matrix's least eigenvector (as the SVD's last right
        # singular vector, without the (N, 3) left factor)
        n = np.linalg.eigh(Q.T @ Q)[1][:, 0]
        r = Q @ n
        s = 1.4826 * np.median(np.abs(r)) + 1e-6
        P = P[np.abs(r) < 3 * s]
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
) -> list[tuple[int, int, np.ndarray, float]]:
    """Bright blobs of the left image sized like small rocks at their range: (u0, v0, crop,
    d0) with `crop` a full-resolution boolean mask at (u0, v0) and d0 the height map's
    disparity there (full-resolution pixels); strongest first."""
    import cv2

    H, W = left.shape
    k = int(cfg.candidate_scale)
    kd = int(scale)
    D = np.asarray(disparity_lowres, np.float32)
    # only the rows that hold ground within the range searched (and a margin)
    with np.errstate(invalid="ignore"):
        near = (
            np.isfinite(D)
            & (D * kd >= fx * baseline_m / cfg.max_range_m)
            & (D * kd <= fx * baseline_m / cfg.min_range_m)
        )
    rows = np.flatnonzero(near.any(axis=1))
    if rows.size == 0:
        return []
    r0 = max(int(rows[0]) * kd - 32, 0) // k * k
    r1 = min((int(rows[-1]) + 1) * kd + 32, H)
    h, w = (r1 - r0) // k, W // k
    roi = left[r0 : r0 + h * k]
    small = (cv2.resize(roi, (w, h), interpolation=cv2.INTER_AREA) if k > 1 else roi).astype(
        np.float32
    )
    dv = small - cv2.GaussianBlur(small, (0, 0), cfg.dog_sigma_px)
    e = max(int(cfg.contrast_sigma_px // 2), 1)
    var = cv2.resize(dv * dv, (max(w // e, 1), max(h // e, 1)), interpolation=cv2.INTER_AREA)
    var = cv2.resize(cv2.GaussianBlur(var, (0, 0), 2.0), (w, h), interpolation=cv2.INTER_LINEAR)
    z = dv / (np.sqrt(var) + 2.0)
    # peaks of the contrast (local maxima over 5x5) above contrast_z; each peak's blob is the
    # part of the window around it brighter than half its peak contrast and connected to it
    # (a lit face touching lit regolith does not merge with it)
    peak = (
        (z >= cv2.dilate(z, np.ones((5, 5), np.uint8)))
        & (z > cfg.contrast_z)
        & (small > cfg.sky_level)
    )
    pv, pu = np.nonzero(peak)
    if pv.size == 0:
        return []
    hd, wd = D.shape
    cu = np.clip((pu * k) // kd, 0, wd - 1)
    cv = np.clip((pv * k + r0) // kd, 0, hd - 1)
    pad = np.pad(D, 2, constant_values=np.nan)
    win = np.stack(
        [pad[cv + 2 + a, cu + 2 + b] for a in range(-2, 3) for b in range(-2, 3)], axis=1
    )
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        d0 = np.nanmedian(win, axis=1) * kd
    with np.errstate(divide="ignore", invalid="ignore"):
        Z = fx * baseline_m / d0
    ok = np.isfinite(Z) & (Z >= cfg.min_range_m) & (Z <= cfg.max_range_m)
    order = np.flatnonzero(ok)
    # strongest first by the contrast summed around the peak (a rock's lit face, a few pixels
    # across, before the single bright speckles of the regolith's texture)
    zs = cv2.GaussianBlur(np.maximum(z, 0), (0, 0), 1.5)
    order = order[np.argsort(-zs[pv[order], pu[order]], kind="stable")]
    out = []
    claimed = np.zeros(z.shape, bool)
    for i in order[: 3 * cfg.max_candidates]:  # the strongest peaks only
        if len(out) >= cfg.max_candidates:
            break
        y, x = int(pv[i]), int(pu[i])
        if claimed[y, x]:
            continue
        # the window: a rock of max_width_m at this range, plus a margin
        half = int(np.clip(cfg.max_width_m * fx / Z[i] / k, 3, 40))
        ya, yb, xa, xb = (
            max(y - half, 0),
            min(y + half + 1, h),
            max(x - half, 0),
            min(x + half + 1, w),
        )
        sub = (z[ya:yb, xa:xb] > max(0.5 * z[y, x], 0.6 * cfg.contrast_z)).astype(np.uint8)
        _, lab = cv2.connectedComponents(sub, connectivity=8)
        blob = lab == lab[y - ya, x - xa]
        ys, xs = np.nonzero(blob)
        by0, by1, bx0, bx1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        bw, bh = bx1 - bx0, by1 - by0
        claimed[ya:yb, xa:xb] |= blob
        if ys.size < 2 or bw > cfg.max_aspect * bh:
            continue
        width = max(bw, bh) * k * Z[i] / fx
        if not cfg.min_width_m <= width <= cfg.max_width_m:
            continue
        c = blob[by0:by1, bx0:bx1]
        full = np.repeat(np.repeat(c, k, axis=0), k, axis=1) if k > 1 else c
        out.append(((xa + bx0) * k, (ya + by0) * k + r0, full, float(d0[i])))
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

        d = (
            self._sgbm(nd)
            .compute(cols(L, la, u1), cols(R, la - dmin, u1 - dmin))
            .astype(np.float32)[:, u0 - la :]
            / 16.0
        )
        d[(d <= 0) | (d >= nd - 1)] = np.nan
        return d + dmin


def _fit_plane(P: np.ndarray):
    """Least-squares plane of (N, 3) points: centroid and unit normal towards the optical origin."""
    c = P.mean(axis=0)
    Q = P - c
    _, v = np.linalg.eigh(Q.T @ Q)
    n = v[:, 0]
    if np.dot(n, c) > 0:  # the camera (origin) lies on the normal's side
        n = -n
    return c, n


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
    """
    import cv2

    L, R = left, right
    H, W = L.shape
    fx, cx, cy = camera.fx, camera.cx, camera.cy
    fb = fx * baseline_m
    mt = matcher or _Matcher(cfg.block_size, cfg.band_px, cfg.max_band_px)
    cos_tilt = np.cos(np.radians(cfg.max_tilt_deg))
    out: list[SmallRock] = []
    taken = np.zeros((H, W), bool) if exclude is None else exclude.copy()
    for u0, v0, crop, d0 in small_rock_candidates(L, disparity_lowres, scale, fx, baseline_m, cfg):
        bh, bw = crop.shape
        cu, cv = u0 + bw // 2, v0 + bh // 2
        if taken[min(cv, H - 1), min(cu, W - 1)]:
            continue
        if height_lowres is not None:
            k = int(scale)
            hh = height_lowres[
                max(v0 // k - 1, 0) : (v0 + bh) // k + 2, max(u0 // k - 1, 0) : (u0 + bw) // k + 2
            ]
            if not np.any(hh >= cfg.min_lowres_height_m):  # NaN compares False
                continue
        M = int(max(cfg.window_min_margin_px, cfg.window_margin * max(bw, bh)))
        a0, b0 = max(u0 - M, 0), max(v0 - M, 0)
        a1, b1 = min(u0 + bw + M, W), min(v0 + bh + M, H)
        # the height map's disparities over the window (full-resolution pixels)
        wd_ = disparity_lowres[
            b0 // scale : (b1 - 1) // scale + 1, a0 // scale : (a1 - 1) // scale + 1
        ]
        wd_ = wd_[np.isfinite(wd_)] * scale
        lo, hi = np.percentile(wd_, [5, 95]) if wd_.size >= 8 else (d0, d0)
        d = mt.window(L, R, a0, b0, a1, b1, min(lo, d0), max(hi, d0))
        if d is None:
            continue
        blob = np.zeros(d.shape, np.uint8)
        blob[v0 - b0 : v0 - b0 + bh, u0 - a0 : u0 - a0 + bw] = crop
        g = max(3, int(0.5 * max(bw, bh)))
        ring = cv2.dilate(blob, np.ones((2 * g + 1, 2 * g + 1), np.uint8)) == 0
        inner = cv2.dilate(blob, np.ones((3, 3), np.uint8)) > 0
        ok = np.isfinite(d)
        gr, bl = ring & ok, inner & ok
        n_ring, n_blob = int(np.count_nonzero(gr)), int(np.count_nonzero(bl))
        if n_ring < cfg.min_ring_points or n_blob < cfg.min_blob_points:
            continue
        # points (left optical frame) of the window's valid pixels
        vv, uu = np.nonzero(ok)
        Z = fb / d[vv, uu]
        P = np.stack([(uu + a0 - cx) * Z / fx, (vv + b0 - cy) * Z / fx, Z], axis=1)
        idx = np.full(d.shape, -1, np.int64)
        idx[vv, uu] = np.arange(vv.size)
        ring_idx = idx[gr]
        if ring_idx.size > cfg.max_ring_points:  # an even subsample: the fit needs no more
            ring_idx = ring_idx[:: int(np.ceil(ring_idx.size / cfg.max_ring_points))]
        Q = P[ring_idx]
        c, n = _fit_plane(Q)
        r = (Q - c) @ n
        med = np.median(r)
        s = 1.4826 * np.median(np.abs(r - med)) + 1e-4
        keep = np.abs(r - med) < 3 * s
        if np.count_nonzero(keep) >= cfg.min_ring_points // 2:
            c, n = _fit_plane(Q[keep])
            r = (Q[keep] - c) @ n
            s = 1.4826 * np.median(np.abs(r - np.median(r))) + 1e-4
        hP = (P - c) @ n
        if cfg.quadric and np.count_nonzero(keep) >= 12:
            e1 = np.cross(n, [0.0, 0.0, 1.0])
            e1 /= np.linalg.norm(e1) + 1e-12
            e2 = np.cross(n, e1)
            X = P - c
            a1, a2 = X @ e1, X @ e2
            A = np.stack([np.ones_like(a1), a1, a2, a1 * a1, a1 * a2, a2 * a2], axis=1)
            ri = ring_idx
            sel = ri
            coef = np.zeros(6)
            for _ in range(2):
                As = A[sel]
                try:  # normal equations: a 6x6 solve (lstsq's SVD costs far more here)
                    coef = np.linalg.solve(As.T @ As + 1e-9 * np.eye(6), As.T @ hP[sel])
                except np.linalg.LinAlgError:
                    break
                res = hP[ri] - A[ri] @ coef
                mr = np.median(res)
                s = 1.4826 * np.median(np.abs(res - mr)) + 1e-4
                sel = ri[np.abs(res - mr) < 3 * s]
                if sel.size < 12:
                    break
            hP = hP - A @ coef
        hall = np.full(d.shape, np.nan, np.float32)
        hall[vv, uu] = hP
        hb = hall[bl]
        top = float(np.quantile(hb, 0.9))
        depth = float(np.median(P[idx[bl], 2]))
        width = max(bw, bh) * depth / fx
        tilt_ok = up_optical is None or abs(float(np.dot(n, up_optical))) >= cos_tilt
        if trace is not None:
            trace.append(
                dict(
                    box=(u0, v0, u0 + bw, v0 + bh),
                    top=top,
                    noise=float(s),
                    width=width,
                    depth=depth,
                    aspect=bw / max(bh, 1),
                    tilt_ok=tilt_ok,
                )
            )
        reason = None
        if not tilt_ok:
            reason = "not_ground"  # the surroundings are a wall, the lander, a boulder's face
        elif (
            top < cfg.min_top_m
            or top < cfg.min_snr * s
            or (top < cfg.confident_top_m and top < cfg.low_top_snr * s)
        ):
            reason = "flat"
        elif top > cfg.max_top_per_width * width + cfg.top_margin_m:
            reason = "too_tall"
        if reason is not None:
            if keep_rejected:
                out.append(
                    SmallRock(u0, v0, crop.copy(), P[idx[bl]], top, float(s), width, depth, reason)
                )
            continue
        # the rock: the blob and the raised pixels next to it (its unlit side)
        with np.errstate(invalid="ignore"):
            raised = hall > max(0.5 * top, 0.5 * cfg.min_top_m)
        grown = cv2.dilate(blob, np.ones((5, 5), np.uint8)) > 0
        rock = ((raised & grown) | (blob > 0)).astype(np.uint8)
        _, lab = cv2.connectedComponents(rock, connectivity=8)
        ids = np.unique(lab[blob > 0])
        rock = np.isin(lab, ids[ids > 0])
        sel = idx[rock & ok]
        if sel.size < cfg.min_blob_points:
            continue
        ys, xs = np.nonzero(rock)
        y0r, y1r, x0r, x1r = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
        width = (x1r - x0r) * depth / fx
        if width > cfg.max_width_m:
            if keep_rejected:
                out.append(
                    SmallRock(
                        u0, v0, crop.copy(), P[idx[bl]], top, float(s), width, depth, "too_wide"
                    )
                )
            continue
        out.append(
            SmallRock(
                a0 + x0r,
                b0 + y0r,
                rock[y0r:y1r, x0r:x1r].copy(),
                P[sel],
                top,
                float(s),
                width,
                depth,
            )
        )
        # the rock and one rock width around it: other bright fragments of it are not rocks again
        g2 = max(x1r - x0r, y1r - y0r)
        taken[max(b0 + y0r - g2, 0) : b0 + y1r + g2, max(a0 + x0r - g2, 0) : a0 + x1r + g2] = True
    return out
