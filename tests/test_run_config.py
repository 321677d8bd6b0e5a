"""One run configuration that round-trips (issue 10 item 4): RunConfig to and from plain
values, clear ConfigErrors naming the key, options overriding a file, and a run repeated from
its own config.json giving the same outputs."""

import json

import numpy as np
import pytest

from _loop_data import synthetic_traverse
from lunarloc.config.run import OdometryConfig, RunConfig, config_from_dict, load_config_file
from lunarloc.core.errors import ConfigError
from lunarloc.online.loop import FixKind, LoopConfig


@pytest.mark.parametrize(
    "cfg",
    [
        RunConfig(),
        RunConfig.for_detections(),
        RunConfig(
            loop=LoopConfig(window_m=5.0, fix_kind="pose"),
            odometry=OdometryConfig(source="imu", scale_error=-0.01),
        ),
    ],
)
def test_round_trip_through_json(cfg):
    d = json.loads(json.dumps(cfg.to_dict()))
    back = RunConfig.from_dict(d)
    assert back == cfg
    assert back.to_dict() == d
    assert isinstance(back.loop.fix_kind, FixKind) and isinstance(back.detector.pairs, tuple)


@pytest.mark.parametrize(
    "data, key",
    [
        ({"loop": {"window_m": 0}}, "window_m"),
        ({"loop": {"window": 8}}, "loop.window"),
        ({"loop": {"aggregation": {"radius_m": "x"}}}, "loop.aggregation.radius_m"),
        ({"localization": {"mode": "3d"}}, "localization.mode"),
        (
            {"localization": {"search": {"epsilon_m": float("nan")}}},
            "localization.search.epsilon_m",
        ),
        ({"localization": {"epsilon_m": float("nan")}}, "localization.search.epsilon_m"),
        ({"detector": {"stereo": {"num_disparities": 1.5}}}, "detector.stereo.num_disparities"),
        ({"detector": {"pairs": [["FrontLeft"]]}}, "detector.pairs[0]"),
        ({"odometry": {"source": "wheels"}}, "wheels"),
        ({"odometry": {"visual": {"max_features": True}}}, "visual.max_features"),
        ({"loop": {"crop_reference": "yes"}}, "loop.crop_reference"),
        ({"sensors": {}}, "sensors"),
        ({"loop": [1, 2]}, "loop"),
    ],
)
def test_bad_settings_name_the_key(data, key):
    with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
        RunConfig.from_dict(data)


def test_info_and_extra_sections_are_skipped(tmp_path):
    d = {**RunConfig().to_dict(), "info": {"archive": "x.lac"}, "scenario": {"seed": 3}}
    p = tmp_path / "config.json"
    p.write_text(json.dumps(d))
    cfg, extra = load_config_file(p, ("scenario",))
    assert cfg == RunConfig() and extra == {"scenario": {"seed": 3}}
    with pytest.raises(ConfigError, match="scenario"):
        load_config_file(p)  # a section nobody reads is an error, not silently dropped
    p.write_text("{not json")
    with pytest.raises(ConfigError, match=str(p)):
        load_config_file(p)


def test_options_override_the_file():
    cfg = RunConfig().with_options(loop__window_m=6.0, loop__fix_kind=None, odometry__source="imu")
    assert (
        cfg.loop.window_m == 6.0
        and cfg.loop.fix_kind is FixKind.LANDMARKS
        and cfg.odometry.source == "imu"
    )
    with pytest.raises(ConfigError, match="loop"):
        RunConfig().with_options(loop__window_m=-1.0)
    # settings of one section are applied together: fastsam needs weights
    cfg = RunConfig().with_options(detector__segmenter="fastsam", detector__weights="w.pt")
    assert cfg.detector.weights == "w.pt"


def test_nested_defaults_kept_for_missing_keys():
    cfg = config_from_dict(LoopConfig, {"window_m": 9.0})
    assert cfg.window_m == 9.0 and cfg.aggregation == LoopConfig().aggregation


def test_scaling_base_is_a_setting():
    a = RunConfig().detector_for(640)
    b = RunConfig(detector_tuned_width_px=640).detector_for(640)
    assert (
        a.stereo.num_disparities
        < b.stereo.num_disparities
        == RunConfig().detector.stereo.num_disparities
    )


def _write_traverse_csv(path, trav):
    from lunarloc.io.maps import format_boulders

    with open(path, "w") as fh:
        fh.write("frame,x,y,z,detections,boulders\n")
        for f, p in zip(trav.frames, trav.rover_xyz):
            d = trav.detections_xyz[trav.detection_frame == f]
            fh.write(f'{f},{p[0]},{p[1]},{p[2]},{len(d)},"{format_boulders(d)}"\n')


def test_bench_loop_repeated_from_its_config_gives_the_same_outputs(tmp_path, capsys):
    from lunarloc.cli import main

    data = tmp_path / "data" / "csv"
    data.mkdir(parents=True)
    for k, seed in ((1, 0), (2, 0)):
        _write_traverse_csv(
            data / f"traverse_{k}.csv",
            synthetic_traverse(seed=seed, length_m=10.0 if k == 1 else 14.0)[1],
        )
    first = tmp_path / "first"
    assert (
        main(
            [
                "bench",
                "loop",
                "--data",
                str(tmp_path / "data"),
                "--out",
                str(first),
                "--heading-drift",
                "0.1",
                "--scale-error",
                "0.03",
            ]
        )
        == 0
    )
    cfg = json.loads((first / "traverse_1" / "config.json").read_text())
    assert (
        cfg["odometry"]["heading_drift_deg_per_m"] == 0.1
        and cfg["info"]["traverse"] == "traverse_1"
    )
    again = tmp_path / "again"
    assert (
        main(
            [
                "bench",
                "loop",
                "--data",
                str(tmp_path / "data"),
                "--out",
                str(again),
                "--config",
                str(first / "traverse_1" / "config.json"),
            ]
        )
        == 0
    )
    for k in (1, 2):
        for name in ("trajectory.tum", "trajectory_online.tum", "vehicle_map.csv", "config.json"):
            assert (first / f"traverse_{k}" / name).read_bytes() == (
                again / f"traverse_{k}" / name
            ).read_bytes(), name
        a, b = (
            json.loads((d / f"traverse_{k}" / "attempts.json").read_text()) for d in (first, again)
        )
        strip = lambda rows: [
            {k: v for k, v in r.items() if not k.startswith("time_")} for r in rows
        ]  # noqa: E731
        assert strip(a) == strip(b) and len(a) > 0
    # an option overrides the file: another drift, another odometry
    other = tmp_path / "other"
    assert (
        main(
            [
                "bench",
                "loop",
                "--data",
                str(tmp_path / "data"),
                "--out",
                str(other),
                "--config",
                str(first / "traverse_1" / "config.json"),
                "--heading-drift",
                "0.0",
                "--traverses",
                "1",
            ]
        )
        == 0
    )
    assert (
        json.loads((other / "traverse_1" / "config.json").read_text())["odometry"][
            "heading_drift_deg_per_m"
        ]
        == 0.0
    )
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"loop": {"window_m": "wide"}}))
    assert (
        main(
            [
                "bench",
                "loop",
                "--data",
                str(tmp_path / "data"),
                "--out",
                str(tmp_path / "x"),
                "--config",
                str(bad),
            ]
        )
        == 2
    )
    assert "loop.window_m" in capsys.readouterr().err


def _localize_maps(tmp_path):
    """A reference map and a vehicle map (25 of its landmarks, shifted) as CSV files."""
    from lunarloc.io.maps import LandmarkMap, save_map

    rng = np.random.default_rng(3)
    ref = rng.uniform(0, 20, (60, 3)) * [1, 1, 0.02]
    save_map(LandmarkMap(ref), tmp_path / "ref.csv")
    save_map(LandmarkMap(ref[:25] + [0.3, -0.2, 0.0]), tmp_path / "veh.csv")


def test_localize_takes_and_reports_its_config(tmp_path, capsys):
    from lunarloc.cli import main

    _localize_maps(tmp_path)
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"localization": {"epsilon_m": 0.04, "min_inliers": 7}}))
    assert (
        main(
            [
                "localize",
                str(tmp_path / "ref.csv"),
                str(tmp_path / "veh.csv"),
                "--json",
                "--config",
                str(cfg),
                "--epsilon",
                "0.06",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert (
        out["success"] and out["config"]["localization"]["search"]["epsilon_m"] == 0.06
    )  # the option wins
    assert (
        out["config"]["localization"]["acceptance"]["min_inliers"] == 7
    )  # the file's setting is kept
    cfg.write_text(json.dumps({"localization": {"epsilon": 0.04}}))
    assert (
        main(
            ["localize", str(tmp_path / "ref.csv"), str(tmp_path / "veh.csv"), "--config", str(cfg)]
        )
        == 2
    )
    assert "localization.epsilon" in capsys.readouterr().err


def test_demo_config_errors_before_any_work(tmp_path, capsys):
    from lunarloc.cli import main

    cfg = tmp_path / "config.json"
    cfg.write_text(json.dumps({**RunConfig().to_dict(), "scenario": {"seed": 1, "rocks": 5}}))
    assert main(["demo", "--out", str(tmp_path / "d"), "--config", str(cfg)]) == 2
    assert "rocks" in capsys.readouterr().err and not (tmp_path / "d" / "data").exists()


# --------------------------------------------------------------------------- tuning constants (item 4)

TUNING = {  # section path -> today's value (the constant the code held before it became a setting)
    ("localization", "refinement", "irls_rounds"): 5,
    ("localization", "refinement", "rounds"): 3,
    ("localization", "distortion", "fit_rounds"): 3,
    ("localization", "uncertainty", "sigma_floor_m"): 0.005,
    ("index", "neighbours"): 12,
    ("index", "min_side_ratio"): 0.2,
    ("detector", "stereo", "p1_per_block_px2"): 24,
    ("detector", "stereo", "p2_per_block_px2"): 96,
    ("detector", "points", "p1_per_block_px2"): 8,
    ("detector", "points", "p2_per_block_px2"): 32,
}


@pytest.mark.parametrize("cfg", [RunConfig(), RunConfig.for_detections()])
def test_tuning_constants_are_written_with_todays_values(cfg):
    d = json.loads(json.dumps(cfg.to_dict()))
    for path, value in TUNING.items():
        node = d
        for k in path:
            node = node[k]
        assert node == value, path
    assert cfg.detector.stereo.P1 == 8 * 3 * 11**2 and cfg.detector.stereo.P2 == 32 * 3 * 11**2


@pytest.mark.parametrize("path", list(TUNING))
def test_tuning_constants_are_read_back(path, tmp_path):
    value = TUNING[path]
    new = value * 2 if isinstance(value, int) else value * 3
    data: dict = {}
    node = data
    for k in path[:-1]:
        node = node.setdefault(k, {})
    node[path[-1]] = new
    if path[-1] == "p1_per_block_px2":
        node[path[-1].replace("p1", "p2")] = 1000  # keep P2 > P1
    p = tmp_path / "config.json"
    p.write_text(json.dumps(data))
    cfg, _ = load_config_file(p)
    obj = cfg
    for k in path:
        obj = getattr(obj, k)
    assert obj == new
    assert RunConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize(
    "data, key",
    [
        ({"localization": {"irls_rounds": 0}}, "irls_rounds"),
        ({"localization": {"refine_rounds": 1.5}}, "localization.refinement.rounds"),
        ({"localization": {"distortion_fit_rounds": -1}}, "distortion_fit_rounds"),
        ({"localization": {"registration_sigma_floor_m": 0}}, "registration_sigma_floor_m"),
        ({"index": {"neighbours": 2}}, "neighbours"),
        ({"index": {"triangles": 2}}, "index.triangles"),
        ({"detector": {"stereo": {"p1_per_block_px2": 200}}}, "p1_per_block_px2"),
        ({"detector": {"fullres_p2_per_block_px2": 4}}, "fullres_p2_per_block_px2"),
    ],
)
def test_bad_tuning_constants_name_the_key(data, key):
    with pytest.raises(ConfigError, match=key):
        RunConfig.from_dict(data)


def test_localization_rounds_and_sigma_floor_are_used(monkeypatch):
    """The settings reach the code: IRLS runs `irls_rounds` re-fits, and the sigma floor
    bounds the predicted error from below."""
    import importlib

    from lunarloc.core.geometry import make_transform, rot_z
    from lunarloc.io.maps import LandmarkMap

    loc_config = importlib.import_module("lunarloc.localization.config")
    loc_localize = importlib.import_module("lunarloc.localization.localize")
    loc_register = importlib.import_module("lunarloc.localization.register")
    rng = np.random.default_rng(5)
    P = rng.uniform(-5, 5, (20, 3)) * [1, 1, 0.05]
    T = make_transform(rot_z(0.3), [1.0, -2.0, 0.0])
    Q = P @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.002, P.shape)
    calls = []
    real = loc_register._register
    monkeypatch.setattr(loc_register, "_register", lambda *a, **k: calls.append(1) or real(*a, **k))
    for rounds in (1, 4):
        calls.clear()
        loc_register._register_robust(P, Q, loc_config.LocalizationConfig(irls_rounds=rounds))
        assert len(calls) == rounds + 1  # the first fit, then one per round
    monkeypatch.undo()
    ref, veh = LandmarkMap(Q), LandmarkMap(P)
    rigid = {
        "max_predicted_error_m": 10.0,
        "odometry_scale_error": 0.0,
        "odometry_heading_drift_deg_per_m": 0.0,
    }
    small = loc_localize.localize(ref, veh, loc_config.LocalizationConfig(**rigid))
    big = loc_localize.localize(
        ref, veh, loc_config.LocalizationConfig(registration_sigma_floor_m=0.05, **rigid)
    )
    assert small.success and big.success
    assert big.predicted_error_m > 3 * small.predicted_error_m


def test_index_section_reaches_localize(tmp_path, capsys):
    """`localize --config` passes the index section to the indexed search."""
    from lunarloc.cli import main

    _localize_maps(tmp_path)
    cfg = tmp_path / "cfg.json"
    args = [
        "localize",
        str(tmp_path / "ref.csv"),
        str(tmp_path / "veh.csv"),
        "--json",
        "--search",
        "indexed",
    ]
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["success"]
    cfg.write_text(json.dumps({"index": {"min_votes": 100_000}}))  # no region gets that many votes
    assert main([*args, "--config", str(cfg)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (
        out["config"]["index"]["min_votes"] == 100_000
        and not out["success"]
        and not out["candidates"]
    )


def test_the_demo_odometry_source_is_set_in_one_place():
    """The scenario has no odometry setting of its own: the run configuration's
    odometry.source is it (the simulator's drifting record by default)."""
    from lunarloc.pipeline.scenario import ScenarioConfig, demo_run_config

    assert demo_run_config().odometry.source == "record:odometry"
    assert "odometry" not in ScenarioConfig().to_dict()
    with pytest.raises(ConfigError, match="scenario.odometry.*odometry.source"):
        ScenarioConfig.from_dict({"seed": 3, "odometry": "visual"})


def test_a_section_given_in_part_keeps_the_rest_of_its_own_default():
    # {"detector": {"height_stereo": {"uniqueness_ratio": ...}}} changes that one setting and
    # keeps the height map's half-resolution SGBM (not StereoConfig's full-resolution
    # defaults); a partial loop section keeps the run's own loop defaults
    from dataclasses import replace

    from lunarloc.perception.detector import DetectorConfig

    hs = DetectorConfig().height_stereo
    cfg = RunConfig.from_dict(
        {"detector": {"height_stereo": {"uniqueness_ratio": hs.uniqueness_ratio + 1}}, "loop": {}}
    )
    assert cfg.detector.height_stereo == replace(hs, uniqueness_ratio=hs.uniqueness_ratio + 1)
    assert cfg.detector.height_stereo.downscale == hs.downscale != 1
    assert cfg.detector.height_filters == DetectorConfig().height_filters
    assert cfg.loop == RunConfig().loop and cfg.localization == RunConfig().localization
