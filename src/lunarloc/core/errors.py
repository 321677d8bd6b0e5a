"""One small exception hierarchy for the whole library.

Library code raises these; only the CLI turns them into messages and exit codes.
"""

from __future__ import annotations


class LunarLocError(Exception):
    """Base class of every error lunarloc raises on purpose."""


class InputError(LunarLocError, ValueError):
    """Input data is malformed, empty, non-finite or degenerate."""


class FileFormatError(InputError):
    """A file (CSV, map, archive) cannot be parsed; the message names the file and where."""


class ArchiveError(FileFormatError):
    """A `.lac` archive is unreadable, truncated, or lacks a required member."""


class DegenerateGeometryError(InputError):
    """Points are too few, coincident or collinear to determine a rigid transform."""


class ConfigError(LunarLocError, ValueError):
    """A configuration value is out of its valid range."""


class DependencyError(LunarLocError, ImportError):
    """An optional dependency is missing; the message says what to install."""


class MissingFileError(FileFormatError, FileNotFoundError):
    """An input path does not exist (still a FileNotFoundError for callers that catch that)."""

    def __str__(self) -> str:
        return str(self.args[0]) if len(self.args) == 1 else super().__str__()


class NotAFileError(FileFormatError):
    """An input path is a directory (or a device, a socket) where a regular file is expected."""


class UnreadableFileError(FileFormatError):
    """An input file exists but cannot be read (permissions, I/O error)."""


class LimitError(InputError):
    """An input exceeds a stated size limit (member, field, row, shape); see docs/robustness.md."""


class MissingColumnError(FileFormatError, KeyError):
    """A table lacks a column (still a KeyError for callers that catch that)."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class CheckFailedError(LunarLocError):
    """A check or gate did not pass (the CLI exits 1, not 2)."""


class OutputError(LunarLocError):
    """An output path cannot be written: exists (without overwrite), is a folder, has no
    writable parent folder, or the disk is full."""


def file_error(path, exc: OSError, action: str = "read") -> LunarLocError:
    """Our error for an OSError raised while `action`-ing `path` (one line, names the path)."""
    import errno

    if isinstance(exc, FileNotFoundError):
        return MissingFileError(f"{path}: no such file")
    if isinstance(exc, IsADirectoryError):
        return NotAFileError(f"{path}: is a folder, expected a file")
    if isinstance(exc, NotADirectoryError):
        return MissingFileError(f"{path}: a parent of this path is a file, not a folder")
    if isinstance(exc, PermissionError):
        cls = OutputError if action == "write" else UnreadableFileError
        return cls(f"{path}: permission denied ({action})")
    if exc.errno == errno.ENOSPC:
        return OutputError(f"{path}: no space left on device")
    cls = OutputError if action == "write" else UnreadableFileError
    return cls(f"{path}: cannot {action} ({exc.strerror or exc})")


def require(module: str, extra: str, hint: str | None = None):
    """Import an optional dependency lazily, or raise DependencyError with an install hint."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on environment
        msg = f"'{module}' is required for this feature: pip install 'lunarloc[{extra}]'"
        if hint:
            msg += f" ({hint})"
        raise DependencyError(msg) from exc


def import_cv2():
    """OpenCV's ``cv2``, or DependencyError with the install hint. OpenCV is not a hard
    dependency (the ``opencv`` extra): any one of its wheels works, and an environment that
    pins one (the LAC leaderboard pins opencv-python) must not get a second."""
    import importlib
    import sys

    cv2 = sys.modules.get("cv2")  # the detector asks about a hundred times a frame
    if cv2 is not None:
        return cv2
    try:
        return importlib.import_module("cv2")
    except ImportError as exc:
        raise DependencyError(
            "OpenCV (cv2) is required for images (segmentation, stereo, visual odometry): "
            "pip install 'lunarloc[opencv]', or keep the one OpenCV wheel your environment "
            "already has (opencv-python, opencv-python-headless or a contrib one)"
        ) from exc
