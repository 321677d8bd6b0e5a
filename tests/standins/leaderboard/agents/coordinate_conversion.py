"""The right-handed poses an agent sees, converted from CARLA's left-handed ones.

Right-handed: x forward, y left, z up (metres); roll, pitch, yaw in radians, rotation
``Rz(yaw) Ry(pitch) Rx(roll)``. Conversion: y and the pitch and yaw angles change sign,
degrees become radians. The classes carry only ``x, y, z`` / ``roll, pitch, yaw`` (and the
transform a ``transform(x, y, z)`` method): no matrix accessor, as in the leaderboard.
"""

from __future__ import annotations

import math

import numpy as np

import carla


class Vector:
    __slots__ = ("x", "y", "z")

    def __init__(self, carla_vector):
        self.x, self.y, self.z = carla_vector.x, -carla_vector.y, carla_vector.z

    def __str__(self) -> str:
        return f"Vector3D(x={round(self.x, 6)}, y={round(self.y, 6)}, z={round(self.z, 6)})"


class Location:
    __slots__ = ("x", "y", "z")

    def __init__(self, carla_location):
        self.x, self.y, self.z = carla_location.x, -carla_location.y, carla_location.z

    def __str__(self) -> str:
        return f"Location(x={round(self.x, 6)}, y={round(self.y, 6)}, z={round(self.z, 6)})"


class Rotation:
    __slots__ = ("roll", "pitch", "yaw")

    def __init__(self, carla_rotation):
        self.roll = math.radians(carla_rotation.roll)
        self.pitch = -math.radians(carla_rotation.pitch)
        self.yaw = -math.radians(carla_rotation.yaw)

    def __str__(self) -> str:
        return f"Rotation(roll={round(self.roll, 6)}, pitch={round(self.pitch, 6)}, yaw={round(self.yaw, 6)})"


class Transform:
    __slots__ = ("location", "rotation")

    def __init__(self, carla_transform):
        self.location = Location(carla_transform.location)
        self.rotation = Rotation(carla_transform.rotation)

    def transform(self, x, y, z) -> Location:
        """A point given in this transform's frame, in the parent frame (right-handed)."""
        return toRHCSlocation(toLHCStransform(self).transform(carla.Location(x, -y, z)))

    def __str__(self) -> str:
        return f"Transform({self.location}, {self.rotation})"


def toLHCSlocation(location) -> carla.Location:
    return carla.Location(location.x, -location.y, location.z)


def toLHCSrotation(rotation) -> carla.Rotation:
    return carla.Rotation(
        pitch=-math.degrees(rotation.pitch),
        yaw=-math.degrees(rotation.yaw),
        roll=math.degrees(rotation.roll),
    )


def toLHCStransform(transform) -> carla.Transform:
    return carla.Transform(toLHCSlocation(transform.location), toLHCSrotation(transform.rotation))


def toRHCSlocation(location) -> Location:
    return Location(location)


def toRHCSrotation(rotation) -> Rotation:
    return Rotation(rotation)


def toRHCStransform(transform) -> Transform:
    return Transform(transform)


def get_lander_transform(
    rover_transform: carla.Transform, lander_transform: carla.Transform
) -> Transform:
    """The lander's pose relative to the rover (both CARLA transforms), right-handed.

    The leaderboard extracts the relative angles with asin/acos and sign tests, which keeps
    pitch and roll within +-90 degrees; a lander stands upright, so plain ZYX angles agree."""
    loc = rover_transform.inverse_transform(lander_transform.location)
    M = (
        np.array(rover_transform.get_inverse_matrix())[:3, :3]
        @ np.array(lander_transform.get_matrix())[:3, :3]
    )
    pitch = math.asin(float(np.clip(M[2, 0], -1.0, 1.0)))
    yaw = math.atan2(M[1, 0], M[0, 0])
    roll = math.atan2(-M[2, 1], M[2, 2])
    rot = carla.Rotation(pitch=math.degrees(pitch), yaw=math.degrees(yaw), roll=math.degrees(roll))
    return toRHCStransform(carla.Transform(loc, rot))


def rh_matrix(transform) -> np.ndarray:
    """4x4 of a right-handed Transform (a test helper, not a leaderboard function)."""
    r = transform.rotation
    cy, sy, cp, sp, cr, sr = (
        math.cos(r.yaw),
        math.sin(r.yaw),
        math.cos(r.pitch),
        math.sin(r.pitch),
        math.cos(r.roll),
        math.sin(r.roll),
    )
    T = np.eye(4)
    T[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    T[:3, 3] = (transform.location.x, transform.location.y, transform.location.z)
    return T


def carla_transform_from_rh(T: np.ndarray) -> carla.Transform:
    """The CARLA (left-handed) transform of a right-handed 4x4 pose (a test helper)."""
    R = np.asarray(T, float)[:3, :3]
    pitch = math.asin(float(np.clip(-R[2, 0], -1.0, 1.0)))
    yaw = math.atan2(R[1, 0], R[0, 0])
    roll = math.atan2(R[2, 1], R[2, 2])
    x, y, z = (float(v) for v in np.asarray(T, float)[:3, 3])
    return carla.Transform(
        carla.Location(x, -y, z),
        carla.Rotation(pitch=-math.degrees(pitch), yaw=-math.degrees(yaw), roll=math.degrees(roll)),
    )
