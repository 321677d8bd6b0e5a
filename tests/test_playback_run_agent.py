"""PlaybackAgent.run_agent drives a leaderboard agent as the leaderboard does: the call
order, setup before any vehicle status, the eight-position sensor check, SensorPosition keys,
only active cameras, grayscale views, right-handed Transforms without a matrix method,
get_transform() None in evaluation, the control type checked."""

from __future__ import annotations

import numpy as np
import pytest

from lunarloc import LacAgentBase, PlaybackAgent, SensorPosition, VehicleVelocityControl
from lunarloc.core.errors import InputError
from lunarloc.io.lac.archive import LacWriter

W, H = 32, 24


@pytest.fixture
def archive(tmp_path):
    cams = {
        n: {
            "camera_active": n in ("FrontLeft", "FrontRight", "Left"),
            "light_intensity": 0.5,
            "width": W,
            "height": H,
            "use_semantic": False,
        }
        for n in ("FrontLeft", "FrontRight", "Left")
    }
    init = {
        "fiducials": False,
        "lander": [6.0, -1.0, -0.4, 0.0, 0.0, 0.2],
        "rover": [1.0, 2.0, 0.3, 0.0, 0.1, 0.5],
        "cameras": cams,
    }
    rng = np.random.default_rng(0)
    with LacWriter(tmp_path / "p.lac", init) as w:
        for f in range(6):
            w.add_frame(
                f,
                x=1.0 + 0.01 * f,
                y=2.0,
                z=0.3,
                yaw=0.5,
                mission_time=0.05 * f,
                linear_speed=0.2,
                angular_speed=0.0,
                accel_z=1.622,
            )
            if f % 2:
                for n in ("FrontLeft", "FrontRight"):
                    w.add_camera_frame(
                        n,
                        f,
                        [0.28, 0.081 if n == "FrontLeft" else -0.081, 0.131, 0, 0, 0],
                        light_intensity=0.5,
                        grayscale=rng.integers(0, 256, (H, W), dtype=np.uint8),
                    )
    return tmp_path / "p.lac"


class Probe(LacAgentBase):
    """Records what it sees; activates the front pair only."""

    def setup(self, path_to_conf_file):
        self.calls = ["setup"]
        self.conf = path_to_conf_file
        with pytest.raises(AttributeError):  # no vehicle status before the first tick
            self.get_camera_position(SensorPosition.FrontLeft)
        self.initial = self.get_initial_position()
        self.seen = []

    def use_fiducials(self):
        return False

    def sensors(self):
        return {
            p: {
                "camera_active": p.name in ("FrontLeft", "FrontRight"),
                "light_intensity": 0.0,
                "width": W,
                "height": H,
            }
            for p in SensorPosition
        }

    def run_step(self, input_data):
        self.calls.append("run_step")
        g = input_data["Grayscale"]
        self.seen.append(
            {
                k: (None if v is None else (v.shape, v.dtype, v.flags.c_contiguous))
                for k, v in g.items()
            }
        )
        self.cam = self.get_camera_position(SensorPosition.FrontLeft)
        self.truth = self.get_transform()
        self.imu = self.get_imu_data()
        return VehicleVelocityControl(1.0, -9.0)

    def finalize(self):
        self.calls.append("finalize")


def test_run_agent_as_the_leaderboard(archive):
    agent = Probe()
    with PlaybackAgent(archive) as env:
        cmds = env.run_agent(agent, "conf.toml", evaluation=True)
    assert agent.calls == ["setup"] + ["run_step"] * 6 + ["finalize"] and agent.conf == "conf.toml"
    assert all(
        set(s) == {SensorPosition.FrontLeft, SensorPosition.FrontRight} for s in agent.seen
    )  # active only
    assert agent.seen[0][SensorPosition.FrontLeft] is None
    assert agent.seen[1][SensorPosition.FrontLeft] == (
        (H, W),
        np.uint8,
        False,
    )  # a view, as the leaderboard's
    assert agent.truth is None  # evaluation
    tf = agent.initial
    assert (tf.location.x, tf.location.y, tf.rotation.pitch) == pytest.approx((1.0, 2.0, 0.1))
    assert not hasattr(tf, "matrix") and not hasattr(tf, "get_matrix")
    assert agent.cam.location.y == pytest.approx(0.081)
    assert agent.imu.shape == (6,)
    assert cmds[0].linear_target_velocity == pytest.approx(0.49) and cmds[
        0
    ].angular_target_velocity == pytest.approx(-4.13)


def test_run_agent_training_mode_answers_get_transform(archive):
    agent = Probe()
    with PlaybackAgent(archive) as env:
        env.run_agent(agent, "", evaluation=False, max_ticks=3)
    assert agent.calls[-1] == "finalize" and agent.calls.count("run_step") == 3
    assert agent.truth.location.x == pytest.approx(1.02)


class StringKeys(Probe):
    def sensors(self):
        return {p.name: c for p, c in super().sensors().items()}


class SevenPositions(Probe):
    def sensors(self):
        s = super().sensors()
        del s[SensorPosition.Back]
        return s


class TupleCommand(Probe):
    def run_step(self, input_data):
        return (0.2, 0.0)


@pytest.mark.parametrize(
    "cls, match",
    [
        (StringKeys, "is a string"),
        (SevenPositions, "SensorPosition.Back"),
        (TupleCommand, "VehicleVelocityControl"),
    ],
)
def test_run_agent_refuses_what_the_leaderboard_refuses(archive, cls, match):
    with PlaybackAgent(archive) as env, pytest.raises((InputError, AssertionError), match=match):
        env.run_agent(cls(), "")


def test_run_agent_loads_an_agent_file_like_the_leaderboard(archive, tmp_path):
    f = tmp_path / "no_entry_agent.py"
    f.write_text("class A:\n    def __init__(self, env):\n        pass\n")
    with (
        PlaybackAgent(archive) as env,
        pytest.raises(InputError, match="not a leaderboard agent file"),
    ):
        env.run_agent(f)
    f2 = tmp_path / "args_agent.py"
    f2.write_text(
        "def get_entry_point():\n    return 'A'\nclass A:\n    def __init__(self, env):\n        pass\n"
    )
    with PlaybackAgent(archive) as env, pytest.raises(InputError, match="no arguments"):
        env.run_agent(f2)
