"""Odometry sources: record, IMU dead reckoning, visual (when present), ground truth; the
``lunarloc odometry`` command, ``--odometry`` on run; bad input gives one clear error."""

from __future__ import annotations

import io
import json
import math
import tarfile

import numpy as np
import pytest

from lunarloc.io.lac.archive import LacArchive, LacWriter
from lunarloc.core.errors import ArchiveError, ConfigError, InputError
from lunarloc.core.geometry import matrix_to_pose, pose_to_matrix
from lunarloc.odometry.source import (
    OdometrySource,
    archive_odometry,
    default_odometry_source,
    ground_truth_poses,
    odometry_drift,
    parse_odometry_source,
)

G = 1.622
DT = 0.05
CAM = {
    "camera_active": True,
    "light_intensity": 0.0,
    "width": 16,
    "height": 12,
    "use_semantic": False,
}


def drive(n=400, v=0.25, w=0.1, rover0=(2.0, -1.0, 0.3, 0.0, 0.0, 0.4), roll_true=0.0):
    """Exact states of a rover driving an arc on flat ground (optionally rolled by `roll_true`)."""
    x0, y0, z0, _, _, yaw0 = rover0
    t = np.arange(n) * DT
    yaw = yaw0 + w * t
    x = x0 + v / w * (np.sin(yaw) - math.sin(yaw0))
    y = y0 - v / w * (np.cos(yaw) - math.cos(yaw0))
    states = []
    for k in range(n):
        R = pose_to_matrix(0, 0, 0, roll_true, 0.0, yaw[k])[:3, :3]
        up_body = R.T @ np.array([0.0, 0.0, 1.0])
        a_body = np.array([0.0, w * v, 0.0])  # centripetal
        f = a_body + G * up_body
        gyro = np.array([0.0, 0.0, w])  # world-frame rate, as the LAC leaderboard computes it
        states.append(
            dict(
                x=x[k],
                y=y[k],
                z=z0,
                roll=roll_true,
                pitch=0.0,
                yaw=yaw[k],
                accel_x=f[0],
                accel_y=f[1],
                accel_z=f[2],
                gyro_x=gyro[0],
                gyro_y=gyro[1],
                gyro_z=gyro[2],
                mission_time=t[k],
                linear_speed=v,
                angular_speed=w,
            )
        )
    return states


def write(path, states, *, rover0=None, customs=(), lander=(5.0, 0.0, 0.0, 0.0, 0.0, 0.0)):
    s0 = states[0]
    rover = rover0 or [s0["x"], s0["y"], s0["z"], s0["roll"], s0["pitch"], s0["yaw"]]
    init = {
        "lander": list(lander),
        "rover": list(rover),
        "cameras": {"FrontLeft": dict(CAM), "FrontRight": dict(CAM)},
    }
    with LacWriter(path, init) as w:
        for k, st in enumerate(states):
            w.add_frame(k, **st)
        for name, cols, rows in customs:
            w.add_custom(name, cols, rows)
    return path


@pytest.fixture
def arc(tmp_path):
    states = drive()
    poses = [
        [k, s["x"] + 10, s["y"] - 5, s["z"], s["roll"], s["pitch"], s["yaw"]]
        for k, s in enumerate(states)
    ]
    mats = [[k, *pose_to_matrix(*p[1:])[:4].ravel()] for k, p in enumerate(poses) if k % 10 == 0]
    customs = [
        ("shifted", ["frame", "x", "y", "z", "roll", "pitch", "yaw"], poses),
        ("orbslam", ["frame"] + [f"m{i}{j}" for i in range(4) for j in range(4)], mats),
    ]
    return write(tmp_path / "arc.lac", states, customs=customs), states


# ------------------------------------------------------------------------------ parsing


def test_parse_odometry_source():
    assert parse_odometry_source("record:orbslam") == (OdometrySource.RECORD, "orbslam")
    assert parse_odometry_source("record") == (OdometrySource.RECORD, "odometry")
    assert parse_odometry_source(" IMU ") == (OdometrySource.IMU, None)
    assert parse_odometry_source("ground-truth") == (OdometrySource.GROUND_TRUTH, None)
    assert parse_odometry_source(OdometrySource.VISUAL) == (OdometrySource.VISUAL, None)
    for bad in ("lidar", "record:", "imu:x", ""):
        with pytest.raises(ConfigError):
            parse_odometry_source(bad)


# ------------------------------------------------------------------------------ sources


def test_imu_dead_reckoning_follows_an_arc(arc):
    path, states = arc
    with LacArchive(path) as a:
        tr = archive_odometry(a, "imu")
        assert tr.source == "imu" and not tr.evaluation_only and len(tr) == a.n_frames
        np.testing.assert_allclose(tr.T_map_rover[0], a.initial_rover_pose(), atol=1e-12)
        d = odometry_drift(tr.T_map_rover, ground_truth_poses(a))
    assert d["path_length_m"] == pytest.approx(0.25 * 399 * DT, rel=1e-3)
    assert d["final_error_pct"] < 0.1 and d["heading_error_deg"] < 0.01 and d["rmse_m"] < 0.01


def test_imu_roll_converges_to_gravity(tmp_path):
    """initial.toml says level, the accelerometer says rolled 0.1 rad: roll follows gravity."""
    states = drive(n=300, w=1e-9, roll_true=0.1)
    path = write(tmp_path / "roll.lac", states, rover0=[2.0, -1.0, 0.3, 0.0, 0.0, 0.4])
    with LacArchive(path) as a:
        tr = archive_odometry(a, "imu")
    rolls = np.array([matrix_to_pose(T)[3] for T in tr.T_map_rover])
    assert rolls[0] == 0.0 and abs(rolls[-1] - 0.1) < 2e-3  # 15 s = 7.5 time constants
    yaws = np.array([matrix_to_pose(T)[5] for T in tr.T_map_rover])
    assert np.abs(yaws - 0.4).max() < 1e-3  # the tilt correction does not turn the heading


def test_record_sources_anchor_to_the_initial_pose_and_bridge_gaps(arc):
    path, states = arc
    with LacArchive(path) as a:
        gt = ground_truth_poses(a)
        shifted = archive_odometry(a, "record:shifted")  # map frame offset by (10, -5): motion kept
        np.testing.assert_allclose(shifted.T_map_rover, gt, atol=1e-9)
        orb = archive_odometry(a, "record:orbslam")  # m00..m33 every 10th frame, IMU in between
        assert orb.source == "record:orbslam" and orb.measured.sum() == 40 and not orb.measured[5]
        d = odometry_drift(orb.T_map_rover, gt)
        assert d["max_error_m"] < 1e-3


def test_ground_truth_is_marked_evaluation_only(arc):
    path, _ = arc
    with LacArchive(path) as a:
        tr = archive_odometry(a, "ground-truth")
        assert tr.evaluation_only and tr.label == "ground-truth (evaluation only)"
        assert odometry_drift(tr.T_map_rover, ground_truth_poses(a))["rmse_m"] == 0.0


def test_default_source_without_images_is_imu(arc):
    path, _ = arc
    with LacArchive(path) as a:
        assert default_odometry_source(a) == "imu"
        with pytest.raises(InputError, match="front stereo pair"):
            archive_odometry(a, "visual")


# ------------------------------------------------------------------------------ bad input


def _rewrite(src, dst, edit):
    with tarfile.open(src, "r:gz") as tf:
        members = [(m.name, tf.extractfile(m).read()) for m in tf.getmembers() if m.isfile()]
    with tarfile.open(dst, "w:gz") as tf:
        for name, data in members:
            data = edit(name, data)
            if data is None:
                continue
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return dst


def _set_cell(line: int, column: str, text: str):
    """An edit for _rewrite: frames.csv's `column` on (0-based text) line `line` set to `text`."""
    from lunarloc.io.lac.archive import FRAME_COLUMNS

    def edit(name, data):
        if name != "frames.csv":
            return data
        lines = data.decode().split("\n")
        cells = lines[line].split(",")
        cells[FRAME_COLUMNS.index(column)] = text
        lines[line] = ",".join(cells)
        return "\n".join(lines).encode()

    return edit


def test_missing_and_corrupt_records(arc, tmp_path):
    path, _ = arc
    with LacArchive(path) as a:
        with pytest.raises(
            ArchiveError, match=r"no custom record 'nope' \(custom records: orbslam, shifted\)"
        ):
            archive_odometry(a, "record:nope")
    cases = {
        "empty": (b"\n", "empty"),
        "header only": (b"frame,x,y,z,roll,pitch,yaw\n", "empty"),
        "columns": (b"frame,a,b\n0,1,2\n", "x,y,z,roll,pitch,yaw or m00..m33"),
        "text": (
            b"frame,x,y,z,roll,pitch,yaw\n0,0,0,0,0,0,0\n1,0.1,oops,0,0,0,0\n",
            "'y' holds 'oops' at line 3",
        ),
        "nan": (
            b"frame,x,y,z,roll,pitch,yaw\n0,0,0,0,0,0,0\n1,,0,0,0,0,0\n",
            "'x' is empty or not finite at line 3",
        ),
        "duplicate": (
            b"frame,x,y,z,roll,pitch,yaw\n0,0,0,0,0,0,0\n0,0,0,0,0,0,0\n",
            "appears twice",
        ),
        "not a rotation": (
            b"frame,"
            + ",".join(f"m{i}{j}" for i in range(3) for j in range(4)).encode()
            + b"\n0,2,0,0,0,0,1,0,0,0,0,1,0\n",
            "not a rotation",
        ),
    }
    for i, (text, msg) in enumerate(cases.values()):
        bad = _rewrite(
            path,
            tmp_path / f"bad{i}.lac",
            lambda n, d, t=text: t if n == "custom/shifted.csv" else d,
        )
        with LacArchive(bad) as a, pytest.raises(ArchiveError, match=msg) as exc:
            archive_odometry(a, "record:shifted")
        assert "custom/shifted.csv" in str(exc.value) and "\n" not in str(exc.value)


def test_imu_column_of_text_and_nan_speed(arc, tmp_path):
    path, _ = arc

    with pytest.raises(ArchiveError, match=r"frames.csv.*'n/a'.*gyro_z.*line 6"):
        LacArchive(_rewrite(path, tmp_path / "t.lac", _set_cell(5, "gyro_z", "n/a")))

    with LacArchive(_rewrite(path, tmp_path / "n.lac", _set_cell(7, "linear_speed", ""))) as a:
        with pytest.raises(
            InputError, match=r"'linear_speed' is not a finite number at frame 6 \(line 8"
        ):
            archive_odometry(a, "imu")
        archive_odometry(a, "ground-truth")  # the pose columns are fine


def test_camera_table_listing_absent_images(tmp_path):
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.zeros((12, 16), np.uint8)).save(buf, format="PNG")
    path = write(tmp_path / "c.lac", drive(n=5))
    table = (
        b"frame,enable,camera_x,camera_y,camera_z,camera_roll,camera_pitch,camera_yaw,light_intensity,grayscale,semantic\n"
        b"2,True,0.28,0.081,0.131,0,0,0,0,FrontLeft_grayscale_2.png,\n"
        b"4,True,0.28,0.081,0.131,0,0,0,0,FrontLeft_grayscale_4.png,\n"
    )

    members = {
        **_members(path),
        "cameras/FrontLeft/FrontLeft_frames.csv": table,
        "cameras/FrontLeft/grayscale/FrontLeft_grayscale_2.png": buf.getvalue(),
    }  # no image of frame 4
    with tarfile.open(tmp_path / "c3.lac", "w:gz") as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    with pytest.raises(
        ArchiveError,
        match=r"FrontLeft_grayscale_4.png: image listed in .*line 3 \(frame 4\) is absent",
    ):
        LacArchive(tmp_path / "c3.lac")


def _members(path):
    with tarfile.open(path, "r:gz") as tf:
        return {m.name: tf.extractfile(m).read() for m in tf.getmembers() if m.isfile()}


# ------------------------------------------------------------------------------ CLI


def test_odometry_command(arc, tmp_path, capsys):
    from lunarloc.cli.app import main

    path, _ = arc
    out = tmp_path / "o" / "imu.tum"
    assert (
        main(
            [
                "odometry",
                str(path),
                "--source",
                "imu",
                "-o",
                str(out),
                "--json",
                str(tmp_path / "d.json"),
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert (
        "odometry imu" in text
        and "final error" in text
        and "heading error" in text
        and "RMSE" in text
    )
    rows = np.loadtxt(out)
    assert rows.shape == (400, 8)
    d = json.loads((tmp_path / "d.json").read_text())
    assert d["source"] == "imu" and d["final_error_pct"] < 0.1
    assert main(["odometry", str(path), "--source", "ground-truth"]) == 0
    assert "(evaluation only)" in capsys.readouterr().out
    assert main(["odometry", str(path), "--source", "sonar"]) == 2
    assert "unknown odometry source 'sonar'" in capsys.readouterr().err


@pytest.fixture(scope="module")
def bare_image_archive(tmp_path_factory):
    """A simulated traverse with the front pair and no custom record at all (a bare LAC archive)."""
    from lunarloc.sim.simulate import SimulationConfig, simulate_dataset

    out = tmp_path_factory.mktemp("bare")
    cfg = SimulationConfig(
        duration_s=6.0,
        image_rate_hz=2.0,
        width=320,
        height=180,
        cameras=("FrontLeft", "FrontRight"),
        semantic=False,
    )
    simulate_dataset(0, 1, out, cfg)
    bare = _rewrite(
        out / "traverse_0.lac",
        out / "bare.lac",
        lambda n, d: None if n.startswith("custom/") else d,
    )
    return bare, out / "rocks.csv"


def test_run_on_a_bare_archive_names_its_odometry(bare_image_archive, tmp_path, capsys):
    from lunarloc.cli.app import main

    bare, rocks = bare_image_archive
    with LacArchive(bare) as a:
        assert a.custom_records == [] and default_odometry_source(a) == "visual"
    out = tmp_path / "run"
    assert (
        main(
            [
                "run",
                str(bare),
                "--reference",
                str(rocks),
                "-o",
                str(out),
                "--odometry",
                "imu",
                "--no-plot",
            ]
        )
        == 0
    )
    assert json.loads((out / "config.json").read_text())["info"]["odometry_source"] == "imu"
    assert "odometry: imu" in capsys.readouterr().out
    assert (
        main(
            [
                "run",
                str(bare),
                "--reference",
                str(rocks),
                "-o",
                str(tmp_path / "run2"),
                "--odometry",
                "record:odometry",
            ]
        )
        == 2
    )
    assert "no custom record 'odometry'" in capsys.readouterr().err


def test_detect_with_odometry(bare_image_archive, tmp_path, capsys):
    from lunarloc.cli.app import main

    bare, _ = bare_image_archive
    csv = tmp_path / "det.csv"
    assert main(["detect", str(bare), "-o", str(csv), "--odometry", "imu"]) == 0
    assert json.loads(csv.with_suffix(".csv.config.json").read_text())["info"]["pose"] == "imu"
    from lunarloc.io.maps import load_traverse

    prov = load_traverse(csv).pose_provenance  # the file says which poses placed it
    assert (prov.poses, prov.detail, prov.stated_by) == (
        "odometry",
        "imu",
        "the file's pose column",
    )
    assert "placed with imu poses" in capsys.readouterr().out
    assert main(["detect", str(bare), "-o", str(csv), "--odometry", "wheels"]) == 2


def test_visual_dispatch_on_a_simulated_traverse(bare_image_archive):
    bare, _ = bare_image_archive
    with LacArchive(bare) as a:
        tr = archive_odometry(a, "visual")
        pairs = set(a.camera_frames("FrontLeft")["frame"].tolist())
        assert tr.source == "visual" and len(tr) == a.n_frames
        assert set(tr.frames[tr.measured].tolist()) == pairs
        np.testing.assert_allclose(tr.T_map_rover[0], a.initial_rover_pose(), atol=1e-9)
        d = odometry_drift(tr.T_map_rover, ground_truth_poses(a))
    assert d["rmse_m"] < 0.1 and d["max_heading_error_deg"] < 2.0


def test_a_record_with_every_frame_needs_no_imu(arc, tmp_path):
    path, _ = arc

    with LacArchive(_rewrite(path, tmp_path / "g.lac", _set_cell(3, "gyro_x", ""))) as a:
        np.testing.assert_allclose(
            archive_odometry(a, "record:shifted").T_map_rover, ground_truth_poses(a), atol=1e-9
        )
        with pytest.raises(InputError, match="'gyro_x' is not a finite number at frame 2"):
            archive_odometry(a, "record:orbslam")  # every 10th frame: the IMU bridges the others


def test_step_errors_score_each_step_against_the_true_one():
    from lunarloc.odometry.source import step_errors

    _pose = pose_to_matrix

    # a true path of 0.15 m steps turning 2 degrees a step; the estimate repeats it except one
    # step 3 cm too long and turned 0.5 degrees more (later poses follow it: steps stay exact)
    G = [np.eye(4)]
    for _ in range(20):
        G.append(G[-1] @ _pose(0.15, 0, 0, 0, 0, np.radians(2.0)))
    E = [np.eye(4)]
    for k in range(20):
        extra = _pose(0.03, 0, 0, 0, 0, np.radians(0.5)) if k == 7 else np.eye(4)
        E.append(E[-1] @ _pose(0.15, 0, 0, 0, 0, np.radians(2.0)) @ extra)
    out = step_errors(np.stack(E), np.stack(G))
    assert out["steps"] == 20 and out["steps_over_2cm"] == 1
    assert out["step_cm_max"] == pytest.approx(3.0, abs=1e-6)
    assert out["step_horizontal_cm_max"] == pytest.approx(3.0, abs=1e-6)
    assert out["step_yaw_deg_max"] == pytest.approx(0.5, abs=1e-6)
    assert out["step_cm_p50"] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(InputError, match="equal length"):
        step_errors(np.stack(E)[:3], np.stack(G)[:4])
