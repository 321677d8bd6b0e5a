"""The IMU as the leaderboard computes it: finite differences of the rover's true pose.

Every agent tick (20 Hz, ``dt`` = 0.05 s), from the right-handed pose (position ``p_k``,
rotation ``R_k = Rz(yaw) Ry(pitch) Rx(roll)``):

* angular velocity: the skew part of ``(R_k - R_{k-1}) / dt @ R_k^T``, read as
  ``(W[2, 1], W[0, 2], W[1, 0])``: the *spatial* (world-frame) rate, not the body rate;
* acceleration: ``R_k^T ((p_k - 2 p_{k-1} + p_{k-2}) / dt^2 + g)``, ``g = (0, 0, 1.622)``:
  the body-frame specific force;
* first tick: ``g`` (unrotated) and zero rate; second tick: ``g`` (unrotated) and the rate.
No noise. Returned as float64 ``[ax, ay, az, wx, wy, wz]``.
"""

from __future__ import annotations

import numpy as np

from leaderboard.agents.coordinate_conversion import toRHCStransform

GRAVITY_MPS2 = np.array([0.0, 0.0, 1.622])


def rotation_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy, cp, sp, cr, sr = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


class IMU:
    def __init__(self, vehicle, dt: float = 0.05):
        self._vehicle = vehicle
        self.dt = dt
        self._p = [None, None, None]  # p_k, p_{k-1}, p_{k-2}
        self._R = [None, None]  # R_k, R_{k-1}

    def get_data(self) -> np.ndarray:
        tf = toRHCStransform(self._vehicle.get_transform())
        p = np.array([tf.location.x, tf.location.y, tf.location.z])
        R = rotation_zyx(tf.rotation.yaw, tf.rotation.pitch, tf.rotation.roll)
        self._p = [p, self._p[0], self._p[1]]
        self._R = [R, self._R[0]]
        if self._R[1] is None:
            acc, gyro = GRAVITY_MPS2.copy(), np.zeros(3)
        else:
            W = (self._R[0] - self._R[1]) / self.dt @ self._R[0].T
            gyro = np.array([W[2, 1], W[0, 2], W[1, 0]])
            if self._p[2] is None:
                acc = GRAVITY_MPS2.copy()
            else:
                acc = self._R[0].T @ (
                    (self._p[0] - 2.0 * self._p[1] + self._p[2]) / self.dt**2 + GRAVITY_MPS2
                )
        return np.array([*acc, *gyro], dtype=np.float64)
