"""`lunarloc score`: the LAC's geometric-map and rock-map scores of a produced map."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from lunarloc.cli.app import app, console


@app.command("score")
def score_cmd(
    produced: Path = typer.Argument(..., help="The team's LAC geometric map (.npy, N x N x 4)."),
    truth: Path = typer.Argument(..., help="The ground-truth LAC geometric map (.npy), e.g. from simulate."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object."),
    height_tolerance: float = typer.Option(0.05, help="Height error allowed per cell, metres (LAC: 0.05)."),
) -> None:
    """Score PRODUCED against TRUTH as the LAC does: share of cells with height error below
    the tolerance (geometric map) and the F1 over per-cell rock flags (rock map)."""
    from lunarloc.cli.checks import positive
    from lunarloc.io.overhead import MAX_HEIGHT_TOLERANCE_M, load_lac_grid, score_geometric_map

    positive(height_tolerance, "--height-tolerance", MAX_HEIGHT_TOLERANCE_M, "m")  # before reading the maps
    s = score_geometric_map(load_lac_grid(produced), load_lac_grid(truth), height_tolerance)
    if as_json:
        typer.echo(json.dumps(s))
        return
    con = console()
    con.print(f"{produced.name} vs {truth.name} ({s['cells']} cells)")
    con.print(f"geometric map: {s['geometric']:.1%} of cells within {height_tolerance * 100:g} cm in height")
    con.print(
        f"rock map: precision {s['rock_precision']:.3f}, recall {s['rock_recall']:.3f}, F1 {s['rock_f1']:.3f} "
        f"({s['rock_cells_produced']} rock cells produced, {s['rock_cells_true']} true)"
    )
