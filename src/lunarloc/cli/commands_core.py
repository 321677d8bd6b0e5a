"""`lunarloc map`, `lunarloc localize`, `lunarloc bench pairs`."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from lunarloc.cli.app import app, console
from lunarloc.cli.checks import (
    JSON_OUT_OPT,
    JSON_STDOUT_OPT,
    OVERWRITE_OPT,
    check_json_out,
    enum_value,
    number,
    positive,
    write_json_out,
)
from lunarloc.localization.large import Search
from lunarloc.localization.config import Mode, Registration, Solver

bench_app = typer.Typer(
    help="Benchmarks that reproduce the published figures.", no_args_is_help=True
)
app.add_typer(bench_app, name="bench")


def _agg(radius: Optional[float], min_sightings: Optional[int]):
    from lunarloc.io.maps import AggregationConfig

    positive(radius, "--radius", 10.0, "m")
    d = AggregationConfig()
    return AggregationConfig(
        radius_m=radius if radius is not None else d.radius_m,
        min_sightings=min_sightings if min_sightings is not None else d.min_sightings,
    )


RADIUS_OPT = typer.Option(
    None, "--radius", help="Clustering radius in metres (default from AggregationConfig)."
)
SIGHT_OPT = typer.Option(
    None, "--min-sightings", min=1, max=1_000_000, help="Detections needed per landmark."
)
MAX_EPSILON_M = 0.3
"""Largest --epsilon accepted: beyond it nearly every pair of associations is 'consistent' and
the consistency graph grows quadratically in memory (6.5 GB measured at 5 m)."""


def _map_suffix(out: Path) -> None:
    from lunarloc.core.errors import ConfigError

    if out.suffix.lower() not in (".csv", ".npz"):
        raise ConfigError(f"{out}: unknown map format {out.suffix!r} (use .csv or .npz)")


@app.command("map")
def map_cmd(
    traverse: Path = typer.Argument(..., help="Traverse CSV (frame,x,y,z,detections,boulders)."),
    out: Optional[Path] = typer.Option(
        None, "-o", "--out", help="Output landmark map (.csv or .npz)."
    ),
    lac_grid: Optional[Path] = typer.Option(
        None,
        "--lac-grid",
        help="Also write the rocks as a LAC geometric map (.npy, 180 x 180 cells of 0.15 m).",
    ),
    radius: Optional[float] = RADIUS_OPT,
    min_sightings: Optional[int] = SIGHT_OPT,
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """Build a landmark map (one landmark per rock) from a traverse's detections."""
    from lunarloc.core.errors import InputError
    from lunarloc.io.maps import load_traverse, save_map, traverse_map
    from lunarloc.io.outputs import check_output_file

    if out is None and lac_grid is None:
        raise InputError(
            "nothing to write: give -o/--out MAP (.csv/.npz) and/or --lac-grid GRID.npy"
        )
    if out is not None:
        _map_suffix(out)
        check_output_file(out, overwrite, "landmark map")  # before the computation, not after
    if lac_grid is not None:
        if lac_grid.suffix.lower() != ".npy":
            raise InputError(f"{lac_grid}: a LAC geometric map is written as .npy")
        check_output_file(lac_grid, overwrite, "LAC geometric map")
    trav = load_traverse(traverse)
    lm = traverse_map(trav, _agg(radius, min_sightings))
    written = []
    if out is not None:
        save_map(lm, out)
        written.append(str(out))
    if lac_grid is not None:
        import numpy as np

        from lunarloc.io.outputs import atomic_path
        from lunarloc.io.overhead import landmarks_to_lac_grid

        grid = landmarks_to_lac_grid(lm)
        with atomic_path(lac_grid) as tmp:
            np.save(tmp, grid)
        written.append(str(lac_grid))
    typer.echo(
        f"{traverse.name}: {len(trav.detections_xyz)} detections in {len(trav.frames)} frames "
        f"-> {len(lm)} landmarks -> {', '.join(written)}"
    )


@app.command("localize")
def localize_cmd(
    reference: Path = typer.Argument(
        ...,
        help="Reference map: landmark CSV/.npz, traverse CSV, rocks.csv, LAC geometric map (.npy) "
        "or rock catalogue CSV.",
    ),
    vehicle: Path = typer.Argument(
        ...,
        help="Vehicle map: landmark CSV/.npz or traverse CSV (then its path is used: the pose is "
        "judged at the traverse's last position, and a fitted distortion places each landmark "
        "where it was seen from).",
    ),
    as_json: bool = JSON_STDOUT_OPT,
    json_out: Optional[Path] = JSON_OUT_OPT,
    config: Optional[Path] = typer.Option(
        None,
        "--config",
        help="Run configuration (its localization section is used); options given override it.",
    ),
    mode: Optional[Mode] = typer.Option(
        None, help="gravity (IMU-levelled maps, default) or 6dof (any rotation)."
    ),
    solver: Optional[Solver] = typer.Option(
        None, help="exact (maximum clique, default) or clipper."
    ),
    epsilon: Optional[float] = typer.Option(
        None,
        help=f"Pairwise distance tolerance in metres, in (0, {MAX_EPSILON_M:g}] (default 0.05).",
    ),
    registration: Optional[Registration] = typer.Option(
        None, help="se3 (default) or yaw (4-DoF, exactly levelled maps)."
    ),
    max_size_ratio: Optional[float] = typer.Option(
        None, help="Prune associations whose size ratio exceeds this (maps with a size column)."
    ),
    dem: Optional[Path] = typer.Option(
        None, "--dem", help="LAC geometric map giving heights to a catalogue without z."
    ),
    odometry_scale_error: Optional[float] = typer.Option(
        None,
        help="Bound on the vehicle map's relative scale error (its odometry's spec, 0.03 = 3 %; 0: "
        "a rigid map). Stated bounds win; without them a file that says its poses were the ground "
        "truth (a LunarLoc dataset traverse CSV, or a 'pose' column / '# pose:' line saying "
        "ground-truth) is judged rigid, and any other map's distortion is fitted from the maps, "
        "under a prior of real rover odometry (0.012 deg/m, 0.3 %; docs/verification.md) when the "
        "vehicle is a traverse CSV (its path known).",
    ),
    odometry_drift: Optional[float] = typer.Option(
        None, help="Bound on the odometry's heading drift, degrees per metre (0: a rigid map)."
    ),
    radius: Optional[float] = RADIUS_OPT,
    min_sightings: Optional[int] = SIGHT_OPT,
    search: Search = typer.Option(
        Search.AUTO.value,
        help="full (every association), indexed (rock-triangle index, for large references) "
        "or auto (indexed from 2,000 reference rocks).",
    ),
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """Localize VEHICLE in REFERENCE. Exit code 0 whether or not it localized.

    The same in Python: veh = load_vehicle(VEHICLE); localize(load_reference(REFERENCE), veh.map,
    query_xyz=veh.query_xyz, path_xyz=veh.path_xyz)."""
    from lunarloc.config.run import RunConfig, load_config_file
    from lunarloc.localization.config import LocalizationConfig
    from lunarloc.localization.large import localize_large
    from lunarloc.localization.warmup import prepare_kernels
    from lunarloc.io.maps import load_vehicle
    from lunarloc.pipeline.reference import load_reference

    mode, solver, registration, search = (
        enum_value(v) for v in (mode, solver, registration, search)
    )
    positive(epsilon, "--epsilon", MAX_EPSILON_M, "m")
    check_json_out(json_out, overwrite)
    number(max_size_ratio, "--max-size-ratio", 1.0, 1e6)
    # one-shot: odometry bounds not stated unless given (the distortion is fitted from the maps)
    run_cfg = (
        load_config_file(config)[0]
        if config is not None
        else RunConfig.for_detections(localization=LocalizationConfig())
    )
    run_cfg = run_cfg.with_options(
        localization__mode=mode,
        localization__solver=solver,
        localization__search__epsilon_m=epsilon,
        localization__registration=registration,
        localization__search__max_size_ratio=max_size_ratio,
        localization__distortion__scale_error=odometry_scale_error,
        localization__distortion__heading_drift_deg_per_m=odometry_drift,
    )
    cfg: LocalizationConfig = run_cfg.localization
    agg = _agg(radius, min_sightings)
    ref = load_reference(reference, agg, dem=dem)
    # a traverse CSV: its map, the path that built it and the rover's last position
    v = load_vehicle(vehicle, agg)
    veh = v.map
    # compiled or loaded here, announced, and never counted in the result's time
    kernels = prepare_kernels()
    res = localize_large(
        ref, veh, cfg, run_cfg.index, search=search, query_xyz=v.query_xyz, path_xyz=v.path_xyz
    )
    if as_json or json_out is not None:
        from lunarloc.io.runs import to_json_ready

        doc = {
            **res.to_dict(),
            "config": to_json_ready(run_cfg.to_dict()),
            "kernels": kernels.to_dict(),
        }
        write_json_out(doc, json_out, as_json)
        if as_json:
            return

    con = console()
    status = (
        "[green]localized[/green]" if res.success else f"[red]not localized[/red]: {res.reason}"
    )
    from lunarloc.pipeline.reference import reference_summary

    con.print(
        f"{vehicle.name} ({len(veh)} landmarks) in {reference.name} "
        f"({reference_summary(reference, ref)}): {status}"
    )
    con.print(
        f"inliers {res.num_inliers} (needed {res.required_inliers}, competitor "
        f"{res.competitor_size}), RMSE {res.residual_rmse_m * 100:.2f} cm, yaw {res.yaw_deg:.2f} "
        f"deg, tilt {res.tilt_deg:.2f} deg, {res.time_s * 1000:.0f} ms"
    )
    if res.search == "indexed":
        con.print(
            f"indexed search: {len(res.candidates)} candidate region(s), answer from candidate "
            f"{res.winner + 1}"
        )
    if math.isfinite(res.predicted_error_m):
        con.print(
            f"predicted 1-sigma error {res.predicted_error_m * 100:.1f} cm, "
            f"{res.predicted_rotation_deg:.2f} deg; near misses {res.near_misses} (chance "
            f"{res.near_misses_expected:.1f})"
        )
    if res.odometry_bounds:
        con.print(res.odometry_bounds["text"], markup=False)
    if res.distortion_fit:
        f = res.distortion_fit
        con.print(
            f"fitted heading drift {math.degrees(f['drift_rad_per_m']):+.3f} +- "
            f"{math.degrees(f['drift_se']):.3f} deg/m, scale error {f['scale_error'] * 100:+.2f} "
            f"+- {f['scale_se'] * 100:.2f} % "
            f"({'along the given path' if f['path_given'] else 'path unknown: straight stand-in'}"
            + (
                ""
                if f.get("prior", "none") == "none"
                else f"; odometry prior {cfg.distortion.prior_drift_deg_per_m:g} deg/m, "
                f"{(cfg.distortion.prior_scale_error or 0) * 100:g} %: {f['prior']}"
            )
            + ")"
        )
    if res.checks:
        from rich.table import Table

        table = Table(title="checks (the first that fails is the reason)")
        for col in ("check", "value", "", "limit", "passed"):
            table.add_column(col, justify="left" if col == "check" else "right")
        for c in res.checks:
            table.add_row(
                c.name,
                f"{c.value:.4g}",
                c.relation,
                f"{c.limit:.4g}",
                "yes" if c.passed else "[red]no[/red]",
            )
        con.print(table)
    if res.success:  # no transform for a pose that is not trusted
        con.print("T_ref_veh =")
        for row in res.T_ref_veh:
            con.print("  " + " ".join(f"{v:+.6f}" for v in row))


@bench_app.command("pairs")
def bench_pairs_cmd(
    data: Path = typer.Option(
        ..., "--data", help="lunarloc-data folder (with csv/traverse_N.csv)."
    ),
    out: Path = typer.Option(
        Path("bench-output"), "--out", help="Folder for pairs.csv and pairs.json."
    ),
    only_paper: bool = typer.Option(False, "--paper", help="Only the paper's five pairs."),
    seed: int = typer.Option(0, help="Seed of the random vehicle transforms."),
    heading_drift: float = typer.Option(
        0.0, "--heading-drift", help="Simulated heading drift, degrees per metre travelled."
    ),
    drift: Optional[float] = typer.Option(
        None, "--drift", hidden=True, help="Old name of --heading-drift."
    ),
    scale_error: float = typer.Option(0.0, help="Simulated odometry scale error (0.01 = 1%)."),
    window: Optional[float] = typer.Option(
        None, help="Vehicle map from the last WINDOW metres of the path only (use with drift)."
    ),
    mode: Mode = typer.Option(Mode.GRAVITY.value, help="gravity or 6dof."),
    solver: Solver = typer.Option(Solver.EXACT.value, help="exact or clipper."),
    odometry_bounds: bool = typer.Option(
        True,
        "--odometry-bounds/--no-odometry-bounds",
        help="Tell the localizer the simulated drift as its odometry's bounds (scale, heading "
        "drift).",
    ),
    check: bool = typer.Option(
        False, "--check", help="Exit 1 unless the acceptance targets are met."
    ),
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """Localize traverse pairs of the LunarLoc dataset; table on screen, CSV + JSON in --out."""
    from rich.progress import Progress
    from rich.table import Table

    from lunarloc.pipeline.bench import pairs_problems, pairs_to_run, write_pairs
    from lunarloc.pipeline.evaluation import PAPER_PAIRS, DriftModel, bench_pairs, find_traverses
    from lunarloc.localization.config import DistortionConfig, LocalizationConfig
    from lunarloc.io.outputs import check_output_dir

    mode, solver = enum_value(mode), enum_value(solver)
    # --drift: the old name, kept as a hidden alias
    drift = heading_drift if drift is None else drift
    number(drift, "--heading-drift", 0.0, 10.0, unit="deg/m")
    number(scale_error, "--scale-error", -0.5, 0.5)
    positive(window, "--window", 1e6, "m")
    check_output_dir(out, overwrite, ("pairs.csv", "pairs.json"), marker=None)

    pairs = pairs_to_run(find_traverses(data), only_paper)
    cfg = LocalizationConfig(
        mode=mode,
        solver=solver,
        distortion=DistortionConfig(
            scale_error=abs(scale_error) if odometry_bounds else None,
            heading_drift_deg_per_m=abs(drift) if odometry_bounds else None,
        ),
    )
    con = console()
    with Progress(console=con, transient=True) as prog:
        task = prog.add_task("localizing pairs", total=len(pairs))
        summary = bench_pairs(
            data,
            pairs,
            seed=seed,
            loc_config=cfg,
            drift=DriftModel(drift, scale_error),
            window_m=window,
            progress=lambda r: prog.update(
                task, advance=1, description=f"pair {r.reference}-{r.vehicle}"
            ),
        )
    res = summary.results
    table = Table(title="LunarLoc traverse pairs (reference - vehicle)")
    for col in (
        "pair",
        "segs ref",
        "segs veh",
        "inliers",
        "err@origin cm",
        "err@rover cm",
        "rot deg",
        "success",
        "correct",
        "time s",
        "reason",
    ):
        if col == "reason":
            table.add_column(col, no_wrap=True, overflow="ellipsis", max_width=48)
        else:
            table.add_column(col, justify="right")
    paper = [r for r in res if (r.reference, r.vehicle) in PAPER_PAIRS]
    shown = paper + [
        r
        for r in res
        if (r.reference, r.vehicle) not in PAPER_PAIRS and not (r.success and r.correct)
    ]
    for r in shown:
        table.add_row(
            f"{r.reference}-{r.vehicle}",
            str(r.segs_ref),
            str(r.segs_veh),
            str(r.inliers),
            f"{r.err_origin_m * 100:.2f}",
            f"{r.err_rover_m * 100:.2f}",
            f"{r.rot_err_deg:.3f}",
            "yes" if r.success else "[red]no[/red]",
            "yes" if r.correct else "[red]no[/red]",
            f"{r.time_s:.3f}",
            "" if r.success else r.reason[:60],
        )
    con.print(table)
    d = summary.to_dict()
    con.print(
        f"pairs {d['pairs']}: correct {d['correct']}, success claimed {d['success']} "
        f"(of which correct {d['success_and_correct']}), confident-wrong {d['confident_wrong']}; "
        f"time median {d['median_time_s']:.3f} s, max {d['max_time_s']:.3f} s"
    )
    big = max(res, key=lambda r: r.segs_ref * r.segs_veh)
    con.print(
        f"largest pair {big.reference}-{big.vehicle} ({big.segs_ref}x{big.segs_veh} landmarks): "
        f"{big.time_s:.3f} s"
    )
    csv_path, json_path = write_pairs(summary, out)
    con.print(f"wrote {csv_path} and {json_path}")
    if check:
        bad = pairs_problems(summary, only_paper)
        if bad:
            for b in bad:
                con.print(f"[red]CHECK FAILED[/red] {b}")
            raise typer.Exit(1)
        con.print("[green]checks passed[/green]")
