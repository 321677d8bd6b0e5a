"""How the association kernels are compiled and loaded: ahead of time when built, numba's
JIT (with its on-disk cache) otherwise.

A warm ``lunarloc localize`` used to spend about 0.45 s of its 1.2 s on numba alone, even
with every kernel in numba's cache: ``import numba`` (0.17 s) and, at the first call, the
set-up of numba's CPU target (its typing and lowering registries, ~0.25 s) that precedes
loading any cached kernel. ``lunarloc warm-up`` (run by ``make``) therefore also compiles
the kernels *ahead of time*, with ``numba.pycc``, into one extension module next to this
file (``_aot_kernels*.so`` and its table ``_aot_kernels.json``); a process that finds it
calls the compiled functions directly and never imports numba.

:func:`njit` replaces ``numba.njit`` in the kernel modules. It returns a :class:`Kernel`
that, when called from Python:

1. uses the ahead-of-time function compiled for exactly these argument types (dtype, number
   of dimensions, C-contiguous, writable) if the module exists and was built from the
   current source of every kernel module (a SHA-256 of each file is recorded at build time
   and compared at the first call: an edited kernel never runs stale machine code);
2. otherwise imports numba and calls ``numba.njit(**options)(func)``, exactly as before (the
   kernels of every kernel module are made numba dispatchers at once, so that kernels
   calling kernels compile as before). A missing, stale or unloadable build, an argument
   type it was not built for, or ``LUNARLOC_AOT=0`` all take this path.

The build harvests the signatures to compile from the warm-up it is given
(:func:`lunarloc.localization.warmup.warm_up`: every
mode and solver), run on the JIT path in the building process, and compiles each with the
GIL released (as ``nogil=True`` kernels do under the JIT), for the host CPU.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "njit",
    "Kernel",
    "jit_only",
    "aot_status",
    "build_aot",
    "AotBuild",
    "AOT_MODULE",
    "prepare_kernels",
    "KernelPreparation",
    "exercising",
]

AOT_MODULE = "_aot_kernels"
"""Name of the ahead-of-time extension module (in this package)."""
AOT_FORMAT = 1
"""Version of the table layout in ``_aot_kernels.json``."""
_HERE = Path(__file__).resolve().parent
logger = logging.getLogger(__name__)

_REGISTRY: list["Kernel"] = []
_LOCK = threading.RLock()
_STATE: dict = {"table": None, "reason": "not loaded yet", "jit_only": 0}


def njit(*args, **options):
    """Drop-in for ``numba.njit`` (``@njit`` or ``@njit(**options)``) that defers numba to the
    first call that needs it (see the module docstring)."""
    if args and callable(args[0]) and not options:
        return Kernel(args[0], {})
    if args:
        raise TypeError("njit: signatures are not supported here; pass options only")
    return lambda func: Kernel(func, options)


class Kernel:
    """A numba kernel whose compilation is deferred; calls go to the ahead-of-time build when
    it holds this argument signature, else to ``numba.njit(**options)(func)``. Attributes of
    the numba dispatcher (``signatures``, ``py_func``, ...) are forwarded to it."""

    def __init__(self, func, options: dict):
        self.func = func
        self.options = dict(options)
        self.key = f"{func.__module__}.{func.__qualname__}"
        self._dispatcher = None
        self._aot = None  # tuple of (arg checks, compiled function), resolved at the first call
        self.__name__ = func.__name__
        self.__qualname__ = func.__qualname__
        self.__doc__ = func.__doc__
        self.__module__ = func.__module__
        self.__wrapped__ = func
        with _LOCK:
            _REGISTRY.append(self)

    def __repr__(self) -> str:
        return f"<lunarloc kernel {self.key}>"

    @property
    def dispatcher(self):
        """The numba dispatcher (imports numba and makes every kernel one, once)."""
        if self._dispatcher is None:
            _materialize()
        return self._dispatcher

    def __getattr__(self, name):  # only for attributes not found on the Kernel itself
        if name.startswith("__") or name in ("_dispatcher", "_aot", "func", "options", "key"):
            raise AttributeError(name)
        return getattr(self.dispatcher, name)

    def __call__(self, *args):
        entries = self._aot
        if entries is None:
            entries = self._aot = _aot_entries(self.key)
        for checks, fn in entries:
            if _matches(checks, args) and not _STATE["jit_only"]:
                return fn(*args)
        return self.dispatcher(*args)


def _materialize() -> None:
    """Import numba and make every registered kernel a numba dispatcher; the kernel modules'
    globals then name the dispatchers, so a kernel calling another compiles as under
    ``numba.njit`` (numba cannot type a :class:`Kernel`). Kernels registered later (a kernel
    module imported after this) are made dispatchers at their first call through here."""
    with _LOCK:
        fresh = [k for k in _REGISTRY if k._dispatcher is None]
        if not fresh:
            return
        import numba

        for k in fresh:
            k._dispatcher = numba.njit(**k.options)(k.func)
        for mod_name in {k.func.__module__ for k in fresh}:
            mod = sys.modules.get(mod_name)
            if mod is None:
                continue
            for name, value in list(vars(mod).items()):
                if isinstance(value, Kernel) and value._dispatcher is not None:
                    setattr(mod, name, value._dispatcher)


@contextmanager
def jit_only():
    """Within this block kernels run on numba's JIT path even where an ahead-of-time build
    exists (``lunarloc warm-up`` fills numba's cache this way, for the fallback)."""
    with _LOCK:
        _STATE["jit_only"] += 1
    try:
        _materialize()
        yield
    finally:
        with _LOCK:
            _STATE["jit_only"] -= 1


# --------------------------------------------------------------------------- argument checks

_SCALARS = {
    "i8": (int, np.int64),
    "i4": (np.int32,),
    "f8": (float, np.float64),
    "f4": (np.float32,),
    "b1": (bool, np.bool_),
}
"""Scalar codes of the table and the Python types numba types the same way (``int`` is
typed int64 and ``float`` float64; ``bool`` is not an ``int`` here: exact types are checked)."""


def _compile_checks(spec: list) -> tuple | None:
    """A table entry's argument spec as fast checks: (dtype, ndim) for an array, a tuple of
    exact types for a scalar. None if the spec holds something unknown."""
    out = []
    for s in spec:
        if s[0] == "array":
            out.append((np.dtype(s[1]), int(s[2])))
        elif s[0] == "scalar" and s[1] in _SCALARS:
            out.append(_SCALARS[s[1]])
        else:
            return None
    return tuple(out)


def _matches(checks: tuple, args: tuple) -> bool:
    if len(args) != len(checks):
        return False
    for a, c in zip(args, checks):
        if type(c[0]) is type:  # scalar: exact Python/NumPy types
            if type(a) not in c:
                return False
        else:
            if type(a) is not np.ndarray or a.ndim != c[1] or a.dtype != c[0]:
                return False
            f = a.flags
            if not (f.c_contiguous and f.writeable and f.aligned):
                return False
    return True


# --------------------------------------------------------------------------- loading


def _table_path(folder: Path) -> Path:
    return folder / f"{AOT_MODULE}.json"


def _sources() -> dict[str, str]:
    """SHA-256 of the source file of every module that defines kernels, by module name."""
    out = {}
    for mod_name in sorted({k.func.__module__ for k in _REGISTRY}):
        path = getattr(sys.modules.get(mod_name), "__file__", None)
        if path is None:
            continue
        out[mod_name] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return out


def _load_table(folder: Path = _HERE) -> dict:
    """{kernel key: ((checks, function), ...)} of the ahead-of-time build in `folder`, or {}
    (with ``_STATE["reason"]`` saying why) when it is absent, stale, disabled or unloadable."""
    if os.environ.get("LUNARLOC_AOT", "1").strip().lower() in ("0", "false", "no", "off"):
        _STATE["reason"] = "disabled by LUNARLOC_AOT=0"
        return {}
    path = _table_path(folder)
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        _STATE["reason"] = "not built (run `lunarloc warm-up`)"
        return {}
    except (OSError, ValueError) as exc:
        _STATE["reason"] = f"unreadable table {path.name}: {exc}"
        return {}
    if not isinstance(meta, dict) or meta.get("format") != AOT_FORMAT:
        _STATE["reason"] = f"{path.name}: unknown format"
        return {}
    current, built = _sources(), meta.get("sources") or {}
    if built != current:
        changed = sorted(k for k in set(current) | set(built) if current.get(k) != built.get(k))
        _STATE["reason"] = (
            f"stale: built from other sources of {', '.join(changed)} (run `lunarloc warm-up`)"
        )
        return {}
    try:
        import importlib.util

        spec = importlib.util.spec_from_file_location(
            f"{__package__}.{AOT_MODULE}", folder / str(meta.get("module"))
        )
        if spec is None or spec.loader is None:
            raise ImportError(f"not an extension module: {meta.get('module')}")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        if mod.aot_build_id() != meta.get("build_id"):  # a module from another build than the table
            raise ImportError("build id differs from the table's")
    except (
        Exception
    ) as exc:  # missing, broken, foreign or mismatched binary: the JIT path still works
        _STATE["reason"] = f"cannot load {meta.get('module')}: {type(exc).__name__}: {exc}"
        return {}
    table: dict = {}
    for key, entries in (meta.get("kernels") or {}).items():
        for e in entries:
            checks = _compile_checks(e.get("args", []))
            fn = getattr(mod, str(e.get("export")), None)
            if checks is not None and fn is not None:
                table.setdefault(key, []).append((checks, fn))
    _STATE["reason"] = f"loaded ({sum(len(v) for v in table.values())} compiled signatures)"
    return {k: tuple(v) for k, v in table.items()}


def _aot_entries(key: str) -> tuple:
    with _LOCK:
        if _STATE["table"] is None:
            _STATE["table"] = _load_table()
        return _STATE["table"].get(key, ())


def aot_status() -> str:
    """One line: whether the ahead-of-time kernels are in use in this process, and if not why."""
    with _LOCK:
        if _STATE["table"] is None:
            _STATE["table"] = _load_table()
        return _STATE["reason"]


# --------------------------------------------------------------------------- first use

ANNOUNCE_AFTER_S = 1.0
"""A kernel preparation still running after this many seconds is announced (WARNING)."""
_PREP_LOCK = threading.Lock()
_PREP: dict = {"done": None}
_EXERCISING = threading.local()


@dataclass(frozen=True)
class KernelPreparation:
    """What :func:`prepare_kernels` did in this process: ``source`` is ``"aot"`` (the
    ahead-of-time module was loaded: nothing to compile), ``"cache"`` (numba loaded every
    kernel from its on-disk cache), ``"compiled"`` (numba compiled ``compiled`` kernel
    signatures, cached on disk for later processes) or ``"ready"`` (nothing left to do in this
    process); ``seconds`` is the wall time it took, never part of a localization's time."""

    source: str
    seconds: float
    compiled: int = 0
    detail: str = ""

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "seconds": round(self.seconds, 3),
            "compiled": self.compiled,
            "detail": self.detail,
        }


@contextmanager
def exercising():
    """Marks the calls made while exercising the kernels (they must not prepare them again)."""
    outer = getattr(_EXERCISING, "active", False)
    _EXERCISING.active = True
    try:
        yield
    finally:
        _EXERCISING.active = outer


def _compiled_signatures() -> int:
    """How many kernel signatures numba compiled (cache misses) in this process so far."""
    with _LOCK:
        kernels = [k for k in _REGISTRY if k._dispatcher is not None]
    return sum(sum(k._dispatcher.stats.cache_misses.values()) for k in kernels)


def prepare_kernels(exercise) -> KernelPreparation:
    """Once a process, before any timed stage: load the ahead-of-time module if it is built,
    else call ``exercise()`` (it runs every kernel on a small problem, so that numba loads
    them from its cache or compiles them into it; it returns the seconds it worked, 0.0
    when there was nothing left to do). Later calls return at once (``"ready"``).

    Neither path needs ``numba.pycc``. Logs a WARNING when the work is still going after
    :data:`ANNOUNCE_AFTER_S` (a compile: the first use after an install) and a closing line
    with the seconds it took (WARNING after a compile or an announced load, else INFO)."""
    if getattr(_EXERCISING, "active", False):
        return KernelPreparation("ready", 0.0, detail="inside the kernel exercise")
    with _PREP_LOCK:
        done = _PREP["done"]
        if done is not None:
            return KernelPreparation(
                "ready", 0.0, detail=f"done earlier in this process ({done.source})"
            )
        t0 = time.perf_counter()
        status = aot_status()
        if status.startswith("loaded"):
            _PREP["done"] = KernelPreparation("aot", time.perf_counter() - t0, detail=status)
            logger.debug("association kernels: ahead-of-time module %s", status)
            return _PREP["done"]
        announce = threading.Timer(
            ANNOUNCE_AFTER_S,
            logger.warning,
            args=(
                "preparing the association kernels: numba compiles them on the first use after "
                "install (up to a minute, once; cached for later runs; `lunarloc warm-up` does it "
                "ahead of time) ...",
            ),
        )
        announce.daemon = True
        before = _compiled_signatures()
        announce.start()
        try:
            with exercising():
                worked = exercise()
        finally:
            announce.cancel()
        seconds = time.perf_counter() - t0
        compiled = _compiled_signatures() - before
        why = f"ahead-of-time module {status}"
        if worked == 0.0:  # exercised earlier in this process (the online loop warms up itself)
            done = KernelPreparation("ready", seconds, 0, "warmed up earlier in this process")
        elif compiled:
            done = KernelPreparation("compiled", seconds, compiled, why)
            logger.warning(
                "association kernels compiled in %.1f s (%d signatures; cached for later runs; not "
                "counted as localization time)",
                seconds,
                compiled,
            )
        else:
            done = KernelPreparation("cache", seconds, 0, why)
            # announced above (a slow load, a busy machine): the closing line at the same level
            logger.log(
                logging.WARNING if seconds >= ANNOUNCE_AFTER_S else logging.INFO,
                "association kernels loaded from numba's cache in %.2f s (%s; not counted as "
                "localization time)",
                seconds,
                why,
            )
        _PREP["done"] = done
        return done


# --------------------------------------------------------------------------- building


@dataclass
class AotBuild:
    """What :func:`build_aot` did: the module written (None if not built), how many kernel
    signatures it holds, the seconds it took, and why not where it was not built."""

    path: Path | None
    signatures: int = 0
    seconds: float = 0.0
    reason: str = ""
    skipped: list = field(default_factory=list)


def _spec_of(sig) -> list | None:
    """A numba argument signature as the table's spec, or None when it holds a type the
    table cannot check cheaply (such signatures stay on the JIT path)."""
    from numba import types
    from numba.np.numpy_support import as_dtype

    spec = []
    for t in sig:
        if isinstance(t, types.Array):
            if t.layout != "C" or not t.mutable or not t.aligned:
                return None
            spec.append(["array", as_dtype(t.dtype).str, t.ndim])
        elif isinstance(t, types.Boolean):
            spec.append(["scalar", "b1"])
        elif isinstance(t, (types.Integer, types.Float)) and as_dtype(t).str[1:] in _SCALARS:
            spec.append(["scalar", as_dtype(t).str[1:]])
        else:
            return None
    return spec


def _host_cpu() -> str:
    import llvmlite.binding as llvm

    return llvm.get_host_cpu_name()


def build_aot(exercise, folder: Path | None = None, *, verbose: bool = False) -> AotBuild:
    """Compile every kernel signature that ``exercise()`` uses (run once on the JIT path to harvest
    them; :func:`lunarloc.localization.warmup.build_kernels` passes its warm-up), ahead of time,
    into ``folder`` (default: this package's folder, where :func:`njit` looks). Needs a C
    compiler and Python's headers; raises ``OSError``/``RuntimeError`` style errors from the
    toolchain, which the caller reports (the JIT path keeps working without the build)."""
    import secrets
    import shutil
    import tempfile
    import time
    import warnings

    t0 = time.perf_counter()
    folder = Path(folder) if folder is not None else _HERE
    exercise()  # every kernel signature the pipeline uses, on the JIT path (once a process)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba.pycc is deprecated (still shipped and working)
        from numba.core.compiler import Flags
        from numba.pycc import CC
        import numba.pycc.compiler as pycc_compiler

    class _NoGilFlags(Flags):
        """The exported wrappers release the GIL around the native call, as ``nogil=True``
        does under the JIT (the yaw-bin sweep runs kernels on several threads)."""

        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            self.release_gil = True

    kernels: dict[str, list] = {}
    skipped = []
    with tempfile.TemporaryDirectory(prefix="lunarloc-aot-") as tmp:
        cc = CC(AOT_MODULE)
        cc.output_dir = tmp
        cc.verbose = verbose
        cc.target_cpu = _host_cpu()
        build_id = secrets.randbits(62)  # ties the module to its table (see _load_table)
        ns: dict = {}
        exec(f"def aot_build_id():\n    return {build_id}\n", ns)
        cc.export("aot_build_id", "i8()")(ns["aot_build_id"])
        n = 0
        for k in _REGISTRY:
            for sig in k.dispatcher.signatures:
                spec = _spec_of(sig)
                if spec is None:
                    skipped.append(f"{k.key}{sig}")
                    continue
                export = f"k{n}_{k.func.__name__.strip('_')}"
                cc.export(export, k.dispatcher.overloads[sig].signature)(k.func)
                kernels.setdefault(k.key, []).append(
                    {"export": export, "args": spec, "numba_signature": str(sig)}
                )
                n += 1
        if n == 0:
            return AotBuild(
                None, 0, time.perf_counter() - t0, "no kernel signature to compile", skipped
            )
        saved = pycc_compiler.Flags
        pycc_compiler.Flags = _NoGilFlags
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cc.compile()
        finally:
            pycc_compiler.Flags = saved
        built = [
            p
            for p in Path(tmp).iterdir()
            if p.name.startswith(AOT_MODULE) and p.suffix in (".so", ".pyd")
        ]
        if len(built) != 1:
            raise RuntimeError(
                f"numba.pycc wrote {[p.name for p in Path(tmp).iterdir()]}, expected one "
                f"{AOT_MODULE} module"
            )
        import numba

        meta = {
            "format": AOT_FORMAT,
            "module": built[0].name,
            "build_id": build_id,
            "sources": _sources(),
            "numba": numba.__version__,
            "python": sys.version.split()[0],
            "target_cpu": cc.target_cpu,
            "kernels": kernels,
        }
        folder.mkdir(parents=True, exist_ok=True)
        table = _table_path(folder)
        table.unlink(missing_ok=True)  # no table names a half-written module
        for old in folder.glob(f"{AOT_MODULE}.*"):
            if old.suffix in (".so", ".pyd"):
                old.unlink()
        target = folder / built[0].name
        staged = folder / f".{built[0].name}.tmp-{os.getpid()}"
        shutil.copyfile(built[0], staged)
        os.replace(staged, target)
        staged = folder / f".{table.name}.tmp-{os.getpid()}"
        staged.write_text(json.dumps(meta, indent=1))
        os.replace(staged, table)
    with _LOCK:
        if folder == _HERE:
            _STATE["table"] = None  # reload on the next call
            for k in _REGISTRY:
                k._aot = None
    return AotBuild(target, n, time.perf_counter() - t0, "", skipped)
