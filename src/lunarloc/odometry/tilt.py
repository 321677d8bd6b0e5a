"""Gravity-aided chaining of visual odometry: heading and distance from vision, roll and pitch from
gravity.

Stereo visual odometry estimates all six degrees of freedom, and its roll and pitch
drift like its heading does (under the rover's lamps, by about 2 degrees over 75 m
on a simulated LAC traverse). A tilt error bends every later step out of the
horizontal: the rover seems to climb or sink (z error of tens of centimetres), and
a local rock map built on that trajectory is tilted against the reference, which the
localizer's tilt check then refuses. Roll and pitch are observable from gravity
(:func:`lunarloc.odometry.imu.integrate_imu` holds them with the accelerometer), so
:class:`GravityAlignedChain` chains the visual odometry's *relative* motions and,
at every image pair, turns the attitude about a horizontal axis until its "up"
agrees with the IMU's. The correction is about a horizontal axis, so the heading
stays the visual odometry's (to second order in the tilt correction).

Frames: ``map`` (z up), ``rover`` (x forward, y left, z up), ``odo`` (the visual
odometry's own frame). ``R[2, :]`` of a ``R_map_rover`` is the map's up in the rover frame.
"""

from __future__ import annotations

import math

import numpy as np

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.core.geometry import invert_transform

__all__ = ["align_tilt", "GravityAlignedChain"]


def _rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def align_tilt(R_map_rover: np.ndarray, up_rover: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """`R_map_rover` turned (in the rover frame, about the axis perpendicular to both "up"
    directions) by `gain` times the angle between its up direction ``R[2, :]`` and
    `up_rover` (the map's up in the rover frame from gravity). Heading is kept."""
    R = np.asarray(R_map_rover, float)
    u_cur = R[2, :] / np.linalg.norm(R[2, :])
    u_ref = np.asarray(up_rover, float)
    n = float(np.linalg.norm(u_ref))
    if not np.isfinite(n) or n == 0:
        raise InputError(f"gravity direction {u_ref.tolist()} is not a finite non-zero vector")
    u_ref = u_ref / n
    axis = np.cross(u_ref, u_cur)
    s, c = float(np.linalg.norm(axis)), float(u_ref @ u_cur)
    if s < 1e-12:
        return R.copy()
    # R' = R C with C u_ref = u_cur, so R'[2, :] = C^T u_cur = u_ref (gain 1)
    return R @ _rotation_about(axis / s, gain * math.atan2(s, c))


class GravityAlignedChain:
    """Chains visual-odometry poses into map poses whose roll and pitch follow gravity.

    Call :meth:`add` at every image pair with the visual odometry's ``T_odo_rover`` and
    the IMU's ``T_map_rover`` (only its attitude's "up" is used). The first call anchors
    the chain at `T_map_start` (default: the IMU pose). Each later call applies the
    visual motion since the previous pair to the previous *corrected* pose (so the
    translation follows the corrected attitude), then aligns the tilt with `gain`
    (1: take gravity's roll and pitch; 0: pure visual odometry).
    """

    def __init__(self, gain: float = 1.0):
        if not 0.0 <= gain <= 1.0:
            raise ConfigError(f"tilt gain {gain} must be in [0, 1]")
        self.gain = float(gain)
        self._T_map_last: np.ndarray | None = None
        self._T_odo_last: np.ndarray | None = None

    def add(
        self, T_odo_rover: np.ndarray, T_map_imu: np.ndarray, T_map_start: np.ndarray | None = None
    ) -> np.ndarray:
        """The corrected ``T_map_rover`` at this pair (4x4)."""
        T_odo = np.asarray(T_odo_rover, float)
        if self._T_map_last is None:
            T = np.array(T_map_imu if T_map_start is None else T_map_start, float)
        else:
            T = self._T_map_last @ invert_transform(self._T_odo_last) @ T_odo
        if self.gain > 0:
            T[:3, :3] = align_tilt(T[:3, :3], np.asarray(T_map_imu, float)[2, :3], self.gain)
        self._T_map_last, self._T_odo_last = T.copy(), T_odo.copy()
        return T
