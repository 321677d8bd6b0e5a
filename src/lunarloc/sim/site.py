"""Seeded procedural lunar site: terrain heightfield, craters, rocks and a lander.

Frames and units
----------------
* Site (world / map) frame: x east, y north, z up, metres. The lander stands at
  the origin; the site spans ``[-size_m/2, size_m/2]`` in x and y. The terrain
  extends ``terrain_margin_m`` beyond the site (without rocks) so cameras near
  the edge still see ground, not the void.
* Rocks are irregular ellipsoids (low-order lobes, knobs, planar fractures). The ground-truth record
of a rock is
  ``id, x, y, z, radius``: (x, y, z) is the centre of the ellipsoid (it can lie
  below the ground for deeply buried rocks) and ``radius`` the nominal radius in
  metres (the horizontal semi-axes are within about 0.75-1.2 x radius, the
  vertical one 0.55-0.85 x radius).

* The lander stands at the origin (yaw 0): an octagonal body, a deck, tanks, a
  solar array, four legs, and 16 AprilTag-like fiducial panels in four groups of
  2 x 2 on the body's diagonal faces, at the positions and size of the LAC
  lander's fiducials (``LAC_FIDUCIALS``: lander frame, metres).

Everything is a pure function of the seed and the :class:`SiteConfig`; the mesh
construction needs the optional ``sim`` extra (trimesh) and is imported lazily.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from lunarloc.core.errors import ConfigError, require

__all__ = [
    "SiteConfig",
    "Rocks",
    "Site",
    "FiducialPanels",
    "LAC_FIDUCIALS",
    "generate_site",
    "load_rocks_csv",
    "sample_power_law",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

ROCK_CSV_COLUMNS = ("id", "x", "y", "z", "radius")

LAC_FIDUCIALS: tuple[tuple[float, float, float, int], ...] = (
    # x, y, z (lander frame, metres) and tag id of the LAC lander's fiducials, groups A-D,
    # each a 2 x 2 block on one diagonal face (top left, top right, lower left, lower right)
    (0.691, -1.033, 0.894, 243),
    (1.033, -0.691, 0.894, 71),
    (0.691, -1.033, 0.412, 462),
    (1.033, -0.691, 0.412, 37),
    (1.033, 0.691, 0.894, 0),
    (0.691, 1.033, 0.894, 3),
    (1.033, 0.691, 0.412, 2),
    (0.691, 1.033, 0.412, 1),
    (-0.691, 1.033, 0.894, 10),
    (-1.033, 0.691, 0.894, 11),
    (-0.691, 1.033, 0.412, 8),
    (-1.033, 0.691, 0.412, 9),
    (-1.033, -0.691, 0.894, 464),
    (-0.691, -1.033, 0.894, 459),
    (-1.033, -0.691, 0.412, 258),
    (-0.691, -1.033, 0.412, 5),
)
LAC_FIDUCIAL_SIZE_M = 0.339  # side of a fiducial panel
_TAG_CELLS = 10  # tag pattern: white border, black border, 6 x 6 data cells


@dataclass
class FiducialPanels:
    """Square fiducial panels on the lander (site frame, metres).

    A panel spans ``centre + a * u_axis + b * v_axis`` for ``a, b`` in
    ``[-size/2, size/2]``; ``u_axis`` points right and ``v_axis`` down in the tag
    image as seen from the front (along ``-normal``). ``bits[i]`` is the pattern,
    ``(cells, cells)`` with 1 white and 0 black, row 0 at the top.
    """

    centers: np.ndarray  # (P, 3)
    normals: np.ndarray  # (P, 3) outward
    u_axes: np.ndarray  # (P, 3)
    v_axes: np.ndarray  # (P, 3)
    size_m: np.ndarray  # (P,)
    tag_ids: np.ndarray  # (P,)
    bits: np.ndarray  # (P, cells, cells)

    def __len__(self) -> int:
        return int(self.centers.shape[0])


def _tag_bits(tag_id: int) -> np.ndarray:
    """An AprilTag-like pattern (not a decodable AprilTag): white ring, black ring, seeded data
    cells."""
    n = _TAG_CELLS
    rng = np.random.default_rng([int(tag_id), 0x7A6])
    bits = np.ones((n, n))
    bits[1:-1, 1:-1] = 0.0
    bits[2:-2, 2:-2] = rng.integers(0, 2, size=(n - 4, n - 4))
    return bits


@dataclass(frozen=True)
class SiteConfig:
    """Parameters of the procedural site (defaults mimic the LAC map used in the paper)."""

    size_m: float = 27.0  # side of the square site (LAC: 27 m x 27 m)
    terrain_margin_m: float = 12.0  # rock-free terrain beyond the site edge, for the view
    resolution_m: float = 0.1  # heightfield grid spacing
    relief_m: float = 1.0  # peak-to-peak height of the rolling terrain inside the site
    n_craters: int = 6  # number of craters inside the site
    crater_radius_m: tuple[float, float] = (0.8, 3.5)  # crater rim radius range
    crater_depth_ratio: float = 0.12  # depth / radius of a (degraded) crater
    n_rocks: int = 386  # LAC: 386 rocks
    rock_radius_m: tuple[float, float] = (0.03, 1.0)  # nominal radius range (truncated power law)
    rock_size_exponent: float = 1.6  # N(>r) ~ r^-exponent (cumulative power law)
    rock_burial: tuple[float, float] = (0.15, 0.55)  # fraction of the rock height below ground
    lander_radius_m: float = 1.6  # lander footprint radius (legs)
    lander_height_m: float = 2.6  # lander total height
    lander_keepout_m: float = 1.2  # no rocks / rover within lander_radius + keepout
    flatten_radius_m: float = 3.0  # terrain levelled under the lander within this radius
    rover_start_xy: tuple[float, float] = (-4.0, -3.0)  # every traverse starts here (metres)
    # --- the LAC look (``SiteConfig.lac_style()``); all off by default, so the sites of
    # existing seeds stay bit for bit the same. They draw from their own random streams.
    n_small_craters: int = 0  # extra small craters (fresh, steep: shadows in the mid-field)
    small_crater_radius_m: tuple[float, float] = (0.2, 1.0)  # their rim radius range
    small_crater_depth_ratio: float = 0.18  # their depth / radius
    hummock_m: float = (
        0.0  # std of extra terrain relief at about 0.3 m scale (metres; casts small shadows)
    )
    n_small_rocks: int = 0  # extra small rocks (the LAC's gravel), besides the n_rocks population
    # their nominal radius range (power law)
    small_rock_radius_m: tuple[float, float] = (0.02, 0.05)

    @classmethod
    def lac_style(cls, **overrides) -> SiteConfig:
        """A site that looks more like the LAC's real frames (issue 29): deeper, larger craters
        whose rims tilt the rover 10-20 degrees, a stronger rolling relief, many small fresh
        craters and hummocks that cast shadows under a low sun, and 600 extra rocks of 2-5 cm
        radius on top of the 386 of the LAC's size range. `overrides` replace any field."""
        base = {
            "relief_m": 1.6,
            "n_craters": 6,
            "crater_radius_m": (1.5, 5.0),
            "crater_depth_ratio": 0.22,
            "n_small_craters": 800,
            "hummock_m": 0.04,
            "n_small_rocks": 600,
        }
        base.update(overrides)
        return cls(**base)

    def validate(self) -> None:
        if self.size_m <= 4.0 * (self.lander_radius_m + self.lander_keepout_m) / 2:
            raise ConfigError(f"site size_m={self.size_m} is too small for the lander")
        if not 0.01 <= self.resolution_m <= 1.0:
            raise ConfigError(f"resolution_m={self.resolution_m} must be in [0.01, 1]")
        lo, hi = self.rock_radius_m
        if not 0 < lo < hi:
            raise ConfigError(f"rock_radius_m={self.rock_radius_m} must satisfy 0 < min < max")
        if self.n_rocks < 0 or self.n_craters < 0:
            raise ConfigError("n_rocks and n_craters must be >= 0")
        if self.rock_size_exponent <= 0:
            raise ConfigError("rock_size_exponent must be > 0")
        b0, b1 = self.rock_burial
        if not 0.0 <= b0 <= b1 < 1.0:
            raise ConfigError(f"rock_burial={self.rock_burial} must satisfy 0 <= min <= max < 1")
        if self.n_small_craters < 0 or self.n_small_rocks < 0:
            raise ConfigError("n_small_craters and n_small_rocks must be >= 0")
        lo, hi = self.small_crater_radius_m
        if not 0 < lo < hi:
            raise ConfigError(
                f"small_crater_radius_m={self.small_crater_radius_m} must satisfy 0 < min < max"
            )
        lo, hi = self.small_rock_radius_m
        if not 0 < lo < hi:
            raise ConfigError(
                f"small_rock_radius_m={self.small_rock_radius_m} must satisfy 0 < min < max"
            )
        if not 0.0 <= self.small_crater_depth_ratio <= 1.0 or not self.crater_depth_ratio >= 0.0:
            raise ConfigError("crater depth ratios must be >= 0 (small craters <= 1)")
        if not 0.0 <= self.hummock_m <= 0.2:
            raise ConfigError(f"hummock_m={self.hummock_m} must be in [0, 0.2]")
        half = self.size_m / 2
        if max(abs(self.rover_start_xy[0]), abs(self.rover_start_xy[1])) > half - 1.0:
            raise ConfigError(f"rover_start_xy={self.rover_start_xy} is outside the site")


@dataclass
class Rocks:
    """Ground-truth rocks (arrays of length N, site frame, metres)."""

    ids: np.ndarray  # (N,) int, 0..N-1
    centers: np.ndarray  # (N, 3) ellipsoid centres
    radii: np.ndarray  # (N,) nominal radius
    axes: np.ndarray  # (N, 3) semi-axes (x, y, z) before the yaw rotation
    yaws: np.ndarray  # (N,) rotation about z, radians
    shape_seeds: np.ndarray  # (N,) seeds of the surface irregularity

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def table(self) -> np.ndarray:
        """(N, 5) array ``id, x, y, z, radius``."""
        return np.column_stack([self.ids, self.centers, self.radii])


@dataclass
class Site:
    """A generated site. Create with :func:`generate_site`.

    Attributes
    ----------
    config, seed : what generated it.
    grid_x, grid_y : (nx,), (ny,) coordinates of the heightfield grid (metres).
    heights : (ny, nx) terrain height ``heights[j, i]`` at ``(grid_x[i], grid_y[j])``.
    rocks : ground-truth rocks.
    lander_xyz : lander base centre on the ground (metres).
    """

    config: SiteConfig
    seed: int
    grid_x: np.ndarray
    grid_y: np.ndarray
    heights: np.ndarray
    rocks: Rocks
    lander_xyz: np.ndarray
    _grad: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    # ------------------------------------------------------------------ queries
    @property
    def half_size(self) -> float:
        return self.config.size_m / 2.0

    @property
    def lander_pose(self) -> list[float]:
        """Lander pose [x, y, z, roll, pitch, yaw] (metres, radians)."""
        return [float(v) for v in self.lander_xyz] + [0.0, 0.0, 0.0]

    @property
    def rover_start_xy(self) -> np.ndarray:
        return np.asarray(self.config.rover_start_xy, dtype=float)

    def _interp(self, grid: np.ndarray, x, y) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        res = self.config.resolution_m
        fx = np.clip((x - self.grid_x[0]) / res, 0.0, len(self.grid_x) - 1.000001)
        fy = np.clip((y - self.grid_y[0]) / res, 0.0, len(self.grid_y) - 1.000001)
        i = np.floor(fx).astype(np.intp)
        j = np.floor(fy).astype(np.intp)
        tx = fx - i
        ty = fy - j
        h00 = grid[j, i]
        h01 = grid[j, i + 1]
        h10 = grid[j + 1, i]
        h11 = grid[j + 1, i + 1]
        return (h00 * (1 - tx) + h01 * tx) * (1 - ty) + (h10 * (1 - tx) + h11 * tx) * ty

    def terrain_height(self, x, y) -> np.ndarray:
        """Terrain height (metres) at site coordinates x, y (scalars or arrays; bilinear)."""
        return self._interp(self.heights, x, y)

    def terrain_gradient(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Smooth terrain slope (dz/dx, dz/dy) at x, y (bilinear in the grid gradient)."""
        if self._grad is None:
            gy, gx = np.gradient(self.heights, self.config.resolution_m)
            self._grad = (gx, gy)
        gx, gy = self._grad
        return self._interp(gx, x, y), self._interp(gy, x, y)

    def terrain_normal(self, x, y) -> np.ndarray:
        """Unit upward terrain normal(s), shape (..., 3)."""
        gx, gy = self.terrain_gradient(x, y)
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def inside(self, x, y, margin: float = 0.0) -> np.ndarray:
        """True where (x, y) lies inside the site shrunk by `margin` metres."""
        h = self.half_size - margin
        return (np.abs(np.asarray(x)) <= h) & (np.abs(np.asarray(y)) <= h)

    # ------------------------------------------------------------------ export
    def rocks_table(self) -> np.ndarray:
        """(N, 5) array ``id, x, y, z, radius`` (site frame, metres)."""
        return self.rocks.table()

    def write_rocks_csv(self, path: str | Path) -> Path:
        """Write the ground-truth rock list as CSV with header ``id,x,y,z,radius``."""
        from lunarloc.io.outputs import atomic_open

        path = Path(path)
        with atomic_open(path, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(ROCK_CSV_COLUMNS)
            for row in self.rocks_table():
                w.writerow([int(row[0])] + [f"{v:.5f}" for v in row[1:]])
        logger.info("wrote %d rocks to %s", len(self.rocks), path)
        return path

    def config_dict(self) -> dict:
        return {"seed": self.seed, **asdict(self.config)}

    # ------------------------------------------------------------------ meshes
    def terrain_mesh(self):
        """Terrain heightfield as a trimesh.Trimesh (two triangles per grid cell)."""
        trimesh = require("trimesh", "sim")
        nx, ny = len(self.grid_x), len(self.grid_y)
        X, Y = np.meshgrid(self.grid_x, self.grid_y)
        V = np.column_stack([X.ravel(), Y.ravel(), self.heights.ravel()])
        I, J = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
        a = (J * nx + I).ravel()
        b, c = a + 1, a + nx
        d = c + 1
        F = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
        return trimesh.Trimesh(V, F, process=False)

    def rock_meshes(self) -> list:
        """One irregular-ellipsoid trimesh.Trimesh per rock, in rock id order (site frame)."""
        trimesh = require("trimesh", "sim")
        bases = {s: trimesh.creation.icosphere(subdivisions=s) for s in (1, 2, 3)}
        meshes = []
        r = self.rocks
        for k in range(len(r)):
            sub = 1 if r.radii[k] < 0.06 else (2 if r.radii[k] < 0.25 else 3)
            unit = bases[sub].vertices
            rng = np.random.default_rng(int(r.shape_seeds[k]))
            # smooth radial irregularity: random low-order lobes (about +-20 %)
            dirs = rng.normal(size=(8, 3))
            dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
            amp = rng.uniform(0.03, 0.09, size=8)
            freq = rng.uniform(1.5, 4.0, size=8)
            bump = 1.0 + (np.cos(unit @ dirs.T * freq) * amp).sum(1)
            bump = np.clip(bump / bump.mean(), 0.8, 1.2)
            # knobs: higher-frequency lobes and a little vertex jitter (a rough, lumpy outline)
            dirs2 = rng.normal(size=(12, 3))
            dirs2 /= np.linalg.norm(dirs2, axis=1, keepdims=True)
            knobs = np.cos(
                unit @ dirs2.T * rng.uniform(4.0, 9.0, 12) + rng.uniform(0, 2 * np.pi, 12)
            )
            bump = bump * (1.0 + knobs @ rng.uniform(0.008, 0.03, 12))
            bump = bump * (1.0 + rng.uniform(-0.025, 0.025, len(bump)) * (sub >= 2))
            # a few planar fractures: vertices beyond a random plane are pushed onto it
            V0 = unit * bump[:, None]
            for _cut in range(int(rng.integers(3, 7))):
                nrm = rng.normal(size=3)
                nrm[2] = abs(nrm[2]) * 0.5 + 0.2 * np.sign(rng.uniform(-1, 1))
                nrm /= np.linalg.norm(nrm)
                excess = np.clip(V0 @ nrm - rng.uniform(0.6, 0.9), 0.0, None)
                V0 = V0 - excess[:, None] * nrm
            bump = np.linalg.norm(V0, axis=1)
            V = unit * bump[:, None] * r.axes[k]
            c, s = np.cos(r.yaws[k]), np.sin(r.yaws[k])
            Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            V = V @ Rz.T + r.centers[k]
            meshes.append(trimesh.Trimesh(V, bases[sub].faces, process=False))
        return meshes

    def lander_parts(self) -> list:
        """The lander's parts as ``(trimesh.Trimesh, albedo scale)`` pairs (site frame): an
        octagonal body whose diagonal faces carry the fiducial panels, a deck, two banded
        tanks, a gridded solar array and four legs with foot pads (sizes from ``lander_radius_m`` /
        ``lander_height_m``; the body's size from the LAC fiducial layout)."""
        trimesh = require("trimesh", "sim")
        cfg = self.config
        base = np.asarray(self.lander_xyz, float)
        parts = []
        # the diagonal faces hold the fiducial centres (LAC layout)
        apothem = np.hypot(0.862, 0.862)
        body_z = (0.1, 1.15)
        body = trimesh.creation.cylinder(
            radius=apothem / np.cos(np.pi / 8), height=body_z[1] - body_z[0], sections=8
        )
        body.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 8, [0, 0, 1]))
        body.apply_translation(base + [0.0, 0.0, sum(body_z) / 2])
        parts.append((body, 0.3))
        deck = trimesh.creation.box(extents=[2.0, 2.0, 0.08])
        deck.apply_translation(base + [0.0, 0.0, body_z[1] + 0.04])
        parts.append((deck, 0.9))
        top = max(cfg.lander_height_m, body_z[1] + 0.8)
        tank_r = 0.3
        for x, y in ((0.35, -0.35), (0.35, 0.45)):
            h = top - body_z[1] - 0.08 - 2 * tank_r
            tank = trimesh.creation.capsule(height=h, radius=tank_r, count=[12, 12])
            tank.apply_translation(base + [x, y, body_z[1] + 0.08 + tank_r + h / 2])
            parts.append((tank, 1.1))
            band = trimesh.creation.cylinder(radius=tank_r + 0.01, height=0.07, sections=16)
            band.apply_translation(base + [x, y, body_z[1] + 0.08 + tank_r + 0.6 * h])
            parts.append((band, 0.05))
        # solar array: a dark panel with a light frame and grid (3 x 4 cells)
        p_h = top - body_z[1] - 0.2
        p_z = (top + body_z[1]) / 2 + 0.05
        panel = trimesh.creation.box(extents=[0.04, 1.2, p_h])
        panel.apply_translation(base + [-0.6, 0.0, p_z])
        parts.append((panel, 0.08))
        for yb in np.linspace(-0.6, 0.6, 4):
            bar = trimesh.creation.box(extents=[0.06, 0.04, p_h])
            bar.apply_translation(base + [-0.6, yb, p_z])
            parts.append((bar, 0.9))
        for zb in np.linspace(p_z - p_h / 2, p_z + p_h / 2, 5):
            bar = trimesh.creation.box(extents=[0.06, 1.24, 0.04])
            bar.apply_translation(base + [-0.6, 0.0, zb])
            parts.append((bar, 0.9))
        for ang in np.arange(4) * np.pi / 2:  # legs on the flat faces, clear of the fiducials
            radial = np.array([np.cos(ang), np.sin(ang), 0.0])
            foot = base + cfg.lander_radius_m * radial
            hip = base + 0.95 * apothem * radial + [0.0, 0.0, 0.8]
            leg = trimesh.creation.cylinder(
                radius=0.05, segment=[foot + [0, 0, 0.05], hip], sections=8
            )
            parts.append((leg, 0.9))
            pad = trimesh.creation.cylinder(radius=0.2, height=0.06, sections=12)
            pad.apply_translation(foot + [0.0, 0.0, 0.02])
            parts.append((pad, 0.9))
        return parts

    def lander_mesh(self):
        """The lander's parts (:meth:`lander_parts`) as one trimesh.Trimesh (without the panels)."""
        trimesh = require("trimesh", "sim")
        return trimesh.util.concatenate([m for m, _ in self.lander_parts()])

    def fiducial_panels(self) -> FiducialPanels:
        """The lander's 16 fiducial panels (``LAC_FIDUCIALS``), 1 cm proud of its body."""
        rows = np.array([r[:3] for r in LAC_FIDUCIALS], float)
        normals = np.column_stack(
            [np.sign(rows[:, 0]), np.sign(rows[:, 1]), np.zeros(len(rows))]
        ) / np.sqrt(2)
        centers = np.asarray(self.lander_xyz, float) + rows + 0.01 * normals
        up = np.array([0.0, 0.0, 1.0])
        u = np.cross(-normals, up)
        v = np.broadcast_to(-up, u.shape).copy()
        ids = np.array([r[3] for r in LAC_FIDUCIALS], int)
        return FiducialPanels(
            centers=centers,
            normals=normals,
            u_axes=u,
            v_axes=v,
            size_m=np.full(len(rows), LAC_FIDUCIAL_SIZE_M),
            tag_ids=ids,
            bits=np.stack([_tag_bits(i) for i in ids]),
        )


# ---------------------------------------------------------------------- generation
def _smooth_noise(rng: np.random.Generator, shape, sigma_cells: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    n = gaussian_filter(rng.normal(size=shape), sigma_cells, mode="reflect")
    return n / (n.std() + 1e-12)


def _crater_profile(r: np.ndarray, R: float, depth: float) -> np.ndarray:
    """Height change of a bowl crater with a raised rim at distance r (metres)."""
    rim = 0.25 * depth
    inside = -depth * (1.0 - (r / R) ** 2) + rim
    outside = rim * np.clip(R / np.maximum(r, 1e-9), 0, 1) ** 4
    return np.where(r < R, inside, outside)


def sample_power_law(
    rng: np.random.Generator, n: int, r_min: float, r_max: float, exponent: float
) -> np.ndarray:
    """Radii from a truncated power law with cumulative count N(>r) ~ r^-exponent (inverse CDF)."""
    u = rng.uniform(size=n)
    a = exponent
    return r_min * (1.0 - u * (1.0 - (r_min / r_max) ** a)) ** (-1.0 / a)


def generate_site(seed: int = 0, config: SiteConfig | None = None) -> Site:
    """Generate the site for `seed` (deterministic: same seed and config, same site)."""
    cfg = config or SiteConfig()
    cfg.validate()
    rng = np.random.default_rng([int(seed), 0x5173])
    half = cfg.size_m / 2.0
    ext = half + cfg.terrain_margin_m
    n = int(round(2 * ext / cfg.resolution_m)) + 1
    grid = np.linspace(-ext, ext, n)
    X, Y = np.meshgrid(grid, grid)

    # rolling terrain: broad + medium undulations, scaled to `relief_m` peak-to-peak in the site
    broad = _smooth_noise(rng, X.shape, 4.0 / cfg.resolution_m)
    medium = _smooth_noise(rng, X.shape, 1.0 / cfg.resolution_m)
    fine = _smooth_noise(rng, X.shape, 0.15 / cfg.resolution_m)
    Z = broad + 0.25 * medium + 0.015 * fine
    ins = (np.abs(X) <= half) & (np.abs(Y) <= half)
    Z = Z * (0.8 * cfg.relief_m / max(np.ptp(Z[ins]), 1e-9))

    # craters, kept away from the lander and the rover start
    start = np.asarray(cfg.rover_start_xy, float)
    for _ in range(cfg.n_craters):
        for _try in range(100):
            R = rng.uniform(*cfg.crater_radius_m)
            c = rng.uniform(-half + 1.0, half - 1.0, size=2)
            if (
                np.hypot(*c) > cfg.lander_radius_m + cfg.flatten_radius_m + R
                and np.hypot(*(c - start)) > R + 1.0
            ):
                break
        Z = Z + _crater_profile(np.hypot(X - c[0], Y - c[1]), R, cfg.crater_depth_ratio * R)

    # the LAC look (off by default): small fresh craters and hummocks, from their own stream
    extra = np.random.default_rng([int(seed), 0x5174])
    if cfg.hummock_m > 0:
        Z = Z + cfg.hummock_m * _smooth_noise(extra, X.shape, max(0.3 / cfg.resolution_m, 0.5))
    if cfg.n_small_craters:
        radii_c = sample_power_law(extra, cfg.n_small_craters, *cfg.small_crater_radius_m, 2.0)
        centres_c = extra.uniform(-ext, ext, size=(cfg.n_small_craters, 2))
        for R, c in zip(radii_c, centres_c):
            w = 3.0 * R  # the rim's outer slope falls as r^-4: 1 % of the rim height at 3 R
            i0, i1 = np.searchsorted(grid, [c[0] - w, c[0] + w])
            j0, j1 = np.searchsorted(grid, [c[1] - w, c[1] + w])
            if i1 <= i0 or j1 <= j0:
                continue
            r = np.hypot(X[j0:j1, i0:i1] - c[0], Y[j0:j1, i0:i1] - c[1])
            Z[j0:j1, i0:i1] += _crater_profile(r, R, cfg.small_crater_depth_ratio * R)

    # level the ground under the lander (smooth blend)
    rr = np.hypot(X, Y)
    w = np.clip((rr - cfg.flatten_radius_m) / 2.0, 0.0, 1.0)
    w = w * w * (3 - 2 * w)
    Z0 = float(np.mean(Z[rr < cfg.flatten_radius_m])) if np.any(rr < cfg.flatten_radius_m) else 0.0
    Z = w * Z + (1 - w) * Z0
    Z = Z - Z0  # lander base at z = 0

    site = Site(cfg, int(seed), grid, grid.copy(), Z, _empty_rocks(), np.zeros(3))

    # rocks: power-law radii, placed without overlap, outside the lander keep-out
    radii = np.sort(sample_power_law(rng, cfg.n_rocks, *cfg.rock_radius_m, cfg.rock_size_exponent))[
        ::-1
    ]
    keep_r = cfg.lander_radius_m + cfg.lander_keepout_m
    xy = np.zeros((0, 2))
    rad = np.zeros(0)
    for r in radii:
        for _try in range(200):
            p = rng.uniform(-half + r, half - r, size=2)
            if np.hypot(*p) < keep_r + r:
                continue
            if np.hypot(*(p - start)) < 1.5 + 1.4 * r:  # the rover must start in the clear
                continue
            if len(rad) and np.any(np.hypot(*(xy - p).T) < 1.1 * (rad + r)):
                continue
            break
        else:
            continue  # site too crowded for this rock; skip it
        xy = np.vstack([xy, p])
        rad = np.append(rad, r)
    if len(rad) < cfg.n_rocks:
        logger.warning("placed only %d of %d rocks (site too crowded)", len(rad), cfg.n_rocks)
    # shuffle so ids are not ordered by size
    order = rng.permutation(len(rad))
    xy, rad = xy[order], rad[order]
    m = len(rad)
    axes = np.column_stack(
        [
            rad * rng.uniform(0.85, 1.2, m),
            rad * rng.uniform(0.75, 1.1, m),
            rad * rng.uniform(0.55, 0.85, m),
        ]
    )
    burial = rng.uniform(*cfg.rock_burial, size=m)
    ground = site.terrain_height(xy[:, 0], xy[:, 1]) if m else np.zeros(0)
    z = ground + axes[:, 2] * (1.0 - 2.0 * burial)
    site.rocks = Rocks(
        ids=np.arange(m),
        centers=np.column_stack([xy, z]) if m else np.zeros((0, 3)),
        radii=rad,
        axes=axes,
        yaws=rng.uniform(0, 2 * np.pi, m),
        shape_seeds=rng.integers(0, 2**31 - 1, m),
    )
    if cfg.n_small_rocks:
        _add_small_rocks(site, np.random.default_rng([int(seed), 0x5175]), cfg, start, keep_r)
    logger.debug(
        "site seed=%d: %d rocks, relief %.2f m", seed, len(site.rocks), float(np.ptp(Z[ins]))
    )
    return site


def _add_small_rocks(
    site: Site, rng: np.random.Generator, cfg: SiteConfig, start: np.ndarray, keep_r: float
) -> None:
    """Append ``cfg.n_small_rocks`` small rocks (power-law radii in ``small_rock_radius_m``) to
    `site.rocks`, clear of the other rocks, the lander and the rover start; their ids follow
    the others'."""
    half = cfg.size_m / 2.0
    r0 = site.rocks
    radii = sample_power_law(
        rng, cfg.n_small_rocks, *cfg.small_rock_radius_m, cfg.rock_size_exponent
    )
    cand = rng.uniform(-half + 0.1, half - 0.1, size=(4 * len(radii), 2))
    xy_all, r_all = r0.centers[:, :2].copy(), r0.radii.copy()
    xy, rad = [], []
    k = 0
    for r in radii:
        while k < len(cand):
            p = cand[k]
            k += 1
            if np.hypot(*p) < keep_r + r or np.hypot(*(p - start)) < 1.0:
                continue
            if len(r_all) and np.any(np.hypot(*(xy_all - p).T) < 1.1 * (r_all + r)):
                continue
            xy.append(p)
            rad.append(r)
            xy_all = np.vstack([xy_all, p])
            r_all = np.append(r_all, r)
            break
    m = len(rad)
    if m == 0:
        return
    xy, rad = np.asarray(xy), np.asarray(rad)
    axes = np.column_stack(
        [
            rad * rng.uniform(0.85, 1.2, m),
            rad * rng.uniform(0.75, 1.1, m),
            rad * rng.uniform(0.55, 0.85, m),
        ]
    )
    burial = rng.uniform(*cfg.rock_burial, size=m)
    z = site.terrain_height(xy[:, 0], xy[:, 1]) + axes[:, 2] * (1.0 - 2.0 * burial)
    n0 = len(r0)
    site.rocks = Rocks(
        ids=np.arange(n0 + m),
        centers=np.vstack([r0.centers, np.column_stack([xy, z])]),
        radii=np.concatenate([r0.radii, rad]),
        axes=np.vstack([r0.axes, axes]),
        yaws=np.concatenate([r0.yaws, rng.uniform(0, 2 * np.pi, m)]),
        shape_seeds=np.concatenate([r0.shape_seeds, rng.integers(0, 2**31 - 1, m)]),
    )


def _empty_rocks() -> Rocks:
    return Rocks(
        np.zeros(0, int),
        np.zeros((0, 3)),
        np.zeros(0),
        np.zeros((0, 3)),
        np.zeros(0),
        np.zeros(0, int),
    )


def load_rocks_csv(path: str | Path) -> np.ndarray:
    """Read a ``id,x,y,z,radius`` CSV back as an (N, 5) float array."""
    from lunarloc.core.errors import FileFormatError

    path = Path(path)
    with path.open(newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        if header is None or tuple(h.strip() for h in header) != ROCK_CSV_COLUMNS:
            raise FileFormatError(
                f"{path}: expected header {','.join(ROCK_CSV_COLUMNS)}, got {header}"
            )
        rows = [[float(v) for v in row] for row in reader if row]
    return np.asarray(rows, dtype=float).reshape(-1, 5)
