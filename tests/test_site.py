"""Procedural site: determinism, rock sizes, burial, lander keep-out, CSV export."""

import numpy as np
import pytest

from lunarloc.sim.site import SiteConfig, generate_site, load_rocks_csv
from lunarloc.core.errors import ConfigError


@pytest.fixture(scope="module")
def site():
    return generate_site(3)


def test_seeded_determinism(site):
    again = generate_site(3)
    np.testing.assert_array_equal(site.heights, again.heights)
    np.testing.assert_array_equal(site.rocks_table(), again.rocks_table())
    other = generate_site(4)
    assert not np.allclose(site.rocks_table()[:, 1:3], other.rocks_table()[:, 1:3])


def test_terrain_relief_and_lander_flat(site):
    X, Y = np.meshgrid(site.grid_x, site.grid_y)
    inside = site.inside(X, Y)
    relief = np.ptp(site.heights[inside])
    assert 0.6 < relief < 2.0
    assert abs(float(site.terrain_height(0.0, 0.0))) < 1e-6  # lander base at z = 0
    # bilinear query reproduces grid nodes
    i, j = 100, 200
    assert np.isclose(site.terrain_height(site.grid_x[i], site.grid_y[j]), site.heights[j, i])


def test_rock_count_and_heavy_tailed_sizes(site):
    cfg = site.config
    r = site.rocks.radii
    assert len(r) == cfg.n_rocks == 386
    assert r.min() >= cfg.rock_radius_m[0] and r.max() <= cfg.rock_radius_m[1]
    # heavy tail: many small rocks, a few large ones
    assert np.median(r) < 0.07
    assert r.max() / np.median(r) > 5
    assert 5 <= np.sum(r > 0.2) <= 60
    # cumulative count N(>r) ~ r^-a: log-log slope close to the configured exponent
    rs = np.sort(r)[::-1]
    n = np.arange(1, len(rs) + 1)
    sel = rs < 0.3
    slope = np.polyfit(np.log(rs[sel]), np.log(n[sel]), 1)[0]
    assert -2.2 < slope < -1.1


def test_rocks_partly_buried_and_outside_keepout(site):
    rk = site.rocks
    ground = site.terrain_height(rk.centers[:, 0], rk.centers[:, 1])
    top = rk.centers[:, 2] + rk.axes[:, 2]
    bottom = rk.centers[:, 2] - rk.axes[:, 2]
    assert np.all(top > ground) and np.all(bottom < ground)
    d = np.hypot(rk.centers[:, 0], rk.centers[:, 1])
    assert np.all(d > site.config.lander_radius_m + site.config.lander_keepout_m)
    assert np.all(site.inside(rk.centers[:, 0], rk.centers[:, 1]))


def test_rocks_csv_round_trip(site, tmp_path):
    p = site.write_rocks_csv(tmp_path / "rocks.csv")
    assert p.read_text().splitlines()[0] == "id,x,y,z,radius"
    table = load_rocks_csv(p)
    np.testing.assert_allclose(table, site.rocks_table(), atol=1e-5)


def test_config_validation():
    with pytest.raises(ConfigError):
        generate_site(0, SiteConfig(rock_radius_m=(0.5, 0.1)))
    with pytest.raises(ConfigError):
        generate_site(0, SiteConfig(resolution_m=0.0))


def test_rock_meshes_match_records(site):
    meshes = site.rock_meshes()
    assert len(meshes) == len(site.rocks)
    k = int(np.argmax(site.rocks.radii))
    c = meshes[k].vertices.mean(axis=0)
    assert np.linalg.norm(c[:2] - site.rocks.centers[k, :2]) < 0.3 * site.rocks.radii[k]


def test_rocks_are_irregular_not_ellipsoids(site):
    """Knobs and fractures: a rock's surface departs from its ellipsoid by several percent,
    differently from rock to rock."""
    meshes = site.rock_meshes()
    rk = site.rocks
    devs = []
    for k in np.argsort(-rk.radii)[:10]:
        c, s = np.cos(rk.yaws[k]), np.sin(rk.yaws[k])
        local = (meshes[k].vertices - rk.centers[k]) @ np.array(
            [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        )
        r_ell = np.linalg.norm(local / rk.axes[k], axis=1)  # 1 on the ellipsoid
        devs.append(np.std(r_ell))
        assert r_ell.max() < 1.3 and r_ell.min() > 0.5
    assert np.median(devs) > 0.04
    assert np.ptp(devs) > 0.005


def test_lander_fiducial_panels_follow_the_lac_layout(site):
    from lunarloc.sim.site import LAC_FIDUCIALS

    p = site.fiducial_panels()
    assert len(p) == 16
    lac = np.array([r[:3] for r in LAC_FIDUCIALS])
    np.testing.assert_allclose(p.centers - 0.01 * p.normals, site.lander_xyz + lac, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(p.normals, axis=1), 1.0)
    assert np.all(np.abs(p.normals[:, 2]) < 1e-12)
    # outward: the normal points away from the lander's axis
    assert np.all(
        np.einsum("ij,ij->i", p.normals[:, :2], p.centers[:, :2] - site.lander_xyz[:2]) > 0
    )
    # u right, v down, both in the panel's plane
    np.testing.assert_allclose(np.einsum("ij,ij->i", p.u_axes, p.normals), 0.0, atol=1e-12)
    np.testing.assert_allclose(p.v_axes, np.broadcast_to([0.0, 0.0, -1.0], p.v_axes.shape))
    # tag pattern: white outer ring, black inner ring, a mix of both inside; all tags differ
    assert np.all(p.bits[:, 0, :] == 1) and np.all(p.bits[:, :, -1] == 1)
    assert np.all(p.bits[:, 1, 1:-1] == 0) and np.all(p.bits[:, 1:-1, 1] == 0)
    inner = p.bits[:, 2:-2, 2:-2].reshape(16, -1)
    assert np.all((inner.mean(1) > 0.1) & (inner.mean(1) < 0.9))
    assert len({row.tobytes() for row in inner}) == 16


def test_lander_parts_within_its_footprint(site):
    pytest.importorskip("trimesh")
    cfg = site.config
    for mesh, albedo in site.lander_parts():
        v = mesh.vertices - site.lander_xyz
        assert np.hypot(v[:, 0], v[:, 1]).max() <= cfg.lander_radius_m + 0.25
        assert v[:, 2].min() >= -0.05 and v[:, 2].max() <= cfg.lander_height_m + 0.01
        assert albedo > 0
    assert len(site.lander_mesh().faces) > 100


def test_rocks_csv_write_is_atomic(site, tmp_path, monkeypatch):
    """A failure half-way through writing leaves the previous file intact, never a truncated one."""
    path = tmp_path / "rocks.csv"
    site.write_rocks_csv(path)
    before = path.read_text()

    def broken_table():
        yield site.rocks_table()[0]
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(site, "rocks_table", broken_table)
    with pytest.raises(Exception):
        site.write_rocks_csv(path)
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["rocks.csv"]
