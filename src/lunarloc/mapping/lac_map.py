"""The LAC geometric map from what the rover sees: terrain heights and rock flags per cell.

A :class:`LacMapper` takes, per stereo frame, the rover-frame points of the stereo the
detector already computes (:attr:`lunarloc.perception.stereo.HeightMap.points_rover`; any
(..., 3) array of rover-frame points works) and the frame's rock detections (rover-frame
centres with radii), with the rover's pose in the map frame. :meth:`LacMapper.grid` places
every frame with its current pose and returns the LAC's ``(180, 180, 4)`` array
(``x, y, height, rock flag``; :mod:`lunarloc.io.overhead` has its layout) with per-cell
uncertainty and the cells it interpolated. When the pose graph corrects past poses,
:meth:`LacMapper.repose` moves a frame: what it placed moves with it at the next ``grid()``.

What the LAC scores (:func:`lunarloc.io.overhead.score_geometric_map`): a true cell's height is
the mean of 16 downward rays on a 3.75 cm lattice inside it, its rock flag is set when any of
the rays hits a rock. The mapper estimates both:

* **Heights.** Each frame's points within ``max_range_m`` (horizontal, rover frame) are binned
  in the rover frame (``bin_m`` squares): per bin the mean point and a weight (its point count
  times ``1 / (1 + (range / range_scale_m)^4)``: stereo height noise grows fast with range).
  This per-frame summary (a few thousand bins) is all that is kept of a frame. ``grid()``
  places the bins of every frame with its pose; a cell's height is the **weighted median** of
  the bins that fall in it (robust to stereo outliers and to a rock edge's few points), its
  uncertainty the weighted spread about that median (``height_sigma_m``).
* **Rocks.** Detections are placed with their frame's pose; those of different frames within
  ``rock_merge_m`` of each other are one rock, kept with the median centre and radius when
  enough frames detected it: ``rock_min_sightings`` for a rock of ``small_rock_m`` radius or
  more, ``small_rock_min_sightings`` for a smaller one (the detector's small-rock stage finds
  those; the any-ray rule flags them). With ``rock_cells="footprint"`` every cell with
  **any** of its 16 ray points within the footprint of the centre is flagged (the LAC's any-ray
  rule); with ``rock_cells="model"`` (default) a cell is flagged when its P(rock) reaches
  ``rock_cell_min_p``: boosted trees (:data:`ROCK_CELL_MODEL_PATH`) over the detection clusters
  near it, mapped or not, and its stereo (:data:`ROCK_CELL_FEATURES`). The footprint radius is
  ``rock_radius_scale x radius + rock_radius_margin_m``, for a small rock
  ``radius + small_rock_margin_m``. A large rock (``rock_recentre_min_m``) is moved
  ``rock_recentre_scale x radius`` away from the rover along its sightings' mean viewing
  direction: its detections sit on the side the cameras see.
* **Rock bumps** (off by default). With ``rock_bump_m`` set, observed cells standing that much
  or more above their local ground (the ``rock_ground_quantile`` percentile of the heights in
  a ``rock_ground_window_m`` square) are flagged too. On the tuning site it added more false
  rock cells (terrain roughness, crater rims) than true ones at every threshold from 3 to
  7 cm, so it stays off (docs/lac-map.md).
* **Cells never seen** (``fill``): ``all`` (default) fills every unseen cell with the
  Gaussian-weighted mean of the seen heights at the smallest scale (1, 2, 4, ... cells) that
  reaches one (normalised convolution), with no rock; ``near`` only those within ``fill_max_m`` of a
  seen cell; ``none`` leaves
  them unfilled (the LAC's -inf). An unfilled cell always fails the LAC's geometric score and
  counts nothing for productivity, so ``all`` can only gain points; the estimate says which
  cells were interpolated and how far from a seen cell (``fill_distance_m``).
* **Bounded memory.** At most ``max_frames`` frames are kept re-placeable; older ones are
  frozen into per-cell sums at their last pose (their heights then join each cell's median
  as one weighted mean) and can no longer move. Memory: the frozen sums (three N x N arrays)
  plus ``max_frames`` summaries (about 16 bytes a bin; :meth:`LacMapper.memory_bytes`).

The live layer (:meth:`LacMapper.live_cells`, what :class:`LacMapWriter` writes into the
leaderboard's map every tick): each frame folded in once at the pose it was added with
(running weighted means, rock-footprint votes), the cells it changed marked for writing;
cheap (the frame's bins), approximate (no re-placing, no medians); :meth:`LacMapper.grid`
is the map for the end.

Excluded areas (:meth:`LacMapper.exclude_disc`, e.g. the lander: its points are not terrain)
drop the points and detections placed inside them; their cells are interpolated.
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.core.validate import rigid_transform
from lunarloc.io.overhead import LAC_CELL_M, LAC_CELLS, LAC_RAY_OFFSETS, UNFILLED, empty_lac_grid

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = [
    "LacMapperConfig",
    "LacMapEstimate",
    "LacMapper",
    "LacMapWriter",
    "write_geometric_map",
    "save_lac_map",
    "cells_path",
    "load_observed_cells",
    "frame_inputs",
    "LANDER_EXCLUSION_M",
    "ROCK_CELL_FEATURES",
    "ROCK_CELL_MODEL_PATH",
    "rock_cell_probability",
]

FILL_MODES = ("all", "near", "none")
ROCK_CELL_MODES = ("footprint", "model")

#: the per-cell rock model (``LacMapperConfig.rock_cells = "model"``): boosted trees as plain
#: arrays, trained by ``benchmarks/bench_lac_map.py train-rock-cells`` on development sites
ROCK_CELL_MODEL_PATH = Path(__file__).with_name("lac_rock_cells.npz")
#: the model's per-cell features (:meth:`LacMapper.rock_cell_features`), in its column order
ROCK_CELL_FEATURES = (
    "margin_m",  # nearest ray point's distance to the cell's cluster, minus its footprint radius
    "dnorm",  # that distance over the cluster's radius
    "log_r",  # log of the cluster's median radius (m, at least 1 cm)
    "log_s",  # log of its sightings (distinct frames)
    "kept",  # 1 when the sightings rule maps it (the footprint rule's rock)
    "rspread",  # its radii's interquartile range over the median
    "cspread",  # its detections' median distance from their median centre (m)
    "rng_med",  # its detections' median range (m)
    "rng_min",  # ... and smallest
    "ncov",  # clusters within reach of the cell
    "bump",  # the cell's height above its local ground (30 % quantile over 1.05 m; m)
    "hsig",  # the cell's height_sigma_m (0 unobserved)
    "logw",  # log(1 + the cell's stereo weight)
)

#: the lander's exclusion disc radius (m) callers pass to :meth:`LacMapper.exclude_disc`: its
#: body and legs are not terrain (the detector's ``on_lander`` drops detections within it too)
LANDER_EXCLUSION_M = 2.2


@dataclass(frozen=True)
class LacMapperConfig:
    """How the mapper bins, weights, fuses and fills (metres)."""

    size_m: float = LAC_CELL_M * LAC_CELLS  # side of the square map (LAC: 27 m)
    cell_m: float = LAC_CELL_M  # cell side (LAC: 0.15 m)
    centre_xy: tuple[float, float] = (0.0, 0.0)  # map centre in the map frame (LAC: the origin)
    bin_m: float = 0.05  # rover-frame bin of a frame's summary
    min_range_m: float = 0.3  # points nearer than this (horizontal, rover frame) are dropped
    max_range_m: float = 4.0  # ... and farther than this
    range_scale_m: float = 2.0  # bin weight count / (1 + (range / range_scale_m)^4)
    max_abs_z_m: float = 3.0  # rover-frame points higher or lower than this are dropped
    max_frames: int = 2000  # frames kept re-placeable; older ones are frozen at their pose
    rock_min_sightings: int = (
        3  # frames that must detect a rock (small_rock_m or larger) before it is mapped
    )
    rock_merge_m: float = 0.10  # detections of different frames nearer than this are one rock
    rock_max_range_m: float = (
        6.0  # detections farther than this (horizontal, rover frame) are dropped
    )
    rock_radius_scale: float = 1.05  # footprint radius = scale x estimated radius + margin
    rock_radius_margin_m: float = 0.0
    # small rocks (median radius under small_rock_m; the small-rock stage's finds): their own
    # sightings floor and footprint radius = radius + small_rock_margin_m (no scale)
    small_rock_m: float = 0.05
    small_rock_min_sightings: int = 2
    small_rock_margin_m: float = 0.01
    # large rocks (median radius rock_recentre_min_m or more; None: off) are moved
    # rock_recentre_scale x radius x the mean of their sightings' unit viewing directions (rover
    # -> rock): a large rock's detections sit on the side the cameras see (docs/lac-map.md)
    rock_recentre_min_m: float | None = 0.2
    rock_recentre_scale: float = 0.1
    rock_bump_m: float | None = (
        None  # observed cells this high over their local ground are rock cells (None: off)
    )
    rock_ground_window_m: float = (
        1.05  # the local ground: a low quantile of the heights in this square
    )
    rock_ground_quantile: float = 30.0  # ... this percentile
    # how rock cells are decided: "footprint" (any ray point inside a mapped rock's disc) or
    # "model" (a per-cell P(rock) from the detection clusters near the cell and the stereo
    # heights, ROCK_CELL_MODEL_PATH; flagged from rock_cell_min_p); docs/lac-map.md
    rock_cells: str = "model"
    rock_cell_min_p: float = 0.4
    rock_cell_reach_m: float = 0.10  # cells this far beyond a cluster's footprint are candidates
    fill: str = "all"  # unseen cells: all | near | none (module docstring)
    fill_max_m: float = 1.0  # `near`: fill within this distance of a seen cell

    def __post_init__(self) -> None:
        n = self.size_m / self.cell_m
        if not (self.cell_m > 0 and n >= 2 and abs(n - round(n)) < 1e-6):
            raise ConfigError(
                f"size_m={self.size_m} must be a whole number (>= 2) of cells of "
                f"cell_m={self.cell_m}"
            )
        if not 0 < self.bin_m <= self.cell_m:
            raise ConfigError(f"bin_m={self.bin_m} must be in (0, cell_m]")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise ConfigError("need 0 <= min_range_m < max_range_m")
        if self.range_scale_m <= 0 or self.max_abs_z_m <= 0:
            raise ConfigError("range_scale_m and max_abs_z_m must be > 0")
        if self.max_frames < 1 or self.rock_min_sightings < 1 or self.small_rock_min_sightings < 1:
            raise ConfigError(
                "max_frames, rock_min_sightings and small_rock_min_sightings must be >= 1"
            )
        if not (self.small_rock_m >= 0 and math.isfinite(self.small_rock_margin_m)):
            raise ConfigError("small_rock_m must be >= 0, small_rock_margin_m finite")
        if self.rock_merge_m < 0 or self.rock_max_range_m <= 0 or self.rock_radius_scale < 0:
            raise ConfigError(
                "rock_merge_m and rock_radius_scale must be >= 0, rock_max_range_m > 0"
            )
        if self.rock_cells not in ROCK_CELL_MODES:
            raise ConfigError(
                f"rock_cells={self.rock_cells!r}: one of {', '.join(ROCK_CELL_MODES)}"
            )
        if not (0 < self.rock_cell_min_p < 1 and self.rock_cell_reach_m >= 0):
            raise ConfigError("rock_cell_min_p must lie in (0, 1), rock_cell_reach_m be >= 0")
        if self.fill not in FILL_MODES:
            raise ConfigError(f"fill={self.fill!r}: one of {', '.join(FILL_MODES)}")
        if self.fill_max_m < 0:
            raise ConfigError("fill_max_m must be >= 0")
        if self.rock_recentre_min_m is not None and not (
            self.rock_recentre_min_m >= 0 and math.isfinite(self.rock_recentre_scale)
        ):
            raise ConfigError(
                "rock_recentre_min_m must be >= 0 (or None), rock_recentre_scale finite"
            )
        if self.rock_bump_m is not None and not self.rock_bump_m > 0:
            raise ConfigError("rock_bump_m must be > 0 (or None)")
        if self.rock_ground_window_m < 2 * self.cell_m or not 0 <= self.rock_ground_quantile <= 100:
            raise ConfigError(
                "rock_ground_window_m must span >= 2 cells, rock_ground_quantile lie in [0, 100]"
            )

    @property
    def cells(self) -> int:
        return int(round(self.size_m / self.cell_m))

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class LacMapEstimate:
    """What :meth:`LacMapper.grid` returns. Arrays are (N, N), cell [i, j] as in :attr:`array`.

    array : the LAC map (N, N, 4): x, y, height (m), rock flag (0/1); -inf where unfilled.
    observed : cells that hold points of at least one frame.
    interpolated : cells filled without being observed.
    height_sigma_m : weighted spread of the observed heights about the cell's height (NaN
        unobserved).
    weight : sum of the bin weights in the cell (0 unobserved).
    fill_distance_m : distance from the cell centre to the nearest observed cell centre (0
        observed).
    rocks : (K, 3) the mapped rocks: x, y (map frame), footprint radius (m).
    rock_probability : P(rock) per cell from the per-cell model (``rock_cells="model"``; 0
        where no detection cluster is near), None with the footprint rule.
    """

    array: np.ndarray
    observed: np.ndarray
    interpolated: np.ndarray
    height_sigma_m: np.ndarray
    weight: np.ndarray
    fill_distance_m: np.ndarray
    rocks: np.ndarray
    rock_probability: np.ndarray | None = None

    @property
    def filled(self) -> np.ndarray:
        return np.isfinite(self.array[:, :, 2])


@dataclass
class _Frame:
    T_map_rover: np.ndarray  # (4, 4)
    bins: np.ndarray  # (K, 4) float32: rover-frame x, y, z, weight
    rocks: np.ndarray  # (M, 4) float32: rover-frame x, y, z, radius
    seq: int = 0  # order of arrival (a rock's sightings count distinct frames)


def _check_T(T, what: str) -> np.ndarray:
    """`T` as a float64 4x4 rigid transform (:func:`lunarloc.core.validate.rigid_transform`)."""
    return rigid_transform(T, what)


class LacMapper:
    """Fuse stereo frames into the LAC geometric map (module docstring).

    Per frame: :meth:`add_frame`; when the pose graph corrects past poses: :meth:`repose`;
    the map: :meth:`grid`. Frame ids are any hashable (the frame number, the tick)."""

    def __init__(self, config: LacMapperConfig | None = None) -> None:
        self.config = cfg = config or LacMapperConfig()
        self._grid0 = empty_lac_grid(cfg.size_m, cfg.cell_m, cfg.centre_xy)
        n = cfg.cells
        self._lo = np.array([self._grid0[0, 0, 0], self._grid0[0, 0, 1]]) - cfg.cell_m / 2.0
        self._frames: OrderedDict = OrderedDict()
        self._seq = 0
        self._frozen_w = np.zeros((n, n))
        self._frozen_wz = np.zeros((n, n))
        self._frozen_wz2 = np.zeros((n, n))
        # map-frame x, y, radius, seq, viewing direction (unit x, y: rover -> rock), range
        # (horizontal, rover frame)
        self._frozen_rocks = np.zeros((0, 7))
        self._discs: list[tuple[float, float, float]] = []
        self.frozen_frames = 0
        # the live layer (live_cells): per-cell running sums at the poses frames were added
        # with, rock-footprint votes, and the cells changed since they were last handed out
        self._live_w = np.zeros(n * n)
        self._live_wz = np.zeros(n * n)
        self._live_votes = np.zeros(n * n, np.int32)
        self._live_dirty = np.zeros(n * n, bool)
        self._live_cursor = 0
        # the rover-frame bin lattice: keys in a (side x side) square
        self._half = int(math.ceil(cfg.max_range_m / cfg.bin_m)) + 1
        self._side = 2 * self._half + 1

    # ------------------------------------------------------------------ inputs
    def exclude_disc(self, centre_xy, radius_m: float) -> None:
        """Drop points and detections placed within `radius_m` of `centre_xy` (map frame),
        e.g. the lander (its body and legs are not terrain)."""
        c = np.asarray(centre_xy, float).reshape(-1)
        if (
            c.shape[0] < 2
            or not np.all(np.isfinite(c[:2]))
            or not (math.isfinite(radius_m) and radius_m > 0)
        ):
            raise InputError(
                f"exclude_disc: need a finite centre (x, y) and radius > 0, got {centre_xy}, "
                f"{radius_m}"
            )
        self._discs.append((float(c[0]), float(c[1]), float(radius_m)))

    def add_frame(self, frame_id, T_map_rover, points_rover=None, rocks_rover=None) -> int:
        """Add what one frame saw, placed with `T_map_rover` (4x4, rover -> map).

        points_rover : (..., 3) rover-frame points (x forward, y left, z up; NaN rows are
            skipped), e.g. a stereo HeightMap's ``points_rover``; several pairs of one frame may
            be added under the same `frame_id` (they are merged; the pose is the last given).
        rocks_rover : (M, 4) rover-frame rock centres and radii (m), or (M, 3) centres
            (radius 0: the cell holding the centre).
        Returns the number of bins the frame's summary holds. Raises InputError on a bad pose
        or array shape."""
        T = _check_T(T_map_rover, f"frame {frame_id}: T_map_rover")
        bins = self._summarise(points_rover, frame_id)
        rocks = self._rocks(rocks_rover, frame_id)
        old = self._frames.get(frame_id)
        self._live_add(T, bins, rocks)
        if old is not None:
            old.T_map_rover = T
            old.bins = np.concatenate([old.bins, bins])
            old.rocks = np.concatenate([old.rocks, rocks])
            return len(old.bins)
        self._frames[frame_id] = _Frame(T, bins, rocks, self._seq)
        self._seq += 1
        while len(self._frames) > self.config.max_frames:
            self._freeze(*self._frames.popitem(last=False))
        return len(bins)

    def repose(self, frame_id, T_map_rover) -> bool:
        """Move frame `frame_id` to `T_map_rover` (e.g. the pose graph's corrected pose).
        Returns False when the frame is unknown or already frozen (then nothing moves)."""
        fr = self._frames.get(frame_id)
        if fr is None:
            return False
        fr.T_map_rover = _check_T(T_map_rover, f"frame {frame_id}: T_map_rover")
        return True

    @property
    def frame_ids(self) -> list:
        """Ids of the frames that can still be re-placed (oldest first)."""
        return list(self._frames.keys())

    def __len__(self) -> int:
        return len(self._frames)

    def memory_bytes(self) -> int:
        """Bytes held: frame summaries, frozen sums and rocks."""
        n = sum(
            f.bins.nbytes + f.rocks.nbytes + f.T_map_rover.nbytes for f in self._frames.values()
        )
        live = (
            self._live_w.nbytes
            + self._live_wz.nbytes
            + self._live_votes.nbytes
            + self._live_dirty.nbytes
        )
        return int(n + self._frozen_w.nbytes * 3 + self._frozen_rocks.nbytes + live)

    # ------------------------------------------------------------------ the live layer
    def _live_add(self, T: np.ndarray, bins: np.ndarray, rocks: np.ndarray) -> None:
        """Fold one frame into the live layer at `T` (cost: its bins and detections)."""
        fr = _Frame(T, bins, rocks)
        c, z, w = self._place_bins(fr)
        if len(c):
            np.add.at(self._live_w, c, w)
            np.add.at(self._live_wz, c, w * z)
            self._live_dirty[c] = True
        xy, r, _, _ = self._place_rocks(fr)
        if len(r):
            cfg = self.config
            r_fp = np.where(
                r < cfg.small_rock_m,
                r + cfg.small_rock_margin_m,
                cfg.rock_radius_scale * r + cfg.rock_radius_margin_m,
            )
            hit = np.flatnonzero(
                _rock_cells(np.column_stack([xy, np.maximum(r_fp, 0.0)]), self._grid0, cfg.cell_m)
            )
            self._live_votes[hit] += 1  # once per frame and cell
            self._live_dirty[hit] = True

    def live_cells(self, min_weight: float = 20.0, max_cells: int | None = None):
        """Cells that changed since they were last handed out and hold at least `min_weight`
        of stereo (the bins' weights, as :attr:`LacMapEstimate.weight`), at most `max_cells`
        of them (the rest wait for the next call, which goes on in cell order from there).

        The live layer is cheap and approximate: each frame is folded in once, at the pose it
        was added with (a later :meth:`repose` does not move it), heights are weighted means
        (not medians) and a cell is a rock cell when footprints of at least
        ``rock_min_sightings`` frames cover it. It is what an agent writes during the run;
        :meth:`grid` is the map (re-placed frames, medians, fused rocks, fill) for the end.
        Returns ``(i, j, height_m, rock)`` arrays. Cost: O(cells) for the scan."""
        if min_weight < 0 or (max_cells is not None and max_cells < 0):
            raise InputError("live_cells: min_weight and max_cells must be >= 0")
        ready = np.flatnonzero(self._live_dirty & (self._live_w >= max(min_weight, 1e-12)))
        if max_cells is not None and len(ready) > max_cells:
            # round robin: from where the last bounded call stopped, so no cell waits forever
            k = int(np.searchsorted(ready, self._live_cursor))
            ready = np.r_[ready[k:], ready[:k]][: int(max_cells)]
            self._live_cursor = int(ready[-1]) + 1 if len(ready) else 0
        self._live_dirty[ready] = False
        n = self.config.cells
        h = self._live_wz[ready] / self._live_w[ready]
        rock = self._live_votes[ready] >= min(
            self.config.rock_min_sightings, self.config.small_rock_min_sightings
        )
        return ready // n, ready % n, h, rock

    # ------------------------------------------------------------------ summaries
    def _summarise(self, points, frame_id) -> np.ndarray:
        cfg = self.config
        if points is None:
            return np.zeros((0, 4), np.float32)
        P = np.asarray(points, dtype=np.float32)
        if P.ndim < 1 or P.shape[-1] != 3:
            raise InputError(
                f"frame {frame_id}: points_rover must be (..., 3), got shape {P.shape}"
            )
        P = P.reshape(-1, 3)
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        with np.errstate(invalid="ignore"):
            r = np.hypot(x, y)
            ok = (r >= cfg.min_range_m) & (r <= cfg.max_range_m) & (np.abs(z) <= cfg.max_abs_z_m)
        if not np.any(ok):
            return np.zeros((0, 4), np.float32)
        x, y, z = x[ok], y[ok], z[ok]
        ix = np.floor(x / cfg.bin_m).astype(np.int64) + self._half
        iy = np.floor(y / cfg.bin_m).astype(np.int64) + self._half
        key = ix * self._side + iy
        m = self._side * self._side
        cnt = np.bincount(key, minlength=m)
        used = np.flatnonzero(cnt)
        c = cnt[used].astype(np.float64)
        mx = np.bincount(key, x, minlength=m)[used] / c
        my = np.bincount(key, y, minlength=m)[used] / c
        mz = np.bincount(key, z, minlength=m)[used] / c
        w = c / (1.0 + (np.hypot(mx, my) / cfg.range_scale_m) ** 4)
        return np.column_stack([mx, my, mz, w]).astype(np.float32)

    def _rocks(self, rocks, frame_id) -> np.ndarray:
        cfg = self.config
        if rocks is None:
            return np.zeros((0, 4), np.float32)
        R = np.asarray(rocks, dtype=float)
        if R.size == 0:
            return np.zeros((0, 4), np.float32)
        if R.ndim != 2 or R.shape[1] not in (3, 4):
            raise InputError(
                f"frame {frame_id}: rocks_rover must be (M, 3) or (M, 4), got shape {R.shape}"
            )
        if R.shape[1] == 3:
            R = np.column_stack([R, np.zeros(len(R))])
        ok = (
            np.all(np.isfinite(R), axis=1)
            & (R[:, 3] >= 0)
            & (np.hypot(R[:, 0], R[:, 1]) <= cfg.rock_max_range_m)
        )
        return R[ok].astype(np.float32)

    def _freeze(self, frame_id, fr: _Frame) -> None:
        """Fold a frame into the frozen sums at its current pose (it can no longer move)."""
        c, z, w = self._place_bins(fr)
        n = self.config.cells
        self._frozen_w += np.bincount(c, w, minlength=n * n).reshape(n, n)
        self._frozen_wz += np.bincount(c, w * z, minlength=n * n).reshape(n, n)
        self._frozen_wz2 += np.bincount(c, w * z * z, minlength=n * n).reshape(n, n)
        D = self._rock_rows(fr)
        if len(D):
            self._frozen_rocks = np.concatenate([self._frozen_rocks, D])
        self.frozen_frames += 1
        log.debug("mapper: froze frame %s (%d bins)", frame_id, len(fr.bins))

    # ------------------------------------------------------------------ placing
    def _keep_outside_discs(self, xy: np.ndarray) -> np.ndarray:
        keep = np.ones(len(xy), dtype=bool)
        for cx, cy, r in self._discs:
            keep &= (xy[:, 0] - cx) ** 2 + (xy[:, 1] - cy) ** 2 > r * r
        return keep

    def _place_bins(self, fr: _Frame):
        """Cell ids (flat), heights and weights of a frame's bins at its pose (inside the map)."""
        cfg = self.config
        if len(fr.bins) == 0:
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
        T = fr.T_map_rover
        P = fr.bins[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        i = np.floor((P[:, 0] - self._lo[0]) / cfg.cell_m).astype(np.int64)
        j = np.floor((P[:, 1] - self._lo[1]) / cfg.cell_m).astype(np.int64)
        n = cfg.cells
        ok = (i >= 0) & (i < n) & (j >= 0) & (j < n)
        if self._discs:
            ok &= self._keep_outside_discs(P[:, :2])
        return (i * n + j)[ok], P[ok, 2], fr.bins[ok, 3].astype(np.float64)

    def _place_rocks(self, fr: _Frame):
        """Map-frame centres (x, y), radii, viewing directions (unit x, y, from the rover
        towards the rock) and ranges (horizontal, rover frame) of a frame's detections at its
        pose (outside the excluded discs)."""
        if len(fr.rocks) == 0:
            return np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2)), np.zeros(0)
        T = fr.T_map_rover
        p = fr.rocks[:, :3].astype(np.float64)
        P = p @ T[:3, :3].T + T[:3, 3]
        keep = self._keep_outside_discs(P[:, :2]) if self._discs else np.ones(len(P), bool)
        d = np.column_stack([p[:, :2], np.zeros(len(p))]) @ T[:3, :3].T
        d = d[:, :2] / np.maximum(np.linalg.norm(d[:, :2], axis=1, keepdims=True), 1e-9)
        rng = np.hypot(p[:, 0], p[:, 1])
        return P[keep, :2], fr.rocks[keep, 3].astype(np.float64), d[keep], rng[keep]

    def _rock_rows(self, fr: _Frame) -> np.ndarray:
        """A frame's placed detections as rows of x, y, radius, seq, view x, view y, range."""
        xy, r, view, rng = self._place_rocks(fr)
        return np.column_stack([xy, r, np.full(len(r), fr.seq), view, rng])

    # ------------------------------------------------------------------ the map
    def grid(self) -> LacMapEstimate:
        """The LAC map of everything added so far, every frame at its current pose."""
        cfg = self.config
        n = cfg.cells
        cs, zs, ws = [], [], []
        for fr in self._frames.values():
            c, z, w = self._place_bins(fr)
            cs.append(c)
            zs.append(z)
            ws.append(w)
        fz = np.flatnonzero(self._frozen_w.reshape(-1) > 0)
        if len(fz):  # frozen frames: one weighted mean per cell
            fw = self._frozen_w.reshape(-1)[fz]
            cs.append(fz)
            zs.append(self._frozen_wz.reshape(-1)[fz] / fw)
            ws.append(fw)
        c = np.concatenate(cs) if cs else np.zeros(0, np.int64)
        z = np.concatenate(zs) if zs else np.zeros(0)
        w = np.concatenate(ws) if ws else np.zeros(0)
        height = np.full(n * n, np.nan)
        sigma = np.full(n * n, np.nan)
        weight = np.bincount(c, w, minlength=n * n) if len(c) else np.zeros(n * n)
        if len(c):
            med = _weighted_median(c, z, w, n * n)
            height[:] = med
            spread2 = np.bincount(c, w * (z - med[c]) ** 2, minlength=n * n)
            fzw2 = self._frozen_wz2.reshape(-1)
            if len(fz):  # the frozen cells' own spread about their mean
                mean_f = self._frozen_wz.reshape(-1)[fz] / self._frozen_w.reshape(-1)[fz]
                spread2[fz] += np.maximum(
                    fzw2[fz] - self._frozen_w.reshape(-1)[fz] * mean_f**2, 0.0
                )
            with np.errstate(invalid="ignore", divide="ignore"):
                sigma = np.sqrt(spread2 / weight)
        observed = (weight > 0).reshape(n, n)
        height = height.reshape(n, n)
        sigma = np.where(observed, sigma.reshape(n, n), np.nan)
        out = self._grid0.copy()
        out[:, :, 2] = np.where(observed, height, UNFILLED)
        out[:, :, 3] = np.where(observed, 0.0, UNFILLED)
        filled_h, dist = _fill(out[:, :, :3], observed, cfg)
        interpolated = np.isfinite(filled_h) & ~observed
        out[:, :, 2] = filled_h
        out[:, :, 3] = np.where(np.isfinite(filled_h), 0.0, UNFILLED)
        rocks = self._fused_rocks()
        prob = None
        if cfg.rock_cells == "model":
            cells, X = self.rock_cell_features(filled_h, sigma, weight.reshape(n, n))
            prob = np.zeros(n * n)
            if len(cells):
                prob[cells] = rock_cell_probability(X)
            prob = prob.reshape(n, n)
            flags = prob >= cfg.rock_cell_min_p
        else:
            flags = _rock_cells(rocks, self._grid0, cfg.cell_m)
        if cfg.rock_bump_m is not None and observed.any():
            flags |= self._bumps(filled_h, observed)
        out[:, :, 3] = np.where(flags, 1.0, out[:, :, 3])
        # a flagged cell with no height yet: its height from its neighbourhood is unknown, but
        # a flag without a height scores as filled only when both are set; give it the nearest
        out[:, :, 2] = np.where(
            flags & ~np.isfinite(out[:, :, 2]), _nearest_fill(out[:, :, 2]), out[:, :, 2]
        )
        return LacMapEstimate(
            out, observed, interpolated, sigma, weight.reshape(n, n), dist, rocks, prob
        )

    def rock_cell_features(self, height, height_sigma, weight):
        """The per-cell rock model's inputs (:data:`ROCK_CELL_FEATURES`): the cells within
        ``rock_cell_reach_m`` of a detection cluster's footprint (any ray point; every cluster,
        mapped or not, :meth:`_clusters`), each described by the cluster that covers it best (a
        mapped one first, then the one reaching furthest over it) and by its own stereo:
        `height` (N, N; unfilled cells take the nearest filled one's), `height_sigma`,
        `weight` as :class:`LacMapEstimate` has them. Returns flat cell ids (C,) and (C, F)."""
        from scipy import ndimage

        cfg = self.config
        n = cfg.cells
        cl = self._clusters()
        xs, ys = self._grid0[:, 0, 0], self._grid0[0, :, 1]
        off = LAC_RAY_OFFSETS * cfg.cell_m
        lo_x, lo_y = xs[0] - cfg.cell_m / 2, ys[0] - cfg.cell_m / 2
        ids, qs, ds = [], [], []
        for q in range(len(cl["x"])):
            x, y, reach = cl["x"][q], cl["y"][q], cl["fp"][q] + cfg.rock_cell_reach_m
            i0 = max(int(math.floor((x - reach - lo_x) / cfg.cell_m)), 0)
            i1 = min(int(math.floor((x + reach - lo_x) / cfg.cell_m)) + 1, n)
            j0 = max(int(math.floor((y - reach - lo_y) / cfg.cell_m)), 0)
            j1 = min(int(math.floor((y + reach - lo_y) / cfg.cell_m)) + 1, n)
            if i1 <= i0 or j1 <= j0:
                continue
            dx = np.min(np.abs(xs[i0:i1, None] + off[None, :] - x), axis=1)
            dy = np.min(np.abs(ys[j0:j1, None] + off[None, :] - y), axis=1)
            d = np.sqrt(dx[:, None] ** 2 + dy[None, :] ** 2)
            a, b = np.nonzero(d <= reach)
            ids.append((i0 + a) * n + (j0 + b))
            qs.append(np.full(len(a), q))
            ds.append(d[a, b])
        if not ids:
            return np.zeros(0, np.int64), np.zeros((0, len(ROCK_CELL_FEATURES)))
        cid, q, d = np.concatenate(ids), np.concatenate(qs), np.concatenate(ds)
        margin = d - cl["fp"][q]
        # per cell: a mapped cluster first, then the smallest margin, then the first cluster
        order = np.lexsort((q, margin, ~cl["kept"][q], cid))
        cid, q, d, margin = cid[order], q[order], d[order], margin[order]
        cells, first, ncov = np.unique(cid, return_index=True, return_counts=True)
        q, d, margin = q[first], d[first], margin[first]
        h = np.where(np.isfinite(height), height, _nearest_fill(height))
        h = np.where(np.isfinite(h), h, 0.0)
        k = max(3, int(round(1.05 / cfg.cell_m)) | 1)
        bump = (h - ndimage.percentile_filter(h, 30, size=k, mode="nearest")).reshape(-1)
        hsig = np.nan_to_num(np.asarray(height_sigma, float).reshape(-1), nan=0.0)
        logw = np.log1p(np.asarray(weight, float).reshape(-1))
        r = cl["r"][q]
        X = np.column_stack(
            [
                margin,
                d / np.maximum(r, 0.01),
                np.log(np.maximum(r, 0.01)),
                np.log(cl["s"][q]),
                cl["kept"][q].astype(float),
                cl["rspread"][q],
                cl["cspread"][q],
                cl["rng_med"][q],
                cl["rng_min"][q],
                ncov.astype(float),
                bump[cells],
                hsig[cells],
                logw[cells],
            ]
        )
        X[~np.isfinite(X)] = 0.0
        return cells.astype(np.int64), X

    def _bumps(self, h: np.ndarray, observed: np.ndarray) -> np.ndarray:
        """Observed cells at least ``rock_bump_m`` above their local ground (a low percentile
        of the heights around them): rocks too small or too flat for the detector."""
        from scipy import ndimage

        cfg = self.config
        k = max(3, int(round(cfg.rock_ground_window_m / cfg.cell_m)) | 1)
        hh = np.where(np.isfinite(h), h, _nearest_fill(h))
        if not np.all(np.isfinite(hh)):
            return np.zeros(h.shape, bool)
        ground = ndimage.percentile_filter(hh, cfg.rock_ground_quantile, size=k, mode="nearest")
        return observed & (hh - ground >= cfg.rock_bump_m)

    def _fused_rocks(self) -> np.ndarray:
        """Detections of all frames merged into rocks: (K, 3) x, y, footprint radius of the
        rocks detected often enough (:meth:`_clusters`' ``kept``)."""
        cl = self._clusters()
        k = cl["kept"]
        return np.column_stack([cl["x"][k], cl["y"][k], cl["fp"][k]]).reshape(-1, 3)

    def _clusters(self) -> dict:
        """Detections of all frames merged into clusters (those of different frames within
        ``rock_merge_m`` of each other, chained). Per cluster (arrays of length K): ``x``, ``y``
        (the members' median, large rocks recentred), ``r`` (median radius), ``s`` (distinct
        frames), ``kept`` (enough sightings: a mapped rock), ``fp`` (footprint radius),
        ``rspread`` (the radii's interquartile range over the median), ``cspread`` (the
        members' median distance from their median centre, m), ``rng_med`` / ``rng_min`` (the
        detections' median / smallest range, m)."""
        cfg = self.config
        parts = [self._frozen_rocks]
        for fr in self._frames.values():
            if len(fr.rocks):
                parts.append(self._rock_rows(fr))
        D = np.concatenate(parts)
        names = ("x", "y", "r", "s", "fp", "rspread", "cspread", "rng_med", "rng_min")
        if len(D) == 0:
            out = {k: np.zeros(0) for k in names}
            out["kept"] = np.zeros(0, bool)
            return out
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        pairs = (
            cKDTree(D[:, :2]).query_pairs(cfg.rock_merge_m, output_type="ndarray")
            if cfg.rock_merge_m > 0
            else None
        )
        if pairs is None or len(pairs) == 0:
            labels = np.arange(len(D))
            k = len(D)
        else:
            adj = coo_matrix(
                (np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(D), len(D))
            )
            k, labels = connected_components(adj, directed=False)
        # sightings: distinct frames per rock
        seen = np.unique(np.column_stack([labels, D[:, 3]]), axis=0)
        sightings = np.bincount(seen[:, 0].astype(np.int64), minlength=k)
        order = np.argsort(labels, kind="stable")
        starts = np.searchsorted(labels[order], np.arange(k))
        ends = np.searchsorted(labels[order], np.arange(k), side="right")
        rows = np.zeros((k, len(names)))
        kept = np.zeros(k, bool)
        for q in range(k):
            g = D[order[starts[q] : ends[q]]]
            r = float(np.median(g[:, 2]))
            x0, y0 = float(np.median(g[:, 0])), float(np.median(g[:, 1]))
            x, y = x0, y0
            if cfg.rock_recentre_min_m is not None and r >= cfg.rock_recentre_min_m:
                # away from the rover along the mean of the sightings' unit viewing directions
                # (its length < 1 where they differ: seen from all sides, the median is centred)
                v = g[:, 4:6].mean(axis=0)
                x += cfg.rock_recentre_scale * r * float(v[0])
                y += cfg.rock_recentre_scale * r * float(v[1])
            if r < cfg.small_rock_m:
                kept[q] = sightings[q] >= cfg.small_rock_min_sightings
                r_fp = r + cfg.small_rock_margin_m
            else:
                kept[q] = sightings[q] >= cfg.rock_min_sightings
                r_fp = cfg.rock_radius_scale * r + cfg.rock_radius_margin_m
            q25, q75 = np.percentile(g[:, 2], [25, 75])
            rng = g[:, 6]
            rng_ok = rng[np.isfinite(rng)]
            rows[q] = (
                x,
                y,
                r,
                sightings[q],
                max(r_fp, 0.0),
                (q75 - q25) / max(r, 1e-3),
                float(np.median(np.hypot(g[:, 0] - x0, g[:, 1] - y0))),
                float(np.median(rng_ok)) if len(rng_ok) else np.nan,
                float(np.min(rng_ok)) if len(rng_ok) else np.nan,
            )
        out = {n: rows[:, j] for j, n in enumerate(names)}
        out["kept"] = kept
        return out


@lru_cache(maxsize=1)
def _rock_cell_model(path: str):
    """The per-cell rock model's arrays (``ROCK_CELL_MODEL_PATH``)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            m = {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise ConfigError(f"the per-cell rock model {path} cannot be read: {e}") from e
    if tuple(str(f) for f in m["features"]) != ROCK_CELL_FEATURES:
        raise ConfigError(f"{path}: its features are not ROCK_CELL_FEATURES")
    return m


def rock_cell_probability(X: np.ndarray, path=None) -> np.ndarray:
    """P(rock) of cells from their :data:`ROCK_CELL_FEATURES` rows (C, F): boosted trees (each
    node: go left when the feature is at most the threshold), summed onto the baseline
    log-odds, through the logistic function."""
    m = _rock_cell_model(str(path or ROCK_CELL_MODEL_PATH))
    X = np.asarray(X, float)
    feat, thr, left, right, leaf, value = (
        m[k] for k in ("feature", "threshold", "left", "right", "is_leaf", "value")
    )
    raw = np.full(len(X), float(m["baseline"]))
    rows = np.arange(len(X))
    for t in range(feat.shape[0]):
        node = np.zeros(len(X), np.int64)
        for _ in range(int(m["max_depth"]) + 1):
            f = feat[t, node]
            go_left = X[rows, f] <= thr[t, node]
            node = np.where(leaf[t, node], node, np.where(go_left, left[t, node], right[t, node]))
        raw += value[t, node]
    return 1.0 / (1.0 + np.exp(-raw))


def _weighted_median(c: np.ndarray, z: np.ndarray, w: np.ndarray, size: int) -> np.ndarray:
    """Per group id `c` (0..size-1), the weighted median of `z` (NaN for empty groups)."""
    order = np.lexsort((z, c))
    cs, zs, ws = c[order], z[order], w[order]
    cw = np.cumsum(ws)
    groups, start = np.unique(cs, return_index=True)
    end = np.r_[start[1:], len(cs)]
    base = np.where(start > 0, cw[np.maximum(start - 1, 0)], 0.0)
    total = cw[end - 1] - base
    idx = np.searchsorted(cw, base + 0.5 * total, side="left")
    idx = np.clip(idx, start, end - 1)
    out = np.full(size, np.nan)
    out[groups] = zs[idx]
    return out


def _nearest_fill(h: np.ndarray) -> np.ndarray:
    """`h` with every non-finite cell given the nearest finite cell's value (all -inf if none)."""
    from scipy import ndimage

    ok = np.isfinite(h)
    if not np.any(ok):
        return h
    _, (ii, jj) = ndimage.distance_transform_edt(~ok, return_indices=True)
    return h[ii, jj]


def _fill(xyh: np.ndarray, observed: np.ndarray, cfg: LacMapperConfig):
    """Heights with the unseen cells filled by `cfg.fill`, and each cell's distance to the
    nearest observed cell (metres)."""
    from scipy import ndimage

    h = xyh[:, :, 2].copy()
    n = h.shape[0]
    if not np.any(observed):
        return h, np.full((n, n), np.inf)
    dist = ndimage.distance_transform_edt(~observed) * cfg.cell_m
    if cfg.fill == "none" or np.all(observed):
        return h, dist
    # normalised convolution at growing scales: each unseen cell takes the Gaussian-weighted
    # mean of the observed heights at the smallest scale (1, 2, 4, ... cells) that reaches any
    want = ~observed
    if cfg.fill == "near":
        want &= dist <= cfg.fill_max_m
    m = observed.astype(float)
    hz = np.where(observed, h, 0.0)
    todo = want.copy()
    sigma = 1.0
    while np.any(todo) and sigma <= 2 * n:
        den = ndimage.gaussian_filter(m, sigma, mode="constant", truncate=3.0)
        num = ndimage.gaussian_filter(hz, sigma, mode="constant", truncate=3.0)
        ok = todo & (den > 1e-3)
        h[ok] = num[ok] / den[ok]
        todo &= ~ok
        sigma *= 2.0
    if np.any(todo):
        _, (ii, jj) = ndimage.distance_transform_edt(~observed, return_indices=True)
        h[todo] = h[ii, jj][todo]
    return h, dist


def _rock_cells(rocks: np.ndarray, grid: np.ndarray, cell_m: float) -> np.ndarray:
    """(N, N) bool: cells with any of their 16 LAC ray points within a rock's footprint."""
    n = grid.shape[0]
    flags = np.zeros((n, n), dtype=bool)
    if len(rocks) == 0:
        return flags
    xs, ys = grid[:, 0, 0], grid[0, :, 1]
    off = LAC_RAY_OFFSETS * cell_m
    lo_x, lo_y = xs[0] - cell_m / 2, ys[0] - cell_m / 2
    for x, y, r in rocks:
        r = max(float(r), 0.0)
        i0 = max(int(math.floor((x - r - lo_x) / cell_m)), 0)
        i1 = min(int(math.floor((x + r - lo_x) / cell_m)) + 1, n)
        j0 = max(int(math.floor((y - r - lo_y) / cell_m)), 0)
        j1 = min(int(math.floor((y + r - lo_y) / cell_m)) + 1, n)
        if i1 <= i0 or j1 <= j0:
            continue
        # nearest ray point of each cell to the centre, per axis (the lattice is separable)
        dx = np.min(np.abs(xs[i0:i1, None] + off[None, :] - x), axis=1)
        dy = np.min(np.abs(ys[j0:j1, None] + off[None, :] - y), axis=1)
        hit = dx[:, None] ** 2 + dy[None, :] ** 2 <= r * r
        if (
            r == 0 or not hit.any()
        ):  # a point rock or one between the rays: the cell holding its centre
            i, j = int((x - lo_x) // cell_m), int((y - lo_y) // cell_m)
            if 0 <= i < n and 0 <= j < n:
                flags[i, j] = True
        flags[i0:i1, j0:j1] |= hit
    return flags


def write_geometric_map(grid, geometric_map) -> int:
    """Write a map into the leaderboard's ``GeometricMap`` (any object with
    ``set_cell_height(i, j, h)`` and ``set_cell_rock(i, j, flag)``; the agent's
    ``self.get_geometric_map()``). `grid` is a :class:`LacMapEstimate` or an (N, N, 4) LAC array
    in the same cell layout (x with the first index). Unfilled cells (-inf) are left as they
    are. Returns the number of cells written (height and flag both set).

    Raises InputError when `grid` is not an (N, N, 4) array, or when the target map reports a
    different cell count or different cell centres (``get_cell_number()`` /
    ``get_map_array()``, where it has them)."""
    arr = grid.array if isinstance(grid, LacMapEstimate) else np.asarray(grid, dtype=float)
    if arr.ndim != 3 or arr.shape[2] != 4 or arr.shape[0] != arr.shape[1]:
        raise InputError(f"expected an (N, N, 4) LAC map, got shape {arr.shape}")
    _check_target(geometric_map, arr)
    written = 0
    h, f = arr[:, :, 2], arr[:, :, 3]
    for i, j in zip(*np.nonzero(np.isfinite(h) | np.isfinite(f))):
        i, j = int(i), int(j)
        both = True
        if np.isfinite(h[i, j]):
            geometric_map.set_cell_height(i, j, float(h[i, j]))
        else:
            both = False
        if np.isfinite(f[i, j]):
            geometric_map.set_cell_rock(i, j, bool(f[i, j] >= 0.5))
        else:
            both = False
        written += both
    return written


def _check_target(geometric_map, arr: np.ndarray) -> None:
    """InputError unless `geometric_map` has the setters and, where it says, `arr`'s cells."""
    for name in ("set_cell_height", "set_cell_rock"):
        if not callable(getattr(geometric_map, name, None)):
            raise InputError(f"the geometric map ({type(geometric_map).__name__}) has no {name}()")
    n = arr.shape[0]
    get_n = getattr(geometric_map, "get_cell_number", None)
    if callable(get_n) and int(get_n()) != n:
        raise InputError(f"the geometric map has {int(get_n())} cells a side, the mapper's {n}")
    get_arr = getattr(geometric_map, "get_map_array", None)
    if callable(get_arr):
        target = np.asarray(get_arr(), dtype=float)
        if (
            target.shape[:2] == arr.shape[:2]
            and np.max(np.abs(target[:, :, :2] - arr[:, :, :2])) > 1e-6
        ):
            raise InputError(
                "the geometric map's cell centres differ from the mapper's: is the mapper's "
                "centre_xy / size_m the map's?"
            )


class LacMapWriter:
    """Writes a :class:`LacMapper`'s map into the leaderboard's ``GeometricMap`` during the run.

    :meth:`step` (call it every tick) writes the cells of the mapper's live layer
    (:meth:`LacMapper.live_cells`) that became confident (at least `min_weight` of stereo) or
    changed since, at most `max_cells_per_step` a call, so a tick's cost stays bounded;
    :meth:`finish` (in ``finalize``) writes the whole map of :meth:`LacMapper.grid`
    (re-placed frames, medians, fused rocks, interpolated cells) over it.

    The target is checked once here (setters, cell count, cell centres: InputError)."""

    def __init__(
        self,
        mapper: LacMapper,
        geometric_map,
        min_weight: float = 20.0,
        max_cells_per_step: int = 400,
    ):
        if not isinstance(mapper, LacMapper):
            raise InputError(f"LacMapWriter needs a LacMapper, got {type(mapper).__name__}")
        if not (min_weight >= 0 and max_cells_per_step >= 1):
            raise InputError("LacMapWriter: min_weight must be >= 0 and max_cells_per_step >= 1")
        _check_target(geometric_map, mapper._grid0)
        self.mapper, self.geometric_map = mapper, geometric_map
        self.min_weight, self.max_cells_per_step = float(min_weight), int(max_cells_per_step)
        n = mapper.config.cells
        self._written = np.zeros((n, n), bool)

    @property
    def cells_written(self) -> int:
        """Distinct cells written so far (height and flag)."""
        return int(self._written.sum())

    def step(self) -> int:
        """Write up to ``max_cells_per_step`` confident cells; returns how many."""
        i, j, h, rock = self.mapper.live_cells(self.min_weight, self.max_cells_per_step)
        gm = self.geometric_map
        for a, b, z, r in zip(i.tolist(), j.tolist(), h.tolist(), rock.tolist()):
            gm.set_cell_height(a, b, z)
            gm.set_cell_rock(a, b, r)
        self._written[i, j] = True
        return len(i)

    def finish(self) -> int:
        """Write the mapper's whole map (:func:`write_geometric_map` of ``grid()``); returns
        the cells written."""
        est = self.mapper.grid()
        k = write_geometric_map(est, self.geometric_map)
        self._written |= est.filled & np.isfinite(est.array[:, :, 3])
        return k


def save_lac_map(estimate: LacMapEstimate, path) -> tuple:
    """Write the map as ``PATH`` (``np.save`` of the (N, N, 4) LAC array; -inf where
    unfilled) and its per-cell side data as ``PATH`` with suffix ``.cells.npz``
    (``observed``, ``interpolated``, ``height_sigma_m``, ``weight``, ``fill_distance_m``,
    ``rocks``, and ``rock_probability`` with the per-cell rock model; what ``lunarloc score
    --seen-only`` reads). Returns both paths."""
    from lunarloc.io.outputs import atomic_open

    path = Path(path)
    side = cells_path(path)
    with atomic_open(path, "wb") as fh:
        np.save(fh, estimate.array)
    with atomic_open(side, "wb") as fh:
        np.savez_compressed(
            fh,
            observed=estimate.observed,
            interpolated=estimate.interpolated,
            height_sigma_m=estimate.height_sigma_m,
            weight=estimate.weight,
            fill_distance_m=estimate.fill_distance_m,
            rocks=estimate.rocks,
            **(
                {"rock_probability": estimate.rock_probability}
                if estimate.rock_probability is not None
                else {}
            ),
        )
    return path, side


def cells_path(path):
    """The side file of a map written by :func:`save_lac_map`: ``map.npy`` -> ``map.cells.npz``."""
    from pathlib import Path

    path = Path(path)
    return path.with_name(path.stem + ".cells.npz")


def load_observed_cells(path, shape: tuple[int, int]) -> np.ndarray:
    """The ``observed`` mask of a map's side file (:func:`cells_path`); FileFormatError when it
    is missing, unreadable or not of `shape`."""
    from lunarloc.core.errors import FileFormatError

    side = cells_path(path)
    if not side.is_file():
        raise FileFormatError(
            f"{side}: no such file (the cells the cameras saw are written next to a map by "
            f"`lunarloc run --lac-map`)"
        )
    try:
        with np.load(side, allow_pickle=False) as z:
            obs = np.asarray(z["observed"])
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise FileFormatError(f"{side}: not a map's cell file ({exc})") from None
    if obs.shape != tuple(shape) or obs.dtype != bool:
        raise FileFormatError(
            f"{side}: observed mask of shape {obs.shape} and dtype {obs.dtype}, expected bool "
            f"{tuple(shape)}"
        )
    return obs


def frame_inputs(fd, detector=None, images=None) -> tuple[np.ndarray | None, np.ndarray]:
    """What :meth:`LacMapper.add_frame` takes from one frame of the detector
    (:class:`~lunarloc.perception.detector.FrameDetections`, detected with ``keep_depth=True``):
    the rover-frame stereo points of its pairs (each pair's ``height.points_rover``; a pair
    without one gets it from ``detector.height_map`` when `detector` and its `images` are
    given) and its detections as (M, 4) rover-frame centres and radii. Points None when no
    pair has any."""
    pts = []
    for pair in fd.pairs:
        hm = getattr(pair, "height", None)
        if (
            hm is None
            and detector is not None
            and images
            and getattr(pair, "T_rover_optical", None) is not None
        ):
            right = next((b for a, b in detector.config.pairs if a == pair.camera), None)
            if images.get(pair.camera) is not None and images.get(right) is not None:
                hm = detector.height_map(images[pair.camera], images[right], pair.T_rover_optical)
        if hm is not None:
            P = np.asarray(hm.points_rover, np.float32).reshape(-1, 3)
            T_level_rover = getattr(hm, "T_level_rover", None)
            if (
                T_level_rover is not None
            ):  # a levelled height map (DetectorConfig.level_from_stereo): back to the rover frame
                P = P @ np.asarray(T_level_rover, np.float32)[:3, :3]  # p_rover = R^T p_level
            pts.append(P)
    rocks = np.array([[*d.p_rover, d.radius_m] for d in fd.detections], float).reshape(-1, 4)
    return (np.concatenate(pts) if pts else None), rocks
