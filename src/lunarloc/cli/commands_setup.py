"""`lunarloc warm-up`: build numba's cache now rather than at the first localization."""

from __future__ import annotations

import typer

from lunarloc.cli.app import app


@app.command("warm-up")
def warm_up_cmd() -> None:
    """Compile (or load from numba's cache) every association kernel; `make` runs it after
    installing, so the first real call starts fast."""
    from lunarloc.warmup import warm_up

    s = warm_up(force=True)
    typer.echo(f"association kernels ready in {s:.1f} s")
