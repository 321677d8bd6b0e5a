"""Compile every numba kernel once, so that no localization call pays for it.

The association kernels are compiled with ``cache=True``: the first process that runs them
compiles (seconds) and writes numba's cache; later processes load it (milliseconds).
``warm_up()`` runs them on a tiny synthetic pair so that this happens at a chosen moment:
``make`` calls ``lunarloc warm-up`` after installing, and :class:`lunarloc.online.loop.LoopState`
calls it before its stage timers start, so compile time is never counted as run time.

A user who installed the wheel and never ran ``lunarloc warm-up`` is not left waiting in
silence either: the first :func:`~lunarloc.localization.localize.localize` of a process
prepares the kernels *before* its stage timers start
(:func:`lunarloc.association.aot.prepare_kernels`), and logs (WARNING, which the CLI shows)
a line when that takes more than a second and another saying how long it took and whether
numba compiled or only loaded its cache. Neither path needs ``numba.pycc`` (deprecated by
numba): the ahead-of-time module is an optional speed-up on top.
"""

from __future__ import annotations

__all__ = ["warm_up", "build_kernels", "prepare_kernels"]


def warm_up(force: bool = False, jit: bool = False) -> float:
    """Compile (or load from the cache) every association kernel, in every mode and solver.
    Returns the seconds it took (about 0 once done in this process).

    Where the ahead-of-time kernels are built (:mod:`lunarloc.association.aot`) this only
    loads them; ``jit=True`` runs numba's JIT path even then, compiling into numba's cache
    (``lunarloc warm-up``: the fallback for argument types the build does not hold)."""
    from lunarloc.localization.localize import warm_kernels

    return warm_kernels(force=force, jit=jit)


def prepare_kernels():
    """The kernels ready without compiling in a timed stage (what the first ``localize`` of a
    process does; the CLI calls it itself to report it): a
    :class:`~lunarloc.association.aot.KernelPreparation`."""
    from lunarloc.localization.localize import prepare_kernels as prepare

    return prepare()


def build_kernels(folder=None, *, verbose: bool = False):
    """Compile every kernel signature :func:`warm_up` uses ahead of time
    (:func:`lunarloc.association.aot.build_aot` with this warm-up as the harvest)."""
    from lunarloc.association.aot import build_aot

    return build_aot(lambda: warm_up(jit=True), folder, verbose=verbose)
