"""Stand-in for the few parts of the ``carla`` module (the LAC build of CARLA 0.9.15) that a
Lunar Autonomy Challenge agent and the leaderboard touch. Written for lunarloc's tests from
the public behaviour of that API; no CARLA code.

CARLA's own geometry is *left-handed* (x forward, y right, z up; angles in degrees, pitch
and yaw clockwise seen from +y / +z). The leaderboard converts every pose to a
right-handed form before an agent sees it (:mod:`leaderboard.agents.coordinate_conversion`);
an agent only sees :class:`SensorPosition`, :class:`VehicleVelocityControl` and the
leaderboard's right-handed ``Transform``.
"""

from __future__ import annotations

import enum
import math

import numpy as np


class SensorPosition(enum.IntEnum):
    """The eight camera / lamp positions of the IPEx rover. In CARLA a Boost.Python enum:
    members are ints, hashable, with ``.name``; ``str()`` gives the bare name."""

    Front = 0
    FrontLeft = 1
    FrontRight = 2
    Left = 3
    Right = 4
    BackLeft = 5
    BackRight = 6
    Back = 7

    def __str__(self) -> str:
        return self.name

    def __repr__(self) -> str:
        return f"carla.libcarla.SensorPosition.{self.name}"


class RadiatorCoverState(enum.IntEnum):
    Close = 0
    Open = 1

    def __str__(self) -> str:
        return self.name


class VehicleVelocityControl:
    """The command an agent returns: linear (m/s) and angular (rad/s) target velocities."""

    __slots__ = ("linear_target_velocity", "angular_target_velocity")

    def __init__(self, linear_target_velocity: float = 0.0, angular_target_velocity: float = 0.0):
        self.linear_target_velocity = float(linear_target_velocity)
        self.angular_target_velocity = float(angular_target_velocity)

    def __repr__(self) -> str:
        return (
            f"VehicleVelocityControl(linear_target_velocity={self.linear_target_velocity}, "
            f"angular_target_velocity={self.angular_target_velocity})"
        )


# ----------------------------------------------------------------------------- left-handed geometry


class Vector3D:
    __slots__ = ("x", "y", "z")

    def __init__(self, x: float = 0.0, y: float = 0.0, z: float = 0.0):
        self.x, self.y, self.z = float(x), float(y), float(z)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(x={self.x:.6f}, y={self.y:.6f}, z={self.z:.6f})"


class Location(Vector3D):
    __slots__ = ()


class Rotation:
    """Degrees; the constructor's positional order is (pitch, yaw, roll), as in CARLA."""

    __slots__ = ("pitch", "yaw", "roll")

    def __init__(self, pitch: float = 0.0, yaw: float = 0.0, roll: float = 0.0):
        self.pitch, self.yaw, self.roll = float(pitch), float(yaw), float(roll)

    def __repr__(self) -> str:
        return f"Rotation(pitch={self.pitch:.6f}, yaw={self.yaw:.6f}, roll={self.roll:.6f})"


class Transform:
    """A left-handed pose: ``location`` (metres) and ``rotation`` (degrees)."""

    __slots__ = ("location", "rotation")

    def __init__(self, location: Location | None = None, rotation: Rotation | None = None):
        self.location = location if location is not None else Location()
        self.rotation = rotation if rotation is not None else Rotation()

    def get_matrix(self) -> list[list[float]]:
        """4x4 (list of rows) mapping local to world, left-handed."""
        cy, sy = (
            math.cos(math.radians(self.rotation.yaw)),
            math.sin(math.radians(self.rotation.yaw)),
        )
        cp, sp = (
            math.cos(math.radians(self.rotation.pitch)),
            math.sin(math.radians(self.rotation.pitch)),
        )
        cr, sr = (
            math.cos(math.radians(self.rotation.roll)),
            math.sin(math.radians(self.rotation.roll)),
        )
        loc = self.location
        return [
            [cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr, loc.x],
            [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr, loc.y],
            [sp, -cp * sr, cp * cr, loc.z],
            [0.0, 0.0, 0.0, 1.0],
        ]

    def get_inverse_matrix(self) -> list[list[float]]:
        return np.linalg.inv(np.array(self.get_matrix())).tolist()

    def transform(self, location: Location) -> Location:
        p = np.array(self.get_matrix()) @ np.array([location.x, location.y, location.z, 1.0])
        return Location(*p[:3])

    def inverse_transform(self, location: Location) -> Location:
        p = np.array(self.get_inverse_matrix()) @ np.array(
            [location.x, location.y, location.z, 1.0]
        )
        return Location(*p[:3])

    def __repr__(self) -> str:
        return f"Transform({self.location!r}, {self.rotation!r})"
