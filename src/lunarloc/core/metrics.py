"""Trajectory error of a run: absolute trajectory error (ATE) and path length.

Both trajectories are (F, 6) poses (x, y, z, roll, pitch, yaw) in the same frame (``map``),
so no alignment is done: the error is what the rover would see. Metres.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ate", "path_length"]


def ate(est: np.ndarray, gt: np.ndarray) -> dict:
    """Absolute trajectory error of positions (no alignment: both are in ``map``): RMSE and
    max of the 3D error and RMSE of the horizontal error, metres."""
    e = np.linalg.norm(est[:, :3] - gt[:, :3], axis=1)
    eh = np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)
    return {
        "rmse_m": round(float(np.sqrt(np.mean(e**2))), 4),
        "max_m": round(float(e.max()), 4),
        "rmse_xy_m": round(float(np.sqrt(np.mean(eh**2))), 4),
    }


def path_length(P: np.ndarray) -> float:
    """Length (m) of the polyline through the positions ``P[:, :3]``."""
    return float(np.linalg.norm(np.diff(P[:, :3], axis=0), axis=1).sum()) if len(P) > 1 else 0.0
