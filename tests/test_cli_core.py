import json

import numpy as np
import pytest

from conftest import make_pair
from lunarloc.cli import main
from lunarloc.io.maps import LandmarkMap, load_map, save_map


def write_traverse_csv(path, world_rocks, rng, n_frames=12):
    """A traverse CSV whose every frame re-detects the rocks with 5 mm noise."""
    lines = ["frame,x,y,z,detections,boulders"]
    for f in range(n_frames):
        det = world_rocks + rng.normal(0, 0.005, world_rocks.shape)
        b = "[" + ", ".join(f"({x:.6f}, {y:.6f}, {z:.6f})" for x, y, z in det) + "]"
        lines.append(f'{f},{0.1 * f},0,0,{len(det)},"{b}"')
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def maps(tmp_path, rng):
    ref, veh, T, _ = make_pair(rng, n_ref=80, n_common=25, n_outliers=5)
    ref_p = save_map(ref, tmp_path / "ref.csv")
    veh_p = save_map(veh, tmp_path / "veh.npz")
    return ref_p, veh_p, T


def test_localize_json(maps, capsys):
    ref_p, veh_p, T = maps
    assert main(["localize", str(ref_p), str(veh_p), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["success"] is True
    veh = load_map(veh_p).positions_xyz
    est = veh @ np.array(d["T_ref_veh"])[:3, :3].T + np.array(d["T_ref_veh"])[:3, 3]
    true = veh @ T[:3, :3].T + T[:3, 3]
    assert np.max(np.linalg.norm(est - true, axis=1)) < 0.05
    for key in ("num_inliers", "inliers", "residual_rmse_m", "time_s", "reason"):
        assert key in d


def test_localize_human_output_and_failure_exit_zero(tmp_path, rng, capsys):
    a = save_map(LandmarkMap(rng.uniform(-10, 10, (40, 3))), tmp_path / "a.csv")
    b = save_map(LandmarkMap(rng.uniform(-10, 10, (30, 3))), tmp_path / "b.csv")
    assert main(["localize", str(a), str(b)]) == 0
    assert "not localized" in capsys.readouterr().out


def test_map_from_traverse_then_localize(tmp_path, rng, capsys):
    ref, veh, T, common = make_pair(rng, n_ref=60, n_common=25, n_outliers=0)
    t_ref = write_traverse_csv(tmp_path / "traverse_ref.csv", ref.positions_xyz, rng)
    assert main(["map", str(t_ref), "-o", str(tmp_path / "ref_map.csv")]) == 0
    lm = load_map(tmp_path / "ref_map.csv")
    assert len(lm) == 60
    save_map(veh, tmp_path / "veh.csv")
    # a traverse CSV is accepted directly as the reference argument
    assert main(["localize", str(t_ref), str(tmp_path / "veh.csv"), "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()[-1]
    assert json.loads(out)["success"]


def test_errors_are_one_line_and_nonzero(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("x,y\n1,2\n")
    assert main(["localize", str(bad), str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "missing column 'z'" in err and len(err.splitlines()) == 1
    assert main(["localize", str(tmp_path / "nope.csv"), str(bad)]) == 2
    assert "no such file" in capsys.readouterr().err
    empty = save_map(LandmarkMap(np.zeros((0, 3))), tmp_path / "empty.csv")
    assert main(["localize", str(empty), str(empty)]) == 2
    assert "empty" in capsys.readouterr().err
    assert main(["localize", str(empty), str(empty), "--mode", "sideways"]) == 2


def test_bench_requires_data(tmp_path, capsys):
    assert main(["bench", "pairs", "--data", str(tmp_path)]) == 2
    assert "no traverse" in capsys.readouterr().err


def test_usage_errors_exit_2(capsys):
    assert main(["localize", "--bogus"]) == 2
    assert "No such option" in capsys.readouterr().err
    assert main(["no-such-command"]) == 2


def test_lazy_command_table_matches_registered_commands():
    """`main` imports only the invoked command's module (issue 14: a warm `localize` should
    not import the renderer or the fusion stack); the table it uses must name every command
    the modules register, in the module that registers it."""
    import importlib

    app_mod = importlib.import_module("lunarloc.cli.app")
    app_mod._register_commands()
    registered = {c.name for c in app_mod.app.registered_commands} | {
        g.name for g in app_mod.app.registered_groups
    }
    assert registered == set(app_mod._MODULES_OF_COMMAND)
    for name, modules in app_mod._MODULES_OF_COMMAND.items():
        owners = [
            m
            for m in modules
            if any(
                getattr(c.callback, "__module__", "") == f"lunarloc.cli.{m}"
                for c in app_mod.app.registered_commands
                if c.name == name
            )
        ]
        if name != "bench":  # a group: its subcommands live in several modules
            assert owners == list(modules), name
    assert set(m for ms in app_mod._MODULES_OF_COMMAND.values() for m in ms) == set(
        app_mod._COMMAND_MODULES
    )


def test_help_lists_every_command(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    from lunarloc.cli.app import _MODULES_OF_COMMAND

    for name in _MODULES_OF_COMMAND:
        assert name in out


def test_localize_imports_only_its_module(tmp_path):
    """In a fresh process, `lunarloc localize --help` leaves the other command modules unimported."""
    import subprocess
    import sys

    code = (
        "import sys; from lunarloc.cli import main; main(['localize', '--help']); "
        "print(sorted(m for m in sys.modules if m.startswith('lunarloc.cli.commands_')))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert out.strip().splitlines()[-1] == "['lunarloc.cli.commands_core']"


def test_localize_traverse_vehicle_uses_its_path(tmp_path, rng, capsys):
    """A traverse CSV as the vehicle: the localizer is given its path (the pose judged at the
    traverse's last position; a fitted bend places each landmark where it was seen from),
    as the pair benchmark does; a landmark map as the vehicle gets the straight stand-in. The
    traverse says its poses were odometry (a 'pose' column, as lunarloc's writers state it), so no
    bounds are taken from it and the bend is fitted; the map made from it keeps that provenance."""
    from lunarloc.core.geometry import make_transform, transform_points

    rocks = np.c_[rng.uniform(0, 20, 70), rng.uniform(-4, 4, 70), rng.uniform(-0.05, 0.05, 70)]
    c, s_ = np.cos(0.6), np.sin(0.6)
    T_ref_veh = make_transform(
        np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1]]), np.array([3.0, -2.0, 0.1])
    )
    ref_p = save_map(LandmarkMap(transform_points(T_ref_veh, rocks)), tmp_path / "ref.csv")
    lines = ["frame,x,y,z,detections,boulders,pose"]
    for f, x in enumerate(
        np.arange(0.0, 20.01, 0.25)
    ):  # the rover drives along x, seeing rocks within 4 m
        near = rocks[np.linalg.norm(rocks[:, :2] - [x, 0.0], axis=1) < 4.0]
        det = near + rng.normal(0, 0.005, near.shape)
        b = "[" + ", ".join(f"({p:.6f}, {q:.6f}, {r:.6f})" for p, q, r in det) + "]"
        lines.append(f'{f},{x:.3f},0,0,{len(det)},"{b}",odometry:visual')
    t_veh = tmp_path / "traverse_veh.csv"
    t_veh.write_text("\n".join(lines) + "\n")
    assert main(["localize", str(ref_p), str(t_veh), "--json"]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert d["success"], d["reason"]
    assert np.allclose(np.array(d["T_ref_veh"]), T_ref_veh, atol=0.02)
    fit = d["distortion_fit"]
    assert fit["path_given"] is True and fit["placement"] == "sightings"
    assert d["odometry_bounds"]["source"] == "prior"
    assert d["odometry_bounds"]["pose_provenance"]["detail"] == "visual"
    assert main(["map", str(t_veh), "-o", str(tmp_path / "veh.csv")]) == 0
    capsys.readouterr()
    assert main(["localize", str(ref_p), str(tmp_path / "veh.csv"), "--json"]) == 0
    d = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    fit = d["distortion_fit"]
    assert fit["path_given"] is False and fit["placement"] == "straight stand-in"
    assert d["odometry_bounds"]["pose_provenance"]["poses"] == "odometry"
