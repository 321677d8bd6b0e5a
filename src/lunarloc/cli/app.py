"""The `lunarloc` Typer application and its single error handler."""

from __future__ import annotations

import enum
import errno
import logging
import os
import sys
from typing import Optional

import typer

from lunarloc.core.errors import LunarLocError


class LogLevel(str, enum.Enum):
    """--log-level choices (-v is info, -vv debug, -q error; default warning)."""

    DEBUG = "debug"
    INFO = "info"
    WARNING = "warning"
    ERROR = "error"


app = typer.Typer(
    name="lunarloc",
    help="Rock-landmark global localization for planetary rovers (LunarLoc).",
    no_args_is_help=True,
    add_completion=True,  # --install-completion / --show-completion (bash, zsh, fish, PowerShell)
    pretty_exceptions_enable=False,
)


def console(stderr: bool = False):
    """A rich console for command output; 130 columns when not a terminal (CI logs,
    files), so that tables are not squeezed to the 80-column default. ``stderr=True``: the
    human-readable lines go to stderr (a command whose stdout carries ``--json``)."""
    import sys

    from rich.console import Console

    stream = sys.stderr if stderr else sys.stdout
    return Console(width=None if stream.isatty() else 130, stderr=stderr)


_COMMAND_MODULES = (
    "commands_core",
    "commands_data",
    "commands_sim",
    "commands_perception",
    "commands_run",
    "commands_campaign",
    "commands_setup",
    "commands_odometry",
    "commands_overhead",
)
"""Every command module; importing one registers its commands on `app`."""

_MODULES_OF_COMMAND = {
    "map": ("commands_core",),
    "localize": ("commands_core",),
    "bench": ("commands_core", "commands_run"),  # `bench pairs` and `bench loop`
    "info": ("commands_data",),
    "simulate": ("commands_sim",),
    "detect": ("commands_perception",),
    "run": ("commands_run",),
    "plot": ("commands_run",),
    "demo": ("commands_run",),
    "campaign": ("commands_campaign",),
    "warm-up": ("commands_setup",),
    "odometry": ("commands_odometry",),
    "score": ("commands_overhead",),
}
"""Where each top-level command lives, so that a call imports only its own module (the
renderer, OpenCV, fusion and the campaign engine stay out of `lunarloc localize`). A name
not listed here (``--help``, a typo, a command added without updating this table) imports
every module, so the table can only make a call faster, never hide a command; a test checks
that it matches what the modules register."""


def _register_commands(argv: list[str] | None = None) -> None:
    """Import the command modules: only the invoked command's when ``argv`` names a listed
    one (its first word not starting with ``-``), else all of them (help, listings)."""
    import importlib

    first = next((a for a in (argv or ()) if not a.startswith("-")), None)
    if (
        argv is not None
        and first in _MODULES_OF_COMMAND
        and "--help" not in argv[: argv.index(first)]
    ):
        names = _MODULES_OF_COMMAND[first]
    else:
        names = _COMMAND_MODULES
    for name in names:
        importlib.import_module(f"lunarloc.cli.{name}")


_STATE = {"debug": False}

EXIT_OK, EXIT_CHECK_FAILED, EXIT_USAGE, EXIT_INTERNAL, EXIT_INTERRUPTED = 0, 1, 2, 70, 130
"""Exit codes: 0 success, 1 a check or gate failed, 2 usage or input error, 70 internal
error (a bug: EX_SOFTWARE of sysexits.h), 130 interrupted (Ctrl-C, SIGTERM)."""


def _version(value: bool) -> None:
    if value:
        from lunarloc import __version__

        typer.echo(f"lunarloc {__version__}")
        raise typer.Exit(0)


def log_level(verbose: int, quiet: bool, level: str | None) -> int:
    """The logging level the options ask for (an explicit --log-level wins)."""
    if level is not None:
        return getattr(logging, level.upper())
    if quiet:
        return logging.ERROR
    return {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)


@app.callback()
def _root(
    debug: bool = typer.Option(
        False, "--debug", help="Show the Python traceback of any error (for bug reports)."
    ),
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
    verbose: int = typer.Option(
        0,
        "-v",
        "--verbose",
        count=True,
        help="More log lines on stderr: -v progress notes (INFO), -vv debugging.",
    ),
    quiet: bool = typer.Option(False, "-q", "--quiet", help="Only errors on stderr (no warnings)."),
    level: Optional[LogLevel] = typer.Option(
        None,
        "--log-level",
        case_sensitive=False,
        help="Log level on stderr (overrides -v/-q; default warning).",
    ),
) -> None:
    """Rock-landmark global localization for planetary rovers (LunarLoc)."""
    _STATE["debug"] = debug
    logging.getLogger().setLevel(
        log_level(verbose, quiet, level.value if level is not None else None)
    )


def _one_line(text: str, limit: int = 400) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _fail(msg: str, code: int, exc: BaseException | None = None) -> int:
    if exc is not None and (_STATE["debug"] or os.environ.get("LUNARLOC_DEBUG")):
        import traceback

        traceback.print_exception(type(exc), exc, exc.__traceback__, file=sys.stderr)
    typer.secho(_one_line(msg), err=True, fg=typer.colors.RED if code != EXIT_INTERRUPTED else None)
    return code


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the app; every failure becomes one line on stderr and an exit code
    (see EXIT_*); a traceback only with ``--debug`` (or LUNARLOC_DEBUG=1).

    SIGTERM keeps its default (immediate) action: a Python handler would wait for a long
    numba kernel to return. Outputs are written atomically, so a killed run leaves at most
    a hidden ``.NAME.tmp-*`` file, never a truncated output under its real name."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    # the default of every call (-v/-q/--log-level change it)
    logging.getLogger().setLevel(logging.WARNING)
    _STATE["debug"] = False
    args = sys.argv[1:] if argv is None else list(argv)
    _register_commands(args)
    if "odometry" in args and "--json" in args:
        from lunarloc.cli.checks import legacy_json_argv

        args = legacy_json_argv(args)
    return _run(args)


def _run(argv: list[str] | None) -> int:
    from lunarloc.core.errors import CheckFailedError, file_error

    try:
        # standalone_mode=False makes click *return* the code of a `typer.Exit` raised by a
        # command instead of calling sys.exit; dropping it turned every failed check into 0
        rv = app(args=argv, standalone_mode=False)
    except CheckFailedError as exc:
        return _fail(f"check failed: {exc}", EXIT_CHECK_FAILED, exc)
    except LunarLocError as exc:
        return _fail(f"error: {exc}", EXIT_USAGE, exc)
    except KeyboardInterrupt as exc:
        return _fail("interrupted; partial outputs removed", EXIT_INTERRUPTED, exc)
    except typer.Abort as exc:
        # click turns KeyboardInterrupt *and* EOFError into Abort; only the first is an interruption
        cause = exc.__cause__ or exc.__context__
        if isinstance(cause, KeyboardInterrupt) or cause is None:
            return _fail("interrupted; partial outputs removed", EXIT_INTERRUPTED, exc)
        return _internal(cause)
    except typer.Exit as exc:
        return exc.exit_code
    except OSError as exc:
        if exc.errno is None:
            return _internal(exc)
        write = exc.errno in (errno.ENOSPC, errno.EROFS, errno.EDQUOT)
        what = file_error(exc.filename or "(unnamed file)", exc, "write" if write else "read")
        return _fail(
            f"error: {what}",
            EXIT_USAGE,
            exc,
        )
    except MemoryError as exc:
        return _fail(
            "error: out of memory (the input is larger than this machine can hold)",
            EXIT_INTERNAL,
            exc,
        )
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else EXIT_USAGE)
    except Exception as exc:
        # usage errors (bad option, unknown command): click's ClickException, which newer
        # typer releases vendor; recognised by its interface rather than its module
        if callable(getattr(exc, "show", None)) and isinstance(
            getattr(exc, "exit_code", None), int
        ):
            exc.show()
            return exc.exit_code
        return _internal(exc)
    if rv == EXIT_INTERRUPTED:  # typer turns KeyboardInterrupt into Exit(130), returned here
        return _fail("interrupted; partial outputs removed", EXIT_INTERRUPTED)
    return rv if isinstance(rv, int) else 0


def _internal(exc: BaseException) -> int:
    return _fail(
        f"internal error: {type(exc).__name__}: {exc} (rerun with --debug for the traceback)",
        EXIT_INTERNAL,
        exc,
    )


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
