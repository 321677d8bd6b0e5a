"""Renderer: camera geometry against ground truth, shadows, black sky, semantic encoding."""

import numpy as np
import pytest

pytest.importorskip("trimesh")
pytest.importorskip("embreex")

from lunarloc.data.render import (  # noqa: E402
    SEM_GROUND,
    SEM_ROCK_OFFSET,
    RenderConfig,
    SiteRenderer,
    colorize_semantic,
    semantic_to_rock_id,
    sun_direction,
)
from lunarloc.data.rover import plan_traverse  # noqa: E402
from lunarloc.data.site import SiteConfig, generate_site  # noqa: E402
from lunarloc.geometry import invert_transform, pose_to_matrix, transform_points  # noqa: E402
from lunarloc.perception.camera import PinholeCamera, ipex_rig  # noqa: E402

SMALL = SiteConfig(size_m=16.0, terrain_margin_m=4.0, resolution_m=0.15, n_rocks=150, rover_start_xy=(-3.0, -2.0))
CAM = PinholeCamera(320, 180)


@pytest.fixture(scope="module")
def site():
    return generate_site(7, SMALL)


@pytest.fixture(scope="module")
def renderer(site):
    return SiteRenderer(site)


@pytest.fixture(scope="module")
def traj(site):
    return plan_traverse(site, 40.0, seed=0)


def test_projected_rocks_land_in_their_semantic_mask(site, renderer, traj):
    """Project a point inside each rock's visible top (the centre may be buried) with the
    pinhole model and the rig extrinsics; it must fall in that rock's semantic mask."""
    rig = ipex_rig(CAM)
    rk = site.rocks
    top = rk.centers + np.column_stack([np.zeros((len(rk), 2)), 0.5 * rk.axes[:, 2]])
    checked = matched = 0
    for k in range(0, len(traj), 200):
        for name in ("FrontLeft", "BackLeft"):
            T_world_opt = pose_to_matrix(*traj.poses[k]) @ rig[name].T_rover_optical
            _, sem = renderer.render([T_world_opt], CAM)[0]
            P = transform_points(invert_transform(T_world_opt), top)
            uv, z = CAM.project(P)
            ok = (z > 0.3) & (uv[:, 0] > 2) & (uv[:, 0] < CAM.width - 3) & (uv[:, 1] > 2) & (uv[:, 1] < CAM.height - 3)
            ok &= CAM.fx * 0.4 * rk.axes[:, 2] / np.maximum(z, 1e-9) > 2.0  # at least ~2 px of rock around it
            idx = np.flatnonzero(ok)
            # unoccluded: the first hit along the ray from the camera to the point is that rock
            o = np.repeat(T_world_opt[None, :3, 3], len(idx), axis=0)
            _, label = renderer.cast_rays(o, top[idx] - o)
            idx = idx[label == SEM_ROCK_OFFSET + rk.ids[idx]]
            for i in idx:
                u, v = np.round(uv[i]).astype(int)
                checked += 1
                matched += int(sem[v, u] == SEM_ROCK_OFFSET + rk.ids[i])
    assert checked >= 8
    assert matched / checked >= 0.95


def test_sky_black_and_semantic_encoding(site, renderer, traj):
    rig = ipex_rig(CAM)
    out = renderer.render_rover(traj.poses[0], {n: rig[n] for n in ("FrontLeft", "FrontRight")})
    gray, sem = out["FrontLeft"]
    assert gray.dtype == np.uint8 and sem.dtype == np.uint16 and gray.shape == (180, 320)
    sky = sem == 0
    assert sky[:20].mean() > 0.9  # the top of a level camera's view is sky
    assert np.all(gray[sky] == 0)
    assert np.percentile(gray[sem == SEM_GROUND], 75) > 60  # mostly lit (a hill or the lander may shade some)
    labels = np.unique(sem)
    assert set(labels[labels < SEM_ROCK_OFFSET]) <= {0, 1, 2}
    assert np.all(semantic_to_rock_id(sem)[sem >= SEM_ROCK_OFFSET] < len(site.rocks))
    assert colorize_semantic(sem).shape == (180, 320, 3)
    # deterministic
    again = renderer.render_rover(traj.poses[0], [rig["FrontLeft"]])["FrontLeft"]
    np.testing.assert_array_equal(again[0], gray)
    np.testing.assert_array_equal(again[1], sem)


def test_cast_shadow_on_the_side_away_from_the_sun(site, renderer):
    """Look straight down on the biggest rock: the ground just beyond it, away from the
    sun, is in its shadow; the ground on the sun side is lit."""
    rk = site.rocks
    cam = PinholeCamera(240, 240, 60.0)
    s = sun_direction(renderer.config.sun_elevation_deg, renderer.config.sun_azimuth_deg)
    h = s[:2] / np.linalg.norm(s[:2])
    checked = 0
    for k in np.argsort(-rk.radii)[:8]:
        c = rk.centers[k]
        # optical frame looking down: z_opt = -z_world, x_opt = +x_world, y_opt = -y_world
        T = np.eye(4)
        T[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
        T[:3, 3] = c + [0.0, 0.0, 6.0]
        gray, sem = renderer.render([T], cam)[0]
        reach = 1.25 * rk.axes[k, :2].max() + 0.1
        vals, ground = {}, True
        for side, sign in (("sun", 1.0), ("shadow", -1.0)):
            p = c[:2] + sign * reach * h
            q = np.array([p[0], p[1], float(site.terrain_height(*p))])
            uv, _ = cam.project(transform_points(invert_transform(T), q[None]))
            u, v = np.round(uv[0]).astype(int)
            ground &= bool(sem[v, u] == SEM_GROUND)
            vals[side] = int(gray[v, u])
        if not ground or vals["sun"] < 60:  # another rock there, or the lit side shaded by something else
            continue
        checked += 1
        assert vals["shadow"] < 0.4 * vals["sun"], (k, vals)
    assert checked >= 2
    # and without shadow rays the same pixel is lit
    flat = SiteRenderer.__new__(SiteRenderer)
    flat.__dict__.update(renderer.__dict__)
    flat.config = RenderConfig(shadows=False)
    g2, _ = flat.render([T], cam)[0]
    assert (g2 > gray).sum() > 100
