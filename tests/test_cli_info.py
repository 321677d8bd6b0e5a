"""`lunarloc info`: summary of a small archive, plot with ground-truth rocks, bad archive."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from lunarloc.cli import commands_data  # registers `info` on the app
from lunarloc.cli.app import app as lunarloc_app
from lunarloc.io.lac.archive import LacWriter
from lunarloc.core.errors import ArchiveError

W, H = 32, 24

# A local app with `info` and a second command, so that Typer keeps sub-command
# dispatch whatever other command groups are registered on the real app.
app = typer.Typer()
app.command("info")(commands_data.info)
app.command("noop")(lambda: None)


def test_info_is_registered_on_the_lunarloc_app():
    assert "info" in [c.name for c in lunarloc_app.registered_commands]


@pytest.fixture
def archive(tmp_path):
    path = tmp_path / "traverse_1.lac"
    cams = {
        "FrontLeft": {
            "camera_active": True,
            "light_intensity": 1.0,
            "width": W,
            "height": H,
            "use_semantic": True,
        },
        "FrontRight": {
            "camera_active": True,
            "light_intensity": 1.0,
            "width": W,
            "height": H,
            "use_semantic": False,
        },
    }
    init = {"fiducials": False, "lander": [0.0] * 6, "rover": [0.0] * 6, "cameras": cams}
    g = np.zeros((H, W), np.uint8)
    with LacWriter(path, init, description="three metres east") as w:
        for f in range(31):
            w.add_frame(f, x=0.1 * f, mission_time=0.05 * f)  # 3 m in 1.5 s
            if f % 10 == 0:
                w.add_camera_frame(
                    "FrontLeft", f, [0.28, 0.081, 0.131, 0, 0, 0], grayscale=g, semantic=g
                )
                w.add_camera_frame("FrontRight", f, [0.28, -0.081, 0.131, 0, 0, 0], grayscale=g)
        w.add_custom(
            "rocks",
            ["id", "x", "y", "z", "radius"],
            [[0, 1.0, 0.5, 0.0, 0.2], [1, 2.0, -0.4, 0.0, 0.1]],
        )
        w.add_custom(
            "odometry",
            ["frame", "x", "y", "z", "roll", "pitch", "yaw"],
            [[0, 0, 0, 0, 0, 0, 0], [30, 3.1, 0.1, 0, 0, 0, 0]],
        )
    return path


def test_info_summary(archive):
    result = CliRunner().invoke(app, ["info", str(archive)], terminal_width=150)
    assert result.exit_code == 0, result.output
    out = result.output
    assert "frames      : 31 (0..30)" in out
    assert "duration    : 1.50 s" in out
    assert "path length : 3.00 m" in out
    assert "three metres east" in out
    assert "FrontLeft" in out and "FrontRight" in out
    assert "rocks" in out and "odometry" in out


def test_info_plot(archive, tmp_path):
    out = tmp_path / "plots" / "traj.png"
    result = CliRunner().invoke(app, ["info", str(archive), "--plot", str(out)])
    assert result.exit_code == 0, result.output
    from PIL import Image

    with Image.open(out) as img:
        assert img.size[0] > 200 and img.size[1] > 200


def test_info_bad_archive_raises_archive_error(tmp_path):
    bad = tmp_path / "bad.lac"
    bad.write_bytes(b"not an archive")
    result = CliRunner().invoke(app, ["info", str(bad)])
    assert isinstance(result.exception, ArchiveError)
    assert "bad.lac" in str(result.exception)


@pytest.mark.skipif(
    importlib.util.find_spec("lunarloc.cli.commands_core") is None,
    reason="CLI core commands not registered yet",
)
def test_info_bad_archive_one_line_error(tmp_path, capsys):
    from lunarloc.cli.app import main

    bad = tmp_path / "bad.lac"
    bad.write_bytes(b"not an archive")
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "bad.lac" in err and "not a gzip" in err
