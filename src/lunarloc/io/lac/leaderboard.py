"""The LAC leaderboard's agent-facing types: mirrored here so that an agent runs without the
leaderboard (:class:`LacAgentBase`, :meth:`lunarloc.PlaybackAgent.run_agent`), and read
natively when the leaderboard's own objects are handed to lunarloc.

What an agent sees in the leaderboard (``leaderboard.autoagents.autonomous_agent``, CARLA
0.9.15's LAC build):

* camera keys are ``carla.SensorPosition`` members (``Front``, ``FrontLeft``, ``FrontRight``,
  ``Left``, ``Right``, ``BackLeft``, ``BackRight``, ``Back``): ints with a ``.name``;
* poses are the leaderboard's *right-handed* ``Transform``: ``location.x/y/z`` in metres,
  ``rotation.roll/pitch/yaw`` in radians (``R = Rz(yaw) Ry(pitch) Rx(roll)``), x forward,
  y left, z up, and no matrix method (CARLA's own ``carla.Transform`` is left-handed, in
  degrees: never hand that to lunarloc);
* ``run_step`` must return a ``carla.VehicleVelocityControl(linear m/s, angular rad/s)``
  (positive angular turns left); the base class clamps it to 0.49 m/s and 4.13 rad/s;
* ``input_data = {"Grayscale": {SensorPosition: (H, W) uint8 or None}, "Semantic": {...}}``
  holds only the active cameras, ``None`` on ticks without an image (cameras run at 10 Hz
  on the 20 Hz tick, the first tick has none); the grayscale array is a non-contiguous
  view (``[:, :, 0]`` of CARLA's BGRA buffer);
* the leaderboard builds the agent with no arguments (the file's ``get_entry_point()``
  names the class), calls ``use_fiducials()`` (a bool), ``setup(path_to_conf_file)`` with
  the initial poses set but *no vehicle status yet* (the camera, speed and IMU getters fail
  there), checks ``sensors()`` for all eight positions, then per tick ``agent(mission_time,
  vehicle_status, input_data)`` -> ``run_step``; ``get_transform()`` is None in evaluation.
"""

from __future__ import annotations

import enum
import importlib
import math
import os
import sys
from collections.abc import Mapping

import numpy as np

from lunarloc.core.errors import InputError
from lunarloc.core.geometry import matrix_to_pose, pose_to_matrix

__all__ = [
    "SensorPosition",
    "VehicleVelocityControl",
    "Location",
    "Rotation",
    "Transform",
    "VehicleStatus",
    "LacAgentBase",
    "transform_from_matrix",
    "transform_to_matrix",
    "check_sensors",
    "load_agent_file",
    "camera_name",
    "MAX_LINEAR_SPEED_MPS",
    "MAX_ANGULAR_SPEED_RAD_S",
    "SENSOR_ATTRIBUTES",
]

MAX_LINEAR_SPEED_MPS = 0.49
MAX_ANGULAR_SPEED_RAD_S = 4.13
SENSOR_ATTRIBUTES = ("camera_active", "light_intensity", "width", "height")  # required per position


class SensorPosition(enum.IntEnum):
    """The eight camera / lamp positions, named as ``carla.SensorPosition``'s members."""

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


def camera_name(key) -> str:
    """A camera key as a name: ``"FrontLeft"``, a ``SensorPosition`` member (lunarloc's or
    carla's: its ``.name``) or its string form (``"SensorPosition.FrontLeft"``)."""
    name = getattr(key, "name", None)
    if not isinstance(name, str):
        name = str(key)
    return name.rsplit(".", 1)[-1]


class VehicleVelocityControl:
    """``carla.VehicleVelocityControl``: target linear (m/s) and angular (rad/s, left positive)
    velocity."""

    __slots__ = ("linear_target_velocity", "angular_target_velocity")

    def __init__(self, linear_target_velocity: float = 0.0, angular_target_velocity: float = 0.0):
        self.linear_target_velocity = float(linear_target_velocity)
        self.angular_target_velocity = float(angular_target_velocity)

    def __repr__(self) -> str:
        return (
            f"VehicleVelocityControl({self.linear_target_velocity}, {self.angular_target_velocity})"
        )


class Location:
    __slots__ = ("x", "y", "z")

    def __init__(self, x: float = 0.0, y: float = 0.0, z: float = 0.0):
        self.x, self.y, self.z = float(x), float(y), float(z)

    def __str__(self) -> str:
        return f"Location(x={round(self.x, 6)}, y={round(self.y, 6)}, z={round(self.z, 6)})"


class Rotation:
    """Radians, right-handed, ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""

    __slots__ = ("roll", "pitch", "yaw")

    def __init__(self, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0):
        self.roll, self.pitch, self.yaw = float(roll), float(pitch), float(yaw)

    def __str__(self) -> str:
        roll, pitch, yaw = (round(a, 6) for a in (self.roll, self.pitch, self.yaw))
        return f"Rotation(roll={roll}, pitch={pitch}, yaw={yaw})"


class Transform:
    """The leaderboard's right-handed pose: ``location`` and ``rotation`` only (no matrix
    method, as there; :func:`transform_to_matrix` gives the 4x4)."""

    __slots__ = ("location", "rotation")

    def __init__(self, location: Location | None = None, rotation: Rotation | None = None):
        self.location = location if location is not None else Location()
        self.rotation = rotation if rotation is not None else Rotation()

    def transform(self, x: float, y: float, z: float) -> Location:
        """A point given in this pose's frame, in the parent frame."""
        p = transform_to_matrix(self) @ np.array([x, y, z, 1.0])
        return Location(*p[:3])

    def __str__(self) -> str:
        return f"Transform({self.location}, {self.rotation})"


def transform_from_matrix(T) -> Transform:
    x, y, z, roll, pitch, yaw = matrix_to_pose(np.asarray(T, float))
    return Transform(Location(x, y, z), Rotation(roll, pitch, yaw))


def _is_carla_native(obj) -> bool:
    return type(obj).__module__.split(".", 1)[0] == "carla"


def transform_to_matrix(pose, what: str = "pose") -> np.ndarray:
    """4x4 of a right-handed Transform (anything with ``location.x/y/z`` in metres and
    ``rotation.roll/pitch/yaw`` in radians: the leaderboard's, this module's, PlaybackAgent's).
    CARLA's own left-handed ``carla.Transform`` (degrees) is refused: InputError."""
    if _is_carla_native(pose):
        raise InputError(
            f"{what} is CARLA's left-handed carla.Transform (degrees); pass the leaderboard's "
            "right-handed Transform, as the agent getters return it"
        )
    try:
        loc, rot = pose.location, pose.rotation
        vals = [float(v) for v in (loc.x, loc.y, loc.z, rot.roll, rot.pitch, rot.yaw)]
    except (AttributeError, TypeError, ValueError):
        raise InputError(
            f"{what} must be a Transform with location.x/y/z and rotation.roll/pitch/yaw, "
            f"got {type(pose).__name__}"
        ) from None
    if not all(math.isfinite(v) for v in vals):
        raise InputError(f"{what} is not finite ({vals})")
    return pose_to_matrix(*vals)


class VehicleStatus:
    """What the base class's getters read each tick (``transform`` None in evaluation)."""

    def __init__(
        self,
        linear_speed=0.0,
        angular_speed=0.0,
        transform=None,
        sensor_state=None,
        current_power=None,
    ):
        self.odometry_linear_speed = linear_speed
        self.odometry_angular_speed = angular_speed
        self.front_arm_angle = self.back_arm_angle = None
        self.front_drums_speed = self.back_drums_speed = None
        self.radiator_cover_angle = None
        self.current_power = current_power
        self.consumed_power = None
        self.transform = transform
        self.sensor_state = sensor_state or {p: [None, None, None, None] for p in SensorPosition}


class LacAgentBase:
    """A mirror of the leaderboard's ``AutonomousAgent`` for running an agent without the
    leaderboard: the same setters the leaderboard calls, the same getters (reading the
    per-tick status, so the camera, speed and IMU getters fail before the first tick as
    there), ``__call__`` checking that ``run_step`` returned a ``VehicleVelocityControl``."""

    def __init__(self):
        self._vehicle_status = None
        self._finished = False
        self._geometric_map = None
        self._initial_position = None
        self._initial_lander_position = None
        self._mission_time = 0

    def __call__(self, mission_time, vehicle_status, input_data):
        self._mission_time = mission_time
        self._vehicle_status = vehicle_status
        control = self.run_step(input_data)
        if type(control).__name__ != "VehicleVelocityControl" or not hasattr(
            control, "linear_target_velocity"
        ):
            raise AssertionError(
                f"run_step must return a carla.VehicleVelocityControl, got {type(control).__name__}"
            )
        out = VehicleVelocityControl(
            max(min(control.linear_target_velocity, MAX_LINEAR_SPEED_MPS), -MAX_LINEAR_SPEED_MPS),
            max(
                min(control.angular_target_velocity, MAX_ANGULAR_SPEED_RAD_S),
                -MAX_ANGULAR_SPEED_RAD_S,
            ),
        )
        return out

    # set by the leaderboard
    def set_geometric_map(self, geometric_map):
        self._geometric_map = geometric_map

    def set_initial_position(self, position):
        self._initial_position = position

    def set_initial_lander_position(self, position):
        self._initial_lander_position = position

    def set_imu_data(self, imu_data):
        self._imu_data = imu_data

    def has_finished(self):
        return self._finished

    def mission_complete(self):
        self._finished = True

    # to override
    def setup(self, path_to_conf_file):
        pass

    def use_fiducials(self):
        return True

    def sensors(self):
        return {
            p: {
                "camera_active": False,
                "light_intensity": 0,
                "width": "2448",
                "height": "2048",
                "use_semantic": False,
            }
            for p in SensorPosition
        }

    def run_step(self, input_data):
        return VehicleVelocityControl()

    def finalize(self):
        pass

    # getters
    def get_initial_position(self):
        return self._initial_position

    def get_initial_lander_position(self):
        return self._initial_lander_position

    def get_geometric_map(self):
        return self._geometric_map

    def get_mission_time(self):
        return self._mission_time

    def get_imu_data(self):
        return self._imu_data

    def get_current_power(self):
        return self._vehicle_status.current_power

    def get_linear_speed(self):
        return self._vehicle_status.odometry_linear_speed

    def get_angular_speed(self):
        return self._vehicle_status.odometry_angular_speed

    def get_camera_state(self, camera):
        return self._vehicle_status.sensor_state[camera][0]

    def get_light_state(self, light):
        return self._vehicle_status.sensor_state[light][1]

    def get_camera_position(self, camera):
        return self._vehicle_status.sensor_state[camera][2]

    def get_light_position(self, light):
        return self._vehicle_status.sensor_state[light][3]

    def get_transform(self):
        """None in evaluation (the leaderboard's true pose is for training only)."""
        return self._vehicle_status.transform


def check_sensors(sensors, evaluation: bool = True) -> dict:
    """The leaderboard's check of ``agent.sensors()``: every one of the eight positions (by
    name) with ``camera_active``, ``light_intensity``, ``width``, ``height``; no semantic
    camera in evaluation. Returns ``{name: config}``; InputError naming what is missing."""
    if not isinstance(sensors, Mapping):
        raise InputError(
            f"sensors() must return a dict keyed by SensorPosition, got {type(sensors).__name__}"
        )
    by_name = {camera_name(k): (k, v) for k, v in sensors.items()}
    out = {}
    for p in SensorPosition:
        if p.name not in by_name:
            raise InputError(
                f"sensors(): no entry for SensorPosition.{p.name} (the leaderboard needs all "
                f"eight: {', '.join(q.name for q in SensorPosition)})"
            )
        key, cfg = by_name[p.name]
        if isinstance(key, str):
            raise InputError(
                f"sensors(): key {key!r} is a string; the leaderboard's keys are "
                "carla.SensorPosition members"
            )
        missing = [a for a in SENSOR_ATTRIBUTES if a not in cfg]
        if missing:
            raise InputError(f"sensors(): SensorPosition.{p.name} lacks {', '.join(missing)}")
        if evaluation and cfg.get("use_semantic", False):
            raise InputError(
                f"sensors(): SensorPosition.{p.name} asks for a semantic camera, refused in "
                "evaluation"
            )
        out[p.name] = cfg
    return out


def load_agent_file(path) -> object:
    """Build the agent of a leaderboard agent file as the leaderboard does: import the module
    by the file's base name from its folder, call ``get_entry_point()`` for the class name and
    the class with no arguments. InputError when one of these steps fails."""
    path = os.fspath(path)
    name = os.path.basename(path).split(".")[0]
    folder = os.path.dirname(os.path.abspath(path))
    if folder not in sys.path:
        sys.path.insert(0, folder)
    try:
        module = importlib.import_module(name)
        entry = getattr(module, "get_entry_point")
    except (ImportError, AttributeError) as e:
        raise InputError(f"{path}: not a leaderboard agent file ({e})") from e
    cls = getattr(module, entry(), None)
    if cls is None:
        raise InputError(
            f"{path}: get_entry_point() names {entry()!r}, which the module does not define"
        )
    try:
        return cls()
    except TypeError as e:
        raise InputError(f"{path}: the leaderboard builds the agent with no arguments: {e}") from e
