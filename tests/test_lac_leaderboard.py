"""Conformance: examples/lac_agent.py as the LAC leaderboard runs an agent file.

The leaderboard is a stand-in written here from the public leaderboard's behaviour
(``tests/standins``: ``carla``, ``leaderboard.*``; no leaderboard code copied). The agent
file is loaded by path through the stand-in ``AgentWrapper`` (``get_entry_point()``,
no-argument construction), set up before any vehicle status exists, its ``sensors()``
checked for all eight ``carla.SensorPosition`` members, ticked through the base class
(which asserts a ``carla.VehicleVelocityControl``) over a lunarloc-simulated site in
evaluation mode (``get_transform()`` is None), and finalized.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
STANDINS = ROOT / "tests" / "standins"
AGENT_FILE = ROOT / "examples" / "lac_agent.py"
if str(STANDINS) not in sys.path:
    sys.path.insert(0, str(STANDINS))

pytest.importorskip("embreex", reason="the closed-loop harness renders with lunarloc[sim]")

import carla  # noqa: E402  (the stand-in)
import lunarsim  # noqa: E402
from leaderboard.agents.agent_wrapper import AgentSetupError, AgentWrapper  # noqa: E402
from leaderboard.agents.coordinate_conversion import (
    carla_transform_from_rh,
    rh_matrix,
    toRHCStransform,
)  # noqa: E402
from leaderboard.agents.geometric_map import GeometricMap  # noqa: E402
from leaderboard.agents.imu import IMU  # noqa: E402
from leaderboard.utils.constants import Constants  # noqa: E402

W, H = 640, 360


@pytest.fixture(autouse=True)
def fresh_agent_module():
    """The leaderboard imports the agent file in a fresh process: drop a cached copy (another
    test may have imported it without the leaderboard on the path)."""
    sys.modules.pop(AGENT_FILE.stem, None)
    yield


@pytest.fixture(scope="module")
def small_world():
    return lunarsim.SimWorld(301, n_rocks=100)


def _conf(tmp_path, world, **extra) -> Path:
    return lunarsim.write_agent_config(tmp_path, world, width=W, height=H, output="out", **extra)


# ----------------------------------------------------------------------------- the stand-in itself


def test_standin_transforms_round_trip_and_are_right_handed():
    rng = np.random.default_rng(0)
    for _ in range(20):
        x, y, z = rng.uniform(-10, 10, 3)
        roll, pitch, yaw = rng.uniform(-1.2, 1.2, 3)
        from lunarloc.core.geometry import pose_to_matrix

        T = pose_to_matrix(x, y, z, roll, pitch, yaw)
        lh = carla_transform_from_rh(T)
        assert lh.location.y == pytest.approx(-y)  # CARLA is left-handed
        rh = toRHCStransform(lh)
        assert (rh.rotation.roll, rh.rotation.pitch, rh.rotation.yaw) == pytest.approx(
            (roll, pitch, yaw)
        )
        np.testing.assert_allclose(rh_matrix(rh), T, atol=1e-12)
        # the left-handed matrix is the right-handed one mirrored in y
        S = np.diag([1.0, -1.0, 1.0, 1.0])
        np.testing.assert_allclose(np.array(lh.get_matrix()), S @ T @ S, atol=1e-12)
        p = rh.transform(0.3, -0.2, 0.1)
        np.testing.assert_allclose([p.x, p.y, p.z], (T @ [0.3, -0.2, 0.1, 1.0])[:3], atol=1e-12)
    assert not hasattr(rh, "matrix") and not hasattr(rh, "get_matrix")


def test_standin_imu_is_a_world_frame_rate_and_a_body_frame_specific_force():
    from lunarloc.core.geometry import pose_to_matrix

    class Vehicle:
        T = np.eye(4)

        def get_transform(self):
            return carla_transform_from_rh(self.T)

    v = Vehicle()
    imu = IMU(v)
    out = []
    for k in range(5):  # pitched 30 degrees, turning about the world z axis at 0.4 rad/s
        v.T = pose_to_matrix(0.1 * k, 0.0, 0.0, 0.0, math.radians(30), 0.4 * 0.05 * k)
        out.append(imu.get_data())
    np.testing.assert_allclose(out[0], [0, 0, 1.622, 0, 0, 0])
    np.testing.assert_allclose(
        out[3][3:], [0, 0, 0.4], atol=0.02
    )  # spatial rate: (0, 0, w), not R^T (0, 0, w)
    R = v.T[:3, :3]
    np.testing.assert_allclose(
        out[3][:3], R.T @ [0, 0, 1.622], atol=1e-9
    )  # at constant velocity: R^T g


def test_standin_geometric_map_indexing():
    c = Constants()
    gm = GeometricMap(c)
    assert gm.get_map_array().shape == (180, 180, 4) and gm.get_cell_number() == 180
    assert gm.get_cell_indexes(-13.5 + 0.075, 0.0) == (0, 90)
    assert gm.get_cell_indexes(13.6, 0.0)[0] is None and gm.get_height(20.0, 0.0) is None
    assert gm.set_height(1.0, -2.0, 0.25) and gm.get_height(1.0, -2.0) == 0.25
    assert (
        gm.get_rock(1.0, -2.0) == -np.inf
        and gm.set_rock(1.0, -2.0, True)
        and gm.get_rock(1.0, -2.0) is True
    )
    assert not gm.set_rock(99.0, 0.0, True)


# ----------------------------------------------------------------------------- the agent file


def test_agent_file_loads_through_the_wrapper(tmp_path):
    """get_entry_point(), no-argument construction, a bool from use_fiducials()."""
    wrapper = AgentWrapper(None, str(AGENT_FILE), "", evaluation=True)
    from leaderboard.autoagents.autonomous_agent import AutonomousAgent

    assert isinstance(wrapper.agent, AutonomousAgent)
    assert wrapper.agent_fiducials is False  # the localization points need no fiducials


def test_setup_runs_before_any_vehicle_status_and_configures_all_eight_sensors(
    tmp_path, small_world
):
    world = small_world
    wrapper = AgentWrapper(world, str(AGENT_FILE), str(_conf(tmp_path, world)), evaluation=True)
    wrapper.setup(
        world.vehicle, world.lander, Constants()
    )  # AgentSetupError if setup touched the status
    sensors = wrapper.agent.sensors()
    assert set(sensors) == set(carla.SensorPosition)
    active = {p for p, c in sensors.items() if c["camera_active"]}
    assert {carla.SensorPosition.FrontLeft, carla.SensorPosition.FrontRight} <= active
    assert not any(c.get("use_semantic") for c in sensors.values())  # refused in evaluation


def test_a_missing_reference_is_a_setup_error(tmp_path, small_world):
    world = small_world
    conf = tmp_path / "c.toml"
    conf.write_text('reference = "nowhere.csv"\n')
    wrapper = AgentWrapper(world, str(AGENT_FILE), str(conf), evaluation=True)
    with pytest.raises(AgentSetupError, match="nowhere.csv"):
        wrapper.setup(world.vehicle, world.lander, Constants())


@pytest.mark.parametrize(
    "text, match",
    [
        ('refrence = "x.csv"', "unknown setting 'refrence'"),
        ("width = '640'", "width must be int"),
        ('odometry = "wheels"', "odometry must be"),
    ],
)
def test_bad_settings_are_setup_errors_naming_the_key(tmp_path, small_world, text, match):
    world = small_world
    conf = tmp_path / "c.toml"
    conf.write_text(text + "\n")
    wrapper = AgentWrapper(world, str(AGENT_FILE), str(conf), evaluation=True)
    with pytest.raises(AgentSetupError, match=match):
        wrapper.setup(world.vehicle, world.lander, Constants())


@pytest.fixture(scope="module")
def closed_loop(tmp_path_factory):
    """30 s of mission time, front pair at 640x360, evaluation mode; 800 rocks so that a fix
    comes early (the 386-rock sites of the benchmark take longer: docs/lac-leaderboard.md)."""
    tmp = tmp_path_factory.mktemp("lac")
    world = lunarsim.SimWorld(301, n_rocks=800)
    run = lunarsim.run_agent(AGENT_FILE, _conf(tmp, world), world, 30.0, evaluation=True)
    return run, world, tmp


def test_closed_loop_through_the_leaderboard(closed_loop):
    run, world, tmp = closed_loop
    assert run.ticks == 600 and len(run.run_step_s) == 600
    assert run.get_transform_calls == 0  # the true pose is not available in evaluation
    truth = np.array(run.truth)
    travelled = float(np.linalg.norm(np.diff(truth[:, :2, 3], axis=0), axis=1).sum())
    assert travelled > 5.0  # it drives
    lander = world.site.lander_xyz[:2]
    r = np.linalg.norm(truth[:, :2, 3] - lander, axis=1)
    assert r.min() > 2.0  # around the lander, not into it
    est = run.agent.estimate
    assert est is not None and est.localized
    err = np.linalg.norm(est.T_map_rover[:2, 3] - truth[-1][:2, 3])
    assert err < 0.25


def test_finalize_writes_the_run(closed_loop):
    run, _, tmp = closed_loop
    out = tmp / "out"
    rows = (out / "trajectory.csv").read_text().splitlines()
    assert rows[0].startswith("mission_time_s,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad")
    assert len(rows) == 1 + 600
    import json

    summary = json.loads((out / "summary.json").read_text())
    assert summary["ticks"] == 600 and summary["localized"] is True
    # the example's default fills the map the LAC scores (lac_map on): every cell by finalize()
    assert summary["settings"]["lac_map"] is True
    final = run.agent.get_geometric_map().get_map_array()
    assert np.isfinite(final[:, :, 2]).all() and np.isfinite(final[:, :, 3]).all()


# ----------------------------------------------------------------------------- the LAC map


def test_the_agent_writes_the_map_during_the_run_and_completes_it_in_finalize(tmp_path):
    """lac_map = true: cells go into the leaderboard's GeometricMap while the mission runs
    (as they become confident, at most lac_map_cells_per_tick a tick), and finalize() fills
    every cell."""
    world = lunarsim.SimWorld(302, n_rocks=800)
    counts, last = [], {}

    def observe(agent):
        gm = agent.get_geometric_map()
        a = gm.get_map_array()
        done = np.isfinite(a[:, :, 2]) & np.isfinite(a[:, :, 3])
        counts.append(int(done.sum()))
        last["done"], last["height"] = done, a[:, :, 2].copy()

    cap = 150
    run = lunarsim.run_agent(
        AGENT_FILE,
        _conf(tmp_path, world, lac_map=True, lac_map_cells_per_tick=cap),
        world,
        16.0,
        evaluation=True,
        observe=observe,
    )
    assert run.ticks == len(counts) == 320
    steps = np.diff([0] + counts)
    assert counts[-1] >= 300  # cells written before finalize
    assert steps.max() <= cap  # at most `cap` a tick
    assert np.count_nonzero(steps) >= 3  # written as the rover goes, not at once
    assert len(run.agent.map_write_cpu_s) == run.ticks
    truth = world.ground_truth_map(Constants())
    during = last["done"]
    assert (
        np.mean(np.abs(last["height"] - truth[:, :, 2])[during] < 0.05) >= 0.8
    )  # the live heights are right
    final = run.agent.get_geometric_map().get_map_array()
    assert (
        np.isfinite(final[:, :, 2]).all() and np.isfinite(final[:, :, 3]).all()
    )  # finalize fills every cell
