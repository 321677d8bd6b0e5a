"""Compile every numba kernel once, so that no localization call pays for it.

The association kernels are compiled with ``cache=True``: the first process that runs them
compiles (seconds) and writes numba's cache; later processes load it (milliseconds).
``warm_up()`` runs them on a tiny synthetic pair so that this happens at a chosen moment:
``make`` calls ``lunarloc warm-up`` after installing, and :class:`lunarloc.online.loop.LoopState` calls
it before its stage timers start, so compile time is never counted as run time.

A user who installed the wheel and never ran ``lunarloc warm-up`` is not left waiting in
silence either: :func:`prepare_kernels` runs at the first :func:`~lunarloc.localization.localize.localize`
of a process, *before* its stage timers start, and logs (WARNING, which the CLI shows) a
line when the preparation takes more than a second and another saying how long it took
and whether numba compiled or only loaded its cache. Neither path needs ``numba.pycc``
(deprecated by numba): the ahead-of-time module is an optional speed-up on top.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

__all__ = ["warm_up", "build_kernels", "prepare_kernels", "KernelPreparation"]

logger = logging.getLogger(__name__)

_WARM = False
_PREP_LOCK = threading.Lock()
_PREPARED: "KernelPreparation | None" = None
_PREPARING = threading.local()
ANNOUNCE_AFTER_S = 1.0
"""A preparation still running after this many seconds is announced (a compile, not a cache load)."""


@dataclass(frozen=True)
class KernelPreparation:
    """What :func:`prepare_kernels` did in this process: ``source`` is ``"aot"`` (the
    ahead-of-time module was loaded: nothing to compile), ``"cache"`` (numba loaded every
    kernel from its cache), ``"compiled"`` (numba compiled ``compiled`` kernel signatures,
    now cached on disk for later processes) or ``"ready"`` (already done in this process);
    ``seconds`` is the wall time it took, never part of a localization's ``time_s``."""

    source: str
    seconds: float
    compiled: int = 0
    detail: str = ""

    def to_dict(self) -> dict:
        return {"source": self.source, "seconds": round(self.seconds, 3), "compiled": self.compiled,
                "detail": self.detail}


def _compiled_signatures() -> int:
    """How many kernel signatures numba compiled (cache misses) in this process so far."""
    from lunarloc.association.aot import _REGISTRY

    return sum(sum(k._dispatcher.stats.cache_misses.values()) for k in list(_REGISTRY)
               if k._dispatcher is not None)  # fmt: skip


def prepare_kernels() -> KernelPreparation:
    """Make the association kernels callable without compiling inside a timed stage: load
    the ahead-of-time module if it is built, else run :func:`warm_up` (numba's JIT, from its
    on-disk cache or compiling into it). Once a process; cheap afterwards.

    Logs a WARNING after :data:`ANNOUNCE_AFTER_S` while still running ("compiling ... once")
    and, when it compiled, one with the seconds it took; a cache load is logged at INFO."""
    global _PREPARED
    if getattr(_PREPARING, "active", False):  # warm_up's own localize calls
        return KernelPreparation("ready", 0.0)
    with _PREP_LOCK:
        if _PREPARED is not None:
            return KernelPreparation("ready", 0.0, detail=f"done earlier in this process ({_PREPARED.source})")
        from lunarloc.association.aot import aot_status

        t0 = time.perf_counter()
        status = aot_status()
        if status.startswith("loaded"):
            _PREPARED = KernelPreparation("aot", time.perf_counter() - t0, detail=status)
            logger.debug("association kernels: ahead-of-time module %s", status)
            return _PREPARED
        announce = threading.Timer(ANNOUNCE_AFTER_S, logger.warning, args=(
            "preparing the association kernels: numba compiles them on the first use after install (up to a "
            "minute, once; cached for later runs; `lunarloc warm-up` does it ahead of time) ...",))  # fmt: skip
        announce.daemon = True
        before = _compiled_signatures()
        announce.start()
        try:
            worked = warm_up()
        finally:
            announce.cancel()
        seconds = time.perf_counter() - t0
        compiled = _compiled_signatures() - before
        if worked == 0.0:  # warm_up ran earlier in this process (the online loop calls it)
            _PREPARED = KernelPreparation("ready", seconds, 0, "warmed up earlier in this process")
        elif compiled:
            _PREPARED = KernelPreparation("compiled", seconds, compiled, f"ahead-of-time module {status}")
            logger.warning("association kernels compiled in %.1f s (%d signatures; cached for later runs; "
                           "not counted as localization time)", seconds, compiled)  # fmt: skip
        else:
            _PREPARED = KernelPreparation("cache", seconds, 0, f"ahead-of-time module {status}")
            # announced above (a slow load, e.g. a busy machine): the closing line at the same level
            logger.log(logging.WARNING if seconds >= ANNOUNCE_AFTER_S else logging.INFO,"association kernels loaded from numba's cache in %.2f s (ahead-of-time module %s; "
                        "not counted as localization time)", seconds, status)  # fmt: skip
        return _PREPARED


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
    outer = getattr(_PREPARING, "active", False)
    _PREPARING.active = True  # its localize calls must not prepare the kernels again
    try:
        with jit_only() if jit else contextlib.nullcontext():
            for mode in Mode:
                for solver in Solver:
                    localize(ref, veh, LocalizationConfig(mode=mode, solver=solver))
    finally:
        _PREPARING.active = outer
    _WARM = "jit" if jit else (_WARM or "aot")
    return time.perf_counter() - t0


def build_kernels(folder=None, *, verbose: bool = False):
    """Compile every kernel signature :func:`warm_up` uses ahead of time
    (:func:`lunarloc.association.aot.build_aot` with this warm-up as the harvest)."""
    from lunarloc.association.aot import build_aot

    return build_aot(lambda: warm_up(jit=True), folder, verbose=verbose)
