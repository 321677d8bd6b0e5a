"""Safe writing of outputs: checked before any computation, written to a temporary name in
the same folder and renamed into place, never overwriting unless asked.

* :func:`check_output_file` / :func:`check_output_dir` run *before* a command computes
  anything: the path must not be a folder (or a file, for a folder output), its parent must
  be (or become) a writable folder, and an existing output is refused unless
  ``overwrite=True``. A run folder that holds a previous run is refused, or with
  ``overwrite=True`` cleared of the previous run's files (only the names a run writes; other
  files are left alone, so a figure of an older run cannot be mistaken for this one's).
* :func:`atomic_path` yields a temporary path next to the target (``.NAME.tmp-XXXX.SUFFIX``,
  so writers that pick the format by suffix still work) and renames it over the target when
  the block ends without an exception. On any exception, Ctrl-C included, the temporary file
  is removed and the target is untouched. After a SIGKILL only a hidden ``.tmp-`` file can be
  left, never a truncated file under the real name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from lunarloc.core.errors import OutputError, file_error

__all__ = [
    "check_output_file",
    "check_output_dir",
    "atomic_path",
    "atomic_open",
    "RUN_FILES",
    "remove_partial_outputs",
]

RUN_FILES = (
    "trajectory.tum",
    "trajectory_online.tum",
    "trajectory_odometry.tum",
    "trajectory_groundtruth.tum",
    "attempts.csv",
    "attempts.json",
    "vehicle_map.csv",
    "vehicle_map_odometry.csv",
    "reference_map.csv",
    "rocks.csv",
    "example_frame.npz",
    "config.json",
    "summary.json",
    "map.png",
    "error.png",
    "frame.png",
)
"""Files a run folder (``lunarloc run``, ``lunarloc demo``) holds; ``summary.json`` marks one."""


def remove_partial_outputs(folder: str | os.PathLike, names=RUN_FILES) -> list[str]:
    """Remove from `folder` the outputs `names` and any temporary file of an atomic write
    (``.NAME.tmp-*``): what an interrupted command wrote. Call it only for a folder that held
    none of `names` before the command (``check_output_dir`` cleared or refused them).
    Returns the names removed."""
    d = Path(folder)
    removed = []
    if not d.is_dir():
        return removed
    for p in d.iterdir():
        if p.name in names or (p.name.startswith(".") and ".tmp-" in p.name):
            with contextlib.suppress(OSError):
                if p.is_file() or p.is_symlink():
                    p.unlink()
                    removed.append(p.name)
    return removed


def _writable_dir(d: Path, target: Path) -> None:
    """`d` (the target's parent) must be a writable folder, or creatable."""
    probe = d
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise OutputError(f"{target}: cannot create it, {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise OutputError(f"{target}: folder {probe} is not writable")


def check_output_file(
    path: str | os.PathLike, overwrite: bool = False, what: str = "output"
) -> Path:
    """Check, before computing, that `path` can be written as a file; returns it as a Path."""
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{p}: is a folder; give a file name for the {what}")
    if p.exists() or p.is_symlink():
        if not overwrite:
            raise OutputError(f"{p}: exists; pass --overwrite to replace it")
        if not p.is_file():
            raise OutputError(f"{p}: exists and is not a regular file")
    _writable_dir(p.parent if str(p.parent) else Path("."), p)
    return p


def check_output_dir(
    path: str | os.PathLike,
    overwrite: bool = False,
    names=RUN_FILES,
    marker: str | None = "summary.json",
) -> Path:
    """Check, before computing, that folder `path` can receive outputs named `names`.

    Refused: `path` is a file; its parent is not writable; it holds any of `names` (a
    previous run) and `overwrite` is False. With `overwrite`, those files are removed now
    (and only those). `marker` names the file whose presence marks a previous run (for the
    message)."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise OutputError(f"{p}: is a file; expected an output folder")
    if p.is_dir():
        if not os.access(p, os.W_OK | os.X_OK):
            raise OutputError(f"{p}: folder is not writable")
        old = [n for n in names if (p / n).exists()]
        if old and not overwrite:
            kind = "a previous run" if marker and marker in old else "earlier outputs"
            raise OutputError(
                f"{p}: holds {kind} ({', '.join(old[:3])}{', ...' if len(old) > 3 else ''}); "
                "pass --overwrite to replace it"
            )
        for n in old:
            try:
                (p / n).unlink()
            except OSError as exc:
                raise file_error(p / n, exc, "write") from None
    else:
        _writable_dir(p, p)
    return p


def make_dir(path: str | os.PathLike) -> Path:
    """``mkdir -p`` with our error for a file in the way or a permission problem."""
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        if isinstance(exc, FileExistsError):
            raise OutputError(f"{p}: is a file; expected an output folder") from None
        raise file_error(p, exc, "write") from None
    return p


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path next to `path`; on success rename it to `path` (replacing it),
    on any exception remove it. The parent folder is created if needed."""
    target = Path(path)
    if target.is_dir() or (target.exists() and not target.is_file()):
        # renaming over it would replace a folder or a device node (/dev/null as root)
        raise OutputError(f"{target}: exists and is not a regular file")
    make_dir(target.parent if str(target.parent) else Path("."))
    try:
        fd, tmp = tempfile.mkstemp(
            prefix=f".{target.stem}.tmp-", suffix=target.suffix, dir=target.parent
        )
    except OSError as exc:
        raise file_error(target, exc, "write") from None
    tmp_path = Path(tmp)
    try:
        os.close(fd)
        yield tmp_path
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp creates 0600
        os.replace(tmp_path, target)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp_path.unlink()
        if (
            isinstance(exc, OSError)
            and exc.errno is not None
            and not isinstance(exc, FileNotFoundError)
        ):
            raise file_error(target, exc, "write") from None
        raise


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", **kwargs):
    """Open a temporary file next to `path` for writing; renamed to `path` when the block
    ends without an exception (see :func:`atomic_path`)."""
    if "r" in mode or "a" in mode:
        raise ValueError("atomic_open is for writing ('w' or 'wb')")
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as fh:
            yield fh


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Atomically write `text` (UTF-8) to `path`."""
    with atomic_open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    return Path(path)
