"""CLI smoke runs: lunarloc run / plot / bench loop, and their errors (exit 2, one line)."""

import json

import numpy as np
import pytest

from _loop_data import synthetic_traverse
from lunarloc.cli import main


@pytest.fixture(scope="module")
def tiny_archive(tmp_path_factory):
    from lunarloc.sim.simulate import SimulationConfig, simulate_dataset

    out = tmp_path_factory.mktemp("sim")
    cfg = SimulationConfig(
        duration_s=6.0,
        image_rate_hz=2.0,
        width=320,
        height=180,
        cameras=("FrontLeft", "FrontRight"),
        semantic=False,
    )
    simulate_dataset(0, 1, out, cfg)
    return out


def test_run_and_plot(tiny_archive, tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(
        [
            "run",
            str(tiny_archive / "traverse_0.lac"),
            "--reference",
            str(tiny_archive / "rocks.csv"),
            "-o",
            str(out),
            "--odometry",
            "record:odometry",
        ]
    )
    assert rc == 0
    cfg = json.loads((out / "config.json").read_text())
    assert (
        cfg["info"]["odometry_source"] == "record:odometry"
        and cfg["odometry"]["source"] == "record:odometry"
    )
    s = json.loads((out / "summary.json").read_text())
    assert s["image_frames"] == 13 and "ate_corrected" in s
    assert (out / "trajectory.tum").is_file() and (out / "map.png").is_file()
    assert main(["plot", str(out), "--figdir", str(tmp_path / "figs")]) == 0
    assert (tmp_path / "figs" / "error.png").is_file()
    # the run repeated from its own config.json gives the same outputs
    again = tmp_path / "again"
    assert (
        main(
            [
                "run",
                str(tiny_archive / "traverse_0.lac"),
                "--reference",
                str(tiny_archive / "rocks.csv"),
                "-o",
                str(again),
                "--config",
                str(out / "config.json"),
                "--no-plot",
            ]
        )
        == 0
    )
    for name in (
        "trajectory.tum",
        "trajectory_online.tum",
        "trajectory_odometry.tum",
        "vehicle_map.csv",
        "config.json",
    ):
        assert (out / name).read_bytes() == (again / name).read_bytes(), name


def test_run_errors(tiny_archive, tmp_path, capsys):
    bad = tmp_path / "bad.lac"
    bad.write_bytes(b"garbage")
    assert (
        main(
            [
                "run",
                str(bad),
                "--reference",
                str(tiny_archive / "rocks.csv"),
                "-o",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    empty = tmp_path / "empty.csv"
    empty.write_text("x,y,z\n")
    assert (
        main(
            [
                "run",
                str(tiny_archive / "traverse_0.lac"),
                "--reference",
                str(empty),
                "-o",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "error:" in err and "at least 3" in err
    assert main(["plot", str(tmp_path)]) == 2


def test_bench_loop(tmp_path, capsys):
    from lunarloc.io.maps import format_boulders

    data = tmp_path / "data" / "csv"
    data.mkdir(parents=True)
    for k, seed in ((1, 0), (2, 0)):
        rocks, trav = synthetic_traverse(seed=seed, length_m=10.0 if k == 1 else 14.0)
        with open(data / f"traverse_{k}.csv", "w") as fh:
            fh.write("frame,x,y,z,detections,boulders\n")
            for f, p in zip(trav.frames, trav.rover_xyz):
                d = trav.detections_xyz[trav.detection_frame == f]
                fh.write(f'{f},{p[0]},{p[1]},{p[2]},{len(d)},"{format_boulders(d)}"\n')
    out = tmp_path / "bench"
    assert main(["bench", "loop", "--data", str(tmp_path / "data"), "--out", str(out)]) == 0
    rows = json.loads((out / "loop.json").read_text())
    assert len(rows) == 2 and all(r["fixes"] > 0 for r in rows)


def test_detect_then_map(tiny_archive, tmp_path, capsys):
    """`lunarloc detect` on a 320x180 archive writes the dataset CSV that `lunarloc map` reads,
    with debug overlays, and records the (resolution-scaled) detector config it used."""
    from lunarloc.io.maps import load_traverse

    det = tmp_path / "det.csv"
    rc = main(
        [
            "detect",
            str(tiny_archive / "traverse_0.lac"),
            "-o",
            str(det),
            "--debug-dir",
            str(tmp_path / "dbg"),
        ]
    )
    assert rc == 0
    t = load_traverse(det)
    assert len(t.frames) > 0 and np.all(np.isfinite(t.detections_xyz))
    assert any((tmp_path / "dbg").iterdir())
    cfg = json.loads(det.with_name("det.csv.config.json").read_text())
    assert (
        cfg["info"]["detector_scaled"]["stereo"]["num_disparities"]
        < cfg["detector"]["stereo"]["num_disparities"]
    )  # scaled to 320 px
    det2 = tmp_path / "det2.csv"
    assert (
        main(
            [
                "detect",
                str(tiny_archive / "traverse_0.lac"),
                "-o",
                str(det2),
                "--config",
                str(det.with_name("det.csv.config.json")),
            ]
        )
        == 0
    )
    assert det2.read_bytes() == det.read_bytes()
    assert main(["map", str(det), "-o", str(tmp_path / "m.csv"), "--min-sightings", "1"]) == 0
    assert (
        main(
            [
                "detect",
                str(tiny_archive / "traverse_0.lac"),
                "-o",
                str(det),
                "--segmenter",
                "fastsam",
                "--weights",
                str(tmp_path / "missing.pt"),
            ]
        )
        == 2
    )
