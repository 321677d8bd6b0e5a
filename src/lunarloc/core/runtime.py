"""Process set-up that must happen before heavy imports: a writable numba cache.

The exact max-clique kernels are compiled with ``numba.njit(cache=True)``. numba stores its
cache next to the source (``association/__pycache__``) or in the user cache folder
(``~/.cache/numba``); when neither is writable (a read-only install with an unwritable
``$HOME``, as in some containers and CI runners) decorating the kernels raises
``RuntimeError: cannot cache function ...: no locator available`` and ``import lunarloc``
fails. :func:`ensure_numba_cache_dir` points ``NUMBA_CACHE_DIR`` at a per-user folder under
the system temporary directory in that case (caching keeps working), and warns when no
writable place exists at all.
"""

from __future__ import annotations

import os
import sys
import tempfile
import warnings
from pathlib import Path


def _writable(path: Path) -> bool:
    """True if a file can be created in `path` (creating the folder if needed)."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
        return True
    except OSError:
        return False


def _user_cache_dir() -> Path | None:
    if sys.platform.startswith("win") or sys.platform == "darwin":
        return None  # numba's appdirs rules differ there; leave its own locators in charge
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "numba"


def ensure_numba_cache_dir() -> str | None:
    """Set ``NUMBA_CACHE_DIR`` to a writable folder when numba's default places are not
    writable; returns the folder set (None when nothing needed changing)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    in_tree = Path(__file__).resolve().parent / "association" / "__pycache__"
    user = _user_cache_dir()
    if _writable(in_tree) or (user is None or _writable(user)):
        return None
    try:
        uid = os.getuid()
    except AttributeError:  # pragma: no cover - not POSIX
        uid = 0
    fallback = Path(tempfile.gettempdir()) / f"lunarloc-numba-cache-{uid}"
    if not _writable(fallback):
        warnings.warn(
            "lunarloc: no writable folder for numba's compilation cache (package folder, "
            f"{user} and {fallback} are read-only); set NUMBA_CACHE_DIR to a writable folder",
            RuntimeWarning,
            stacklevel=3,
        )
        return None
    os.environ["NUMBA_CACHE_DIR"] = str(fallback)
    numba = sys.modules.get("numba")
    if numba is not None:  # numba already imported: its config read the environment already
        numba.config.CACHE_DIR = str(fallback)
    return str(fallback)
