"""The LAC-look site options (issue 29): off by default, so existing seeds are unchanged;
on (``SiteConfig.lac_style()``), small rocks down to 2 cm, small craters and crater rims
that tilt the rover 10-20 degrees."""

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError
from lunarloc.sim.rover import plan_traverse
from lunarloc.sim.simulate import traverse_seed
from lunarloc.sim.site import SiteConfig, generate_site


def test_extras_off_by_default_and_drawn_from_their_own_stream():
    base = generate_site(5)
    cfg = SiteConfig()
    assert (cfg.n_small_rocks, cfg.n_small_craters, cfg.hummock_m) == (0, 0, 0.0)
    # small rocks only: the terrain and the first 386 rocks are exactly the default site's
    more = generate_site(5, SiteConfig(n_small_rocks=80))
    np.testing.assert_array_equal(more.heights, base.heights)
    n = len(base.rocks)
    np.testing.assert_array_equal(more.rocks_table()[:n], base.rocks_table())
    extra = more.rocks_table()[n:]
    assert 60 <= len(extra) <= 80
    np.testing.assert_array_equal(
        extra[:, 0], np.arange(n, n + len(extra))
    )  # ids follow the others'
    lo, hi = cfg.small_rock_radius_m
    assert extra[:, 4].min() >= lo and extra[:, 4].max() <= hi
    # clear of the other rocks and of the lander
    xy, r = more.rocks_table()[:, 1:3], more.rocks_table()[:, 4]
    d = np.hypot(*(xy[n:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    d[np.arange(len(extra)), n + np.arange(len(extra))] = np.inf
    assert np.all(d >= 1.1 * (r[n:, None] + r[None, :]) - 1e-9)
    assert np.hypot(*extra[:, 1:3].T).min() > cfg.lander_radius_m + cfg.lander_keepout_m


def test_lac_style_site_has_small_rocks_rougher_terrain_and_tilts_the_rover():
    site = generate_site(11, SiteConfig.lac_style())
    assert site.config.n_small_rocks > 0
    r = site.rocks.radii
    assert np.count_nonzero(r < 0.05) > 500 and r.min() < 0.025
    assert np.count_nonzero(r >= 0.1) >= 30  # the LAC-sized population is still there
    assert (
        abs(float(site.terrain_height(0.0, 0.0))) < 1e-6
    )  # the lander still stands level at z = 0
    # slope statistics: the LAC look is much rougher than the default site
    gy, gx = np.gradient(site.heights, site.config.resolution_m)
    gy0, gx0 = np.gradient(generate_site(11).heights, 0.1)
    assert np.percentile(np.hypot(gx, gy), 90) > 2.0 * np.percentile(np.hypot(gx0, gy0), 90)
    tilts = []
    for i in range(3):
        tr = plan_traverse(site, 60.0, traverse_seed(11, i))
        tilts.append(np.degrees(np.arccos(np.cos(tr.rpy[:, 0]) * np.cos(tr.rpy[:, 1]))))
    tilt = np.concatenate(tilts)
    assert tilt.max() > 10.0
    assert np.mean(tilt > 10.0) > 0.02


def test_lac_style_overrides_and_validation():
    assert SiteConfig.lac_style(n_small_rocks=0).n_small_rocks == 0
    for bad in (
        {"n_small_rocks": -1},
        {"small_rock_radius_m": (0.05, 0.02)},
        {"hummock_m": 0.5},
        {"small_crater_radius_m": (0.0, 1.0)},
        {"n_small_craters": -2},
    ):
        with pytest.raises(ConfigError):
            generate_site(0, SiteConfig(**bad))


def test_terrain_up_normal_removes_the_dark_crest_dots_and_is_off_by_default():
    pytest.importorskip("trimesh")
    pytest.importorskip("embreex")
    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.sim.render import SEM_GROUND, RenderConfig, SiteRenderer

    assert (
        RenderConfig().terrain_up_normal is False
        and RenderConfig.lac_style().terrain_up_normal is True
    )
    cfg = SiteConfig.lac_style(
        size_m=16.0,
        terrain_margin_m=4.0,
        n_rocks=60,
        n_small_rocks=100,
        n_small_craters=300,
        rover_start_xy=(-3.0, -2.0),
    )
    site = generate_site(2, cfg)
    cam = PinholeCamera(640, 360)
    mount = ipex_rig(cam)["FrontLeft"]
    base = SiteRenderer(site, RenderConfig(lighting="sun", sun_elevation_deg=12.0))
    up = base.with_config(RenderConfig.lac_style(lighting="sun", sun_elevation_deg=12.0))
    dark_old, dark_new, differ = 0, 0, 0
    for yaw in (0.0, 1.6, 3.2, 4.8):
        pose = [-3.0, -2.0, float(site.terrain_height(-3.0, -2.0)) + 0.2, 0.0, 0.0, yaw]
        g0, s0 = base.render_rover(pose, [mount])["FrontLeft"]
        g1, s1 = up.render_rover(pose, [mount])["FrontLeft"]
        np.testing.assert_array_equal(s0, s1)  # the geometry is the same; only the shading changes
        ground = s0 == SEM_GROUND
        # ground pixels at the ambient level (gray ~25: a cast shadow, or a crest pixel whose flipped
        # normal faces away from the sun)
        dark_old += int(np.count_nonzero(ground & (g0 < 40)))
        dark_new += int(np.count_nonzero(ground & (g1 < 40)))
        differ += int(np.count_nonzero(g0 != g1))
    assert differ > 0
    assert dark_new < dark_old
