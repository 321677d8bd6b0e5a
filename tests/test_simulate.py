"""Simulated traverses written as `.lac` archives; round trip and the CLI."""

import numpy as np
import pytest

pytest.importorskip("trimesh")
pytest.importorskip("embreex")

from lunarloc.sim.rover import RoverConfig  # noqa: E402
from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse  # noqa: E402
from lunarloc.sim.site import SiteConfig  # noqa: E402
from lunarloc.core.errors import ConfigError  # noqa: E402

SMALL_SITE = SiteConfig(
    size_m=14.0, terrain_margin_m=3.0, resolution_m=0.2, n_rocks=80, rover_start_xy=(-3.0, -2.0)
)


def _cfg(**kw):
    base = dict(site=SMALL_SITE, duration_s=3.0, image_rate_hz=2.0, width=64, height=36)
    base.update(kw)
    return SimulationConfig(**base)


def test_traverse_round_trip(tmp_path):
    lac = pytest.importorskip("lunarloc.io.lac.archive")
    cfg = _cfg()
    site = simulate_site(2, cfg)
    path, traj = simulate_traverse(site, tmp_path / "t.lac", 0, cfg)
    with lac.LacArchive(path) as a:
        assert a.n_frames == len(traj) == 61
        np.testing.assert_allclose(
            a.poses(), traj.poses, rtol=5e-15, atol=1e-22
        )  # 15-digit floats (pandas-safe)
        assert set(a.cameras) == {"FrontLeft", "FrontRight", "BackLeft", "BackRight"}
        assert a.image_count("FrontLeft") == 7  # frames 0, 10, ..., 60
        g = a.grayscale("FrontLeft", 10)
        s = a.semantic("FrontLeft", 10)
        assert g.shape == (36, 64) and g.dtype == np.uint8
        assert s.shape == (36, 64) and s.dtype == np.uint16
        rocks = a.custom("rocks").to_array(["id", "x", "y", "z", "radius"])
        np.testing.assert_allclose(rocks, site.rocks_table(), rtol=5e-15, atol=1e-22)
        odo = a.custom("odometry")
        assert odo.n_rows == len(traj)
        row = a.camera_row("BackLeft", 0)
        assert row["camera_x"] == pytest.approx(-0.28) and row["camera_yaw"] == pytest.approx(np.pi)
    from lunarloc.sim.render import SiteRenderer
    from lunarloc.perception.camera import PinholeCamera, ipex_rig

    rig = ipex_rig(PinholeCamera(64, 36))
    g2, s2 = SiteRenderer(site, cfg.render).render_rover(traj.poses[10], [rig["FrontLeft"]])[
        "FrontLeft"
    ]
    np.testing.assert_array_equal(g, g2)
    np.testing.assert_array_equal(s, s2)


def test_config_validation():
    with pytest.raises(ConfigError):
        _cfg(image_rate_hz=3.0).validate()  # does not divide 20 Hz
    with pytest.raises(ConfigError):
        _cfg(image_rate_hz=20.0).validate()
    with pytest.raises(ConfigError):
        _cfg(cameras=("Left",)).validate()
    assert _cfg(rover=RoverConfig()).frames_per_image == 10


def test_cli_simulate(tmp_path, monkeypatch):
    pytest.importorskip("lunarloc.io.lac.archive")
    from typer.testing import CliRunner

    from lunarloc.cli import commands_sim  # noqa: F401
    from lunarloc.cli.app import app

    try:  # a second command keeps typer from collapsing the app into one command
        from lunarloc.cli import commands_data  # noqa: F401
    except ImportError:
        pass
    from lunarloc.sim import simulate as sim

    from lunarloc.sim.site import generate_site

    monkeypatch.setattr(
        sim, "simulate_site", lambda seed, config=None: generate_site(seed, SMALL_SITE)
    )
    res = CliRunner().invoke(
        app,
        [
            "simulate",
            "--seed",
            "1",
            "--traverses",
            "2",
            "--out",
            str(tmp_path),
            "--duration",
            "1",
            "--width",
            "48",
            "--height",
            "27",
            "--front-only",
        ],
    )
    assert res.exit_code == 0, res.output
    assert (tmp_path / "rocks.csv").exists()
    assert (tmp_path / "traverse_0.lac").exists() and (tmp_path / "traverse_1.lac").exists()
    lac = pytest.importorskip("lunarloc.io.lac.archive")
    with (
        lac.LacArchive(tmp_path / "traverse_0.lac") as a0,
        lac.LacArchive(tmp_path / "traverse_1.lac") as a1,
    ):
        np.testing.assert_allclose(a0.poses()[0, :2], a1.poses()[0, :2])  # same start
        assert a0.image_count("FrontLeft") == 3 and a0.image_count("BackLeft") == 0


def test_cli_simulate_lac_style_builds_the_lac_look_site(tmp_path, monkeypatch):
    """--lac-style passes SiteConfig.lac_style() and RenderConfig.lac_style() to the simulation
    (the site and renderer settings recorded in simulation.json say which was used)."""
    pytest.importorskip("lunarloc.io.lac.archive")
    import json

    from typer.testing import CliRunner

    from lunarloc.cli import commands_sim  # noqa: F401
    from lunarloc.cli.app import app
    from lunarloc.sim import simulate as sim
    from lunarloc.sim.site import SiteConfig

    seen = []

    def fake_dataset(seed, n, out, cfg, progress=None):
        seen.append(cfg)
        return []

    monkeypatch.setattr(sim, "simulate_dataset", fake_dataset)
    args = ["simulate", "--out", str(tmp_path / "x"), "--duration", "1", "--traverses", "0"]
    for extra in ([], ["--lac-style"]):
        res = CliRunner().invoke(app, args + extra + ["--overwrite"])
        assert res.exit_code == 0, res.output
    plain, lac = seen
    assert plain.site == SiteConfig() and not plain.render.terrain_up_normal
    assert lac.site == SiteConfig.lac_style() and lac.render.terrain_up_normal
    assert lac.site.n_small_rocks > plain.site.n_small_rocks
    json.dumps(lac.to_dict())  # the config it records stays serialisable
