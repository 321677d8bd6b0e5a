"""Synthetic rock fields of any size and vehicle windows cut from them, with the known
transform: ground truth for the scaling benchmark and the indexed-search tests.

The density defaults to what a LAC site holds (~400 rocks on 27 m x 27 m, ~0.55 per
square metre; a 200 m x 200 m area mapped from above holds ~20,000). Heights follow a
smooth random terrain (a few sinusoids of 8-60 m wavelength, +-0.5 m) plus the rock's
own height scatter, so height differences between nearby rocks are small, as on the
real sites.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lunarloc.core.errors import InputError
from lunarloc.core.geometry import (
    euler_to_rotation,
    invert_transform,
    make_transform,
    transform_points,
)
from lunarloc.io.maps import LandmarkMap

__all__ = ["LAC_ROCK_DENSITY_PER_M2", "VehicleWindow", "uniform_rock_field", "vehicle_window"]

LAC_ROCK_DENSITY_PER_M2 = 0.55


def uniform_rock_field(
    rng: np.random.Generator, n: int, density_per_m2: float = LAC_ROCK_DENSITY_PER_M2
) -> LandmarkMap:
    """`n` rocks uniformly on a square whose side gives `density_per_m2` (metres)."""
    if n < 3 or not density_per_m2 > 0:
        raise InputError(
            f"a rock field needs n >= 3 and a positive density, got n={n}, density={density_per_m2}"
        )
    side = math.sqrt(n / density_per_m2)
    xy = rng.uniform(0.0, side, (n, 2))
    z = rng.normal(0.0, 0.05, n)
    for _ in range(4):  # smooth terrain: random plane waves
        k = 2 * math.pi / rng.uniform(8.0, 60.0)
        a = rng.uniform(0, 2 * math.pi)
        z += 0.125 * np.sin(
            k * (xy[:, 0] * math.cos(a) + xy[:, 1] * math.sin(a)) + rng.uniform(0, 2 * math.pi)
        )
    return LandmarkMap(np.c_[xy, z], frame="site")


@dataclass
class VehicleWindow:
    """A vehicle map cut from a field: ``vehicle`` in its own frame, the true
    ``T_ref_veh``, and which reference rock each vehicle landmark is (-1: outlier)."""

    vehicle: LandmarkMap
    T_ref_veh: np.ndarray
    ref_index: np.ndarray


def vehicle_window(
    rng: np.random.Generator,
    reference: LandmarkMap,
    n_landmarks: int = 150,
    outlier_fraction: float = 0.15,
    detect_prob: float = 0.85,
    noise_m: float = 0.015,
    max_tilt_deg: float = 0.5,
) -> VehicleWindow:
    """A window of `n_landmarks` around a random rock: the reference rocks nearest to it
    that the rover detected (`detect_prob`), each with Gaussian noise `noise_m` per axis,
    plus `outlier_fraction` spurious landmarks in the same area, expressed in a random
    frame (any yaw, tilt up to `max_tilt_deg`, translation up to 100 m)."""
    P = reference.positions_xyz
    n_out = int(round(outlier_fraction * n_landmarks))
    n_true = n_landmarks - n_out
    if n_true < 3 or n_true > detect_prob * len(P):
        raise InputError(
            f"a window of {n_landmarks} landmarks does not fit a {len(P)}-rock reference"
        )
    centre = P[rng.integers(len(P)), :2]
    k = min(len(P), int(math.ceil(n_true / detect_prob)) + 1)
    _, near = cKDTree(P[:, :2]).query(centre, k=k)
    near = np.asarray(near)
    seen = near[rng.random(len(near)) < detect_prob][:n_true]
    if len(seen) < n_true:  # unlucky draw: fill from the nearest undetected rocks
        rest = near[~np.isin(near, seen)]
        seen = np.r_[seen, rest[: n_true - len(seen)]]
    true_xyz = P[seen] + rng.normal(0.0, noise_m, (n_true, 3))
    lo, hi = P[seen, :2].min(axis=0), P[seen, :2].max(axis=0)
    out_xyz = np.c_[rng.uniform(lo, hi, (n_out, 2)), rng.normal(P[seen, 2].mean(), 0.2, n_out)]
    world = np.vstack([true_xyz, out_xyz])
    idx = np.r_[seen, np.full(n_out, -1)]
    perm = rng.permutation(len(world))
    roll, pitch = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
    T_veh_ref = make_transform(
        euler_to_rotation(roll, pitch, rng.uniform(-math.pi, math.pi)), rng.uniform(-100, 100, 3)
    )
    veh = LandmarkMap(transform_points(T_veh_ref, world[perm]), frame="vehicle")
    return VehicleWindow(veh, invert_transform(T_veh_ref), idx[perm].astype(np.int64))
