"""The component takes what the LAC leaderboard hands an agent: the right-handed Transform
(CARLA's left-handed one refused), SensorPosition keys, grayscale views of a BGRA buffer,
None on ticks without images, a Semantic group, any image size without a rig (the LAC's
fixed pinholes), and the IMU as the leaderboard computes it (world-frame gyro)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lunarloc import CameraRig, OnlineLocalizer, SensorPosition, as_transform_matrix
from lunarloc.core.errors import ConfigError, InputError
from lunarloc.core.geometry import pose_to_matrix
from lunarloc.io.lac.leaderboard import Location, Rotation, Transform, transform_from_matrix
from lunarloc.io.maps import LandmarkMap
from lunarloc.odometry.imu import ImuOdometryConfig, ImuSamples, integrate_imu

IMU_REST = np.array([0.0, 0.0, 1.622, 0.0, 0.0, 0.0])


def test_the_right_handed_transform_is_taken_and_carlas_left_handed_one_refused():
    tf = Transform(Location(1.0, -2.0, 0.3), Rotation(0.1, -0.2, 2.5))
    np.testing.assert_allclose(
        as_transform_matrix(tf), pose_to_matrix(1.0, -2.0, 0.3, 0.1, -0.2, 2.5)
    )
    np.testing.assert_allclose(
        as_transform_matrix(transform_from_matrix(as_transform_matrix(tf))), as_transform_matrix(tf)
    )

    class LeftHanded:  # what carla.Transform looks like to lunarloc: degrees, y mirrored
        location, rotation = Location(1.0, 2.0, 0.3), Rotation(5.0, 10.0, -143.0)

    LeftHanded.__module__ = "carla.libcarla"
    with pytest.raises(InputError, match="left-handed"):
        as_transform_matrix(LeftHanded(), "initial_pose")
    with pytest.raises(InputError, match="not finite"):
        as_transform_matrix(Transform(Location(float("nan"), 0, 0)))


def _ref(T0):
    rng = np.random.default_rng(3)
    xy = T0[:2, 3] + rng.uniform(-8, 8, (60, 2))
    return LandmarkMap(np.c_[xy, np.zeros(60)])


def test_leaderboard_input_without_a_rig():
    """No rig, 640x360 BGRA views keyed by SensorPosition, a Semantic group, None between images."""
    T0 = Transform(Location(2.0, -1.0, 0.2), Rotation(0.0, 0.0, 0.7))
    loc = OnlineLocalizer(
        _ref(as_transform_matrix(T0)), T0, lander_pose=Transform(Location(5.0, 0.0, -0.2))
    )
    assert (loc.rig.camera.width, loc.rig.camera.height) == (1280, 720)
    buf = np.zeros((360, 640, 4), np.uint8)
    buf[180:, :, 0] = 90
    view = buf[:, :, 0]
    assert not view.flags.c_contiguous
    none = {
        "Grayscale": {SensorPosition.FrontLeft: None, SensorPosition.FrontRight: None},
        "Semantic": {SensorPosition.FrontLeft: None},
    }
    images = {
        "Grayscale": {SensorPosition.FrontLeft: view, SensorPosition.FrontRight: view},
        "Semantic": {SensorPosition.FrontLeft: np.zeros((360, 640, 3), np.uint8)},
    }
    e = loc.update(0.0, none, IMU_REST, 0.0, 0.0)
    e = loc.update(0.05, images, IMU_REST, 0.0, 0.0)
    assert (loc.rig.camera.width, loc.rig.camera.height) == (
        640,
        360,
    )  # the LAC rig at the delivered size
    assert e.keyframe and e.T_map_rover.shape == (4, 4)
    e = loc.update(0.1, none, IMU_REST, 0.0, 0.0)
    with pytest.raises(
        InputError, match="image shape"
    ):  # once images were processed, the size is fixed
        loc.update(
            0.15,
            {
                "Grayscale": {
                    SensorPosition.FrontLeft: np.zeros((720, 1280), np.uint8),
                    SensorPosition.FrontRight: np.zeros((720, 1280), np.uint8),
                }
            },
            IMU_REST,
            0,
            0,
        )


def test_a_given_rig_keeps_its_size():
    T0 = pose_to_matrix(0, 0, 0.2, 0, 0, 0)
    loc = OnlineLocalizer(_ref(T0), T0, rig=CameraRig.lac(1280, 720))
    img = np.zeros((360, 640), np.uint8)
    with pytest.raises(InputError, match=r"expected \(720, 1280\)"):
        loc.update(0.0, {"Grayscale": {"FrontLeft": img, "FrontRight": img}}, IMU_REST, 0.0, 0.0)


def test_rig_from_sensors_with_leaderboard_keys_and_poses():
    sensors = {
        p: {
            "camera_active": p.name in ("FrontLeft", "FrontRight"),
            "light_intensity": 1.0,
            "width": "640",
            "height": "360",
        }
        for p in SensorPosition
    }
    poses = {
        SensorPosition.FrontLeft: Transform(Location(0.28, 0.081, 0.131)),
        SensorPosition.FrontRight: Transform(Location(0.28, -0.081, 0.131)),
    }
    rig = CameraRig.from_sensors(sensors, poses)
    assert rig.camera.width == 640 and rig.same_mounts(CameraRig.lac(640, 360))
    moved = CameraRig.from_sensors(
        sensors, {SensorPosition.FrontLeft: Transform(Location(0.30, 0.081, 0.131))}
    )
    assert not moved.same_mounts(rig) and not rig.same_mounts(CameraRig.lac(1280, 720))


def _circling_on_a_slope(tilt_deg: float, n: int = 1200, dt: float = 0.05):
    """True poses of a rover circling on a plane tilted by `tilt_deg`, and the IMU the LAC
    leaderboard computes from them (world-frame gyro: skew part of dR/dt R^T)."""
    R_plane = pose_to_matrix(0, 0, 0, math.radians(tilt_deg), 0, 0)
    T = [
        R_plane @ pose_to_matrix(0.3 * k * dt, 0, 0, 0, 0, 0.15 * k * dt) for k in range(n)
    ]  # yaw about the normal
    gyro = np.zeros((n, 3))
    for k in range(1, n):
        W = (T[k][:3, :3] - T[k - 1][:3, :3]) / dt @ T[k][:3, :3].T
        gyro[k] = (W[2, 1], W[0, 2], W[1, 0])
    accel = np.array(
        [Tk[:3, :3].T @ [0, 0, 1.622] for Tk in T]
    )  # (centripetal part left out: small)
    return T, ImuSamples(np.arange(n), np.arange(n) * dt, accel, gyro, np.full(n, 0.3))


def _heading_error_deg(Te, Tt) -> float:
    R = Tt[:3, :3].T @ Te[:3, :3]
    return abs(math.degrees(math.atan2(R[1, 0], R[0, 0])))


def test_imu_odometry_reads_the_leaderboards_gyro_as_world_frame_rates():
    T, s = _circling_on_a_slope(30.0)
    world = integrate_imu(s, T[0], ImuOdometryConfig(compensate_motion=False))
    body = integrate_imu(s, T[0], ImuOdometryConfig(compensate_motion=False, gyro_frame="body"))
    assert _heading_error_deg(world[-1], T[-1]) < 1.0
    assert _heading_error_deg(body[-1], T[-1]) > 10.0  # what lunarloc did before
    with pytest.raises(ConfigError, match="gyro_frame"):
        ImuOdometryConfig(gyro_frame="spatial")


def test_the_simulator_writes_the_leaderboards_gyro():
    from lunarloc.sim.rover import ImuConfig, Trajectory, simulate_imu

    from lunarloc.core.geometry import matrix_to_pose

    T, _ = _circling_on_a_slope(20.0, n=50)
    poses = np.array([matrix_to_pose(Tk) for Tk in T])
    traj = Trajectory(
        t=np.arange(50) * 0.05,
        xyz=poses[:, :3],
        rpy=poses[:, 3:],
        linear_speed=np.full(50, 0.3),
        angular_speed=np.full(50, 0.15),
    )
    _, gyro = simulate_imu(traj, config=ImuConfig(gyro_noise_rad_s=0.0, accel_noise_mps2=0.0))
    normal = T[0][:3, 2]  # the plane's normal: the world-frame rotation axis
    np.testing.assert_allclose(gyro[10], 0.15 * normal, atol=1e-4)
    _, gyro_body = simulate_imu(
        traj, config=ImuConfig(gyro_noise_rad_s=0.0, accel_noise_mps2=0.0, gyro_frame="body")
    )
    np.testing.assert_allclose(gyro_body[10], [0, 0, 0.15], atol=1e-4)
