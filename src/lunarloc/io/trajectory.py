"""Trajectory files: TUM (``t x y z qx qy qz qw`` per line, what evo and the TUM RGB-D tools
read) and KITTI odometry (the top three rows of each 4x4 pose, 12 numbers per line, no
times). Both are written atomically; poses are ``T_map_rover`` (F, 4, 4), metres.

    from lunarloc import write_kitti, write_tum
    write_tum("run.tum", times_s, T_map_rover)        # evo_ape tum truth.tum run.tum
    write_kitti("run.kitti", T_map_rover)             # evo_ape kitti truth.kitti run.kitti
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lunarloc.core.errors import InputError

__all__ = ["write_tum", "read_tum", "write_kitti", "read_kitti"]


def _poses(T_map_rover, n: int | None = None) -> np.ndarray:
    T = np.asarray(T_map_rover, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(f"poses must be an (F, 4, 4) array of T_map_rover; got shape {T.shape}")
    if n is not None and len(T) != n:
        raise InputError(f"{n} times for {len(T)} poses: a TUM file needs one time per pose")
    return T


def write_tum(path: str | Path, times_s, T_map_rover) -> Path:
    """TUM trajectory file from times (F,) in seconds and poses (F, 4, 4); returns the path.
    The position and quaternion come from each pose's x, y, z, roll, pitch, yaw."""
    from scipy.spatial.transform import Rotation

    from lunarloc.core.geometry import matrix_to_pose
    from lunarloc.io.outputs import atomic_open

    times = np.asarray(times_s, dtype=float).reshape(-1)
    T = _poses(T_map_rover, len(times))
    poses = np.array([matrix_to_pose(t) for t in T], float).reshape(-1, 6)
    # x, y, z, w
    q = (
        Rotation.from_euler("ZYX", poses[:, [5, 4, 3]]).as_quat()
        if len(poses)
        else np.zeros((0, 4))
    )
    path = Path(path)
    with atomic_open(path, "w") as fh:
        for t, p, qq in zip(times, poses, q):
            fh.write(
                f"{t:.6f} {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {qq[0]:.8f} {qq[1]:.8f} {qq[2]:.8f} "
                f"{qq[3]:.8f}\n"
            )
    return path


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(times (F,), poses (F, 6) x, y, z, roll, pitch, yaw) from a TUM file."""
    from scipy.spatial.transform import Rotation

    a = np.loadtxt(path, ndmin=2)
    eul = Rotation.from_quat(a[:, 4:8]).as_euler("ZYX")
    return a[:, 0], np.column_stack([a[:, 1:4], eul[:, 2], eul[:, 1], eul[:, 0]])


def write_kitti(path: str | Path, T_map_rover) -> Path:
    """KITTI odometry file from poses (F, 4, 4): per line the top three rows of the pose,
    row-major (r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz); returns the path. KITTI files
    carry no times: write them beside it (or use :func:`write_tum`) where they matter."""
    from lunarloc.io.outputs import atomic_open

    T = _poses(T_map_rover)
    path = Path(path)
    with atomic_open(path, "w") as fh:
        for t in T:
            fh.write(" ".join(f"{v:.9e}" for v in t[:3, :].reshape(-1)) + "\n")
    return path


def read_kitti(path: str | Path) -> np.ndarray:
    """Poses (F, 4, 4) from a KITTI odometry file."""
    a = np.loadtxt(path, ndmin=2)
    if a.shape[1] != 12:
        raise InputError(f"{path}: a KITTI pose line has 12 numbers; got {a.shape[1]}")
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, :] = a.reshape(-1, 3, 4)
    return T
