"""Odometry from a custom record of the archive (``custom/<name>.csv``).

Accepted layouts (a ``frame`` column first, as the LAC recorder writes custom records):

* ``frame, x, y, z, roll, pitch, yaw`` (m, rad; ``R = Rz(yaw) Ry(pitch) Rx(roll)``), e.g.
  lunarloc's simulated ``odometry`` record;
* ``frame, m00 ... m33``: a row-major 4x4 homogeneous transform (``m30..m33`` optional),
  e.g. the LunarLoc dataset's ``orbslam.csv``.

The record's poses are taken as rover poses in the record's own frame; the trajectory
keeps the record's motion relative to its first row and starts it at the archive's
initial rover pose (for a record already in the map frame that starts at that pose,
as lunarloc's, this changes nothing). Frames the record has no row for are bridged by
IMU dead reckoning from the last recorded pose (see :mod:`lunarloc.odometry.imu`).
"""

from __future__ import annotations

import logging

import numpy as np

from lunarloc.core.errors import ArchiveError
from lunarloc.core.geometry import pose_to_matrix

__all__ = ["POSE_COLUMNS", "MATRIX_COLUMNS", "read_record_poses"]

logger = logging.getLogger(__name__)
logger.addHandler(logging.NullHandler())

POSE_COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw")
MATRIX_COLUMNS = tuple(f"m{i}{j}" for i in range(4) for j in range(4))
_ROTATION_TOLERANCE = 1e-3  # max |R^T R - I| entry of an accepted rotation block


def read_record_poses(archive, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(frames (K,), T_rec_rover (K, 4, 4)) from ``custom/<name>.csv``; rows sorted by frame.

    Raises ArchiveError naming the member (and the line) for a missing or empty record,
    missing columns, text or NaN where a number belongs, a duplicate frame or a matrix
    whose rotation block is not a rotation.
    """
    member = f"{archive.path}: custom/{name}.csv"
    if name not in archive.custom_records:
        have = ", ".join(archive.custom_records) or "none"
        raise ArchiveError(f"{archive.path}: no custom record {name!r} (custom records: {have})")
    table = archive.custom(name)
    if not table.columns or table.n_rows == 0:
        raise ArchiveError(f"{member}: the record is empty (no rows): no odometry to read")
    cols = set(table.columns)
    if set(POSE_COLUMNS) <= cols:
        layout = POSE_COLUMNS
    elif set(MATRIX_COLUMNS[:12]) <= cols:
        layout = tuple(c for c in MATRIX_COLUMNS if c in cols)
    else:
        raise ArchiveError(
            f"{member}: needs columns x,y,z,roll,pitch,yaw or m00..m33 (row-major 4x4); has "
            f"{', '.join(table.columns)}"
        )
    if "frame" in cols:
        frames = _numbers(table, "frame", member)
        if np.any(frames != np.round(frames)):
            i = int(np.flatnonzero(frames != np.round(frames))[0])
            raise ArchiveError(
                f"{member}: frame {table['frame'][i]!r} at line {i + 2} is not an integer"
            )
        frames = frames.astype(np.int64)
    elif table.n_rows == archive.n_frames:
        logger.warning("%s: no 'frame' column; rows taken as frames.csv's frames in order", member)
        frames = np.asarray(archive.frame_numbers, np.int64)
    else:
        raise ArchiveError(
            f"{member}: no 'frame' column and {table.n_rows} rows for {archive.n_frames} frames: "
            "cannot align the poses"
        )
    values = np.column_stack([_numbers(table, c, member) for c in layout])
    if layout == POSE_COLUMNS:
        T = np.stack([pose_to_matrix(*row) for row in values])
    else:
        T = np.tile(np.eye(4), (len(values), 1, 1))
        T[:, :3, :] = values[:, :12].reshape(-1, 3, 4)
        R = T[:, :3, :3]
        err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(R)
        bad = np.flatnonzero((err > _ROTATION_TOLERANCE) | (det < 0))
        if len(bad):
            i = int(bad[0])
            raise ArchiveError(
                f"{member}: line {i + 2} (frame {frames[i]}): m00..m22 is not a rotation matrix"
            )
        U, _, Vt = np.linalg.svd(R)
        T[:, :3, :3] = U @ Vt  # remove the rounding of the stored digits
    order = np.argsort(frames, kind="stable")
    frames, T = frames[order], T[order]
    dup = np.flatnonzero(np.diff(frames) == 0)
    if len(dup):
        raise ArchiveError(f"{member}: frame {frames[dup[0]]} appears twice")
    return frames, T


def _numbers(table, column: str, member: str) -> np.ndarray:
    v = np.asarray(table[column])
    if v.dtype == object:
        for i, x in enumerate(v):
            try:
                float(x)
            except (TypeError, ValueError):
                raise ArchiveError(
                    f"{member}: column '{column}' holds {x!r} at line {i + 2}, not a number"
                ) from None
    v = v.astype(float)
    bad = np.flatnonzero(~np.isfinite(v))
    if len(bad):
        raise ArchiveError(
            f"{member}: column '{column}' is empty or not finite at line {int(bad[0]) + 2}"
        )
    return v
