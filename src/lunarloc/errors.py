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
