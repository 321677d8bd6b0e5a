"""IMU dead reckoning with the leaderboard's gyro (world-frame rates) read as body rates
(lunarloc before issue 27) and as world-frame rates (now), on simulated drives.

Usage
-----
    python benchmarks/imu_convention.py [--seconds 60] [--seeds 301 302 303]

Drives, 20 Hz, the IMU computed as the leaderboard's ``agents/imu.py`` does (the stand-in in
``tests/standins``: finite differences of the true pose, skew part of ``dR/dt R^T``):

1. ``slope-<deg>``: a rover circling (0.3 m/s, 0.15 rad/s) on a plane tilted by 10, 20, 30
   and 40 degrees (a crater wall; the real recording of the issue reached 77 degrees pitch);
2. ``site<seed>``: the kinematic rover of the closed-loop harness on a simulated site
   (terrain tilt of a few degrees), driving a loop about the lander with a weaving command.

For each: the heading error at the end and at worst, and the horizontal position error at
the end, integrating with ``ImuOdometryConfig(gyro_frame="body")`` and ``gyro_frame="world"``
(speed from the true motion, so only the attitude differs).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "standins"))

from leaderboard.agents.coordinate_conversion import carla_transform_from_rh  # noqa: E402
from leaderboard.agents.imu import IMU  # noqa: E402

from lunarloc.core.geometry import pose_to_matrix  # noqa: E402
from lunarloc.odometry.imu import ImuOdometryConfig, ImuSamples, integrate_imu  # noqa: E402

DT = 0.05


class _Pose:
    T = np.eye(4)

    def get_transform(self):
        return carla_transform_from_rh(self.T)


def _imu_of(poses: list[np.ndarray]) -> np.ndarray:
    v, imu = _Pose(), None
    out = []
    for T in poses:
        v.T = T
        imu = imu or IMU(v)
        out.append(imu.get_data())
    return np.array(out)


def slope_drive(tilt_deg: float, seconds: float) -> list[np.ndarray]:
    """Circling on a plane tilted about the world x axis by `tilt_deg`."""
    n = int(seconds / DT) + 1
    R_plane = pose_to_matrix(0, 0, 0, math.radians(tilt_deg), 0, 0)
    out, x, y, yaw = [], 0.0, 0.0, 0.0
    for _ in range(n):
        out.append(R_plane @ pose_to_matrix(x, y, 0.0, 0.0, 0.0, yaw))
        x += 0.3 * DT * math.cos(yaw)
        y += 0.3 * DT * math.sin(yaw)
        yaw += 0.15 * DT
    return out


def site_drive(seed: int, seconds: float) -> list[np.ndarray]:
    import lunarsim

    world = lunarsim.SimWorld(seed, n_rocks=50)
    out = []
    for k in range(int(seconds / DT) + 1):
        world.vehicle.command = (0.3, 0.1 + 0.25 * math.sin(0.2 * k * DT))
        world.tick()
        out.append(world.T_world_rover.copy())
    return out


def evaluate(poses: list[np.ndarray]) -> dict:
    imu = _imu_of(poses)
    P = np.array([T[:3, 3] for T in poses])
    speed = np.r_[0.0, np.linalg.norm(np.diff(P, axis=0), axis=1) / DT]
    s = ImuSamples(np.arange(len(poses)), np.arange(len(poses)) * DT, imu[:, :3], imu[:, 3:], speed)
    out = {}
    for frame in ("body", "world"):
        T = integrate_imu(s, poses[0], ImuOdometryConfig(gyro_frame=frame))
        yaw_err = []
        for Te, Tt in zip(T, poses):
            R = (
                Tt[:3, :3].T @ Te[:3, :3]
            )  # heading error: yaw of the relative rotation about the true up
            d = R[:, 0] - R[2, 0] * np.array([0, 0, 1.0])
            yaw_err.append(abs(math.degrees(math.atan2(d[1], d[0]))))
        pos_err = np.linalg.norm(T[-1][:2, 3] - poses[-1][:2, 3])
        out[frame] = (yaw_err[-1], max(yaw_err), float(pos_err))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--seeds", type=int, nargs="*", default=[301, 302, 303])
    a = ap.parse_args(argv)
    drives = {f"slope-{t}": slope_drive(t, a.seconds) for t in (10, 20, 30, 40)}
    for seed in a.seeds:
        drives[f"site{seed}"] = site_drive(seed, a.seconds)
    print(
        "drive  max_tilt_deg  | gyro read as body: heading end / worst (deg), position end (m) "
        "| as world: heading end / worst, position end"
    )
    for name, poses in drives.items():
        tilt = max(math.degrees(math.acos(min(1.0, T[2, 2]))) for T in poses)
        r = evaluate(poses)
        b, w = r["body"], r["world"]
        print(
            f"{name:10s} {tilt:5.1f} | {b[0]:6.2f} / {b[1]:6.2f}  {b[2]:6.2f} | {w[0]:6.2f} / {w[1]:6.2f}  {w[2]:6.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
