"""Replay a `.lac` archive through the LAC ``AutonomousAgent`` API, for offline development.

:class:`PlaybackAgent` answers the same queries an agent makes in the Lunar
Autonomy Challenge (``get_transform()``, ``get_imu_data()``, ``input_data()``
...), from the recorded frame under the cursor, and behaves as the published
``lac_data.PlaybackAgent`` (``Robaire/lac-data``; the same in
``mit-acl/lunarloc-data``) member by member; where that one is silent or differs
from the LAC agent API, as the LAC API. ``tests/test_playback_parity.py`` lists
every member and its behaviour.

Semantics (as the LAC recorder stores data)
-------------------------------------------
* Poses are in metres and radians. ``get_transform()`` is the rover's
  ground-truth pose in the map frame; ``get_camera_position(name)`` is the
  camera's pose relative to the rover; ``get_initial_lander_position()`` is the
  lander's pose relative to the rover at the start (as the LAC returns it; see
  :func:`lunarloc.io.lac.archive.lander_pose_map` for the map-frame pose).
* Camera tables only have rows for frames where a camera produced an image, so
  camera state (enable, light, pose) at a frame is taken from the camera's last
  row at or before that frame. Before its first row (or for a camera that never
  recorded), as published: ``get_camera_state`` is ``False``,
  ``get_camera_position`` a zero pose, ``get_light_state`` initial.toml's
  ``light_intensity``.
* ``input_data()`` is ``{"Grayscale": {name: image or None}, "Semantic": {...}}``
  with *every* configured camera under ``"Grayscale"`` and every ``use_semantic``
  camera under ``"Semantic"``, ``None`` when it has no image at this frame (the
  published agent; the LAC gives ``None`` to an active camera on ticks without an
  image). Grayscale images are (H, W) uint8; semantic images as stored: the LAC's
  (H, W, 3) uint8 palette (rocks (42, 59, 108), lander (160, 190, 110), fiducials
  (30, 170, 250)) or lunarloc's simulated uint16 ids.
* ``get_imu_data()`` is an ndarray ``[ax, ay, az, gx, gy, gz]`` as the LAC returns
  it (the published agent returns a list). Getters the recorder does not record
  (``get_consumed_power``, arm angles, drum speeds, ``get_light_position``) raise
  ``NotImplementedError`` as published.
* ``set_frame(f)``: a frame after the last raises a ValueError, one that is not
  recorded (``3.5``, a gap, a negative number) an IndexError, as published (both
  are :class:`~lunarloc.core.errors.InputError` too).

Driving an agent: :meth:`PlaybackAgent.run_agent` replays the recording into a leaderboard
agent (an agent file or object) exactly as the leaderboard drives one: its call order,
``SensorPosition`` keys, only the active cameras, right-handed Transforms without a matrix
method, ``get_transform()`` None in evaluation. The getters above keep the published
agent's string keys (``tests/test_playback_parity.py``); they also take ``SensorPosition``
members.

Stepping is O(1) and image reads move forward through the archive, so replaying
a whole archive frame by frame is linear in its length.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from lunarloc.io.lac.archive import LacArchive
from lunarloc.io.lac.leaderboard import camera_name
from lunarloc.core.errors import InputError
from lunarloc.core.geometry import matrix_to_pose, pose_to_matrix

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

__all__ = [
    "Location",
    "Rotation",
    "Transform",
    "PlaybackAgent",
    "FrameNotRecordedError",
    "FrameOutOfRangeError",
    "UnknownCameraError",
]


class FrameOutOfRangeError(InputError):
    """``set_frame`` past the last recorded frame (a ValueError, as in the published agent)."""


class FrameNotRecordedError(InputError, IndexError):
    """``set_frame`` to a frame number that is not recorded (an IndexError, as in the published
    agent)."""


class UnknownCameraError(InputError, KeyError):
    """A camera that initial.toml does not configure (a KeyError, as in the published agent)."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


@dataclass(frozen=True)
class Location:
    """Position in metres (carla.Location-like)."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


@dataclass(frozen=True)
class Rotation:
    """Euler angles in radians, R = Rz(yaw) Ry(pitch) Rx(roll) (carla.Rotation-like, but radians as
    in the LAC)."""

    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0


@dataclass(frozen=True)
class Transform:
    """A pose with ``location`` and ``rotation`` attributes, like the LAC's carla.Transform."""

    location: Location = Location()
    rotation: Rotation = Rotation()

    @classmethod
    def from_xyzrpy(cls, pose) -> Transform:
        """From [x, y, z, roll, pitch, yaw] (m, rad)."""
        x, y, z, roll, pitch, yaw = (float(v) for v in pose)
        return cls(Location(x, y, z), Rotation(roll, pitch, yaw))

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> Transform:
        """From a 4x4 homogeneous transform."""
        return cls.from_xyzrpy(matrix_to_pose(T))

    def as_tuple(self) -> tuple[float, float, float, float, float, float]:
        """(x, y, z, roll, pitch, yaw), metres and radians."""
        loc, rot = self.location, self.rotation
        return (loc.x, loc.y, loc.z, rot.roll, rot.pitch, rot.yaw)

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous transform (see :func:`lunarloc.core.geometry.pose_to_matrix`)."""
        return pose_to_matrix(*self.as_tuple())

    get_matrix = matrix  # carla spelling


class PlaybackAgent:
    """Mock LAC agent replaying a `.lac` archive (or an open :class:`LacArchive`).

    The cursor starts at the first recorded frame. Use as a context manager (or
    call :meth:`close`) to release the archive when it was opened from a path.
    """

    def __init__(self, path: str | os.PathLike | LacArchive):
        if isinstance(path, LacArchive):
            self.archive, self._owns = path, False
        else:
            self.archive, self._owns = LacArchive(path), True
        a = self.archive
        self._frames = a.frame_numbers
        if len(self._frames) == 0:
            raise InputError(f"{a.path}: frames.csv has no rows, nothing to play back")
        self._frame_list = self._frames.tolist()
        self._index_of = {f: i for i, f in enumerate(self._frame_list)}
        self._cam_frames = {c: a.camera_frames(c)["frame"] for c in a.cameras}
        self._i = 0
        self._row = a.frame_state(0)

    # -- lifecycle ---------------------------------------------------------------------
    def close(self) -> None:
        if self._owns:
            self.archive.close()

    def __enter__(self) -> PlaybackAgent:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- cursor ------------------------------------------------------------------------
    @property
    def frame(self) -> int:
        """The current frame number."""
        return self._frame_list[self._i]

    @property
    def frame_index(self) -> int:
        """0-based position of the current frame in frames.csv."""
        return self._i

    def set_frame(self, frame: int) -> int:
        """Jump to frame number `frame` (must be a recorded frame); returns it.

        Raises FrameOutOfRangeError (a ValueError) past the last frame and
        FrameNotRecordedError (an IndexError) for a frame that is not recorded, as published.
        """
        lo, hi = self._frame_list[0], self._frame_list[-1]
        try:
            past_end = frame > hi
        except TypeError:
            raise FrameNotRecordedError(f"frame {frame!r} is not a frame number") from None
        if past_end:
            raise FrameOutOfRangeError(
                f"frame {frame} is out of range: the last frame of {self.archive.path} is {hi}"
            )
        i = None
        if isinstance(frame, (int, np.integer)) and not isinstance(frame, bool):
            i = self._index_of.get(int(frame))
        elif isinstance(frame, (float, np.floating)) and float(frame).is_integer():
            # pandas compares 3.0 == 3, as the published agent does
            i = self._index_of.get(int(frame))
        if i is None:
            raise FrameNotRecordedError(
                f"frame {frame} is not in {self.archive.path} (frames {lo}..{hi})"
            )
        self._i = i
        self._row = self.archive.frame_state(i)
        return self.frame

    def step_frame(self) -> int:
        """Advance to the next recorded frame (stays on the last one); returns the frame number."""
        if self._i + 1 < len(self._frame_list):
            self._i += 1
            self._row = self.archive.frame_state(self._i)
        return self.frame

    def at_end(self) -> bool:
        """True when the cursor is on the last recorded frame."""
        return self._i == len(self._frame_list) - 1

    def __iter__(self):
        """Iterate from the current frame to the end, yielding the frame number each step."""
        while True:
            yield self.frame
            if self.at_end():
                return
            self.step_frame()

    # -- constants (initial.toml) ---------------------------------------------------------
    def use_fiducials(self) -> bool:
        return bool(self.archive.initial.get("fiducials", False))

    def sensors(self) -> dict[str, dict]:
        """Camera configuration {name: {camera_active, light_intensity, width, height,
        use_semantic}}
        (numbers stored as strings by older recorders are numbers here)."""
        return self.archive.initial["cameras"]

    def get_initial_position(self) -> Transform:
        """Initial rover pose in the map frame (m, rad)."""
        return Transform.from_xyzrpy(self.archive.initial["rover"])

    def get_initial_lander_position(self) -> Transform:
        """Lander pose relative to the rover at the start (m, rad), as the LAC returns it."""
        return Transform.from_xyzrpy(self.archive.initial["lander"])

    # -- per-frame state -----------------------------------------------------------------
    def get_transform(self) -> Transform:
        """Ground-truth rover pose at the current frame, map frame (m, rad)."""
        r = self._row
        return Transform(
            Location(r["x"], r["y"], r["z"]), Rotation(r["roll"], r["pitch"], r["yaw"])
        )

    def get_transform_matrix(self) -> np.ndarray:
        """4x4 ``T_map_rover`` at the current frame."""
        return self.get_transform().matrix()

    def get_imu_data(self) -> np.ndarray:
        """(6,) float64 ndarray [accel_x, accel_y, accel_z (m/s^2), gyro_x, gyro_y, gyro_z (rad/s)],
        body frame, specific force including gravity (as the LAC returns it)."""
        r = self._row
        return np.array(
            [r["accel_x"], r["accel_y"], r["accel_z"], r["gyro_x"], r["gyro_y"], r["gyro_z"]], float
        )

    def get_mission_time(self) -> float:
        """Mission time, seconds."""
        return self._row["mission_time"]

    def get_current_power(self) -> float:
        """Battery charge, Wh."""
        return self._row["power"]

    def get_linear_speed(self) -> float:
        """m/s."""
        return self._row["linear_speed"]

    def get_angular_speed(self) -> float:
        """rad/s."""
        return self._row["angular_speed"]

    def get_radiator_cover_angle(self) -> float:
        """radians."""
        return self._row["cover_angle"]

    def frame_state(self) -> dict[str, Any]:
        """The whole frames.csv row of the current frame."""
        return dict(self._row)

    # -- not recorded (the published agent raises NotImplementedError) ---------------------
    def get_consumed_power(self) -> float:
        raise NotImplementedError("get_consumed_power not implemented")

    def get_front_arm_angle(self) -> float:
        raise NotImplementedError("get_front_arm_angle not implemented")

    def get_back_arm_angle(self) -> float:
        raise NotImplementedError("get_back_arm_angle not implemented")

    def get_front_drums_speed(self) -> float:
        raise NotImplementedError("get_front_drums_speed not implemented")

    def get_back_drums_speed(self) -> float:
        raise NotImplementedError("get_back_drums_speed not implemented")

    def get_light_position(self, name: str) -> Transform:
        raise NotImplementedError("get_light_position not implemented")

    # -- cameras ---------------------------------------------------------------------------
    def _camera_row(self, name: str) -> dict[str, Any] | None:
        """Last camera-table row at or before the current frame, or None (none yet, or a
        camera that never recorded / is not configured)."""
        frames = self._cam_frames.get(camera_name(name))
        if frames is None or len(frames) == 0:
            return None
        k = int(np.searchsorted(frames, self.frame, side="right")) - 1
        return None if k < 0 else self.archive.camera_frames(camera_name(name)).row(k)

    def get_camera_state(self, name: str) -> bool:
        """Whether camera `name` is enabled at the current frame (False before its first row)."""
        row = self._camera_row(name)
        return False if row is None else bool(row["enable"])

    def get_light_state(self, name: str) -> float:
        """Lamp intensity (0-1) of camera `name` at the current frame; before its first row
        initial.toml's value. UnknownCameraError (a KeyError) for a camera not configured."""
        row = self._camera_row(name)
        if row is None:
            cfg = self.archive.initial["cameras"].get(camera_name(name))
            if cfg is None:
                raise UnknownCameraError(f"no camera named {name!r} in {self.archive.path}")
            return float(cfg.get("light_intensity", 0.0))
        return float(row["light_intensity"])

    def get_camera_position(self, name: str) -> Transform:
        """Pose of camera `name` relative to the rover (m, rad); a zero pose before its first
        row."""
        row = self._camera_row(name)
        if row is None:
            return Transform()
        return Transform.from_xyzrpy(
            [
                row[k]
                for k in (
                    "camera_x",
                    "camera_y",
                    "camera_z",
                    "camera_roll",
                    "camera_pitch",
                    "camera_yaw",
                )
            ]
        )

    # -- driving an agent as the leaderboard does -----------------------------------------
    def run_agent(
        self,
        agent,
        path_to_conf_file: str = "",
        *,
        evaluation: bool = True,
        max_ticks: int | None = None,
        geometric_map=None,
    ) -> list:
        """Replay the recording into a leaderboard agent in the leaderboard's own way and order:

        1. `agent` is an agent file (built as the leaderboard builds it: ``get_entry_point()``,
           no arguments; :func:`~lunarloc.io.lac.leaderboard.load_agent_file`) or an object;
           ``use_fiducials()`` must return a bool;
        2. ``set_geometric_map``, ``set_initial_position`` (the right-handed
           :class:`~lunarloc.io.lac.leaderboard.Transform`), ``set_initial_lander_position``, then
           ``setup(path_to_conf_file)``, with no vehicle status yet (the camera, speed and IMU
           getters of the base class fail there, as in the leaderboard);
        3. ``sensors()`` checked as the leaderboard checks it (all eight ``SensorPosition``
           members, the four attributes, no semantic camera in evaluation);
        4. per recorded frame from the cursor: ``set_imu_data``, then ``agent(mission_time,
           status, input_data)`` (the base class calls ``run_step`` and checks that it returned
           a ``VehicleVelocityControl``). ``input_data`` holds only the cameras the agent
           activated, keyed by ``SensorPosition``, ``None`` without a recorded image, grayscale
           as a non-contiguous (H, W) uint8 view as the leaderboard hands it; the status's
           camera poses are right-handed Transforms, its ``transform`` None in evaluation;
        5. ``finalize()`` after the last frame, ``max_ticks`` ticks or ``mission_complete()``.

        The agent's commands do not move the recording. Returns the commands (clamped as the
        base class clamps them). Errors of the agent's contract are InputError naming the step.
        """
        from lunarloc.io.lac.leaderboard import (
            SensorPosition,
            VehicleStatus,
            check_sensors,
            load_agent_file,
            transform_from_matrix,
        )

        if isinstance(agent, (str, os.PathLike)):
            agent = load_agent_file(agent)
        fiducials = agent.use_fiducials()
        if not isinstance(fiducials, bool):
            raise InputError(f"use_fiducials() must return a bool, got {fiducials!r}")
        initial = self.archive.initial
        agent.set_geometric_map(geometric_map)
        agent.set_initial_position(transform_from_matrix(pose_to_matrix(*initial["rover"])))
        agent.set_initial_lander_position(transform_from_matrix(pose_to_matrix(*initial["lander"])))
        agent.setup(path_to_conf_file)
        sensors = check_sensors(agent.sensors(), evaluation)
        active = [
            p
            for p in SensorPosition
            if sensors[p.name]["camera_active"] not in (False, 0, "False", "false")
        ]
        semantic = {p for p in active if sensors[p.name].get("use_semantic", False)}
        commands = []
        while True:
            input_data = {"Grayscale": {}, "Semantic": {}}
            recorded = self.input_data()
            for p in active:
                img = recorded.get("Grayscale", {}).get(p.name)
                # as the leaderboard hands it: [:, :, 0] of BGRA
                if img is not None and img.ndim == 2:
                    buf = np.empty(img.shape + (4,), np.uint8)
                    buf[:, :, 0] = img
                    img = buf[:, :, 0]
                input_data["Grayscale"][p] = img
                if p in semantic:
                    input_data["Semantic"][p] = recorded.get("Semantic", {}).get(p.name)
            state = {}
            for p in SensorPosition:
                known = p.name in initial["cameras"]
                pose = transform_from_matrix(
                    pose_to_matrix(*self.get_camera_position(p.name).as_tuple())
                )
                state[p] = [
                    self.get_camera_state(p.name) if known else False,
                    self.get_light_state(p.name) if known else 0.0,
                    pose,
                    None,
                ]
            truth = None if evaluation else transform_from_matrix(self.get_transform_matrix())
            status = VehicleStatus(
                self.get_linear_speed(),
                self.get_angular_speed(),
                truth,
                state,
                self.get_current_power(),
            )
            agent.set_imu_data(self.get_imu_data())
            out = agent(self.get_mission_time(), status, input_data)
            # the leaderboard's base class returns a pair
            commands.append(out[0] if isinstance(out, tuple) else out)
            if (
                self.at_end()
                or agent.has_finished()
                or (max_ticks is not None and len(commands) >= max_ticks)
            ):
                break
            self.step_frame()
        agent.finalize()
        return commands

    def input_data(self) -> dict[str, dict[str, np.ndarray | None]]:
        """``{"Grayscale": {name: (H, W) uint8 | None}, "Semantic": {name: image | None}}``.

        Every configured camera is a ``"Grayscale"`` key and every ``use_semantic`` camera a
        ``"Semantic"`` key, ``None`` without an image at this frame; a group with no camera is
        left out (as published).
        """
        a, f = self.archive, self.frame
        requests = [(c, f, k) for c in a.cameras for k in ("grayscale", "semantic")]
        images = a.read_images(requests)
        out: dict[str, dict[str, np.ndarray | None]] = {}
        for name, cfg in a.initial["cameras"].items():
            out.setdefault("Grayscale", {})[name] = images.get((name, f, "grayscale"))
            if cfg.get("use_semantic", False):
                out.setdefault("Semantic", {})[name] = images.get((name, f, "semantic"))
        return out
