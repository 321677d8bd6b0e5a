"""What a lab adopting lunarloc relies on (issue 32): the licence in the package metadata, the
CLI conventions (--version, -v/-q, choices listed, one meaning of --json, one option name
across bench commands, no transform for a pose not trusted), API and CLI giving the same
answer on the same vehicle file, public trajectory writers, the online component's
trajectory, kernels prepared before any timed stage (and without numba.pycc), and
`simulate` writing nothing when the `sim` extra is missing."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import make_pair
from lunarloc.cli import main
from lunarloc.io.maps import LandmarkMap, save_map

ROOT = Path(__file__).resolve().parents[1]


def _traverse_csv(path, world_rocks, rng, n_frames=12):
    """Every frame re-detects the rocks (5 mm noise); the path runs 3 m through their middle."""
    lines = ["frame,x,y,z,detections,boulders"]
    c = world_rocks.mean(axis=0)
    for f in range(n_frames):
        det = world_rocks + rng.normal(0, 0.005, world_rocks.shape)
        b = "[" + ", ".join(f"({x:.6f}, {y:.6f}, {z:.6f})" for x, y, z in det) + "]"
        lines.append(f'{f},{c[0] + 0.25 * f},{c[1] + 0.05 * f},{c[2]},{len(det)},"{b}"')
    path.write_text("\n".join(lines) + "\n")
    return path


# ----------------------------------------------------------------------------- metadata


def _toml(path: Path) -> dict:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    return tomllib.loads(path.read_text())


def test_licence_and_metadata():
    meta = _toml(ROOT / "pyproject.toml")["project"]
    assert meta["license"] == "MIT"
    assert meta["license-files"] == ["LICENSE"]
    lic = (ROOT / "LICENSE").read_text()
    assert lic.startswith("MIT License") and "WITHOUT WARRANTY" in lic
    urls = meta["urls"]
    assert "mit-acl/lunarloc-data" in urls["Dataset"] and "2506.16940" in urls["Paper"]
    import lunarloc

    assert lunarloc.__version__ == meta["version"]
    changelog = (ROOT / "CHANGELOG.md").read_text()
    assert "## [Unreleased]" in changelog and f"## [{meta['version']}]" in changelog


def test_citation_file_names_the_paper():
    yaml = pytest.importorskip("yaml")
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"].startswith("1.2")
    pc = cff["preferred-citation"]
    assert pc["title"].startswith("LunarLoc")
    assert pc["authors"][0]["family-names"] == "Thomas"
    assert cff["version"] == _toml(ROOT / "pyproject.toml")["project"]["version"]


# ----------------------------------------------------------------------------- CLI conventions


def test_version(capsys):
    import lunarloc

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"lunarloc {lunarloc.__version__}"


@pytest.mark.parametrize(
    "args, level",
    [
        ([], logging.WARNING),
        (["-v"], logging.INFO),
        (["-vv"], logging.DEBUG),
        (["-q"], logging.ERROR),
        (["--log-level", "debug"], logging.DEBUG),
        (["-q", "--log-level", "info"], logging.INFO),
    ],
)
def test_log_level_options(args, level, tmp_path, rng):
    a = save_map(LandmarkMap(rng.uniform(-10, 10, (20, 3))), tmp_path / "a.csv")
    assert main([*args, "localize", str(a), str(a), "--json"]) == 0
    assert logging.getLogger().level == level
    main(["localize", str(a), str(a), "--json"])
    assert logging.getLogger().level == logging.WARNING  # each call starts from the default


def test_enum_options_are_choices_listed_in_help(capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "250")  # the help table unwrapped
    monkeypatch.setenv("TERMINAL_WIDTH", "250")
    assert main(["localize", "--help"]) == 0
    out = capsys.readouterr().out
    for listed in ("gravity|6dof", "exact|clipper", "se3|yaw", "auto|full|indexed"):
        assert listed in out, listed
    assert main(["run", "--help"]) == 0
    out = capsys.readouterr().out
    assert "classical|fastsam" in out and "landmarks|pose" in out and "record:NAME" in out
    assert main(["detect", "--help"]) == 0
    assert "ground-truth|odometry" in capsys.readouterr().out


def test_bad_choice_is_a_usage_error(tmp_path, rng, capsys):
    a = save_map(LandmarkMap(rng.uniform(-10, 10, (20, 3))), tmp_path / "a.csv")
    assert main(["localize", str(a), str(a), "--mode", "sideways"]) == 2
    err = capsys.readouterr().err
    assert "sideways" in err and "gravity" in err and "Traceback" not in err


def test_completion_is_offered(capsys):
    assert main(["--help"]) == 0
    assert "--install-completion" in capsys.readouterr().out


def test_bench_commands_share_heading_drift(tmp_path, capsys):
    for cmd in ("pairs", "loop"):
        assert main(["bench", cmd, "--help"]) == 0
        out = capsys.readouterr().out
        assert "--heading-drift" in out and "--drift " not in out  # the old name stays, hidden
        # the hidden alias still parses: the failure is about the missing data, not the option
        rc = main(
            [
                "bench",
                cmd,
                "--data",
                str(tmp_path / "missing"),
                "--out",
                str(tmp_path / cmd),
                "--drift",
                "0.1",
            ]
        )
        err = capsys.readouterr().err
        assert rc == 2 and "No such option" not in err, err


def test_not_localized_prints_no_transform(tmp_path, rng, capsys):
    a = save_map(LandmarkMap(rng.uniform(-10, 10, (40, 3))), tmp_path / "a.csv")
    b = save_map(LandmarkMap(rng.uniform(-10, 10, (30, 3))), tmp_path / "b.csv")
    assert main(["localize", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "not localized" in out and "T_ref_veh" not in out


def test_json_is_stdout_and_json_out_a_file(tmp_path, rng, capsys):
    ref, veh, _, _ = make_pair(rng, n_ref=60, n_common=25, n_outliers=0)
    r, v = save_map(ref, tmp_path / "r.csv"), save_map(veh, tmp_path / "v.csv")
    assert main(["localize", str(r), str(v), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)  # stdout is the JSON object and nothing else
    assert d["success"] and d["kernels"]["source"] in ("aot", "cache", "compiled", "ready")
    out = tmp_path / "res.json"
    assert main(["localize", str(r), str(v), "--json-out", str(out)]) == 0
    assert "localized" in capsys.readouterr().out  # the human-readable report as well
    assert json.loads(out.read_text())["T_ref_veh"] == d["T_ref_veh"]
    assert main(["localize", str(r), str(v), "--json-out", str(out)]) == 2  # no silent overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert main(["localize", str(r), str(v), "--json-out", str(out), "--overwrite"]) == 0


def test_odometry_old_json_file_form_still_works(monkeypatch):
    from lunarloc.cli.checks import legacy_json_argv

    argv = ["odometry", "a.lac", "--json", "drift.json"]
    assert legacy_json_argv(argv) == ["odometry", "a.lac", "--json-out", "drift.json"]
    assert legacy_json_argv(["odometry", "a.lac", "--json"]) == ["odometry", "a.lac", "--json"]


# ----------------------------------------------------------------------------- API == CLI


def test_load_vehicle_gives_what_the_cli_uses(tmp_path, rng, capsys):
    from lunarloc import load_reference, load_vehicle, localize

    ref, veh, T, _ = make_pair(rng, n_ref=70, n_common=30, n_outliers=0)
    r = save_map(ref, tmp_path / "ref.csv")
    t = _traverse_csv(tmp_path / "traverse.csv", veh.positions_xyz, rng)
    v = load_vehicle(t)
    assert v.source == "traverse" and v.path_xyz.shape == (12, 3)
    assert np.allclose(v.query_xyz, v.path_xyz[-1:])
    from lunarloc import LocalizationConfig

    rigid = LocalizationConfig(
        odometry_scale_error=0.0, odometry_heading_drift_deg_per_m=0.0
    )  # a rigid map
    res = localize(load_reference(r), v.map, rigid, **v.localize_kwargs())
    assert (
        main(
            [
                "localize",
                str(r),
                str(t),
                "--json",
                "--odometry-scale-error",
                "0",
                "--odometry-drift",
                "0",
            ]
        )
        == 0
    )
    d = json.loads(capsys.readouterr().out)
    assert res.success and d["success"], res.reason
    assert np.allclose(np.array(d["T_ref_veh"]), res.T_ref_veh, atol=1e-9)
    assert d["predicted_error_m"] == pytest.approx(res.predicted_error_m, rel=1e-9)
    plain = load_vehicle(save_map(veh, tmp_path / "veh.npz"))
    assert plain.source == "map" and plain.path_xyz is None and plain.query_xyz is None


@pytest.mark.realdata
def test_readme_pair_3_5_api_and_cli_agree(capsys):
    import os

    data = (
        Path(os.environ.get("LUNARLOC_DATA", ROOT.parent / "shared" / "data" / "lunarloc-data"))
        / "csv"
    )
    if not (data / "traverse_3.csv").is_file():
        pytest.skip("lunarloc-data not present")
    from lunarloc import load_reference, load_vehicle, localize

    v = load_vehicle(data / "traverse_5.csv")
    res = localize(
        load_reference(data / "traverse_3.csv"), v.map, query_xyz=v.query_xyz, path_xyz=v.path_xyz
    )
    assert (
        main(["localize", str(data / "traverse_3.csv"), str(data / "traverse_5.csv"), "--json"])
        == 0
    )
    d = json.loads(capsys.readouterr().out)
    assert res.success == d["success"]
    assert np.allclose(np.array(d["T_ref_veh"]), res.T_ref_veh, atol=1e-9)


# ----------------------------------------------------------------------------- trajectories


def test_tum_and_kitti_writers_round_trip(tmp_path):
    from lunarloc import write_kitti, write_tum
    from lunarloc.core.errors import InputError
    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.io.trajectory import read_kitti, read_tum

    T = np.stack(
        [pose_to_matrix(0.5 * i, -0.2 * i, 0.01 * i, 0.01, -0.02, 0.3 * i) for i in range(5)]
    )
    t = np.arange(5) * 0.5
    times, poses = read_tum(write_tum(tmp_path / "a.tum", t, T))
    assert np.allclose(times, t) and np.allclose(poses[:, :3], T[:, :3, 3], atol=1e-6)
    assert np.allclose(poses[:, 5], [0.3 * i for i in range(5)], atol=1e-6)
    back = read_kitti(write_kitti(tmp_path / "a.kitti", T))
    assert np.allclose(back, T, atol=1e-8)
    assert len((tmp_path / "a.kitti").read_text().splitlines()[0].split()) == 12
    with pytest.raises(InputError):
        write_tum(tmp_path / "b.tum", t[:3], T)
    with pytest.raises(InputError):
        write_kitti(tmp_path / "b.kitti", T[:, :3, :])


def test_online_localizer_keeps_and_writes_its_trajectory(tmp_path):
    from lunarloc import CameraRig, OnlineLocalizer
    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.io.trajectory import read_kitti, read_tum

    rig = CameraRig.from_calibration(160, 90, fx=114.25)
    rng = np.random.default_rng(3)
    loc = OnlineLocalizer(
        LandmarkMap(np.c_[rng.uniform(-10, 10, (50, 2)), np.zeros(50)]), np.zeros(6), rig=rig
    )
    imu = np.array([0.0, 0.0, 1.62, 0.0, 0.0, 0.0])
    returned = []
    for i in range(30):
        T = pose_to_matrix(0.02 * i, 0.0, 0.0, 0.0, 0.0, 0.001 * i)
        returned.append(loc.update(0.05 * i, None, imu, 0.4, 0.02, odometry=T).T_map_rover)
    times, T_hist = loc.trajectory()
    assert np.allclose(times, 0.05 * np.arange(30))
    assert np.allclose(T_hist, np.stack(returned))
    t2, poses = read_tum(loc.write_trajectory(tmp_path / "online.tum"))
    assert np.allclose(t2, times) and np.allclose(poses[:, :3], T_hist[:, :3, 3], atol=1e-6)
    assert np.allclose(
        read_kitti(loc.write_trajectory(tmp_path / "online.kitti", "kitti")), T_hist, atol=1e-8
    )
    from lunarloc.core.errors import InputError

    with pytest.raises(InputError):
        loc.write_trajectory(tmp_path / "x", "csv")


# ----------------------------------------------------------------------------- kernels at first use


def test_kernel_preparation_is_announced_and_done_once(monkeypatch, caplog):
    import time

    from lunarloc.association import aot

    monkeypatch.setattr(aot, "_PREP", {"done": None})
    monkeypatch.setattr(aot, "ANNOUNCE_AFTER_S", 0.05)
    monkeypatch.setattr(aot, "aot_status", lambda: "not built (run `lunarloc warm-up`)")
    calls = []

    def exercise():
        calls.append(1)
        time.sleep(0.3)  # a slow preparation: it must be announced while it runs
        return 0.3

    with caplog.at_level(logging.INFO, logger="lunarloc.association.aot"):
        first = aot.prepare_kernels(exercise)
        second = aot.prepare_kernels(exercise)
    assert calls == [1] and first.source in ("cache", "compiled") and second.source == "ready"
    text = caplog.text
    assert (
        "preparing the association kernels" in text and "not counted as localization time" in text
    )


def test_localize_prepares_kernels_before_its_first_stage(monkeypatch, rng):
    from lunarloc.association import aot
    from lunarloc.localization import localize as L

    order = []
    monkeypatch.setattr(aot, "_PREP", {"done": None})
    monkeypatch.setattr(aot, "aot_status", lambda: "not built")
    monkeypatch.setattr(L, "warm_kernels", lambda: order.append("prepare") or 0.5)
    real = L.putative_associations
    monkeypatch.setattr(
        L, "putative_associations", lambda *a, **k: order.append("associations") or real(*a, **k)
    )
    ref, veh, _, _ = make_pair(rng, n_ref=40, n_common=20, n_outliers=0)
    L.localize(ref, veh)
    L.localize(ref, veh)
    assert order == ["prepare", "associations", "associations"]


def test_works_without_numba_pycc(tmp_path):
    """numba has deprecated numba.pycc: with it gone, `lunarloc warm-up` says the ahead-of-time
    build is skipped, exits 0, and localization runs on numba's JIT."""
    code = (
        "import sys; sys.modules['numba.pycc'] = None\n"  # any import of numba.pycc now fails
        "from lunarloc.cli import main\n"
        "rc = main(['warm-up'])\n"
        "from lunarloc.association.aot import aot_status\n"
        "from lunarloc.localization.warmup import prepare_kernels\n"
        "print('RC', rc, prepare_kernels().source)\n"
        f"rc = main(['localize', {str(tmp_path / 'r.csv')!r}, {str(tmp_path / 'v.csv')!r}, '--json'])\n"
        "print('RC2', rc)\n"
    )
    rng = np.random.default_rng(5)
    ref, veh, _, _ = make_pair(rng, n_ref=50, n_common=25, n_outliers=0)
    save_map(ref, tmp_path / "r.csv")
    save_map(veh, tmp_path / "v.csv")
    env = {
        "LUNARLOC_AOT": "0",
        **{k: v for k, v in __import__("os").environ.items() if k != "LUNARLOC_AOT"},
    }
    env["LUNARLOC_AOT"] = (
        "0"  # never load a build made elsewhere: the JIT path is the one under test
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=900, env=env
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "ahead-of-time kernels not built" in proc.stderr
    lines = proc.stdout.splitlines()
    assert "RC 0 ready" in lines and "RC2 0" in lines
    assert json.loads(lines[lines.index("RC2 0") - 1])["success"] is True


# ----------------------------------------------------------------------------- simulate without the sim extra


def test_simulate_without_sim_extra_writes_nothing(tmp_path, monkeypatch, capsys):
    for mod in ("trimesh", "embreex", "embreex.rtcore_scene", "embreex.mesh_construction"):
        monkeypatch.setitem(sys.modules, mod, None)
    out = tmp_path / "sim"
    assert (
        main(["simulate", "--out", str(out), "--duration", "2", "--width", "64", "--height", "36"])
        == 2
    )
    err = capsys.readouterr().err
    assert "lunarloc[sim]" in err
    assert not out.exists() or not any(out.iterdir())
    from lunarloc.core.errors import DependencyError
    from lunarloc.sim.simulate import SimulationConfig, simulate_dataset

    with pytest.raises(DependencyError):
        simulate_dataset(0, 1, out, SimulationConfig(duration_s=2.0, width=64, height=36))
    assert not out.exists() or not any(out.iterdir())
