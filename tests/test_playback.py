"""PlaybackAgent: the LAC AutonomousAgent API over a `.lac` archive, write -> playback round trip."""

from __future__ import annotations

import numpy as np
import pytest

from lunarloc.io.lac.archive import LacArchive, LacWriter, _IndexedGzipReader, float_text
from lunarloc.io.lac.playback import PlaybackAgent, Transform
from lunarloc.core.errors import InputError
from lunarloc.core.geometry import pose_to_matrix

W, H = 32, 24
FL_POSE = [0.28, 0.081, 0.131, 0.0, 0.0, 0.0]


def _write(path, n_frames=10, first_image=3, every=2):
    cams = {
        "FrontLeft": {
            "camera_active": True,
            "light_intensity": 0.25,
            "width": W,
            "height": H,
            "use_semantic": True,
        },
        "BackLeft": {
            "camera_active": False,
            "light_intensity": 0.0,
            "width": W,
            "height": H,
            "use_semantic": False,
        },
    }
    init = {
        "fiducials": True,
        "lander": [0.1, 0.2, 0.3, 0.0, 0.0, 1.0],
        "rover": [1.0, 2.0, 0.0, 0.0, 0.0, 0.5],
        "cameras": cams,
    }
    rng = np.random.default_rng(7)
    poses, images = {}, {}
    with LacWriter(path, init) as w:
        for f in range(n_frames):
            pose = np.array([float(float_text(v)) for v in rng.normal(size=6)])  # as stored
            poses[f] = pose
            w.add_frame(
                f,
                x=pose[0],
                y=pose[1],
                z=pose[2],
                roll=pose[3],
                pitch=pose[4],
                yaw=pose[5],
                accel_x=0.1 * f,
                accel_y=0.2,
                accel_z=1.62,
                gyro_x=0.01,
                gyro_y=0.02,
                gyro_z=0.03 * f,
                mission_time=0.05 * f,
                power=300.0 - f,
                linear_speed=0.3,
                angular_speed=-0.1,
                cover_angle=0.7,
            )
            if f >= first_image and (f - first_image) % every == 0:
                g = rng.integers(0, 256, (H, W), dtype=np.uint8)
                s = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
                light = 1.0 if f > 5 else 0.5
                w.add_camera_frame(
                    "FrontLeft", f, FL_POSE, light_intensity=light, grayscale=g, semantic=s
                )
                images[f] = (g, s)
    return poses, images


@pytest.fixture
def archive(tmp_path):
    path = tmp_path / "play.lac"
    poses, images = _write(path)
    return path, poses, images


def test_round_trip_poses_and_images(archive):
    path, poses, images = archive
    with PlaybackAgent(path) as agent:
        seen = []
        while True:
            f = agent.frame
            seen.append(f)
            t = agent.get_transform()
            assert isinstance(t, Transform)
            assert t.as_tuple() == tuple(poses[f])  # exact
            assert (t.location.x, t.rotation.yaw) == (poses[f][0], poses[f][5])
            np.testing.assert_array_equal(agent.get_transform_matrix(), pose_to_matrix(*poses[f]))
            np.testing.assert_array_equal(t.matrix(), pose_to_matrix(*poses[f]))
            imu = agent.get_imu_data()
            assert isinstance(imu, np.ndarray) and imu.shape == (6,) and imu.dtype == np.float64
            np.testing.assert_allclose(imu, [0.1 * f, 0.2, 1.62, 0.01, 0.02, 0.03 * f], rtol=5e-15)
            assert agent.get_mission_time() == pytest.approx(0.05 * f, rel=5e-15)
            assert agent.get_linear_speed() == 0.3 and agent.get_angular_speed() == -0.1
            assert (
                agent.get_current_power() == 300.0 - f and agent.get_radiator_cover_angle() == 0.7
            )
            data = agent.input_data()
            assert set(data) == {"Grayscale", "Semantic"}
            if f in images:
                assert list(data["Grayscale"]) == ["FrontLeft", "BackLeft"] and list(
                    data["Semantic"]
                ) == ["FrontLeft"]
                assert data["Grayscale"]["BackLeft"] is None
                np.testing.assert_array_equal(data["Grayscale"]["FrontLeft"], images[f][0])
                np.testing.assert_array_equal(data["Semantic"]["FrontLeft"], images[f][1])
            else:  # every configured camera, None without an image (as published)
                assert data == {
                    "Grayscale": {"FrontLeft": None, "BackLeft": None},
                    "Semantic": {"FrontLeft": None},
                }
            if agent.at_end():
                break
            assert agent.step_frame() == f + 1
        assert seen == list(range(10))
        assert agent.step_frame() == 9 and agent.at_end()  # stays on the last frame


def test_constants(archive):
    path, _, _ = archive
    with PlaybackAgent(path) as agent:
        assert agent.use_fiducials() is True
        assert agent.get_initial_position().as_tuple() == (1.0, 2.0, 0.0, 0.0, 0.0, 0.5)
        lander = agent.get_initial_lander_position()
        assert (lander.location.z, lander.rotation.yaw) == (0.3, 1.0)
        assert set(agent.sensors()) == {"FrontLeft", "BackLeft"}
        assert agent.sensors()["FrontLeft"]["use_semantic"] is True


def test_camera_state_follows_last_row(archive):
    path, _, _ = archive
    with PlaybackAgent(path) as agent:
        # before the first camera row, as published: False, a zero pose, initial.toml's light
        assert agent.frame == 0
        assert (
            agent.get_camera_state("FrontLeft") is False
            and agent.get_light_state("FrontLeft") == 0.25
        )
        assert agent.get_camera_position("FrontLeft").as_tuple() == (0.0,) * 6
        assert (
            agent.get_camera_state("BackLeft") is False and agent.get_light_state("BackLeft") == 0.0
        )
        agent.set_frame(3)
        assert agent.get_camera_state("FrontLeft") is True
        agent.set_frame(4)  # last row is frame 3
        assert agent.get_light_state("FrontLeft") == 0.5
        assert agent.get_camera_position("FrontLeft").as_tuple() == tuple(FL_POSE)
        agent.set_frame(7)
        assert agent.get_light_state("FrontLeft") == 1.0
        assert agent.get_camera_state("Nope") is False  # as published
        with pytest.raises(KeyError, match="Nope"):
            agent.get_light_state("Nope")


def test_set_frame_and_random_access(archive):
    path, poses, images = archive
    with PlaybackAgent(path) as agent:
        for f in (9, 3, 7, 0, 5):
            assert agent.set_frame(f) == f
            assert agent.get_transform().as_tuple() == tuple(poses[f])
            if f in images:
                np.testing.assert_array_equal(
                    agent.input_data()["Grayscale"]["FrontLeft"], images[f][0]
                )
        with pytest.raises(
            ValueError, match="frame 42"
        ):  # past the end: ValueError, as in lac_data
            agent.set_frame(42)
        with pytest.raises(
            IndexError, match="3.5"
        ):  # not a recorded frame: IndexError, as in lac_data
            agent.set_frame(3.5)
        assert agent.set_frame(4.0) == 4
        agent.set_frame(0)
        assert list(agent) == list(range(10))


def test_full_playback_is_forward_only(tmp_path, monkeypatch):
    path = tmp_path / "long.lac"
    _write(path, n_frames=60, first_image=0, every=1)
    with LacArchive(path, checkpoint_spacing=2048) as archive:
        with PlaybackAgent(archive) as agent:
            restores = []
            orig = _IndexedGzipReader._restore
            monkeypatch.setattr(
                _IndexedGzipReader, "_restore", lambda self, k: (restores.append(k), orig(self, k))
            )
            n = 0
            for _ in agent:
                n += sum(v is not None for v in agent.input_data()["Grayscale"].values())
            assert n == 60
            assert len(restores) <= 1  # one jump back to the first image, then forward only
        # the agent closed, the archive it borrowed is still open and readable
        assert archive._file is not None and not archive._file.closed
        assert archive.grayscale("FrontLeft", 0) is not None


def test_empty_frames_table_is_an_error(tmp_path):
    path = tmp_path / "empty.lac"
    with LacWriter(path, {"lander": [0] * 6, "rover": [0] * 6, "cameras": {}}):
        pass
    with pytest.raises(InputError, match="no rows"):
        PlaybackAgent(path)
