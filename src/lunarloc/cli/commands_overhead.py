"""`lunarloc score`: the LAC's map scores and points of a produced map."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lunarloc.cli.app import app, console
from lunarloc.cli.checks import (
    JSON_OUT_OPT,
    JSON_STDOUT_OPT,
    OVERWRITE_OPT,
    check_json_out,
    positive,
    write_json_out,
)


@app.command("score")
def score_cmd(
    produced: Path = typer.Argument(
        ..., help="The team's LAC geometric map (.npy, N x N x 4; -inf marks unfilled cells)."
    ),
    truth: Path = typer.Argument(
        ..., help="The ground-truth LAC geometric map (.npy), e.g. from simulate."
    ),
    as_json: bool = JSON_STDOUT_OPT,
    json_out: Optional[Path] = JSON_OUT_OPT,
    height_tolerance: float = typer.Option(
        0.05, help="Height error allowed per cell, metres (LAC: 0.05)."
    ),
    seen_only: bool = typer.Option(
        False,
        "--seen-only",
        help="Score the geometric and rock maps over the cells the "
        "cameras saw only (PRODUCED's .cells.npz, written by `run --lac-map`).",
    ),
    mission_time: Optional[float] = typer.Option(
        None,
        "--mission-time",
        help="Mission time in seconds, for the "
        "productivity (default: the LAC's 24 h, i.e. the share of cells filled).",
    ),
    fiducials: bool = typer.Option(
        False, "--fiducials", help="The agent used the lander's fiducials (no localization points)."
    ),
    figure: Optional[Path] = typer.Option(
        None, "--figure", help="Also write a PNG: produced map, true map, per-cell error."
    ),
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """Score PRODUCED against TRUTH as the LAC does: share of cells with height error below
    the tolerance (geometric map; unfilled cells fail), precision / recall / F1 over the
    per-cell rock flags (rock map), mapping productivity, and the LAC's points."""
    from lunarloc.io.overhead import MAX_HEIGHT_TOLERANCE_M, load_lac_grid, score_geometric_map

    # before reading the maps
    positive(height_tolerance, "--height-tolerance", MAX_HEIGHT_TOLERANCE_M, "m")
    positive(mission_time, "--mission-time", 1e7, "s")
    check_json_out(json_out, overwrite)
    p = load_lac_grid(produced, allow_unfilled=True)
    t = load_lac_grid(truth)
    cells = None
    if seen_only:
        from lunarloc.mapping.lac_map import load_observed_cells

        cells = load_observed_cells(produced, p.shape[:2])
    s = score_geometric_map(
        p, t, height_tolerance, cells=cells, mission_time_s=mission_time, fiducials_used=fiducials
    )
    if figure is not None:
        from lunarloc.viz import plot_lac_maps

        plot_lac_maps(
            p,
            t,
            figure,
            observed=cells,
            height_tolerance_m=height_tolerance,
            title=f"{produced.name} vs {truth.name}",
        )
    write_json_out(s, json_out, as_json)
    if as_json:
        return
    con = console()
    where = f"{s['cells']} cells the cameras saw" if seen_only else f"all {s['cells']} cells"
    con.print(f"{produced.name} vs {truth.name} ({where})")
    con.print(
        f"geometric map: {s['geometric']:.1%} of cells within {height_tolerance * 100:g} cm in "
        "height"
    )
    con.print(
        f"rock map: precision {s['rock_precision']:.3f}, recall {s['rock_recall']:.3f}, F1 "
        f"{s['rock_f1']:.3f} ({s['rock_cells_produced']} rock cells produced, "
        f"{s['rock_cells_true']} true)"
    )
    con.print(
        f"productivity: {s['productivity']:.3f} ({s['cells_filled']} cells filled in "
        f"{s['mission_time_s']:g} s)"
    )
    pts = s["points"]
    label = "LAC points (as if the whole map were the cells seen)" if seen_only else "LAC points"
    con.print(
        f"{label}: geometric {pts['geometric_map']:.1f}/300, rocks {pts['rocks_map']:.1f}/300, "
        f"productivity {pts['mapping_productivity']:.1f}/250, localization "
        f"{pts['localization']:.0f}/150, total {pts['total']:.1f}/1000"
    )
    if figure is not None:
        con.print(f"wrote {figure}")
