"""What chance produces: consistent sets and near misses expected from unrelated maps."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from lunarloc.core.geometry import (
    transform_points,
)
from lunarloc.localization.config import Mode


def chance_clique_size(
    num_associations: int,
    mode: "Mode" = Mode.GRAVITY,
    epsilon_m: float = 0.05,
    epsilon_z_m: float = 0.05,
) -> float:
    """Upper envelope of the largest consistent set found between UNRELATED maps with
    `num_associations` putative associations (measured; see docs/results.md, "The acceptance rule").

    Envelope ``a + b * log10(m)`` over the largest chance cliques of 184 unrelated map
    pairs at the default settings: 124 real traverse pairs with every shared rock
    removed and 60 synthetic uniform rock fields of 20-450 landmarks
    (``python benchmarks/chance_cliques.py``; largest seen: 6 real, 9 synthetic; with
    the full acceptance rule, 0 of these and of 136 mirrored real pairs were accepted).
    6-DoF mode: envelope over 40 synthetic pairs of 20-160 landmarks
    (``--mode 6dof --skip-real --synthetic 40 --synthetic-max 160``; largest seen 6).
    Wider search tolerances make chance sets larger: the envelope is scaled by
    ``rho ** gamma``, rho = sqrt(eps_h eps_z) / 5 cm (>= 1), gamma measured with
    ``--epsilon 0.08 / 0.15`` (see _TOLERANCE_EXPONENT).
    """
    a, b = _CHANCE_MODEL[Mode(mode)]
    rho = max(
        1.0,
        math.sqrt(
            max(epsilon_m, 1e-9)
            * max(epsilon_z_m if Mode(mode) is Mode.GRAVITY else epsilon_m, 1e-9)
        )
        / _CHANCE_EPSILON_M,
    )
    return (a + b * math.log10(max(num_associations, 1))) * rho**_TOLERANCE_EXPONENT


# (intercept, slope per decade of associations); measured by benchmarks/chance_cliques.py
_CHANCE_MODEL = {Mode.GRAVITY: (-0.30, 1.83), Mode.SIX_DOF: (-3.69, 2.35)}
_CHANCE_EPSILON_M = (
    0.05  # the search tolerance (horizontal and vertical) the envelope was measured at
)
# measured: largest ratio of chance sets 2.0 at 3x the tolerance, 1.33 at 1.6x (gamma 0.63, 0.61)
_TOLERANCE_EXPONENT = 0.65


def near_miss_excess(
    T, Pv, Pr, inlier_veh: np.ndarray, inner_m: float, outer_m: float, density_radius_m: float = 1.5
) -> tuple[int, float]:
    """(observed, expected by chance) number of non-inlier vehicle landmarks whose nearest
    reference landmark under T lies between `inner_m` and `outer_m`.

    Under a right pose of a rigid map a landmark either has its rock within the noise
    (an inlier) or nothing nearby but chance neighbours; the chance count follows the local
    reference density lambda (rocks within `density_radius_m`): the nearest neighbour is in
    the band with probability exp(-lambda pi r_in^2) (1 - exp(-lambda pi (r_out^2 - r_in^2))).
    A map that is scaled or bent away from its inliers puts its true rocks a little further
    off, in the band: an excess there is the signature of a non-rigid map."""
    Pt = transform_points(T, Pv)
    rest = np.ones(len(Pt), dtype=bool)
    rest[np.asarray(inlier_veh, dtype=np.int64)] = False
    if not np.any(rest):
        return 0, 0.0
    tree = cKDTree(Pr)
    d, _ = tree.query(Pt[rest])
    observed = int(np.sum((d > inner_m) & (d < outer_m)))
    return observed, float(
        _chance_in_band(tree, Pt[rest], inner_m, outer_m, density_radius_m).sum()
    )


def _chance_in_band(
    tree: cKDTree, points: np.ndarray, inner_m: float, outer_m: float, density_radius_m: float = 1.5
) -> np.ndarray:
    """Probability that the nearest reference landmark of each point lies between inner_m
    and outer_m by chance, from the local reference density (rocks within
    `density_radius_m`, a horizontal Poisson model)."""
    counts = tree.query_ball_point(points, density_radius_m, return_length=True)
    lam = np.asarray(counts, float) / (math.pi * density_radius_m**2)
    return np.exp(-lam * math.pi * inner_m**2) * (
        1 - np.exp(-lam * math.pi * (outer_m**2 - inner_m**2))
    )


def chance_refined(T, Pv, Pr, core_veh: np.ndarray, radius_m: float) -> float:
    """Expected number of vehicle landmarks outside the consistent core that refinement
    pairs with a reference landmark within `radius_m` by chance under T: the refined
    inlier count exceeds the core by about this much even for unrelated maps."""
    rest = np.ones(len(Pv), dtype=bool)
    rest[np.asarray(core_veh, dtype=np.int64)] = False
    if not np.any(rest):
        return 0.0
    return float(_chance_in_band(cKDTree(Pr), transform_points(T, Pv[rest]), 0.0, radius_m).sum())
