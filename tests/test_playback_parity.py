"""PlaybackAgent against the published ``lac_data.PlaybackAgent`` (Robaire/lac-data, the same in
mit-acl/lunarloc-data), member by member.

``PUBLISHED`` lists every public member of the published agent with the behaviour this
project reproduces (or, where the LAC agent API says otherwise, follows instead); the test
checks that each is present and behaves so. ``OURS_ONLY`` lists our additions.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from lunarloc.io.lac.archive import LacWriter, float_text
from lunarloc.io.lac.playback import PlaybackAgent, Transform

W, H = 16, 12

PUBLISHED = {
    "set_frame": "past the last frame ValueError; an unrecorded frame (3.5, a gap) IndexError",
    "at_end": "True on the last recorded frame",
    "step_frame": "next recorded frame (skips gaps), stays on the last; returns the frame",
    "input_data": "every configured camera under Grayscale, use_semantic ones under Semantic, None without an image",
    "use_fiducials": "initial.toml fiducials",
    "sensors": "initial.toml [cameras] (numbers stored as strings are numbers here)",
    "get_initial_position": "initial.toml rover",
    "get_initial_lander_position": "initial.toml lander: relative to the rover",
    "get_mission_time": "frames.csv mission_time",
    "get_current_power": "frames.csv power",
    "get_consumed_power": "NotImplementedError",
    "get_imu_data": "ndarray (6,) as the LAC (published: a list)",
    "get_linear_speed": "frames.csv linear_speed",
    "get_angular_speed": "frames.csv angular_speed",
    "get_front_arm_angle": "NotImplementedError",
    "get_back_arm_angle": "NotImplementedError",
    "get_front_drums_speed": "NotImplementedError",
    "get_back_drums_speed": "NotImplementedError",
    "get_radiator_cover_angle": "frames.csv cover_angle",
    "get_transform": "frames.csv pose",
    "get_light_state": "last row at or before the frame; before: initial light; unknown camera KeyError",
    "get_camera_state": "last row at or before the frame; before or unknown camera: False",
    "get_camera_position": "last row at or before the frame; before or unknown camera: zero pose",
    "get_light_position": "NotImplementedError",
}
OURS_ONLY = {
    "frame",
    "frame_index",
    "close",
    "get_transform_matrix",
    "frame_state",
    "archive",
    "run_agent",
}

PALETTE = {"rock": (42, 59, 108), "lander": (160, 190, 110), "fiducial": (30, 170, 250)}


@pytest.fixture
def agent(tmp_path):
    cams = {
        "FrontLeft": {
            "camera_active": True,
            "light_intensity": 0.5,
            "width": W,
            "height": H,
            "use_semantic": True,
        },
        "Right": {
            "camera_active": False,
            "light_intensity": 0.25,
            "width": W,
            "height": H,
            "use_semantic": False,
        },
    }
    init = {
        "fiducials": True,
        "lander": [6.0, -1.0, -0.4, 0.0, 0.0, 0.2],
        "rover": [1.0, 2.0, 0.3, 0.0, 0.0, 0.5],
        "cameras": cams,
    }
    rng = np.random.default_rng(5)
    gray, sem = {}, {}
    with LacWriter(tmp_path / "p.lac", init) as w:
        for f in (0, 1, 2, 3, 5, 6):  # frame 4 missing: a gap
            st = {
                k: float(float_text(v))
                for k, v in zip(
                    ("x", "y", "yaw", "gyro_z", "power", "cover_angle"), rng.normal(size=6)
                )
            }
            w.add_frame(
                f, mission_time=0.05 * f, linear_speed=0.2, angular_speed=0.01, accel_z=1.622, **st
            )
            if f in (2, 5):
                gray[f] = rng.integers(0, 256, (H, W), dtype=np.uint8)
                s = np.zeros((H, W, 3), np.uint8)
                s[: H // 2] = PALETTE["rock"]
                s[H // 2 :] = PALETTE["lander"]
                s[0, 0] = PALETTE["fiducial"]
                sem[f] = s
                w.add_camera_frame(
                    "FrontLeft",
                    f,
                    [0.28, 0.081, 0.131, 0, 0, 0],
                    light_intensity=1.0,
                    grayscale=gray[f],
                    semantic=sem[f],
                )
    with PlaybackAgent(tmp_path / "p.lac") as ag:
        yield ag, gray, sem


def test_every_published_member_exists(agent):
    ag, _, _ = agent
    public = {n for n in dir(PlaybackAgent) if not n.startswith("_")}
    assert set(PUBLISHED) <= public
    assert public - set(PUBLISHED) <= OURS_ONLY | {"archive"}, public - set(PUBLISHED) - OURS_ONLY
    for name in PUBLISHED:
        assert callable(getattr(ag, name)), name


@pytest.mark.parametrize("name", [n for n, b in PUBLISHED.items() if b == "NotImplementedError"])
def test_not_recorded_getters_raise_as_published(agent, name):
    ag, _, _ = agent
    args = ["FrontLeft"] if len(inspect.signature(getattr(ag, name)).parameters) else []
    with pytest.raises(NotImplementedError, match=name):
        getattr(ag, name)(*args)


def test_cursor(agent):
    ag, _, _ = agent
    assert ag.frame == 0 and not ag.at_end()
    assert [ag.step_frame() for _ in range(6)] == [
        1,
        2,
        3,
        5,
        6,
        6,
    ]  # skips the gap, stays at the end
    assert ag.at_end()
    with pytest.raises(ValueError, match="out of range"):
        ag.set_frame(7)
    for bad in (3.5, 4, -1):
        with pytest.raises(IndexError):
            ag.set_frame(bad)
    assert ag.frame == 6  # a failed set_frame leaves the cursor
    assert ag.set_frame(2) is not None and ag.frame == 2


def test_constants_and_state(agent):
    ag, _, _ = agent
    assert ag.use_fiducials() is True
    assert ag.sensors()["FrontLeft"]["width"] == W
    assert ag.get_initial_position().as_tuple() == (1.0, 2.0, 0.3, 0.0, 0.0, 0.5)
    assert ag.get_initial_lander_position().as_tuple() == (6.0, -1.0, -0.4, 0.0, 0.0, 0.2)
    row = ag.archive.frame_state(0)
    t = ag.get_transform()
    assert isinstance(t, Transform) and (t.location.x, t.location.y, t.rotation.yaw) == (
        row["x"],
        row["y"],
        row["yaw"],
    )
    assert (
        ag.get_mission_time() == 0.0
        and ag.get_linear_speed() == 0.2
        and ag.get_angular_speed() == 0.01
    )
    assert (
        ag.get_current_power() == row["power"]
        and ag.get_radiator_cover_angle() == row["cover_angle"]
    )
    imu = ag.get_imu_data()
    assert (
        isinstance(imu, np.ndarray)
        and imu.shape == (6,)
        and imu[2] == 1.622
        and imu[5] == row["gyro_z"]
    )


def test_cameras_before_during_after_rows(agent):
    ag, _, _ = agent
    # frame 0: before FrontLeft's first row (frame 2); Right never recorded
    assert ag.get_camera_state("FrontLeft") is False and ag.get_camera_state("Right") is False
    assert ag.get_camera_position("FrontLeft").as_tuple() == (0.0,) * 6
    assert ag.get_light_state("FrontLeft") == 0.5 and ag.get_light_state("Right") == 0.25
    assert (
        ag.get_camera_state("Nope") is False
        and ag.get_camera_position("Nope").as_tuple() == (0.0,) * 6
    )
    with pytest.raises(KeyError):
        ag.get_light_state("Nope")
    ag.set_frame(3)  # last row at or before: frame 2
    assert ag.get_camera_state("FrontLeft") is True and ag.get_light_state("FrontLeft") == 1.0
    assert ag.get_camera_position("FrontLeft").as_tuple() == (0.28, 0.081, 0.131, 0.0, 0.0, 0.0)


def test_input_data_and_semantic_palette(agent):
    ag, gray, sem = agent
    for f in (0, 1, 2, 3, 5, 6):
        ag.set_frame(f)
        d = ag.input_data()
        assert set(d) == {"Grayscale", "Semantic"}
        assert set(d["Grayscale"]) == {"FrontLeft", "Right"} and set(d["Semantic"]) == {"FrontLeft"}
        assert d["Grayscale"]["Right"] is None
        if f in gray:
            np.testing.assert_array_equal(d["Grayscale"]["FrontLeft"], gray[f])
            s = d["Semantic"]["FrontLeft"]
            assert s.shape == (H, W, 3) and s.dtype == np.uint8
            np.testing.assert_array_equal(s, sem[f])  # the LAC palette passes through unchanged
            assert tuple(s[0, 0]) == PALETTE["fiducial"] and tuple(s[-1, -1]) == PALETTE["lander"]
        else:
            assert d["Grayscale"]["FrontLeft"] is None and d["Semantic"]["FrontLeft"] is None


def test_input_data_without_semantic_cameras_has_no_semantic_group(tmp_path):
    cam = {
        "camera_active": True,
        "light_intensity": 0.0,
        "width": W,
        "height": H,
        "use_semantic": False,
    }
    with LacWriter(
        tmp_path / "g.lac", {"lander": [0.0] * 6, "rover": [0.0] * 6, "cameras": {"FrontLeft": cam}}
    ) as w:
        w.add_frame(0)
    with PlaybackAgent(tmp_path / "g.lac") as ag:
        assert ag.input_data() == {
            "Grayscale": {"FrontLeft": None}
        }  # as published (a defaultdict's keys)
