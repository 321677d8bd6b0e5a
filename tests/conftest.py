"""Shared fixtures: generated rock fields and the optional real dataset."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lunarloc.core.geometry import euler_to_rotation, make_transform, transform_points
from lunarloc.io.maps import LandmarkMap

import os

# the paper's 17 traverses; LUNARLOC_DATA points elsewhere (tests skip when absent)
REAL_DATA = Path(
    os.environ.get("LUNARLOC_DATA")
    or Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lunarloc-data"
)


def rock_field(rng: np.random.Generator, n: int, size: float = 27.0) -> np.ndarray:
    """n rock centres on a gently undulating 27 m x 27 m site (metres)."""
    xy = rng.uniform(-size / 2, size / 2, (n, 2))
    z = 0.3 * np.sin(0.3 * xy[:, 0]) + 0.2 * np.cos(0.25 * xy[:, 1]) + rng.normal(0, 0.05, n)
    return np.c_[xy, z]


def random_T(
    rng: np.random.Generator, max_tilt_deg: float = 1.0, max_t: float = 100.0
) -> np.ndarray:
    roll, pitch = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
    return make_transform(
        euler_to_rotation(roll, pitch, rng.uniform(-np.pi, np.pi)), rng.uniform(-max_t, max_t, 3)
    )


def make_pair(rng, n_ref=150, n_common=40, n_outliers=20, noise=0.01, max_tilt_deg=1.0):
    """Reference map of a site and a vehicle map that sees `n_common` of its rocks (with
    noise) plus `n_outliers` spurious landmarks, in a random frame. Returns
    (ref, veh, T_ref_veh, common_ref_idx)."""
    ref_xyz = rock_field(rng, n_ref)
    # the vehicle sees rocks in one part of the site (partial overlap)
    centre = ref_xyz[rng.integers(n_ref), :2]
    order = np.argsort(np.linalg.norm(ref_xyz[:, :2] - centre, axis=1))
    common = order[:n_common]
    seen = ref_xyz[common] + rng.normal(0, noise, (n_common, 3))
    spurious = np.c_[centre + rng.uniform(-6, 6, (n_outliers, 2)), rng.normal(0, 0.3, n_outliers)]
    world = np.vstack([seen, spurious])
    perm = rng.permutation(len(world))
    world = world[perm]
    T = random_T(rng, max_tilt_deg)
    veh_xyz = transform_points(np.linalg.inv(T), world)
    return LandmarkMap(ref_xyz, frame="ref"), LandmarkMap(veh_xyz, frame="veh"), T, common


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def real_data() -> Path:
    if not (REAL_DATA / "csv").is_dir():
        pytest.skip(f"real LunarLoc data not found at {REAL_DATA} (set LUNARLOC_DATA)")
    return REAL_DATA
