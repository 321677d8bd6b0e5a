"""Maps from above: the LAC geometric map and rock catalogues, as reference landmark maps;
the LAC map written from a site or from detections; the LAC's map scores.

The LAC geometric map
---------------------
A ``(N, N, 4)`` float array (the LAC API's ``get_map_array()``, saved with ``np.save``):
cell ``[i, j]`` holds ``x, y, height, rock flag`` of the cell centre (metres; flag 1 for a
rock cell, 0 otherwise). The LAC map is 27 m x 27 m in 180 x 180 cells of 0.15 m centred
on the site origin; here ``x`` grows with ``i`` and ``y`` with ``j`` (the loader reads the
stored ``x, y`` values, so any layout with regular spacing loads).

Rocks from the grid (the documented grouping rule, :func:`grid_landmarks`): rock cells
(flag >= 0.5) that touch, including diagonally (8-connectivity), form one rock. Its
landmark is at the mean of its cell centres; its ground level is the mean height of the
non-rock cells that border it (the rock's own mean height if none do); its landmark
height is halfway between that ground level and the mean height of its cells (a camera
sees the part above ground, and a vision detection lands near that part's middle); its
size is the diameter of the disc of the same area. Uncertainty: horizontal
``cell / sqrt(12 n)`` (quantisation of the centroid of n cells), vertical a quarter of the
rock's visible height combined with 1 cm.

A map whose heights are all equal (a rock map without heights) gives landmarks without
heights (:data:`NO_HEIGHT_SIGMA_M`): the localizer then associates in 2D + yaw.

Rock catalogues
---------------
CSV with a header naming ``x, y, radius`` and optionally ``z`` and ``sigma_m`` (the
horizontal 1-sigma of each position), any order, one rock per row. Without ``z`` the
heights come from a DEM (a LAC geometric map, nearest cell) when one is given, or the
rocks have no heights (2D + yaw association).
"""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lunarloc.core.errors import FileFormatError, InputError
from lunarloc.io.maps import NO_HEIGHT_SIGMA_M, LandmarkMap

log = logging.getLogger(__name__)

__all__ = [
    "LAC_CELL_M",
    "LAC_CELLS",
    "LAC_RAY_OFFSETS",
    "LAC_MISSION_S",
    "LAC_POINTS",
    "UNFILLED",
    "NO_HEIGHT_SIGMA_M",
    "OverheadConfig",
    "validate_lac_grid",
    "load_lac_grid",
    "grid_landmarks",
    "has_heights",
    "load_rock_catalogue",
    "is_rock_catalogue",
    "empty_lac_grid",
    "site_geometric_map",
    "write_site_geometric_map",
    "landmarks_to_lac_grid",
    "score_geometric_map",
]

LAC_CELL_M = 0.15
LAC_CELLS = 180
#: the LAC's value of a height or rock flag the agent has not completed
UNFILLED = -np.inf
#: the LAC's mission time limit (s): the productivity rate is its cells over this time
LAC_MISSION_S = 24 * 3600.0
#: the LAC's points: geometric map, rock map, mapping productivity, no fiducials
LAC_POINTS = {
    "geometric_map": 300.0,
    "rocks_map": 300.0,
    "mapping_productivity": 250.0,
    "localization": 150.0,
}
_CATALOGUE_COLUMNS = ("x", "y", "z", "radius", "sigma_m")
_HEIGHT_SIGMA_M = 0.01  # a grid rock's height: not quantised, but its cells' heights vary


@dataclass(frozen=True)
class OverheadConfig:
    """How rocks are read from an overhead map."""

    rock_flag_threshold: float = 0.5  # a cell is a rock cell when its flag is at least this
    min_cells: int = 1  # rocks of fewer cells are dropped
    min_radius_m: float = 0.0  # catalogue rocks smaller than this are dropped

    def __post_init__(self) -> None:
        if self.min_cells < 1:
            raise InputError("min_cells must be >= 1")
        if self.min_radius_m < 0:
            raise InputError("min_radius_m must be >= 0")


# --------------------------------------------------------------------------- LAC grid


def validate_lac_grid(
    grid, name: str = "geometric map", allow_unfilled: bool = False
) -> np.ndarray:
    """Check a LAC geometric map array and return it as float64 (N, M, 4).

    allow_unfilled : accept the LAC's "not completed" value (-inf) as a height or rock
        flag (an agent's map; the scorer counts such cells as failures).
    Raises InputError for a wrong shape or dtype, non-finite coordinates or heights,
    irregular cell spacing, or rock flags outside [0, 1]."""
    arr = np.asarray(grid)
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise InputError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
    if arr.ndim != 3 or arr.shape[2] != 4 or arr.shape[0] < 2 or arr.shape[1] < 2:
        raise InputError(
            f"{name}: expected shape (N, N, 4) with cells x, y, height, rock flag (LAC: (180, 180, "
            f"4)); got {arr.shape}"
        )
    arr = arr.astype(np.float64)
    for k, what in ((0, "x"), (1, "y"), (2, "height"), (3, "rock flag")):
        bad = ~np.isfinite(arr[:, :, k])
        if allow_unfilled and k >= 2:
            bad &= ~(arr[:, :, k] == UNFILLED)
        if np.any(bad):
            i, j = np.argwhere(bad)[0]
            raise InputError(
                f"{name}: {int(bad.sum())} cell(s) with a non-finite {what} (first: cell [{i}, "
                f"{j}])"
            )
    flag = arr[:, :, 3]
    flag = flag[flag != UNFILLED] if allow_unfilled else flag
    if np.any(flag < 0) or np.any(flag > 1):
        raise InputError(
            f"{name}: rock flags must lie in [0, 1] (got {flag.min():g} .. {flag.max():g})"
        )
    cell = _cell_size(arr)
    if not cell > 0:
        raise InputError(f"{name}: cell centres do not form a regular grid")
    return arr


def _cell_size(grid: np.ndarray) -> float:
    """Cell spacing (m) from the stored centres; NaN when irregular."""
    dx = np.diff(grid[:, :, 0], axis=0)
    dy = np.diff(grid[:, :, 1], axis=1)
    if dx.size == 0 or dy.size == 0:
        return float("nan")
    cx, cy = float(np.median(np.abs(dx))), float(np.median(np.abs(dy)))
    if cx <= 0 or abs(cx - cy) > 1e-6 * max(cx, 1.0) or np.ptp(dx) > 1e-6 or np.ptp(dy) > 1e-6:
        return float("nan")
    return cx


def load_lac_grid(path: str | Path, allow_unfilled: bool = False) -> np.ndarray:
    """Read a LAC geometric map saved with ``np.save`` (validated; see module docstring;
    `allow_unfilled`: see :func:`validate_lac_grid`)."""
    from lunarloc.io.inputs import check_input_file

    path = check_input_file(path, None, "LAC geometric map")
    _check_npy_header(path)  # shape, dtype and size before anything is allocated
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise FileFormatError(f"{path}: not a NumPy .npy array ({exc})") from None
    if not isinstance(arr, np.ndarray):
        raise FileFormatError(f"{path}: expected one array (np.save), got an archive of several")
    return validate_lac_grid(arr, str(path), allow_unfilled)


#: the largest grid side read (cells); the LAC map is 180
MAX_GRID_CELLS = 4096


def _check_npy_header(path: Path) -> None:
    """Refuse a .npy whose header is not an (N, N, 4) array of numbers, is over
    MAX_GRID_CELLS a side, or declares more data than the file holds."""
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
            else:
                shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
            header_end = fh.tell()
    except (OSError, ValueError, EOFError) as exc:
        raise FileFormatError(f"{path}: not a NumPy .npy array ({exc})") from None
    if dtype.kind not in "fiub" or len(shape) != 3 or shape[2] != 4 or shape[0] != shape[1]:
        raise FileFormatError(
            f"{path}: expected an (N, N, 4) array of numbers (x, y, height, rock flag), "
            f"got dtype {dtype} of shape {shape}"
        )
    if not 1 <= shape[0] <= MAX_GRID_CELLS:
        raise FileFormatError(
            f"{path}: a {shape[0]} x {shape[1]} grid is outside 1..{MAX_GRID_CELLS} cells a side"
        )
    need = int(np.prod(shape)) * dtype.itemsize
    if path.stat().st_size - header_end < need:
        raise FileFormatError(f"{path}: truncated: the header declares {need} bytes of data")


def has_heights(grid: np.ndarray) -> bool:
    """False when every cell has the same height (a rock map without a DEM)."""
    return bool(np.ptp(grid[:, :, 2]) > 0)


def grid_landmarks(grid, config: OverheadConfig | None = None, frame: str = "lac") -> LandmarkMap:
    """Rocks of a LAC geometric map as landmarks (rule in the module docstring).

    Raises InputError when the map has no rock cells."""
    from scipy import ndimage

    cfg = config or OverheadConfig()
    g = validate_lac_grid(grid)
    cell = _cell_size(g)
    rock = g[:, :, 3] >= cfg.rock_flag_threshold
    if not np.any(rock):
        raise InputError(
            "geometric map has no rock cells (rock flag >= "
            f"{cfg.rock_flag_threshold:g}): nothing to localize against"
        )
    labels, n = ndimage.label(rock, structure=np.ones((3, 3), dtype=bool))
    idx = np.arange(1, n + 1)
    count = ndimage.sum_labels(np.ones_like(labels), labels, idx)
    cx = ndimage.mean(g[:, :, 0], labels, idx)
    cy = ndimage.mean(g[:, :, 1], labels, idx)
    top = ndimage.mean(g[:, :, 2], labels, idx)
    # ground level: non-rock cells within one cell of the rock
    ring = ndimage.grey_dilation(labels, footprint=np.ones((3, 3), dtype=bool)) * (~rock)
    ring_count = ndimage.sum_labels(np.ones_like(ring), ring, idx)
    ring_h = ndimage.sum_labels(g[:, :, 2], ring, idx)
    ground = np.where(ring_count > 0, ring_h / np.maximum(ring_count, 1), top)
    keep = count >= cfg.min_cells
    q = cell / math.sqrt(12.0)
    visible = np.maximum(top - ground, 0.0)
    heights = has_heights(g)
    z = (ground + 0.5 * visible) if heights else np.zeros(n)
    sigma_z = (
        np.hypot(0.25 * visible, _HEIGHT_SIGMA_M) if heights else np.full(n, NO_HEIGHT_SIGMA_M)
    )
    size = 2.0 * np.sqrt(count * cell * cell / math.pi)
    log.info(
        "geometric map: %d rock cells in %d rocks (%d kept)", int(rock.sum()), n, int(keep.sum())
    )
    return LandmarkMap(
        np.c_[cx, cy, z][keep],
        sizes=size[keep],
        sightings=count[keep].astype(float),
        frame=frame,
        sigma_xy_m=(q / np.sqrt(count))[keep],
        sigma_z_m=sigma_z[keep],
    )


def _dem_height(grid: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Height of the nearest cell of a LAC grid at each (x, y)."""
    from scipy.spatial import cKDTree

    pts = grid[:, :, :2].reshape(-1, 2)
    _, j = cKDTree(pts).query(np.asarray(xy, float)[:, :2])
    return grid[:, :, 2].reshape(-1)[j]


# --------------------------------------------------------------------------- catalogues


def is_rock_catalogue(path: str | Path) -> bool:
    """True for a CSV whose header names x, y and radius, with only catalogue columns."""
    try:
        with open(path, newline="") as fh:
            head = fh.readline()
    except (OSError, UnicodeDecodeError):
        return False
    cols = [c.strip().lower() for c in head.split(",")]
    return {"x", "y", "radius"} <= set(cols) and set(cols) <= set(_CATALOGUE_COLUMNS)


def load_rock_catalogue(
    path: str | Path, dem=None, config: OverheadConfig | None = None
) -> LandmarkMap:
    """A rock catalogue CSV (``x, y[, z], radius[, sigma_m]``) as a landmark map.

    Without ``z``: heights from `dem` (a LAC geometric map array or a path to one), else
    none (2D + yaw association). Raises FileFormatError naming the file and line for a
    missing column, a bad or non-finite number, a negative radius or sigma."""
    cfg = config or OverheadConfig()
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    with open(path, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip().lower() for h in next(reader)]
        except StopIteration:
            raise FileFormatError(f"{path}: empty file") from None
        missing = [c for c in ("x", "y", "radius") if c not in header]
        if missing:
            raise FileFormatError(
                f"{path}:1: missing column(s) {', '.join(missing)} (catalogue: x, y[, z], radius[, "
                "sigma_m])"
            )
        unknown = [c for c in header if c not in _CATALOGUE_COLUMNS]
        if unknown:
            raise FileFormatError(
                f"{path}:1: unknown column(s) {', '.join(unknown)} (catalogue: x, y[, z], radius[, "
                "sigma_m])"
            )
        col = {c: header.index(c) for c in header}
        lines, rows = [], []
        for row in reader:
            if row and any(v.strip() for v in row):
                lines.append(reader.line_num)
                rows.append(row)
    for line, row in zip(lines, rows):
        if len(row) != len(header):
            raise FileFormatError(f"{path}:{line}: expected {len(header)} fields, got {len(row)}")
    t = np.empty((len(rows), len(header)))
    for r, (line, row) in enumerate(zip(lines, rows)):
        try:
            t[r] = [float(v) for v in row]
        except ValueError as exc:
            raise FileFormatError(f"{path}:{line}: {exc}") from None
    checks = [(~np.isfinite(t).all(axis=1), lambda r: "non-finite value")]
    for name in ("radius", "sigma_m"):
        if name in col:
            checks.append(
                (t[:, col[name]] < 0, lambda r, name=name: f"negative {name} {t[r, col[name]]:g}")
            )
    for bad, message in checks:
        if np.any(bad):
            r = int(np.argmax(bad))
            raise FileFormatError(f"{path}:{lines[r]}: {message(r)}")
    if not rows:
        raise FileFormatError(f"{path}: no rocks")
    t = t[t[:, col["radius"]] >= cfg.min_radius_m]
    xy = t[:, [col["x"], col["y"]]]
    sig_xy = t[:, col["sigma_m"]] if "sigma_m" in col else None
    if "z" in col:
        z, sig_z = t[:, col["z"]], None
    elif dem is not None:
        grid = load_lac_grid(dem) if isinstance(dem, (str, Path)) else validate_lac_grid(dem, "DEM")
        z, sig_z = _dem_height(grid, xy), np.full(len(t), _cell_size(grid) / math.sqrt(12.0))
    else:
        z, sig_z = np.zeros(len(t)), np.full(len(t), NO_HEIGHT_SIGMA_M)
    return LandmarkMap(
        np.c_[xy, z],
        sizes=2.0 * t[:, col["radius"]],
        frame=path.stem,
        sigma_xy_m=sig_xy,
        sigma_z_m=sig_z,
    )


# --------------------------------------------------------------------------- writing LAC maps


def empty_lac_grid(
    size_m: float = LAC_CELL_M * LAC_CELLS, cell_m: float = LAC_CELL_M, centre_xy=(0.0, 0.0)
) -> np.ndarray:
    """A LAC-layout grid (N, N, 4): cell centres in x (first index) and y (second), heights
    and rock flags zero."""
    n = int(round(size_m / cell_m))
    if n < 2:
        raise InputError(
            f"a grid of {size_m} m in {cell_m} m cells has fewer than 2 cells per side"
        )
    c = (np.arange(n) - (n - 1) / 2.0) * cell_m
    gx, gy = np.meshgrid(c + centre_xy[0], c + centre_xy[1], indexing="ij")
    out = np.zeros((n, n, 4))
    out[:, :, 0], out[:, :, 1] = gx, gy
    return out


#: the LAC's ray lattice inside a cell: 4 x 4 downward rays at these offsets from the
#: centre, in cells (3.75 cm apart in a 0.15 m cell)
LAC_RAY_OFFSETS = np.array([-3.0, -1.0, 1.0, 3.0]) / 8.0


def site_geometric_map(site, cell_m: float = LAC_CELL_M, rule: str = "lac") -> np.ndarray:
    """The ground-truth LAC geometric map of a simulated site.

    rule ``lac`` (default; what the LAC's scorer holds): per cell, 16 downward rays on a
    4 x 4 lattice 1/4 cell apart (3.75 cm in a 0.15 m cell, :data:`LAC_RAY_OFFSETS`); the
    cell's height is the mean of the surface heights the rays hit (terrain, or a rock's top
    where it stands above the terrain) and its rock flag is set when any ray hits a rock.
    rule ``centre`` (the earlier rule): one ray at the cell centre (height and flag
    from it). Rocks are the site's ellipsoids; the lander is not in the map (terrain under it)."""
    if rule not in ("lac", "centre"):
        raise InputError(f"unknown ground-truth rule {rule!r} (lac or centre)")
    grid = empty_lac_grid(site.config.size_m, cell_m)
    offsets = LAC_RAY_OFFSETS * cell_m if rule == "lac" else np.zeros(1)
    ox, oy = np.meshgrid(offsets, offsets, indexing="ij")
    # ray points: (N, N, R)
    x = grid[:, :, 0, None] + ox.reshape(1, 1, -1)
    y = grid[:, :, 1, None] + oy.reshape(1, 1, -1)
    h = site.terrain_height(x, y)
    hit = np.zeros(h.shape, dtype=bool)
    rocks = site.rocks
    lo = grid[0, 0, :2] + offsets.min()
    n = grid.shape[0]
    for k in range(len(rocks)):
        c, (a, b, cz), yaw = rocks.centers[k], rocks.axes[k], rocks.yaws[k]
        r = max(a, b)
        i0 = max(int(math.floor((c[0] - r - lo[0]) / cell_m)), 0)
        i1 = min(int(math.ceil((c[0] + r - lo[0]) / cell_m)) + 1, n)
        j0 = max(int(math.floor((c[1] - r - lo[1]) / cell_m)), 0)
        j1 = min(int(math.ceil((c[1] + r - lo[1]) / cell_m)) + 1, n)
        if i1 <= i0 or j1 <= j0:
            continue
        dx, dy = x[i0:i1, j0:j1] - c[0], y[i0:i1, j0:j1] - c[1]
        u = math.cos(yaw) * dx + math.sin(yaw) * dy
        v = -math.sin(yaw) * dx + math.cos(yaw) * dy
        e = 1.0 - (u / a) ** 2 - (v / b) ** 2
        inside = e > 0
        if not np.any(inside):
            continue
        top = c[2] + cz * np.sqrt(np.where(inside, e, 0.0))
        sub_h = h[i0:i1, j0:j1]
        above = inside & (top > sub_h)
        sub_h[above] = top[above]
        hit[i0:i1, j0:j1][above] = True
    grid[:, :, 2] = h.mean(axis=2)
    grid[:, :, 3] = hit.any(axis=2).astype(float)
    return grid


def write_site_geometric_map(site, path: str | Path, rule: str = "lac") -> Path:
    """Write the site's ground-truth LAC geometric map (:func:`site_geometric_map`) as ``.npy``."""
    from lunarloc.io.outputs import atomic_open

    path = Path(path)
    with atomic_open(path, "wb") as fh:
        np.save(fh, site_geometric_map(site, rule=rule))
    return path


def landmarks_to_lac_grid(
    landmarks: LandmarkMap,
    size_m: float = LAC_CELL_M * LAC_CELLS,
    cell_m: float = LAC_CELL_M,
    default_size_m: float = 0.15,
) -> np.ndarray:
    """A team's LAC map from a landmark map (site frame): every cell whose centre lies
    within a landmark's radius (size / 2; `default_size_m` where sizes are unknown; at
    least the cell holding its centre) is flagged a rock. Heights: where landmarks are,
    their height, spread to the other cells by nearest landmark (a coarse DEM from the rock
    tops; cells far from every landmark keep the nearest known height)."""
    from scipy.spatial import cKDTree

    grid = empty_lac_grid(size_m, cell_m)
    P = landmarks.positions_xyz
    if len(P) == 0:
        return grid
    sizes = landmarks.sizes if landmarks.sizes is not None else np.full(len(P), default_size_m)
    cells = grid[:, :, :2].reshape(-1, 2)
    tree = cKDTree(cells)
    flag = np.zeros(len(cells))
    for p, s in zip(P, sizes):
        hits = tree.query_ball_point(p[:2], max(s / 2.0, 1e-9))
        _, nearest = tree.query(p[:2])
        flag[hits] = 1.0
        if (
            abs(cells[nearest, 0] - p[0]) <= cell_m / 2
            and abs(cells[nearest, 1] - p[1]) <= cell_m / 2
        ):
            flag[nearest] = 1.0
    _, j = cKDTree(P[:, :2]).query(cells)
    grid[:, :, 2] = P[j, 2].reshape(grid.shape[:2])
    grid[:, :, 3] = flag.reshape(grid.shape[:2])
    return grid


# --------------------------------------------------------------------------- scoring


#: the largest height tolerance `score` accepts (m); the LAC's is 0.05
MAX_HEIGHT_TOLERANCE_M = 1.0


def score_geometric_map(
    produced,
    truth,
    height_tolerance_m: float = 0.05,
    *,
    cells=None,
    mission_time_s: float | None = None,
    fiducials_used: bool = False,
) -> dict:
    """The LAC's map scores of `produced` against `truth` (same grid), with the scorer's rules:

    ``geometric``: share of cells whose height error is below `height_tolerance_m` (an
    unfilled cell, -inf, fails); ``rock_precision`` / ``rock_recall`` / ``rock_f1`` over
    the per-cell rock flags (a flag >= 0.5 is a rock; unfilled flags count as no rock);
    ``productivity``: cells with both height and flag filled per second of `mission_time_s`
    against the LAC's rate (all cells in 24 h), capped at 1 (default mission time: 24 h,
    so the share of cells filled); ``points``: the LAC's points of each part and their
    ``total`` (300 x geometric + 300 x F1 + 250 x productivity + 150 without fiducials; the
    rock part is 0 when the truth has no rocks, as the scorer does).

    cells : optional (N, N) bool mask: the geometric share and the rock scores over these
        cells only (e.g. those the cameras saw; points then say what the whole map would
        score if it were those cells; productivity always counts the whole map).
    Raises InputError when the grids differ in shape or cell centres, the mask does not fit, or
    the tolerance is not in (0, 1] m (a negative or NaN one scored every map 0.0)."""
    from lunarloc.core.validate import real

    real(
        height_tolerance_m,
        "height_tolerance_m",
        0.0,
        MAX_HEIGHT_TOLERANCE_M,
        lo_open=True,
        unit="m",
    )
    p = validate_lac_grid(produced, "produced map", allow_unfilled=True)
    t = validate_lac_grid(truth, "true map")
    if p.shape != t.shape:
        raise InputError(
            f"produced map has shape {p.shape}, the true map {t.shape}: not the same grid"
        )
    if np.max(np.abs(p[:, :, :2] - t[:, :, :2])) > 1e-6:
        raise InputError(
            "produced and true maps have different cell centres (x, y): not the same grid"
        )
    if cells is None:
        sel = np.ones(p.shape[:2], dtype=bool)
    else:
        sel = np.asarray(cells)
        if sel.shape != p.shape[:2]:
            raise InputError(f"cell mask has shape {sel.shape}, the maps {p.shape[:2]}")
        sel = sel.astype(bool)
    if mission_time_s is not None and not (math.isfinite(mission_time_s) and mission_time_s > 0):
        raise InputError(f"mission time {mission_time_s} s must be > 0")
    filled_h = np.isfinite(p[:, :, 2])
    filled = filled_h & np.isfinite(p[:, :, 3])
    with np.errstate(invalid="ignore"):
        ok_h = filled_h & (np.abs(p[:, :, 2] - t[:, :, 2]) < height_tolerance_m)
    pr, tr = (p[:, :, 3] >= 0.5) & sel, (t[:, :, 3] >= 0.5) & sel
    tp = int(np.sum(pr & tr))
    fp = int(np.sum(pr & ~tr))
    fn = int(np.sum(~pr & tr))
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * tp / (2 * tp + fp + fn) if tp else 0.0
    n_sel = int(sel.sum())
    geometric = float(ok_h[sel].mean()) if n_sel else 0.0
    mission = LAC_MISSION_S if mission_time_s is None else float(mission_time_s)
    rate = int(filled.sum()) / mission
    productivity = min(rate / (p.shape[0] * p.shape[1] / LAC_MISSION_S), 1.0)
    pts = {
        "geometric_map": LAC_POINTS["geometric_map"] * geometric,
        "rocks_map": LAC_POINTS["rocks_map"] * f1 if tr.any() else 0.0,
        "mapping_productivity": LAC_POINTS["mapping_productivity"] * productivity,
        "localization": 0.0 if fiducials_used else LAC_POINTS["localization"],
    }
    pts["total"] = sum(pts.values())
    return {
        "cells": n_sel,
        "geometric": geometric,
        "rock_precision": precision,
        "rock_recall": recall,
        "rock_f1": f1,
        "rock_cells_true": int(tr.sum()),
        "rock_cells_produced": int(pr.sum()),
        "cells_filled": int(filled.sum()),
        "mission_time_s": mission,
        "productivity": productivity,
        "points": pts,
    }
