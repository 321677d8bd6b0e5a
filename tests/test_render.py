"""Renderer: camera geometry against ground truth, shadows, black sky, semantic encoding,
lamps and night, the rover's shadow, the lander's fiducials, the LAC palette."""

from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("trimesh")
pytest.importorskip("embreex")

from lunarloc.sim.render import (  # noqa: E402
    LAC_PALETTE,
    SEM_FIDUCIAL,
    SEM_GROUND,
    SEM_LANDER,
    SEM_ROCK_OFFSET,
    SEM_SKY,
    Lighting,
    RenderConfig,
    SemanticFormat,
    SiteRenderer,
    colorize_semantic,
    rover_lamps,
    semantic_lander_mask,
    semantic_to_palette,
    semantic_to_rock_id,
    sun_direction,
)
from lunarloc.core.errors import ConfigError, InputError  # noqa: E402
from lunarloc.sim.rover import plan_traverse  # noqa: E402
from lunarloc.sim.site import SiteConfig, generate_site  # noqa: E402
from lunarloc.core.geometry import invert_transform, pose_to_matrix, transform_points  # noqa: E402
from lunarloc.perception.camera import PinholeCamera, ipex_rig  # noqa: E402

SMALL = SiteConfig(
    size_m=16.0, terrain_margin_m=4.0, resolution_m=0.15, n_rocks=150, rover_start_xy=(-3.0, -2.0)
)
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
            ok = (
                (z > 0.3)
                & (uv[:, 0] > 2)
                & (uv[:, 0] < CAM.width - 3)
                & (uv[:, 1] > 2)
                & (uv[:, 1] < CAM.height - 3)
            )
            ok &= (
                CAM.fx * 0.4 * rk.axes[:, 2] / np.maximum(z, 1e-9) > 2.0
            )  # at least ~2 px of rock around it
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
    assert (
        np.percentile(gray[sem == SEM_GROUND], 75) > 60
    )  # mostly lit (a hill or the lander may shade some)
    labels = np.unique(sem)
    assert set(labels[labels < SEM_ROCK_OFFSET]) <= {SEM_SKY, SEM_GROUND, SEM_LANDER, SEM_FIDUCIAL}
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
        if (
            not ground or vals["sun"] < 60
        ):  # another rock there, or the lit side shaded by something else
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


# ---------------------------------------------------------------------- lamps, night, palette
def _ground_range(renderer, T_world_opt, cam):
    """Distance (m) from the camera to what each pixel sees, (H, W); inf for sky."""
    dirs = cam.rays_optical().reshape(-1, 3) @ T_world_opt[:3, :3].T
    o = np.broadcast_to(T_world_opt[:3, 3], dirs.shape)
    t, _ = renderer.cast_rays(o, dirs)
    return t.reshape(cam.height, cam.width)


def _front(renderer, pose, cfg):
    rig = ipex_rig(CAM)
    gray, sem = renderer.with_config(cfg).render_rover(pose, [rig["FrontLeft"]])["FrontLeft"]
    T = pose_to_matrix(*pose) @ rig["FrontLeft"].T_rover_optical
    return gray.astype(float), sem, _ground_range(renderer, T, CAM)


def test_lamps_brighten_the_near_field_more_than_the_far(renderer, traj):
    pose = traj.poses[0]
    sun = RenderConfig(lighting=Lighting.SUN)
    g_sun, sem, rng = _front(renderer, pose, sun)
    g_both, sem2, _ = _front(renderer, pose, replace(sun, lighting=Lighting.SUN_LAMPS))
    np.testing.assert_array_equal(sem, sem2)  # lighting never changes the semantics
    ground = sem == SEM_GROUND
    near, far = ground & (rng < 1.5), ground & (rng > 5.0)
    assert near.sum() > 500 and far.sum() > 200
    gain_near = np.median((g_both - g_sun)[near])
    gain_far = np.median((g_both - g_sun)[far])
    assert gain_near > 25
    assert gain_near > 3 * max(gain_far, 1.0)
    assert np.all(g_both >= g_sun)  # light only adds
    # the archive's light_intensity scales the lamps: half intensity, less light
    rig = ipex_rig(CAM)
    r2 = renderer.with_config(replace(sun, lighting=Lighting.SUN_LAMPS))
    g_half = r2.render_rover(pose, [rig["FrontLeft"]], light_intensity=0.5)["FrontLeft"][0].astype(
        float
    )
    assert np.median(g_sun[near]) < np.median(g_half[near]) < np.median(g_both[near])


def test_night_lamps_light_the_near_ground_and_the_sky_stays_black(renderer, traj):
    pose = traj.poses[0]
    night = RenderConfig(lighting=Lighting.SUN_LAMPS, sun_elevation_deg=-5.0)
    g, sem, rng = _front(renderer, pose, night)
    ground = sem == SEM_GROUND
    near, far = ground & (rng < 1.5), ground & (rng > 8.0)
    assert near.sum() > 500 and far.sum() > 100
    assert np.all(g[sem == SEM_SKY] == 0)
    assert np.median(g[near]) > 120
    assert np.median(g[far]) < 0.35 * np.median(g[near])
    # the sun below the horizon gives no light: the same image as lamps alone
    g_lamps, _, _ = _front(renderer, pose, RenderConfig(lighting=Lighting.LAMPS))
    np.testing.assert_array_equal(g, g_lamps)
    # no sun and no lamps: all black
    g_dark, _, _ = _front(
        renderer, pose, RenderConfig(lighting=Lighting.SUN, sun_elevation_deg=-5.0)
    )
    assert g_dark.max() == 0
    # a rear lamp does not light the front camera's view
    T = pose_to_matrix(*pose)
    _, _, inten = rover_lamps(T, {"BackLeft": 1.0, "BackRight": 1.0})
    assert inten.tolist() == [0.0, 0.0, 1.0, 1.0]
    rig = ipex_rig(CAM)
    r = renderer.with_config(RenderConfig(lighting=Lighting.LAMPS))
    g_rear = r.render_rover(
        pose, [rig["FrontLeft"]], light_intensity={"BackLeft": 1.0, "BackRight": 1.0}
    )
    assert np.median(g_rear["FrontLeft"][0][near]) < 0.2 * np.median(g[near])


def test_rover_body_shades_the_ground_ahead(site, renderer, traj):
    """Sun low behind the rover: its body's shadow falls on the ground ahead of the front camera."""
    pose = traj.poses[0]
    behind = np.degrees(pose[5]) + 180.0
    cfg = RenderConfig(lighting=Lighting.SUN, sun_elevation_deg=10.0, sun_azimuth_deg=behind)
    g_with, sem, rng = _front(renderer, pose, cfg)
    g_without, _, _ = _front(renderer, pose, replace(cfg, rover_shadow=False))
    ground = sem == SEM_GROUND
    darker = ground & (g_with < 0.5 * g_without)
    assert darker.sum() > 0.02 * ground.sum()
    assert np.all(g_with <= g_without)
    assert np.median(rng[darker]) < 4.0  # near the rover (0.5 m tall, sun 10 deg: about 3 m long)


def test_lander_and_fiducials_labelled_and_palette(site, renderer):
    """Look at the lander's group-A fiducials from 5 m: lander and fiducial labels, a
    black-and-white tag pattern, the LAC palette colours."""
    panels = site.fiducial_panels()
    n = panels.normals[0]
    eye = np.array([0.862, -0.862, 0.0]) + 5.0 * n
    eye[2] = float(site.terrain_height(*eye[:2])) + 0.6
    target = np.array([0.862, -0.862, 0.65])
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    cfg = RenderConfig(
        lighting=Lighting.SUN,
        sun_elevation_deg=20.0,
        sun_azimuth_deg=np.degrees(np.arctan2(n[1], n[0])),
    )
    gray, sem = renderer.with_config(cfg).render([T], CAM)[0]
    assert (sem == SEM_LANDER).sum() > 500
    fid = sem == SEM_FIDUCIAL
    assert fid.sum() > 1000  # four 0.34 m panels at 5 m
    assert np.sum(gray[fid] < 50) > 0.15 * fid.sum() and np.sum(gray[fid] > 150) > 0.15 * fid.sum()
    # each of the four panels' centres projects onto a fiducial pixel
    uv, depth = CAM.project(transform_points(invert_transform(T), panels.centers[:4]))
    assert np.all(depth > 0)
    for u, v in np.round(uv).astype(int):
        assert sem[v, u] == SEM_FIDUCIAL
    assert np.array_equal(semantic_lander_mask(sem), (sem == SEM_LANDER) | (sem == SEM_FIDUCIAL))

    pal = semantic_to_palette(sem)
    assert pal.shape == sem.shape + (3,) and pal.dtype == np.uint8
    colours = {tuple(int(c) for c in v) for v in np.unique(pal.reshape(-1, 3), axis=0)}
    assert colours <= set(LAC_PALETTE.values())
    np.testing.assert_array_equal(
        pal[fid], np.broadcast_to(LAC_PALETTE["fiducial"], (fid.sum(), 3))
    )
    np.testing.assert_array_equal(pal[sem == SEM_LANDER][0], LAC_PALETTE["lander"])


def test_palette_semantics_have_exactly_the_palette_colours(site, renderer, traj):
    rig = ipex_rig(CAM)
    _, sem = renderer.render_rover(traj.poses[0], [rig["FrontLeft"]])["FrontLeft"]
    rock = sem >= SEM_ROCK_OFFSET
    assert rock.sum() > 20
    pal = semantic_to_palette(sem)
    expected = np.zeros_like(pal)
    for label, name in (
        (SEM_SKY, "sky"),
        (SEM_GROUND, "ground"),
        (SEM_LANDER, "lander"),
        (SEM_FIDUCIAL, "fiducial"),
    ):
        expected[sem == label] = LAC_PALETTE[name]
    expected[rock] = LAC_PALETTE["rock"]
    np.testing.assert_array_equal(pal, expected)
    with pytest.raises(InputError, match="unknown labels"):
        semantic_to_palette(np.array([[1, 5]], np.uint16))
    with pytest.raises(InputError):
        semantic_to_palette(pal)  # already RGB


def test_lighting_and_semantic_format_validation():
    assert RenderConfig(lighting="sun").lighting is Lighting.SUN
    assert Lighting.parse(" SUN+LAMPS ") is Lighting.SUN_LAMPS
    assert str(Lighting.SUN_LAMPS) == "sun+lamps"
    with pytest.raises(ConfigError, match="'sun', 'lamps', 'sun\\+lamps'"):
        RenderConfig(lighting="moon")
    with pytest.raises(ConfigError, match="'ids', 'palette'"):
        SemanticFormat.parse("rgb")
    for bad in (
        dict(lamp_intensity=1.5),
        dict(lamp_cone_deg=(60.0, 30.0)),
        dict(sun_elevation_deg=-100.0),
        dict(highlight_knee=0.0),
        dict(lamp_power=-1.0),
    ):
        with pytest.raises(ConfigError):
            RenderConfig(**bad).validate()
    with pytest.raises(InputError):
        rover_lamps(np.eye(4), {"Front": 1.0})  # no such lamp
    with pytest.raises(InputError):
        rover_lamps(np.eye(4), 2.0)


def test_cli_rejects_an_unknown_lighting(capsys):
    from lunarloc.cli.app import main

    assert main(["simulate", "--out", "unused", "--lighting", "moon"]) == 2
    err = capsys.readouterr().err
    assert "--lighting" in err and "sun+lamps" in err


def test_archive_palette_semantics_and_light_intensity(tmp_path):
    lac = pytest.importorskip("lunarloc.io.lac.archive")
    from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse

    small = SiteConfig(
        size_m=14.0, terrain_margin_m=3.0, resolution_m=0.2, n_rocks=80, rover_start_xy=(-3.0, -2.0)
    )
    base = dict(
        site=small, duration_s=1.0, image_rate_hz=2.0, width=64, height=36, cameras=("FrontLeft",)
    )
    cfg = SimulationConfig(
        **base, semantic_format="palette", render=RenderConfig(lamp_intensity=0.7)
    )
    site = simulate_site(2, cfg)
    path, _ = simulate_traverse(site, tmp_path / "p.lac", 0, cfg)
    with lac.LacArchive(path) as a:
        sem = a.semantic("FrontLeft", 0)
        assert sem.shape == (36, 64, 3) and sem.dtype == np.uint8
        colours = {tuple(int(c) for c in v) for v in np.unique(sem.reshape(-1, 3), axis=0)}
        assert colours <= set(LAC_PALETTE.values()) and len(colours) >= 2
        assert a.camera_row("FrontLeft", 0)["light_intensity"] == pytest.approx(0.7)
    sun_only = SimulationConfig(**base, render=RenderConfig(lighting="sun"))
    path, _ = simulate_traverse(site, tmp_path / "s.lac", 0, sun_only)
    with lac.LacArchive(path) as a:
        assert a.semantic("FrontLeft", 0).dtype == np.uint16  # ids stay the default
        assert a.camera_row("FrontLeft", 0)["light_intensity"] == 0.0
    with pytest.raises(ConfigError):
        SimulationConfig(**base, semantic_format="rgb")


def test_bad_rover_pose_is_an_input_error(renderer, traj):
    rig = ipex_rig(CAM)
    T = pose_to_matrix(*traj.poses[0]) @ rig["FrontLeft"].T_rover_optical
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(InputError, match="T_world_rover"):
        renderer.render([T], CAM, T_world_rover=bad)
    with pytest.raises(InputError, match="light_intensity"):
        renderer.render(
            [T], CAM, T_world_rover=pose_to_matrix(*traj.poses[0]), light_intensity=-0.1
        )
