"""Compile every numba kernel once, so that no localization call pays for it.

The association kernels are compiled with ``cache=True``: the first process that runs them
compiles (seconds) and writes numba's cache; later processes load it (milliseconds).
``warm_up()`` runs them on a tiny synthetic pair so that this happens at a chosen moment:
``make`` calls ``lunarloc warm-up`` after installing, and :class:`lunarloc.loop.LoopState` calls
it before its stage timers start, so compile time is never counted as run time.
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["warm_up"]

_WARM = False


def warm_up(force: bool = False) -> float:
    """Compile (or load from the cache) every association kernel, in every mode and solver.
    Returns the seconds it took (about 0 once done in this process)."""
    global _WARM
    if _WARM and not force:
        return 0.0
    from lunarloc.geometry import euler_to_rotation, make_transform, transform_points
    from lunarloc.localize import LocalizationConfig, Mode, Solver, localize
    from lunarloc.maps import LandmarkMap

    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    ref_xyz = np.c_[rng.uniform(-6, 6, (40, 2)), rng.normal(0, 0.2, 40)]
    T = make_transform(euler_to_rotation(0.0, 0.0, 0.7), np.array([3.0, -2.0, 0.1]))
    veh_xyz = transform_points(np.linalg.inv(T), ref_xyz[:25]) + rng.normal(0, 0.005, (25, 3))
    ref, veh = LandmarkMap(ref_xyz, frame="ref"), LandmarkMap(veh_xyz, frame="veh")
    for mode in Mode:
        for solver in Solver:
            localize(ref, veh, LocalizationConfig(mode=mode, solver=solver))
    _WARM = True
    return time.perf_counter() - t0
