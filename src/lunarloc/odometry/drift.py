"""Simulated odometry drift: a heading error that grows with distance and a scale error.

What :class:`lunarloc.pipeline.sources.TraverseCsvSource` and the pairs benchmark apply to a
true path to play it as drifting odometry would see it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DriftModel", "drifted_path"]


@dataclass(frozen=True)
class DriftModel:
    """Simulated odometry drift applied to a traverse's detections, frame by frame.

    heading_drift_deg_per_m : heading error accumulated per metre travelled (bias).
    scale_error : relative error of travelled distance (0.01 = 1 % too long).
    """

    heading_drift_deg_per_m: float = 0.0
    scale_error: float = 0.0

    @property
    def is_zero(self) -> bool:
        return self.heading_drift_deg_per_m == 0 and self.scale_error == 0


def drifted_path(rover_xyz: np.ndarray, drift: DriftModel) -> tuple[np.ndarray, np.ndarray]:
    """Odometry positions (F, 3) and heading errors psi (F,) in radians for a true path:
    each step is scaled by (1 + scale_error) and rotated by the heading error accumulated
    so far (heading_drift_deg_per_m times the horizontal distance travelled)."""
    g = np.asarray(rover_xyz, dtype=float)
    step = np.diff(g, axis=0, prepend=g[:1])
    dist = np.cumsum(np.linalg.norm(step[:, :2], axis=1))
    psi = np.radians(drift.heading_drift_deg_per_m) * dist
    c, s = np.cos(psi), np.sin(psi)
    rot_step = np.stack(
        [c * step[:, 0] - s * step[:, 1], s * step[:, 0] + c * step[:, 1], step[:, 2]], axis=1
    )
    return g[0] + np.cumsum((1.0 + drift.scale_error) * rot_step, axis=0), psi
