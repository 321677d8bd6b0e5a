"""Compile every numba kernel once, so that no localization call pays for it.

The association kernels are compiled with ``cache=True``: the first process that runs them
compiles (seconds) and writes numba's cache; later processes load it (milliseconds).
``warm_up()`` runs them on a tiny synthetic pair so that this happens at a chosen moment:
``make`` calls ``lunarloc warm-up`` after installing, and :class:`lunarloc.online.loop.LoopState` calls
it before its stage timers start, so compile time is never counted as run time.
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["warm_up", "build_kernels"]

_WARM = False


def warm_up(force: bool = False, jit: bool = False) -> float:
    """Compile (or load from the cache) every association kernel, in every mode and solver.
    Returns the seconds it took (about 0 once done in this process).

    Where the ahead-of-time kernels are built (:mod:`lunarloc.association.aot`) this only
    loads them; ``jit=True`` runs numba's JIT path even then, compiling into numba's cache
    (``lunarloc warm-up``: the fallback for argument types the build does not hold)."""
    global _WARM
    if _WARM in (("jit", True) if jit else ("jit", "aot", True)) and not force:
        return 0.0
    import contextlib

    from lunarloc.association.aot import jit_only
    from lunarloc.core.geometry import euler_to_rotation, make_transform, transform_points
    from lunarloc.localization.localize import LocalizationConfig, Mode, Solver, localize
    from lunarloc.io.maps import LandmarkMap

    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    # 80 x 40 = 3,200 associations: large enough for the search's per-bin bounds (their
    # kernels compile too), small enough to take a moment once compiled
    ref_xyz = np.c_[rng.uniform(-8, 8, (80, 2)), rng.normal(0, 0.2, 80)]
    T = make_transform(euler_to_rotation(0.0, 0.0, 0.7), np.array([3.0, -2.0, 0.1]))
    veh_xyz = transform_points(np.linalg.inv(T), ref_xyz[:40]) + rng.normal(0, 0.005, (40, 3))
    ref, veh = LandmarkMap(ref_xyz, frame="ref"), LandmarkMap(veh_xyz, frame="veh")
    with jit_only() if jit else contextlib.nullcontext():
        for mode in Mode:
            for solver in Solver:
                localize(ref, veh, LocalizationConfig(mode=mode, solver=solver))
    _WARM = "jit" if jit else (_WARM or "aot")
    return time.perf_counter() - t0


def build_kernels(folder=None, *, verbose: bool = False):
    """Compile every kernel signature :func:`warm_up` uses ahead of time
    (:func:`lunarloc.association.aot.build_aot` with this warm-up as the harvest)."""
    from lunarloc.association.aot import build_aot

    return build_aot(lambda: warm_up(jit=True), folder, verbose=verbose)
