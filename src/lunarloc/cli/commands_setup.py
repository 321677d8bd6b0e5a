"""`lunarloc warm-up`: build numba's cache and the ahead-of-time kernels now rather than at
the first localization."""

from __future__ import annotations

import typer

from lunarloc.cli.app import app


@app.command("warm-up")
def warm_up_cmd(
    aot: bool = typer.Option(
        True,
        "--aot/--no-aot",
        help="Also compile the kernels ahead of time (needs a C compiler; a process that finds "
        "them neither imports numba nor waits for it). Without them numba's cache is used.",
    ),
) -> None:
    """Compile (or load from numba's cache) every association kernel, then compile them ahead
    of time; `make` runs it after installing, so the first real call starts fast."""
    from lunarloc.localization.warmup import warm_up

    s = warm_up(force=True, jit=True)
    typer.echo(f"association kernels ready in {s:.1f} s (numba's cache)")
    if not aot:
        return
    from lunarloc.localization.warmup import build_kernels

    try:
        r = build_kernels()
    except (
        Exception
    ) as exc:  # no compiler, no Python headers, a read-only install: the JIT path works
        msg = " ".join(f"{type(exc).__name__}: {exc}".split())[:300]
        typer.echo(
            f"warning: ahead-of-time kernels not built ({msg}); numba's cache is used instead",
            err=True,
        )
        return
    if r.path is None:
        typer.echo(
            f"warning: ahead-of-time kernels not built ({r.reason}); numba's cache is used instead",
            err=True,
        )
        return
    typer.echo(
        f"ahead-of-time kernels: {r.signatures} signatures compiled in {r.seconds:.1f} s -> "
        f"{r.path.name}"
    )
