"""The `lunarloc` Typer application and its single error handler."""

from __future__ import annotations

import logging
import sys

import typer

from lunarloc.errors import LunarLocError

app = typer.Typer(
    name="lunarloc",
    help="Rock-landmark global localization for planetary rovers (LunarLoc).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def console():
    """A rich console for command output; 130 columns when not a terminal (CI logs,
    files), so that tables are not squeezed to the 80-column default."""
    import sys

    from rich.console import Console

    return Console(width=None if sys.stdout.isatty() else 130)


def _register_commands() -> None:
    # Each command group lives in its own module; importing registers it on `app`.
    from lunarloc.cli import commands_core  # noqa: F401
    from lunarloc.cli import commands_data  # noqa: F401
    from lunarloc.cli import commands_sim  # noqa: F401
    from lunarloc.cli import commands_perception  # noqa: F401
    from lunarloc.cli import commands_run  # noqa: F401
    from lunarloc.cli import commands_overhead  # noqa: F401


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the app, turning library errors into one-line messages."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    _register_commands()
    try:
        # standalone_mode=False makes click *return* the code of a `typer.Exit` raised by a
        # command instead of calling sys.exit; dropping it turned every failed check into 0
        rv = app(args=argv, standalone_mode=False)
    except LunarLocError as exc:
        typer.secho(f"error: {exc}", err=True, fg=typer.colors.RED)
        return 2
    except FileNotFoundError as exc:
        typer.secho(f"error: file not found: {exc.filename or exc}", err=True, fg=typer.colors.RED)
        return 2
    except (typer.Abort, KeyboardInterrupt):
        typer.secho("aborted", err=True)
        return 130
    except typer.Exit as exc:
        return exc.exit_code
    except Exception as exc:
        # usage errors (bad option, unknown command): click's ClickException, which newer
        # typer releases vendor; recognised by its interface rather than its module
        if callable(getattr(exc, "show", None)) and isinstance(getattr(exc, "exit_code", None), int):
            exc.show()
            return exc.exit_code
        raise
    return rv if isinstance(rv, int) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
