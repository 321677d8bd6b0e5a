"""Ray-cast renderer of the simulated site: grayscale images with hard sun shadows,
rover lamps and a per-pixel semantic ground truth (Embree through embreex, as used by
trimesh).

Rendering model
---------------
* One Embree BVH holds the whole scene (terrain heightfield mesh, rock meshes,
  lander with its fiducial panels) and is reused for every frame; the rays of
  several cameras (a stereo pair, or all four cameras) are cast in one batch.
* Lighting (:class:`Lighting`): the sun, the rover's lamps, or both (the LAC's
  usual look). Sun: a directional light at ``sun_elevation_deg`` above the
  horizon and ``sun_azimuth_deg`` (counter-clockwise from the site +x axis), with
  hard cast shadows (a shadow ray from every lit hit point toward the sun; the
  rover body, a few boxes, occludes them too). A sun at or below the horizon
  gives no light: with the lamps that is the lunar night.
* Lamps: four spot lights at the LAC light mounts (front pair at x = 0.28 m,
  y = +-0.115 m, z = 0.131 m facing forward; the rear pair mirrored, facing
  back), irradiance ``lamp_power * light_intensity * cone(angle) / d^2`` with a
  smooth cone between ``lamp_cone_deg`` (inner, outer half-angles). Lamps cast
  no shadows (they sit 3.4 cm from the cameras, so their shadows are nearly
  hidden behind the objects that cast them).
* No atmosphere: rays that hit nothing are black sky; sunlit scenes add a small
  ambient term (light scattered from the surrounding terrain).
* Materials: Lunar-Lambert (McEwen) reflectance
  ``(1 - L) cos i + L * 2 cos i / (cos i + cos e)`` for regolith and rocks, with
  seeded procedural albedo texture and bump (multi-octave value noise in site
  coordinates, so it is fixed on the ground and consistent between the two
  cameras of a pair). Rocks have an albedo close to the regolith's and their
  own bump texture; the lander's fiducial panels carry AprilTag-like patterns.

Semantic encoding
-----------------
Ids (``uint16`` single-channel image, 16-bit PNG when stored; the default):

* ``0`` sky (no hit), ``1`` ground (terrain), ``2`` lander, ``3`` lander fiducial
  panel (use :func:`semantic_lander_mask` for "any part of the lander"),
* ``10 + rock_id`` a rock (``rock_id`` as in the ground-truth rock list), so up to
  65525 rocks. Use :func:`semantic_to_rock_id` / :func:`colorize_semantic`.

LAC palette (:data:`LAC_PALETTE`, ``(H, W, 3) uint8`` RGB, :func:`semantic_to_palette`):
rocks (42, 59, 108), lander (160, 190, 110), fiducials (30, 170, 250) as observed
in the LAC's semantic camera; sky (0, 0, 0) and ground (81, 0, 81) as seen in a
LAC team's segmentation training code (CARLA's "ground" colour; unverified
against the simulator itself). :class:`SemanticFormat` chooses which an archive
stores.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import Enum

import numpy as np

from lunarloc.core.errors import ConfigError, InputError, require
from lunarloc.core.geometry import pose_to_matrix
from lunarloc.perception.camera import CameraMount, PinholeCamera

__all__ = [
    "SEM_SKY",
    "SEM_GROUND",
    "SEM_LANDER",
    "SEM_FIDUCIAL",
    "SEM_ROCK_OFFSET",
    "LAC_PALETTE",
    "LAC_LAMPS",
    "ROVER_BOXES",
    "Lighting",
    "SemanticFormat",
    "Lamp",
    "RenderConfig",
    "SiteRenderer",
    "semantic_to_rock_id",
    "semantic_lander_mask",
    "semantic_to_palette",
    "colorize_semantic",
    "sun_direction",
    "rover_lamps",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

SEM_SKY = 0
SEM_GROUND = 1
SEM_LANDER = 2
SEM_FIDUCIAL = 3
SEM_ROCK_OFFSET = 10
"""Semantic label of rock ``k`` is ``SEM_ROCK_OFFSET + k``."""

LAC_PALETTE: dict[str, tuple[int, int, int]] = {
    "sky": (0, 0, 0),
    "ground": (81, 0, 81),
    "rock": (42, 59, 108),
    "lander": (160, 190, 110),
    "fiducial": (30, 170, 250),
}
"""RGB colours of the LAC semantic camera (see the module docstring for their sources)."""

_KIND_TERRAIN, _KIND_ROCK, _KIND_LANDER, _KIND_FIDUCIAL = 0, 1, 2, 3


class _ParsedEnum(str, Enum):
    """A string Enum whose :meth:`parse` names the valid values on a bad one."""

    @classmethod
    def parse(cls, value) -> _ParsedEnum:
        if isinstance(value, cls):
            return value
        try:
            return cls(str(value).strip().lower())
        except ValueError:
            valid = ", ".join(repr(m.value) for m in cls)
            raise ConfigError(f"{cls.__name__.lower()} {value!r} is not one of {valid}") from None

    def __str__(self) -> str:
        return str(self.value)


class Lighting(_ParsedEnum):
    """What lights the scene: the sun, the rover's lamps, or both (the LAC's usual look)."""

    SUN = "sun"
    LAMPS = "lamps"
    SUN_LAMPS = "sun+lamps"

    @property
    def has_sun(self) -> bool:
        return self is not Lighting.LAMPS

    @property
    def has_lamps(self) -> bool:
        return self is not Lighting.SUN


class SemanticFormat(_ParsedEnum):
    """How semantic images are stored: per-rock ids (uint16) or the LAC palette (RGB)."""

    IDS = "ids"
    PALETTE = "palette"


@dataclass(frozen=True)
class Lamp:
    """A spot light on the rover (rover frame: x forward, y left, z up; metres)."""

    name: str  # the camera it belongs to in the LAC (its light_intensity drives it)
    position_m: tuple[float, float, float]
    direction: tuple[float, float, float]  # unit axis of the cone


LAC_LAMPS: tuple[Lamp, ...] = (
    Lamp("FrontLeft", (0.28, 0.115, 0.131), (1.0, 0.0, 0.0)),
    Lamp("FrontRight", (0.28, -0.115, 0.131), (1.0, 0.0, 0.0)),
    Lamp("BackLeft", (-0.28, -0.115, 0.131), (-1.0, 0.0, 0.0)),
    Lamp("BackRight", (-0.28, 0.115, 0.131), (-1.0, 0.0, 0.0)),
)
"""The LAC light mounts beside the IPEx stereo cameras (LAC rover geometry)."""

ROVER_BOXES: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((-0.32, -0.27, 0.16), (0.32, 0.27, 0.36)),  # upper deck (the wide top of the shadow)
    ((0.062, 0.14, -0.25), (0.382, 0.27, 0.201)),  # wheels: LAC centres (+-0.222, +-0.203, 0.041),
    ((0.062, -0.27, -0.25), (0.382, -0.14, 0.201)),  # 0.32 m diameter, 0.127 m wide; extended
    ((-0.382, 0.14, -0.25), (-0.062, 0.27, 0.201)),  # down to the ground
    ((-0.382, -0.27, -0.25), (-0.062, -0.14, 0.201)),
)
"""Axis-aligned boxes (min, max corners, rover frame, metres) that stand in for the
rover body in the sun's shadow rays; the cameras and lamps lie outside them."""


@dataclass(frozen=True)
class RenderConfig:
    """Lighting, material and exposure of the renderer (fields added later come last, so
    positional construction keeps working)."""

    sun_elevation_deg: float = 12.0  # LAC / lunar south pole: low sun, 5-30 deg; <= 0: no sun
    sun_azimuth_deg: float = 135.0  # counter-clockwise from the site +x axis
    shadows: bool = True  # hard cast shadows (shadow rays)
    ground_albedo: float = 0.55  # relative regolith albedo (before exposure)
    rock_albedo: float = 0.6  # relative rock albedo: close to the regolith's (LAC look)
    lander_albedo: float = 1.2  # foil and paint
    albedo_texture: float = 0.35  # strength of the regolith albedo texture (0 = flat)
    bump_strength: float = 1.0  # scale of the small-scale regolith roughness (normal bumps)
    rock_facet: float = 0.35  # 0 = smooth rock shading, 1 = flat facets
    lunar_lambert_L: float = 0.6  # limb-darkening mix of the Lunar-Lambert law
    ambient: float = 0.025  # light in sun shadows, fraction of the direct sun (none at night)
    exposure: float = 1.0  # scale before the gamma curve
    gamma: float = 1.8  # display gamma
    texture_seed: int = 0  # seed of the albedo texture
    lighting: Lighting = Lighting.SUN_LAMPS  # sun, lamps or both (a str is parsed)
    lamp_intensity: float = 1.0  # LAC light_intensity of every lamp, 0-1 (what the archive records)
    lamp_power: float = (
        1.0  # on-axis irradiance at 1 m of one lamp at intensity 1, in units of the sun's
    )
    # full power inside, none beyond (half-angles)
    lamp_cone_deg: tuple[float, float] = (20.0, 50.0)
    rover_shadow: bool = True  # the rover body (ROVER_BOXES) occludes the sun in render_rover
    rock_albedo_spread: float = 0.12  # each rock's albedo within rock_albedo * (1 +- spread)
    rock_bump: float = 3.0  # scale of the rock surface roughness (normal bumps)
    highlight_knee: float = (
        0.75  # radiance above this is compressed smoothly toward 1 (lamp-lit near field)
    )
    # shade the terrain with its upward normal also where that faces away from the camera (a
    # grazing view over a crest) instead of flipping it toward the camera, which turns such
    # pixels black: rows of dark dots along every crest of a rough terrain (the LAC-look site).
    # False (the default) keeps earlier renders bit for bit.
    terrain_up_normal: bool = False

    @classmethod
    def lac_style(cls, **overrides) -> RenderConfig:
        """The renderer settings that go with ``SiteConfig.lac_style()``: the terrain shaded
        with its upward normal at grazing views (``terrain_up_normal``). `overrides` replace
        any field."""
        return cls(**{"terrain_up_normal": True, **overrides})

    def __post_init__(self) -> None:
        object.__setattr__(self, "lighting", Lighting.parse(self.lighting))
        object.__setattr__(self, "lamp_cone_deg", tuple(float(v) for v in self.lamp_cone_deg))

    @property
    def sun_on(self) -> bool:
        """Whether the sun lights the scene (chosen, and above the horizon)."""
        return self.lighting.has_sun and self.sun_elevation_deg > 0.0

    @property
    def lamps_on(self) -> bool:
        return self.lighting.has_lamps and self.lamp_intensity > 0.0

    def validate(self) -> None:
        if not -90.0 <= self.sun_elevation_deg <= 90.0:
            raise ConfigError(f"sun_elevation_deg={self.sun_elevation_deg} must be in [-90, 90]")
        if self.gamma <= 0 or self.exposure <= 0:
            raise ConfigError("gamma and exposure must be > 0")
        if not 0.0 <= self.lunar_lambert_L <= 1.0:
            raise ConfigError("lunar_lambert_L must be in [0, 1]")
        if not 0.0 <= self.lamp_intensity <= 1.0:
            raise ConfigError(
                f"lamp_intensity={self.lamp_intensity} must be in [0, 1] (LAC light_intensity)"
            )
        if self.lamp_power < 0:
            raise ConfigError(f"lamp_power={self.lamp_power} must be >= 0")
        if (
            len(self.lamp_cone_deg) != 2
            or not 0.0 <= self.lamp_cone_deg[0] < self.lamp_cone_deg[1] <= 90.0
        ):
            raise ConfigError(
                f"lamp_cone_deg={self.lamp_cone_deg} must be (inner, outer) with 0 <= inner < "
                "outer <= 90"
            )
        if not 0.0 < self.highlight_knee <= 1.0:
            raise ConfigError(
                f"highlight_knee={self.highlight_knee} must be in (0, 1] (1: hard clip)"
            )
        if not 0.0 <= self.rock_albedo_spread < 1.0:
            raise ConfigError(f"rock_albedo_spread={self.rock_albedo_spread} must be in [0, 1)")


def sun_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector toward the sun in the site frame (z up, azimuth from +x toward +y)."""
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def rover_lamps(
    T_world_rover: np.ndarray,
    light_intensity: float | dict[str, float],
    lamps: tuple[Lamp, ...] = LAC_LAMPS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World positions (L, 3), unit axes (L, 3) and intensities (L,) of the rover's lamps.

    `light_intensity` is one LAC ``light_intensity`` (0-1) for every lamp, or a
    ``{camera name: intensity}`` dict (missing lamps are off).
    """
    T = np.asarray(T_world_rover, float)
    pos = np.array([lp.position_m for lp in lamps], float) @ T[:3, :3].T + T[:3, 3]
    axis = np.array([lp.direction for lp in lamps], float) @ T[:3, :3].T
    if isinstance(light_intensity, dict):
        unknown = set(light_intensity) - {lp.name for lp in lamps}
        if unknown:
            raise InputError(f"light_intensity for unknown lamp(s) {sorted(unknown)}")
        inten = np.array([float(light_intensity.get(lp.name, 0.0)) for lp in lamps])
    else:
        inten = np.full(len(lamps), float(light_intensity))
    if np.any(~np.isfinite(inten)) or np.any(inten < 0) or np.any(inten > 1):
        raise InputError(f"light_intensity must be in [0, 1], got {inten.tolist()}")
    return pos, axis, inten


def semantic_to_rock_id(semantic: np.ndarray) -> np.ndarray:
    """Rock id per pixel (int32), -1 where the pixel is not a rock."""
    s = np.asarray(semantic).astype(np.int32)
    return np.where(s >= SEM_ROCK_OFFSET, s - SEM_ROCK_OFFSET, -1)


def semantic_lander_mask(semantic: np.ndarray) -> np.ndarray:
    """True where a pixel shows any part of the lander (body or fiducial panel)."""
    s = np.asarray(semantic)
    return (s == SEM_LANDER) | (s == SEM_FIDUCIAL)


def semantic_to_palette(semantic: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 image in the LAC semantic palette (:data:`LAC_PALETTE`) of an id image.

    Every rock gets the one rock colour (the palette has no instance ids).
    """
    s = np.asarray(semantic)
    if s.ndim != 2 or not np.issubdtype(s.dtype, np.integer):
        raise InputError(f"semantic ids must be an (H, W) integer image, got {s.dtype} {s.shape}")
    s = s.astype(np.int64)
    lut = np.array(
        [LAC_PALETTE["sky"], LAC_PALETTE["ground"], LAC_PALETTE["lander"], LAC_PALETTE["fiducial"]],
        np.uint8,
    )
    out = np.empty(s.shape + (3,), np.uint8)
    out[...] = LAC_PALETTE["rock"]
    small = s < SEM_ROCK_OFFSET
    known = small & (s >= 0) & (s < len(lut))
    if np.any(small & ~known):
        raise InputError(
            f"semantic ids hold unknown labels {np.unique(s[small & ~known]).tolist()}"
        )
    out[known] = lut[s[known]]
    return out


def colorize_semantic(semantic: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 colour image of a semantic image: sky black, ground dark grey,
    lander gold, each rock a distinct hashed colour."""
    s = np.asarray(semantic).astype(np.int64)
    out = np.zeros(s.shape + (3,), np.uint8)
    out[s == SEM_GROUND] = (70, 70, 80)
    out[s == SEM_LANDER] = (230, 180, 40)
    out[s == SEM_FIDUCIAL] = (30, 170, 250)
    rock = s >= SEM_ROCK_OFFSET
    k = (s[rock] - SEM_ROCK_OFFSET).astype(np.uint64)
    h = (k * np.uint64(2654435761) + np.uint64(12345)) & np.uint64(0xFFFFFF)
    rgb = np.stack(
        [
            (h >> np.uint64(16)) & np.uint64(255),
            (h >> np.uint64(8)) & np.uint64(255),
            h & np.uint64(255),
        ],
        1,
    )
    out[rock] = (80 + (rgb.astype(np.int64) * 175) // 255).astype(np.uint8)
    return out


class _ValueNoise:
    """Seeded, tileable multi-octave value-noise tables (evaluated in :func:`_shade_kernel`).

    Octave k has cell size ``scales_m[k]`` metres, weight ``weights[k]`` (albedo) and
    bump height ``bumps_m[k]`` metres (terrain normal perturbation).
    """

    def __init__(
        self,
        seed: int,
        scales_m=(0.004, 0.012, 0.04, 0.15, 0.6, 2.5),
        weights=(0.15, 0.3, 0.3, 0.2, 0.12, 0.08),
        bumps_m=(0.0002, 0.0004, 0.0015, 0.007, 0.012, 0.0),
    ):
        rng = np.random.default_rng([int(seed), 0xA1B])
        self.tables = rng.uniform(-1.0, 1.0, size=(len(scales_m), 256, 256)).astype(np.float32)
        self.inv_scales = (1.0 / np.asarray(scales_m, np.float64)).astype(np.float32)
        self.offsets = rng.uniform(0, 256, size=(len(scales_m), 2)).astype(np.float32)
        self.weights = np.asarray(weights, np.float32)
        self.bumps = np.asarray(bumps_m, np.float32)


def _shade_kernel_py(
    prim,
    cam_idx,
    cam_origins,
    dirs,
    faces,
    verts,
    face_normals,
    face_kind,
    face_label,
    vertex_normals,
    gx,
    gy,
    grid_x0,
    grid_y0,
    grid_inv_res,
    shift,
    sun,
    noise_tab,
    noise_inv,
    noise_off,
    noise_w,
    noise_bump,
    rock_albedo,
    ground_albedo,
    lander_albedo,
    albedo_texture,
    bump_strength,
    L,
    rock_facet,
    rock_bump,
    face_albedo,
    face_panel,
    panel_origin,
    panel_u,
    panel_v,
    panel_inv_size,
    panel_bits,
    sun_on,
    lamp_pos,
    lamp_axis,
    lamp_power,
    cos_inner,
    cos_outer,
    terrain_up,
    out_direct,
    out_lamp,
    out_albedo,
    out_shadow_origin,
    out_need_shadow,
):  # pragma: no cover - compiled by numba
    """Per-hit shading (compiled with numba): hit point, normals, Lunar-Lambert under the sun
    and the lamps, albedo texture, fiducial patterns.

    Coordinates are in the renderer's local frame (site frame minus ``shift``).
    """
    ny, nx = gx.shape
    n_oct = noise_tab.shape[0]
    n_lamps = lamp_pos.shape[0]
    n_bits = panel_bits.shape[1]
    for k in range(prim.shape[0]):
        f = prim[k]
        c = cam_idx[k]
        ox = cam_origins[c, 0]
        oy = cam_origins[c, 1]
        oz = cam_origins[c, 2]
        dx = dirs[k, 0]
        dy = dirs[k, 1]
        dz = dirs[k, 2]
        nfx = face_normals[f, 0]
        nfy = face_normals[f, 1]
        nfz = face_normals[f, 2]
        i0 = faces[f, 0]
        den = dx * nfx + dy * nfy + dz * nfz
        if abs(den) < 1e-12:
            den = 1e-12
        t = (
            (verts[i0, 0] - ox) * nfx + (verts[i0, 1] - oy) * nfy + (verts[i0, 2] - oz) * nfz
        ) / den
        px = ox + dx * t
        py = oy + dy * t
        pz = oz + dz * t
        if den > 0:  # back face: orient the geometric normal toward the viewer
            nfx = -nfx
            nfy = -nfy
            nfz = -nfz
        # site coordinates for texture / heightfield look-ups
        sx = px + shift[0]
        sy = py + shift[1]
        sz = pz + shift[2]
        kind = face_kind[f]
        # albedo texture and bump gradient (value noise with analytic derivative)
        tex = 0.0
        bx = 0.0
        by = 0.0
        if kind == 1:  # rocks: texture in a skewed plane so vertical faces vary too
            qx = sx + 0.7 * sz
            qy = sy - 0.7 * sz
        else:
            qx = sx
            qy = sy
        for o in range(n_oct):
            inv = noise_inv[o]
            fx = qx * inv + noise_off[o, 0]
            fy = qy * inv + noise_off[o, 1]
            ix = np.floor(fx)
            iy = np.floor(fy)
            tx = fx - ix
            ty = fy - iy
            ux = tx * tx * (3.0 - 2.0 * tx)
            uy = ty * ty * (3.0 - 2.0 * ty)
            a0 = int(ix) & 255
            b0 = int(iy) & 255
            a1 = (a0 + 1) & 255
            b1 = (b0 + 1) & 255
            v00 = noise_tab[o, b0, a0]
            v01 = noise_tab[o, b0, a1]
            v10 = noise_tab[o, b1, a0]
            v11 = noise_tab[o, b1, a1]
            lo = v00 + (v01 - v00) * ux
            hi = v10 + (v11 - v10) * ux
            tex += noise_w[o] * (lo + (hi - lo) * uy)
            hb = noise_bump[o]
            if hb != 0.0:
                dux = 6.0 * tx * (1.0 - tx) * inv
                duy = 6.0 * ty * (1.0 - ty) * inv
                bx += hb * ((v01 - v00) * (1.0 - uy) + (v11 - v10) * uy) * dux
                by += hb * (hi - lo) * duy
        # shading normal
        if kind == 0:  # terrain: bilinear heightfield gradient + bump
            gxf = (sx - grid_x0) * grid_inv_res
            gyf = (sy - grid_y0) * grid_inv_res
            gxf = min(max(gxf, 0.0), nx - 1.000001)
            gyf = min(max(gyf, 0.0), ny - 1.000001)
            gi = int(gxf)
            gj = int(gyf)
            wx = gxf - gi
            wy = gyf - gj
            sxg = (gx[gj, gi] * (1 - wx) + gx[gj, gi + 1] * wx) * (1 - wy) + (
                gx[gj + 1, gi] * (1 - wx) + gx[gj + 1, gi + 1] * wx
            ) * wy
            syg = (gy[gj, gi] * (1 - wx) + gy[gj, gi + 1] * wx) * (1 - wy) + (
                gy[gj + 1, gi] * (1 - wx) + gy[gj + 1, gi + 1] * wx
            ) * wy
            fade = bump_strength / (1.0 + t * 0.25)  # fade the bumps with distance (aliasing)
            nx_ = -(sxg + fade * bx)
            ny_ = -(syg + fade * by)
            nz_ = 1.0
            albedo = ground_albedo * (1.0 + albedo_texture * tex)
        elif kind == 1:  # rock: barycentric vertex normals, mixed with the facet normal, plus bump
            i1 = faces[f, 1]
            i2 = faces[f, 2]
            e0x = verts[i1, 0] - verts[i0, 0]
            e0y = verts[i1, 1] - verts[i0, 1]
            e0z = verts[i1, 2] - verts[i0, 2]
            e1x = verts[i2, 0] - verts[i0, 0]
            e1y = verts[i2, 1] - verts[i0, 1]
            e1z = verts[i2, 2] - verts[i0, 2]
            e2x = px - verts[i0, 0]
            e2y = py - verts[i0, 1]
            e2z = pz - verts[i0, 2]
            d00 = e0x * e0x + e0y * e0y + e0z * e0z
            d01 = e0x * e1x + e0y * e1y + e0z * e1z
            d11 = e1x * e1x + e1y * e1y + e1z * e1z
            d20 = e2x * e0x + e2y * e0y + e2z * e0z
            d21 = e2x * e1x + e2y * e1y + e2z * e1z
            dd = d00 * d11 - d01 * d01
            if abs(dd) < 1e-20:
                dd = 1e-20
            wv = (d11 * d20 - d01 * d21) / dd
            ww = (d00 * d21 - d01 * d20) / dd
            wu = 1.0 - wv - ww
            nx_ = (
                wu * vertex_normals[i0, 0] + wv * vertex_normals[i1, 0] + ww * vertex_normals[i2, 0]
            )
            ny_ = (
                wu * vertex_normals[i0, 1] + wv * vertex_normals[i1, 1] + ww * vertex_normals[i2, 1]
            )
            nz_ = (
                wu * vertex_normals[i0, 2] + wv * vertex_normals[i1, 2] + ww * vertex_normals[i2, 2]
            )
            nn = np.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_) + 1e-12
            s_ = 1.0 if nx_ * nfx + ny_ * nfy + nz_ * nfz >= 0 else -1.0
            nx_ = (1 - rock_facet) * s_ * nx_ / nn + rock_facet * nfx
            ny_ = (1 - rock_facet) * s_ * ny_ / nn + rock_facet * nfy
            nz_ = (1 - rock_facet) * s_ * nz_ / nn + rock_facet * nfz
            # bump: the gradient of the noise height field h(q(s)) projected on the surface
            fade = rock_bump / (1.0 + t * 0.25)
            hgx = fade * bx
            hgy = fade * by
            hgz = fade * 0.7 * (bx - by)
            nn = np.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_) + 1e-12
            nx_ /= nn
            ny_ /= nn
            nz_ /= nn
            gn = hgx * nx_ + hgy * ny_ + hgz * nz_
            nx_ -= hgx - gn * nx_
            ny_ -= hgy - gn * ny_
            nz_ -= hgz - gn * nz_
            albedo = rock_albedo[face_label[f] - 10] * (1.0 + 0.8 * albedo_texture * tex)
        elif kind == 3:  # fiducial panel: a tag pattern on a square
            pid = face_panel[f]
            u = (
                (sx - panel_origin[pid, 0]) * panel_u[pid, 0]
                + (sy - panel_origin[pid, 1]) * panel_u[pid, 1]
                + (sz - panel_origin[pid, 2]) * panel_u[pid, 2]
            ) * panel_inv_size[pid]
            v = (
                (sx - panel_origin[pid, 0]) * panel_v[pid, 0]
                + (sy - panel_origin[pid, 1]) * panel_v[pid, 1]
                + (sz - panel_origin[pid, 2]) * panel_v[pid, 2]
            ) * panel_inv_size[pid]
            cu = min(max(int(u * n_bits), 0), n_bits - 1)
            cv = min(max(int(v * n_bits), 0), n_bits - 1)
            nx_ = nfx
            ny_ = nfy
            nz_ = nfz
            albedo = lander_albedo * face_albedo[f] * (0.02 + 0.98 * panel_bits[pid, cv, cu])
        else:  # lander
            nx_ = nfx
            ny_ = nfy
            nz_ = nfz
            albedo = lander_albedo * face_albedo[f]
        nn = np.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_) + 1e-12
        nx_ /= nn
        ny_ /= nn
        nz_ /= nn
        if nx_ * dx + ny_ * dy + nz_ * dz > 0 and not (terrain_up and kind == 0):
            nx_ = -nx_
            ny_ = -ny_
            nz_ = -nz_
        cos_e = -(nx_ * dx + ny_ * dy + nz_ * dz)
        if cos_e < 0:
            cos_e = 0.0
        # Lunar-Lambert (McEwen 1991): (1 - L) cos i + L * 2 cos i / (cos i + cos e)
        if sun_on:
            cos_i = nx_ * sun[0] + ny_ * sun[1] + nz_ * sun[2]
            if cos_i < 0:
                cos_i = 0.0
            refl = (1.0 - L) * cos_i + L * 2.0 * cos_i / (cos_i + cos_e + 1e-3)
            out_direct[k] = albedo * refl
            out_need_shadow[k] = cos_i > 0 and (nfx * sun[0] + nfy * sun[1] + nfz * sun[2]) > -0.05
        else:
            out_direct[k] = 0.0
            out_need_shadow[k] = False
        # lamps: spot lights, inverse-square fall-off, smooth cone, no shadows
        lamp = 0.0
        for j in range(n_lamps):
            lx = lamp_pos[j, 0] - px
            ly = lamp_pos[j, 1] - py
            lz = lamp_pos[j, 2] - pz
            d2 = lx * lx + ly * ly + lz * lz + 1e-6
            dl = np.sqrt(d2)
            lx /= dl
            ly /= dl
            lz /= dl
            cos_axis = -(lx * lamp_axis[j, 0] + ly * lamp_axis[j, 1] + lz * lamp_axis[j, 2])
            if cos_axis <= cos_outer:
                continue
            w = (cos_axis - cos_outer) / (cos_inner - cos_outer)
            if w > 1.0:
                w = 1.0
            w = w * w * (3.0 - 2.0 * w)
            cos_l = nx_ * lx + ny_ * ly + nz_ * lz
            if cos_l <= 0:
                continue
            refl = (1.0 - L) * cos_l + L * 2.0 * cos_l / (cos_l + cos_e + 1e-3)
            lamp += lamp_power[j] * w * refl / d2
        out_lamp[k] = albedo * lamp
        out_albedo[k] = albedo
        eps = 2e-3 + 2e-4 * t
        out_shadow_origin[k, 0] = px + nfx * eps
        out_shadow_origin[k, 1] = py + nfy * eps
        out_shadow_origin[k, 2] = pz + nfz * eps


def _boxes_occlude_py(
    origins, offset, R, direction, reach2, box_min, box_max, out
):  # pragma: no cover - numba
    """Slab test: ``out[k] |= `` the ray ``q_k + t * d`` (t > 0) hits one of the boxes, with
    ``q_k = R^T (origins[k] + offset)`` and ``d = R^T direction`` in the boxes' frame.
    Rays starting farther than ``sqrt(reach2)`` from the boxes' origin are skipped."""
    d0 = R[0, 0] * direction[0] + R[1, 0] * direction[1] + R[2, 0] * direction[2]
    d1 = R[0, 1] * direction[0] + R[1, 1] * direction[1] + R[2, 1] * direction[2]
    d2 = R[0, 2] * direction[0] + R[1, 2] * direction[1] + R[2, 2] * direction[2]
    d = (d0, d1, d2)
    for k in range(origins.shape[0]):
        if out[k]:
            continue
        rx = origins[k, 0] + offset[0]
        ry = origins[k, 1] + offset[1]
        rz = origins[k, 2] + offset[2]
        if rx * rx + ry * ry + rz * rz > reach2:
            continue
        q = (
            R[0, 0] * rx + R[1, 0] * ry + R[2, 0] * rz,
            R[0, 1] * rx + R[1, 1] * ry + R[2, 1] * rz,
            R[0, 2] * rx + R[1, 2] * ry + R[2, 2] * rz,
        )
        for b in range(box_min.shape[0]):
            t0 = 0.0
            t1 = 1e30
            hit = True
            for a in range(3):
                if abs(d[a]) < 1e-12:
                    if q[a] < box_min[b, a] or q[a] > box_max[b, a]:
                        hit = False
                        break
                else:
                    ta = (box_min[b, a] - q[a]) / d[a]
                    tb = (box_max[b, a] - q[a]) / d[a]
                    if ta > tb:
                        ta, tb = tb, ta
                    t0 = max(t0, ta)
                    t1 = min(t1, tb)
                    if t0 > t1:
                        hit = False
                        break
            if hit:
                out[k] = True
                break


_SHADE_KERNEL = None
_BOX_KERNEL = None


def _shade_kernel():
    """The numba-compiled :func:`_shade_kernel_py` (compiled once, cached on disk)."""
    global _SHADE_KERNEL
    if _SHADE_KERNEL is None:
        import numba

        _SHADE_KERNEL = numba.njit(cache=True, fastmath=True, nogil=True)(_shade_kernel_py)
    return _SHADE_KERNEL


def _box_kernel():
    """The numba-compiled :func:`_boxes_occlude_py`."""
    global _BOX_KERNEL
    if _BOX_KERNEL is None:
        import numba

        _BOX_KERNEL = numba.njit(cache=True, nogil=True)(_boxes_occlude_py)
    return _BOX_KERNEL


class SiteRenderer:
    """Renders a :class:`~lunarloc.sim.site.Site` from camera poses.

    Build once per site (the BVH build takes about a second); then call
    :meth:`render` with the optical-frame poses of one or more cameras, or
    :meth:`render_rover` with a rover pose and camera mounts.
    """

    def __init__(self, site, config: RenderConfig | None = None):
        self.site = site
        self.config = config or RenderConfig()
        self.config.validate()
        require("trimesh", "sim")
        rtcore_scene = require("embreex.rtcore_scene", "sim")
        mesh_construction = require("embreex.mesh_construction", "sim")

        terrain = site.terrain_mesh()
        rocks = site.rock_meshes()
        verts = [np.asarray(terrain.vertices)]
        faces = [np.asarray(terrain.faces)]
        labels = [np.full(len(terrain.faces), SEM_GROUND, np.uint16)]
        kinds = [np.full(len(terrain.faces), _KIND_TERRAIN, np.uint8)]
        albedo_scale = [np.ones(len(terrain.faces), np.float32)]
        panel_of_face = [np.full(len(terrain.faces), -1, np.int32)]
        offset = len(terrain.vertices)
        rock_vn = [np.zeros((len(terrain.vertices), 3))]

        def add(v, f, label, kind, scale=1.0, panel=-1, vn=None):
            nonlocal offset
            verts.append(np.asarray(v, float))
            faces.append(np.asarray(f) + offset)
            labels.append(np.full(len(f), label, np.uint16))
            kinds.append(np.full(len(f), kind, np.uint8))
            albedo_scale.append(np.full(len(f), scale, np.float32))
            panel_of_face.append(np.full(len(f), panel, np.int32))
            rock_vn.append(np.zeros((len(v), 3)) if vn is None else np.asarray(vn))
            offset += len(v)

        for k, m in enumerate(rocks):
            add(
                m.vertices,
                m.faces,
                SEM_ROCK_OFFSET + int(site.rocks.ids[k]),
                _KIND_ROCK,
                vn=m.vertex_normals,
            )
        for part, scale in site.lander_parts():
            add(part.vertices, part.faces, SEM_LANDER, _KIND_LANDER, scale)
        panels = site.fiducial_panels()
        quad = np.array([[0, 1, 2], [0, 2, 3]])
        for i in range(len(panels)):
            o = panels.centers[i] - 0.5 * panels.size_m[i] * (panels.u_axes[i] + panels.v_axes[i])
            u, v = panels.size_m[i] * panels.u_axes[i], panels.size_m[i] * panels.v_axes[i]
            add(np.array([o, o + u, o + u + v, o + v]), quad, SEM_FIDUCIAL, _KIND_FIDUCIAL, panel=i)
        self._panel_origin = panels.centers - 0.5 * panels.size_m[:, None] * (
            panels.u_axes + panels.v_axes
        )
        self._panels = panels

        self.vertices = np.concatenate(verts).astype(np.float64)
        self.faces = np.concatenate(faces).astype(np.int32)
        self.face_label = np.concatenate(labels)
        self.face_kind = np.concatenate(kinds)
        self.face_albedo = np.concatenate(albedo_scale)
        self.face_panel = np.concatenate(panel_of_face)
        self.vertex_normals = np.concatenate(rock_vn).astype(np.float32)
        tri = self.vertices[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.face_normals = (
            n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
        ).astype(np.float32)
        self.face_v0 = tri[:, 0].astype(np.float32)
        n_rocks = len(site.rocks)
        self._materials()
        self.face_normals = np.ascontiguousarray(self.face_normals)
        # Embree works in float32: shift to the scene centre for precision
        self._origin = self.vertices.mean(axis=0)
        self._verts_local = (self.vertices - self._origin).astype(np.float32)
        gy, gx = np.gradient(site.heights, site.config.resolution_m)
        self._gx = np.ascontiguousarray(gx, np.float32)
        self._gy = np.ascontiguousarray(gy, np.float32)
        self._scene = rtcore_scene.EmbreeScene()
        mesh_construction.TriangleMesh(
            scene=self._scene, vertices=self._verts_local, indices=self.faces
        )
        self._panel_origin_f32 = np.ascontiguousarray(self._panel_origin, np.float32)  # site frame
        self._rays_cache: dict[PinholeCamera, np.ndarray] = {}
        logger.debug("renderer: %d triangles (%d rocks)", len(self.faces), n_rocks)

    def _materials(self) -> None:
        """Per-rock albedo and the texture tables (they depend on the config and the site seed)."""
        site = self.site
        rng = np.random.default_rng([int(site.seed), 0x40C])
        spread = self.config.rock_albedo_spread
        self.rock_albedo = (
            self.config.rock_albedo
            * rng.uniform(1.0 - spread, 1.0 + spread, max(len(site.rocks), 1))
        ).astype(np.float32)
        self.texture = _ValueNoise(self.config.texture_seed + 1000 * int(site.seed))

    def with_config(self, config: RenderConfig) -> SiteRenderer:
        """A renderer of the same site with another config, sharing this one's scene (no BVH
        rebuild)."""
        config.validate()
        other = SiteRenderer.__new__(SiteRenderer)
        other.__dict__.update(self.__dict__)
        other.config = config
        other._materials()
        return other

    # --------------------------------------------------------------- ray casts
    def _cast(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """First-hit triangle index per ray (-1 for none); origins/dirs (N, 3) site frame."""
        o = (origins - self._origin).astype(np.float32)
        return np.asarray(self._scene.run(o, dirs.astype(np.float32), query="INTERSECT"))

    def _occluded(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        o = (origins - self._origin).astype(np.float32)
        return (
            np.asarray(self._scene.run(o, np.ascontiguousarray(dirs, np.float32), query="OCCLUDED"))
            == 0
        )

    def cast_rays(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hits of rays (site frame): (distance along the unit ray or inf, semantic label)."""
        origins = np.asarray(origins, float).reshape(-1, 3)
        dirs = np.asarray(dirs, float).reshape(-1, 3)
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        prim = self._cast(origins, dirs)
        hit = prim >= 0
        t = np.full(len(prim), np.inf)
        p = prim[hit]
        nf = self.face_normals[p].astype(float)
        t[hit] = np.einsum("ij,ij->i", self.face_v0[p] - origins[hit], nf) / np.einsum(
            "ij,ij->i", dirs[hit], nf
        )
        label = np.zeros(len(prim), np.uint16)
        label[hit] = self.face_label[p]
        return t, label

    # --------------------------------------------------------------- render
    def _camera_rays(self, camera: PinholeCamera) -> np.ndarray:
        rays = self._rays_cache.get(camera)
        if rays is None:
            rays = camera.rays_optical().reshape(-1, 3).astype(np.float32)
            self._rays_cache[camera] = rays
        return rays

    def render(
        self,
        T_world_optical: list[np.ndarray],
        camera: PinholeCamera,
        *,
        T_world_rover: np.ndarray | None = None,
        light_intensity: float | dict[str, float] | None = None,
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Render cameras with the given optical-frame poses (4x4, site frame; OpenCV axes).

        All cameras share the intrinsics `camera` and are ray-cast in one batch.
        With `T_world_rover` (the rover's pose, 4x4) and a lighting with lamps, the
        rover's lamps light the scene (`light_intensity`: one LAC intensity 0-1 or
        ``{camera: intensity}``; default ``config.lamp_intensity``) and its body
        shades the sun; without it only the sun lights the scene.
        Returns one ``(grayscale (H, W) uint8, semantic (H, W) uint16)`` per pose.
        """
        cfg = self.config
        if len(T_world_optical) == 0:
            return []
        rays = self._camera_rays(camera)
        npx = rays.shape[0]
        n_cam = len(T_world_optical)
        dirs = np.empty((n_cam * npx, 3), np.float32)
        origins = np.empty((n_cam * npx, 3), np.float32)
        for c, T in enumerate(T_world_optical):
            T = np.asarray(T, float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise InputError(
                    f"camera pose {c} must be a finite 4x4 matrix, got shape {T.shape}"
                )
            dirs[c * npx : (c + 1) * npx] = rays @ T[:3, :3].T.astype(np.float32)
            origins[c * npx : (c + 1) * npx] = (T[:3, 3] - self._origin).astype(np.float32)
        if T_world_rover is not None:
            T_world_rover = np.asarray(T_world_rover, float)
            if T_world_rover.shape != (4, 4) or not np.all(np.isfinite(T_world_rover)):
                raise InputError(
                    f"T_world_rover must be a finite 4x4 matrix, got shape {T_world_rover.shape}"
                )
        if T_world_rover is not None and cfg.lamps_on:
            lamp_pos, lamp_axis, inten = rover_lamps(
                T_world_rover, cfg.lamp_intensity if light_intensity is None else light_intensity
            )
            lamp_pos = (lamp_pos - self._origin).astype(np.float32)
            lamp_axis = lamp_axis.astype(np.float32)
            lamp_power = (cfg.lamp_power * inten).astype(np.float32)
        else:
            lamp_pos = np.zeros((0, 3), np.float32)
            lamp_axis = np.zeros((0, 3), np.float32)
            lamp_power = np.zeros(0, np.float32)
        prim = np.asarray(self._scene.run(origins, dirs, query="INTERSECT"))
        hit = np.flatnonzero(prim >= 0)
        p = prim[hit].astype(np.int32)
        cam_idx = (hit // npx).astype(np.int32)
        cam_origins = np.stack(
            [np.asarray(T, float)[:3, 3] - self._origin for T in T_world_optical]
        ).astype(np.float32)
        d = dirs[hit]
        m = hit.size
        direct = np.empty(m, np.float32)
        lamp = np.empty(m, np.float32)
        albedo = np.empty(m, np.float32)
        shadow_origin = np.empty((m, 3), np.float32)
        need_shadow = np.empty(m, np.bool_)
        sun = sun_direction(cfg.sun_elevation_deg, cfg.sun_azimuth_deg).astype(np.float32)
        tx = self.texture
        pn = self._panels
        cone = np.cos(np.radians(cfg.lamp_cone_deg))
        _shade_kernel()(
            p,
            cam_idx,
            cam_origins,
            d,
            self.faces,
            self._verts_local,
            self.face_normals,
            self.face_kind,
            self.face_label,
            self.vertex_normals,
            self._gx,
            self._gy,
            np.float32(self.site.grid_x[0]),
            np.float32(self.site.grid_y[0]),
            np.float32(1.0 / self.site.config.resolution_m),
            self._origin.astype(np.float32),
            sun,
            tx.tables,
            tx.inv_scales,
            tx.offsets,
            tx.weights,
            tx.bumps,
            self.rock_albedo,
            np.float32(cfg.ground_albedo),
            np.float32(cfg.lander_albedo),
            np.float32(cfg.albedo_texture),
            np.float32(cfg.bump_strength),
            np.float32(cfg.lunar_lambert_L),
            np.float32(cfg.rock_facet),
            np.float32(cfg.rock_bump),
            self.face_albedo,
            self.face_panel,
            self._panel_origin_f32,
            pn.u_axes.astype(np.float32),
            pn.v_axes.astype(np.float32),
            (1.0 / np.maximum(pn.size_m, 1e-9)).astype(np.float32),
            pn.bits.astype(np.float32),
            bool(cfg.sun_on),
            lamp_pos,
            lamp_axis,
            lamp_power,
            np.float32(cone[0]),
            np.float32(cone[1]),
            bool(cfg.terrain_up_normal),
            direct,
            lamp,
            albedo,
            shadow_origin,
            need_shadow,
        )
        if cfg.sun_on and cfg.shadows:
            lit = np.flatnonzero(need_shadow)
            if lit.size:
                occ = np.asarray(
                    self._scene.run(
                        shadow_origin[lit],
                        np.broadcast_to(sun, (lit.size, 3)).copy(),
                        query="OCCLUDED",
                    )
                )
                shaded = occ == 0
                if T_world_rover is not None and cfg.rover_shadow:
                    shaded |= self._rover_occludes(shadow_origin[lit], sun, T_world_rover)
                direct[lit[shaded]] = 0.0
        ambient = np.float32(cfg.ambient if cfg.sun_on else 0.0)
        radiance = (direct + lamp + albedo * ambient) * np.float32(cfg.exposure)
        knee = np.float32(cfg.highlight_knee)
        # soft shoulder: x above the knee -> knee + (1 - knee) (1 - exp(-(x - knee) / (1 - knee)))
        if knee < 1.0:
            over = radiance > knee
            radiance[over] = knee + (1 - knee) * -np.expm1(-(radiance[over] - knee) / (1 - knee))
        val = np.clip(radiance, 0.0, 1.0) ** np.float32(1.0 / cfg.gamma)
        gray_all = np.zeros(n_cam * npx, np.uint8)
        gray_all[hit] = (val * 255.0 + 0.5).astype(np.uint8)
        sem_all = np.zeros(n_cam * npx, np.uint16)
        sem_all[hit] = self.face_label[p]
        H, W = camera.height, camera.width
        return [
            (
                gray_all[c * npx : (c + 1) * npx].reshape(H, W),
                sem_all[c * npx : (c + 1) * npx].reshape(H, W),
            )
            for c in range(n_cam)
        ]

    def _rover_occludes(
        self, origins_local: np.ndarray, sun: np.ndarray, T_world_rover: np.ndarray
    ) -> np.ndarray:
        """Which sun shadow rays (origins in the renderer's local frame) hit the rover's boxes."""
        out = np.zeros(len(origins_local), np.bool_)
        reach = 0.5 + 0.6 / max(float(sun[2]), 0.02)  # only points this close can be in its shadow
        boxes = np.asarray(ROVER_BOXES, float)
        _box_kernel()(
            origins_local,
            self._origin - T_world_rover[:3, 3],
            np.ascontiguousarray(T_world_rover[:3, :3]),
            np.asarray(sun, float),
            reach * reach,
            np.ascontiguousarray(boxes[:, 0]),
            np.ascontiguousarray(boxes[:, 1]),
            out,
        )
        return out

    def render_rover(
        self,
        pose_xyzrpy,
        mounts: dict[str, CameraMount] | list[CameraMount],
        *,
        light_intensity: float | dict[str, float] | None = None,
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Render the given cameras of a rover at ``pose_xyzrpy`` (site frame, metres/radians).

        The rover's lamps (when the lighting has them; `light_intensity` as in
        :meth:`render`) and its body's shadow come with the pose.
        All mounts must share one PinholeCamera. Returns ``{name: (grayscale, semantic)}``.
        """
        ms = list(mounts.values()) if isinstance(mounts, dict) else list(mounts)
        if not ms:
            return {}
        cam = ms[0].camera
        if any(m.camera != cam for m in ms):
            raise InputError("render_rover: all cameras must share the same intrinsics")
        T_world_rover = pose_to_matrix(*pose_xyzrpy)
        images = self.render(
            [T_world_rover @ m.T_rover_optical for m in ms],
            cam,
            T_world_rover=T_world_rover,
            light_intensity=light_intensity,
        )
        return {m.name: img for m, img in zip(ms, images)}
