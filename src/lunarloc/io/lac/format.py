"""The `.lac` format's fixed parts: table columns, the ``data_spec`` values, member-name rules,
and the lander's pose conventions (shared by the reader and the writer)."""

from __future__ import annotations

import re

__all__ = [
    "FRAME_COLUMNS",
    "STATE_COLUMNS",
    "CAMERA_COLUMNS",
    "DATA_SPEC",
    "LEGACY_MAP_LANDER_SPECS",
    "lander_pose_map",
    "lander_pose_relative",
]

FRAME_COLUMNS: tuple[str, ...] = (
    "frame",
    "x",
    "y",
    "z",
    "roll",
    "pitch",
    "yaw",
    "accel_x",
    "accel_y",
    "accel_z",
    "gyro_x",
    "gyro_y",
    "gyro_z",
    "mission_time",
    "power",
    "linear_speed",
    "angular_speed",
    "cover_angle",
)
"""Columns of ``frames.csv``, in the LAC recorder's order."""

STATE_COLUMNS: tuple[str, ...] = FRAME_COLUMNS[1:]
"""Per-frame state columns (all float) accepted by :meth:`LacWriter.add_frame`."""

CAMERA_COLUMNS: tuple[str, ...] = (
    "frame",
    "enable",
    "camera_x",
    "camera_y",
    "camera_z",
    "camera_roll",
    "camera_pitch",
    "camera_yaw",
    "light_intensity",
    "grayscale",
    "semantic",
)
"""Columns of ``cameras/<Name>/<Name>_frames.csv``."""

_TIME_FORMAT = "%Y-%m-%d %H:%M:%S"
_RECORD_NAME = re.compile(r"^[A-Za-z0-9_-]+$")
_CAMERA_NAME = re.compile(r"^[A-Za-z0-9_-]+$")

DATA_SPEC = "lunarloc-2"
"""``data_spec`` :class:`LacWriter` writes: ``lander`` in initial.toml is relative to the
rover (as the LAC recorder stores it)."""

LEGACY_MAP_LANDER_SPECS: tuple[str, ...] = ("lunarloc-sim",)
"""``data_spec`` values of archives lunarloc wrote before :data:`DATA_SPEC`, whose
``lander`` is a map-frame pose; the reader converts it to rover-relative."""


def lander_pose_map(initial: dict) -> list[float]:
    """Map-frame lander pose [x, y, z, roll, pitch, yaw] from an initial.toml dict whose
    ``lander`` is relative to the rover and ``rover`` is the rover's map-frame pose:
    ``T_map_lander = T_map_rover @ T_rover_lander``."""
    from lunarloc.core.geometry import matrix_to_pose, pose_to_matrix

    T = pose_to_matrix(*(float(v) for v in initial["rover"])) @ pose_to_matrix(
        *(float(v) for v in initial["lander"])
    )
    return [float(v) for v in matrix_to_pose(T)]


def lander_pose_relative(rover_pose_map, lander_pose_map_) -> list[float]:
    """The rover-relative lander pose initial.toml stores (LAC ``get_initial_lander_position``)
    from map-frame rover and lander poses: ``T_rover_lander = T_map_rover^-1 @ T_map_lander``."""
    from lunarloc.core.geometry import invert_transform, matrix_to_pose, pose_to_matrix

    T_map_rover = pose_to_matrix(*(float(v) for v in rover_pose_map))
    T_map_lander = pose_to_matrix(*(float(v) for v in lander_pose_map_))
    return [float(v) for v in matrix_to_pose(invert_transform(T_map_rover) @ T_map_lander)]
