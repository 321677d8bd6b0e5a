"""Ray-cast renderer of the simulated site: grayscale images with hard sun shadows
and a per-pixel semantic ground truth (Embree through embreex, as used by trimesh).

Rendering model
---------------
* One Embree BVH holds the whole scene (terrain heightfield mesh, rock meshes,
  lander) and is reused for every frame; the rays of several cameras (a stereo
  pair, or all four cameras) are cast in one batch.
* Sun: a directional light at ``sun_elevation_deg`` above the horizon and
  ``sun_azimuth_deg`` (counter-clockwise from the site +x axis). Hard cast
  shadows: a shadow ray is cast from every lit hit point toward the sun.
* No atmosphere: rays that hit nothing are black sky; shadows get only a small
  ambient term (light scattered from the surrounding terrain).
* Regolith: Lunar-Lambert (McEwen) reflectance
  ``(1 - L) cos i + L * 2 cos i / (cos i + cos e)`` with a seeded procedural
  albedo texture (multi-octave value noise in site coordinates, so it is fixed
  on the ground and consistent between the two cameras of a pair). Rocks are a
  little brighter than the regolith, each with its own albedo.

Semantic encoding (``uint16`` single-channel image, 16-bit PNG when stored)
--------------------------------------------------------------------------
* ``0`` sky (no hit), ``1`` ground (terrain), ``2`` lander,
* ``10 + rock_id`` a rock (``rock_id`` as in the ground-truth rock list), so up to
  65525 rocks. Use :func:`semantic_to_rock_id` / :func:`colorize_semantic`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from lunarloc.errors import ConfigError, InputError, require
from lunarloc.geometry import pose_to_matrix
from lunarloc.perception.camera import CameraMount, PinholeCamera

__all__ = [
    "SEM_SKY",
    "SEM_GROUND",
    "SEM_LANDER",
    "SEM_ROCK_OFFSET",
    "RenderConfig",
    "SiteRenderer",
    "semantic_to_rock_id",
    "colorize_semantic",
    "sun_direction",
]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

SEM_SKY = 0
SEM_GROUND = 1
SEM_LANDER = 2
SEM_ROCK_OFFSET = 10
"""Semantic label of rock ``k`` is ``SEM_ROCK_OFFSET + k``."""

_KIND_TERRAIN, _KIND_ROCK, _KIND_LANDER = 0, 1, 2


@dataclass(frozen=True)
class RenderConfig:
    """Lighting, material and exposure of the renderer."""

    sun_elevation_deg: float = 12.0  # LAC / lunar south pole: low sun, 5-30 deg
    sun_azimuth_deg: float = 135.0  # counter-clockwise from the site +x axis
    shadows: bool = True  # hard cast shadows (shadow rays)
    ground_albedo: float = 0.55  # relative regolith albedo (before exposure)
    rock_albedo: float = 0.7  # relative rock albedo (rocks are less weathered)
    lander_albedo: float = 1.2  # foil and paint
    albedo_texture: float = 0.35  # strength of the regolith albedo texture (0 = flat)
    bump_strength: float = 1.0  # scale of the small-scale regolith roughness (normal bumps)
    rock_facet: float = 0.35  # 0 = smooth rock shading, 1 = flat facets
    lunar_lambert_L: float = 0.6  # limb-darkening mix of the Lunar-Lambert law
    ambient: float = 0.025  # light in shadows, fraction of the direct sun
    exposure: float = 1.0  # scale before the gamma curve
    gamma: float = 1.8  # display gamma
    texture_seed: int = 0  # seed of the albedo texture

    def validate(self) -> None:
        if not -10.0 <= self.sun_elevation_deg <= 90.0:
            raise ConfigError(f"sun_elevation_deg={self.sun_elevation_deg} must be in [-10, 90]")
        if self.gamma <= 0 or self.exposure <= 0:
            raise ConfigError("gamma and exposure must be > 0")
        if not 0.0 <= self.lunar_lambert_L <= 1.0:
            raise ConfigError("lunar_lambert_L must be in [0, 1]")


def sun_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector toward the sun in the site frame (z up, azimuth from +x toward +y)."""
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def semantic_to_rock_id(semantic: np.ndarray) -> np.ndarray:
    """Rock id per pixel (int32), -1 where the pixel is not a rock."""
    s = np.asarray(semantic).astype(np.int32)
    return np.where(s >= SEM_ROCK_OFFSET, s - SEM_ROCK_OFFSET, -1)


def colorize_semantic(semantic: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 colour image of a semantic image: sky black, ground dark grey,
    lander gold, each rock a distinct hashed colour."""
    s = np.asarray(semantic).astype(np.int64)
    out = np.zeros(s.shape + (3,), np.uint8)
    out[s == SEM_GROUND] = (70, 70, 80)
    out[s == SEM_LANDER] = (230, 180, 40)
    rock = s >= SEM_ROCK_OFFSET
    k = (s[rock] - SEM_ROCK_OFFSET).astype(np.uint64)
    h = (k * np.uint64(2654435761) + np.uint64(12345)) & np.uint64(0xFFFFFF)
    rgb = np.stack([(h >> np.uint64(16)) & np.uint64(255), (h >> np.uint64(8)) & np.uint64(255), h & np.uint64(255)], 1)
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
        scales_m=(0.012, 0.04, 0.15, 0.6, 2.5),
        weights=(0.3, 0.3, 0.2, 0.12, 0.08),
        bumps_m=(0.0003, 0.001, 0.004, 0.0, 0.0),
    ):
        rng = np.random.default_rng([int(seed), 0xA1B])
        self.tables = rng.uniform(-1.0, 1.0, size=(len(scales_m), 256, 256)).astype(np.float32)
        self.inv_scales = (1.0 / np.asarray(scales_m, np.float64)).astype(np.float32)
        self.offsets = rng.uniform(0, 256, size=(len(scales_m), 2)).astype(np.float32)
        self.weights = np.asarray(weights, np.float32)
        self.bumps = np.asarray(bumps_m, np.float32)


def _shade_kernel_py(
    prim, cam_idx, cam_origins, dirs, faces, verts, face_normals, face_kind, face_label, vertex_normals,
    gx, gy, grid_x0, grid_y0, grid_inv_res, shift, sun, noise_tab, noise_inv, noise_off, noise_w, noise_bump,
    rock_albedo, ground_albedo, lander_albedo, albedo_texture, bump_strength, L, rock_facet,
    out_direct, out_albedo, out_shadow_origin, out_need_shadow,
):  # pragma: no cover - compiled by numba
    """Per-hit shading (compiled with numba): hit point, normals, Lunar-Lambert, albedo texture.

    Coordinates are in the renderer's local frame (site frame minus ``shift``).
    """
    ny, nx = gx.shape
    n_oct = noise_tab.shape[0]
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
        t = ((verts[i0, 0] - ox) * nfx + (verts[i0, 1] - oy) * nfy + (verts[i0, 2] - oz) * nfz) / den
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
        elif kind == 1:  # rock: barycentric vertex normals, mixed with the facet normal
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
            nx_ = wu * vertex_normals[i0, 0] + wv * vertex_normals[i1, 0] + ww * vertex_normals[i2, 0]
            ny_ = wu * vertex_normals[i0, 1] + wv * vertex_normals[i1, 1] + ww * vertex_normals[i2, 1]
            nz_ = wu * vertex_normals[i0, 2] + wv * vertex_normals[i1, 2] + ww * vertex_normals[i2, 2]
            nn = np.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_) + 1e-12
            s_ = 1.0 if nx_ * nfx + ny_ * nfy + nz_ * nfz >= 0 else -1.0
            nx_ = (1 - rock_facet) * s_ * nx_ / nn + rock_facet * nfx
            ny_ = (1 - rock_facet) * s_ * ny_ / nn + rock_facet * nfy
            nz_ = (1 - rock_facet) * s_ * nz_ / nn + rock_facet * nfz
            albedo = rock_albedo[face_label[f] - 10] * (1.0 + 0.6 * albedo_texture * tex)
        else:  # lander
            nx_ = nfx
            ny_ = nfy
            nz_ = nfz
            albedo = lander_albedo
        nn = np.sqrt(nx_ * nx_ + ny_ * ny_ + nz_ * nz_) + 1e-12
        nx_ /= nn
        ny_ /= nn
        nz_ /= nn
        if nx_ * dx + ny_ * dy + nz_ * dz > 0:
            nx_ = -nx_
            ny_ = -ny_
            nz_ = -nz_
        cos_i = nx_ * sun[0] + ny_ * sun[1] + nz_ * sun[2]
        cos_e = -(nx_ * dx + ny_ * dy + nz_ * dz)
        if cos_i < 0:
            cos_i = 0.0
        if cos_e < 0:
            cos_e = 0.0
        # Lunar-Lambert (McEwen 1991): (1 - L) cos i + L * 2 cos i / (cos i + cos e)
        refl = (1.0 - L) * cos_i + L * 2.0 * cos_i / (cos_i + cos_e + 1e-3)
        out_direct[k] = albedo * refl
        out_albedo[k] = albedo
        need = cos_i > 0 and (nfx * sun[0] + nfy * sun[1] + nfz * sun[2]) > -0.05
        out_need_shadow[k] = need
        eps = 2e-3 + 2e-4 * t
        out_shadow_origin[k, 0] = px + nfx * eps
        out_shadow_origin[k, 1] = py + nfy * eps
        out_shadow_origin[k, 2] = pz + nfz * eps


_SHADE_KERNEL = None


def _shade_kernel():
    """The numba-compiled :func:`_shade_kernel_py` (compiled once, cached on disk)."""
    global _SHADE_KERNEL
    if _SHADE_KERNEL is None:
        import numba

        _SHADE_KERNEL = numba.njit(cache=True, fastmath=True, nogil=True)(_shade_kernel_py)
    return _SHADE_KERNEL


class SiteRenderer:
    """Renders a :class:`~lunarloc.data.site.Site` from camera poses.

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
        lander = site.lander_mesh()
        verts = [np.asarray(terrain.vertices)]
        faces = [np.asarray(terrain.faces)]
        labels = [np.full(len(terrain.faces), SEM_GROUND, np.uint16)]
        kinds = [np.full(len(terrain.faces), _KIND_TERRAIN, np.uint8)]
        offset = len(terrain.vertices)
        rock_vn = [np.zeros((len(terrain.vertices), 3))]
        for k, m in enumerate(rocks):
            verts.append(np.asarray(m.vertices))
            faces.append(np.asarray(m.faces) + offset)
            labels.append(np.full(len(m.faces), SEM_ROCK_OFFSET + int(site.rocks.ids[k]), np.uint16))
            kinds.append(np.full(len(m.faces), _KIND_ROCK, np.uint8))
            rock_vn.append(np.asarray(m.vertex_normals))
            offset += len(m.vertices)
        verts.append(np.asarray(lander.vertices))
        faces.append(np.asarray(lander.faces) + offset)
        labels.append(np.full(len(lander.faces), SEM_LANDER, np.uint16))
        kinds.append(np.full(len(lander.faces), _KIND_LANDER, np.uint8))
        rock_vn.append(np.zeros((len(lander.vertices), 3)))

        self.vertices = np.concatenate(verts).astype(np.float64)
        self.faces = np.concatenate(faces).astype(np.int32)
        self.face_label = np.concatenate(labels)
        self.face_kind = np.concatenate(kinds)
        self.vertex_normals = np.concatenate(rock_vn).astype(np.float32)
        tri = self.vertices[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.face_normals = (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)).astype(np.float32)
        self.face_v0 = tri[:, 0].astype(np.float32)
        n_rocks = len(site.rocks)
        rng = np.random.default_rng([int(site.seed), 0x40C])
        self.rock_albedo = (self.config.rock_albedo * rng.uniform(0.8, 1.25, max(n_rocks, 1))).astype(np.float32)
        self.texture = _ValueNoise(self.config.texture_seed + 1000 * int(site.seed))
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
        self._rays_cache: dict[PinholeCamera, np.ndarray] = {}
        logger.debug("renderer: %d triangles (%d rocks)", len(self.faces), n_rocks)

    # --------------------------------------------------------------- ray casts
    def _cast(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """First-hit triangle index per ray (-1 for none); origins/dirs (N, 3) site frame."""
        o = (origins - self._origin).astype(np.float32)
        return np.asarray(self._scene.run(o, dirs.astype(np.float32), query="INTERSECT"))

    def _occluded(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        o = (origins - self._origin).astype(np.float32)
        return np.asarray(self._scene.run(o, np.ascontiguousarray(dirs, np.float32), query="OCCLUDED")) == 0

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
        t[hit] = np.einsum("ij,ij->i", self.face_v0[p] - origins[hit], nf) / np.einsum("ij,ij->i", dirs[hit], nf)
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
        self, T_world_optical: list[np.ndarray], camera: PinholeCamera
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Render cameras with the given optical-frame poses (4x4, site frame; OpenCV axes).

        All cameras share the intrinsics `camera` and are ray-cast in one batch.
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
                raise InputError(f"camera pose {c} must be a finite 4x4 matrix, got shape {T.shape}")
            dirs[c * npx : (c + 1) * npx] = rays @ T[:3, :3].T.astype(np.float32)
            origins[c * npx : (c + 1) * npx] = (T[:3, 3] - self._origin).astype(np.float32)
        prim = np.asarray(self._scene.run(origins, dirs, query="INTERSECT"))
        hit = np.flatnonzero(prim >= 0)
        p = prim[hit].astype(np.int32)
        cam_idx = (hit // npx).astype(np.int32)
        cam_origins = np.stack([np.asarray(T, float)[:3, 3] - self._origin for T in T_world_optical]).astype(
            np.float32
        )
        d = dirs[hit]
        m = hit.size
        direct = np.empty(m, np.float32)
        albedo = np.empty(m, np.float32)
        shadow_origin = np.empty((m, 3), np.float32)
        need_shadow = np.empty(m, np.bool_)
        sun = sun_direction(cfg.sun_elevation_deg, cfg.sun_azimuth_deg).astype(np.float32)
        tx = self.texture
        _shade_kernel()(
            p, cam_idx, cam_origins, d, self.faces, self._verts_local, self.face_normals, self.face_kind,
            self.face_label, self.vertex_normals, self._gx, self._gy, np.float32(self.site.grid_x[0]),
            np.float32(self.site.grid_y[0]), np.float32(1.0 / self.site.config.resolution_m),
            self._origin.astype(np.float32), sun, tx.tables, tx.inv_scales, tx.offsets, tx.weights, tx.bumps,
            self.rock_albedo, np.float32(cfg.ground_albedo), np.float32(cfg.lander_albedo),
            np.float32(cfg.albedo_texture), np.float32(cfg.bump_strength), np.float32(cfg.lunar_lambert_L),
            np.float32(cfg.rock_facet), direct, albedo, shadow_origin, need_shadow,
        )  # fmt: skip
        if cfg.shadows:
            lit = np.flatnonzero(need_shadow)
            if lit.size:
                occ = np.asarray(
                    self._scene.run(shadow_origin[lit], np.broadcast_to(sun, (lit.size, 3)).copy(), query="OCCLUDED")
                )
                direct[lit[occ == 0]] = 0.0
        radiance = direct + albedo * np.float32(cfg.ambient)
        val = np.clip(radiance * np.float32(cfg.exposure), 0.0, 1.0) ** np.float32(1.0 / cfg.gamma)
        gray_all = np.zeros(n_cam * npx, np.uint8)
        gray_all[hit] = (val * 255.0 + 0.5).astype(np.uint8)
        sem_all = np.zeros(n_cam * npx, np.uint16)
        sem_all[hit] = self.face_label[p]
        H, W = camera.height, camera.width
        return [
            (gray_all[c * npx : (c + 1) * npx].reshape(H, W), sem_all[c * npx : (c + 1) * npx].reshape(H, W))
            for c in range(n_cam)
        ]

    def render_rover(
        self, pose_xyzrpy, mounts: dict[str, CameraMount] | list[CameraMount]
    ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Render the given cameras of a rover at ``pose_xyzrpy`` (site frame, metres/radians).

        All mounts must share one PinholeCamera. Returns ``{name: (grayscale, semantic)}``.
        """
        ms = list(mounts.values()) if isinstance(mounts, dict) else list(mounts)
        if not ms:
            return {}
        cam = ms[0].camera
        if any(m.camera != cam for m in ms):
            raise InputError("render_rover: all cameras must share the same intrinsics")
        T_world_rover = pose_to_matrix(*pose_xyzrpy)
        images = self.render([T_world_rover @ m.T_rover_optical for m in ms], cam)
        return {m.name: img for m, img in zip(ms, images)}
