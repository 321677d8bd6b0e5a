"""Option checks shared by the commands: enum choices that list the valid values, numbers
that must be finite and inside a stated range. Each failure is a ConfigError (exit 2)."""

from __future__ import annotations

import enum
from collections.abc import Iterable

import typer

from lunarloc.core.errors import ConfigError
from lunarloc.core.validate import OPTION_WORDING, real

OVERWRITE_OPT = typer.Option(
    False, "--overwrite", help="Replace existing outputs (refused otherwise)."
)
ODOMETRY_METAVAR = "[visual|imu|record:NAME|ground-truth]"
"""--odometry / --source take a name or record:NAME, so they are not a closed choice; the
metavar lists them in --help all the same."""
JSON_STDOUT_OPT = typer.Option(
    False, "--json", help="Print one JSON object on stdout (nothing else)."
)
JSON_OUT_OPT = typer.Option(
    None, "--json-out", help="Also write the JSON object to this file.", dir_okay=False
)


def enum_value(value):
    """The string value of an Enum option (Typer passes the member), None unchanged."""
    return value.value if isinstance(value, enum.Enum) else value


def check_json_out(path, overwrite: bool) -> None:
    """Before any work: a ``--json-out`` file may be written (refused if it exists, unless
    --overwrite)."""
    if path is not None:
        from lunarloc.io.outputs import check_output_file

        check_output_file(path, overwrite, "JSON output")


def write_json_out(doc: dict, path, to_stdout: bool) -> None:
    """`doc` as one JSON line on stdout (``--json``) and/or into `path` (``--json-out``,
    atomically)."""
    import json

    text = json.dumps(doc)
    if to_stdout:
        typer.echo(text)
    if path is not None:
        from lunarloc.io.outputs import atomic_open

        with atomic_open(path, "w") as fh:
            fh.write(json.dumps(doc, indent=2) + "\n")


def choice(value: str, valid: type[enum.Enum] | Iterable[str], option: str) -> str:
    """`value` if it is one of `valid` (an Enum's values or strings), else ConfigError listing
    them."""
    values = (
        [m.value for m in valid]
        if isinstance(valid, type) and issubclass(valid, enum.Enum)
        else list(valid)
    )
    if value not in values:
        raise ConfigError(f"{option} must be one of {', '.join(map(str, values))}; got {value!r}")
    return value


def number(
    value: float | None,
    option: str,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    unit: str = "",
) -> float | None:
    """`value` (unchanged) if finite and within [lo, hi] (open ends with lo_open / hi_open); None
    passes. The check is :func:`lunarloc.core.validate.real`'s, worded for an option."""
    if value is None:
        return None
    real(
        value,
        option,
        lo,
        hi,
        lo_open=lo_open,
        hi_open=hi_open,
        unit=unit,
        error=ConfigError,
        wording=OPTION_WORDING,
    )
    return value


def positive(
    value: float | None, option: str, hi: float | None = None, unit: str = ""
) -> float | None:
    """Finite, > 0 and (when given) <= hi."""
    return number(value, option, 0.0, hi, lo_open=True, unit=unit)


def legacy_json_argv(argv: list[str]) -> list[str]:
    """``odometry ... --json FILE.json`` (the form before --json became the stdout flag of every
    command) rewritten as ``--json-out FILE.json``, with a deprecation warning on stderr."""
    out = list(argv)
    for i, a in enumerate(out[:-1]):
        if (
            a == "--json"
            and out[i + 1].lower().endswith(".json")
            and not out[i + 1].startswith("-")
        ):
            typer.secho(
                f"warning: `--json {out[i + 1]}` is deprecated: --json now prints JSON on stdout; "
                f"use --json-out {out[i + 1]}",
                err=True,
                fg=typer.colors.YELLOW,
            )
            out[i] = "--json-out"
    return out
