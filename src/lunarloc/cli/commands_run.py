"""`lunarloc run`, `lunarloc plot`, `lunarloc demo`, `lunarloc bench loop`."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from lunarloc.cli.app import app, console
from lunarloc.cli.checks import ODOMETRY_METAVAR, OVERWRITE_OPT, enum_value, number, positive
from lunarloc.cli.commands_core import bench_app
from lunarloc.online.loop import FixKind
from lunarloc.perception.segment import SegmenterKind


CONFIG_OPT = typer.Option(
    None,
    "--config",
    help="Run configuration (a run folder's config.json); options given override it.",
)


def _run_config(config: Optional[Path], default, extra_sections: tuple[str, ...] = ()):
    """(RunConfig, extra sections) from --config FILE, or (`default`, {})."""
    from lunarloc.config.run import load_config_file

    if config is None:
        return default, {}
    return load_config_file(config, extra_sections)


def _print_summary(s: dict, title: str) -> None:
    from rich.table import Table

    t = Table(title=title)
    t.add_column("")
    t.add_column("odometry", justify="right")
    t.add_column("corrected", justify="right")
    t.add_column("online", justify="right")
    if "ate_odometry" in s:
        for key, lab in (("rmse_m", "ATE RMSE (m)"), ("max_m", "ATE max (m)")):
            t.add_row(
                lab, *(f"{s[f'ate_{n}'][key]:.3f}" for n in ("odometry", "corrected", "online"))
            )
        t.add_row(
            "final error (m)",
            f"{s['final_error_odometry_m']:.3f}",
            f"{s['final_error_corrected_m']:.3f}",
            "",
        )
    con = console()
    con.print(t)
    mx = s.get("max_accepted_fix_error_m")
    con.print(
        f"path {s['path_length_m']:.1f} m in {s['duration_s']:.0f} s; attempts {s['attempts']}, "
        f"localized {s['localized']}, fixes {s['fixes']} (gate rejected {s['rejected_by_gate']})"
        + (f", worst accepted fix {mx * 100:.1f} cm" if mx is not None else "")
    )
    per = ", ".join(f"{k} {v:.1f} ms" for k, v in s["time_per_image_frame_ms"].items())
    rt = s.get("real_time_fraction")
    con.print(
        f"time per image frame: {per}; real-time fraction {rt:.3f} ({1 / rt:.1f}x faster than real "
        "time)"
        if rt
        else per
    )


def with_small_rocks(cfg, small_rocks: bool | None, lac_map: bool):
    """`cfg` with the detector's small-rock stage as ``--small-rocks/--no-small-rocks`` says;
    not given: on when the run writes a LAC map (its rock map needs the rocks under 5 cm the
    any-ray rule flags; docs/lac-map.md), else as `cfg` has it."""
    if small_rocks is None:
        if not lac_map:
            return cfg
        small_rocks = True
    from dataclasses import replace

    return cfg.with_options(
        detector__small_rocks=replace(cfg.detector.small_rocks, enabled=bool(small_rocks))
    )


@app.command("run")
def run_cmd(
    archives: list[Path] = typer.Argument(
        ...,
        help="Vehicle traverse .lac archive (stereo images; any custom records); "
        "several: rovers of one site on one clock (docs/multi-rover.md).",
    ),
    reference: Optional[Path] = typer.Option(
        None,
        "--reference",
        "-r",
        help="Reference map: landmark CSV/.npz, traverse CSV, rocks.csv (id,x,y,z,radius), "
        "LAC geometric map (.npy) or rock catalogue CSV (required with one archive).",
    ),
    share_maps: bool = typer.Option(
        False,
        "--share-maps",
        help="Several archives: also localize against the other rovers' live maps.",
    ),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder."),
    config: Optional[Path] = CONFIG_OPT,
    segmenter: Optional[SegmenterKind] = typer.Option(
        None, "--segmenter", help="Default from the config: classical."
    ),
    weights: Optional[Path] = typer.Option(
        None, "--weights", help="FastSAM checkpoint for --segmenter fastsam."
    ),
    every_m: Optional[float] = typer.Option(
        None, "--every-m", help="Localize after this many metres of travel (default 1.5) ..."
    ),
    every_s: Optional[float] = typer.Option(
        None, "--every-s", help="... or this many seconds (default 20)."
    ),
    window_m: Optional[float] = typer.Option(
        None, "--window-m", help="Local map: detections of the last N metres (default 8)."
    ),
    fix: Optional[FixKind] = typer.Option(
        None, "--fix", help="How fixes enter the pose graph (default landmarks)."
    ),
    plot: bool = typer.Option(True, "--plot/--no-plot", help="Write the figures into OUT."),
    odometry: Optional[str] = typer.Option(
        None,
        "--odometry",
        metavar=ODOMETRY_METAVAR,
        help="Odometry source: visual | imu | record:NAME | ground-truth (evaluation only). "
        "Default: visual when the archive has front stereo pairs, else imu.",
    ),
    overwrite: bool = OVERWRITE_OPT,
    lac_map: Optional[Path] = typer.Option(
        None,
        "--lac-map",
        help="Also write the LAC geometric map (.npy, 180 x 180 x 4) from the stereo points and "
        "detections, placed with the corrected poses, and its cells' side data (.cells.npz); score "
        "it with `lunarloc score`.",
    ),
    small_rocks: Optional[bool] = typer.Option(
        None,
        "--small-rocks/--no-small-rocks",
        help="The detector's small-rock stage (the rocks under 5 cm radius the LAC's any-ray rule "
        "flags). Default: on with --lac-map, else as the configuration says (on).",
    ),
) -> None:
    """Online localization over a traverse: detect, map, localize against REFERENCE, fuse.
    Several archives play on one mission clock, each rover also using the others' maps with
    --share-maps."""
    from tqdm import tqdm

    from lunarloc.config.run import RunConfig
    from lunarloc.io.inputs import check_input_file
    from lunarloc.io.outputs import check_output_dir
    from lunarloc.pipeline.runner import run
    from lunarloc.pipeline.reference import load_reference
    from lunarloc.io.runs import write_run
    from lunarloc.pipeline.sources import ArchiveSource

    segmenter, fix = enum_value(segmenter), enum_value(fix)
    positive(every_m, "--every-m", 1e6, "m")
    positive(every_s, "--every-s", 1e7, "s")
    positive(window_m, "--window-m", 1e6, "m")
    if weights is not None:
        check_input_file(weights, None, "FastSAM weights")
    cfg, _ = _run_config(config, RunConfig())
    cfg = cfg.with_options(
        detector__segmenter=segmenter,
        detector__weights=str(weights) if weights else None,
        loop__localize_every_m=every_m,
        loop__localize_every_s=every_s,
        loop__window_m=window_m,
        loop__fix_kind=fix,
        odometry__source=odometry,
    )
    cfg = with_small_rocks(cfg, small_rocks, lac_map is not None)
    if len(archives) > 1 or share_maps:
        from lunarloc.cli.commands_multirover import run_several

        if lac_map is not None:
            from lunarloc.core.errors import ConfigError

            raise ConfigError("--lac-map takes one archive")

        return run_several(
            archives, reference, out, cfg, share_maps=share_maps, plot=plot, overwrite=overwrite
        )
    archive = archives[0]
    if reference is None:
        from lunarloc.core.errors import ConfigError

        raise ConfigError(
            "--reference MAP is required with one archive (several archives can use --share-maps "
            "instead)"
        )
    check_input_file(archive, None, ".lac archive")
    check_output_dir(out, overwrite)  # a previous run is refused, or cleared with --overwrite
    mapper = None
    if lac_map is not None:
        from lunarloc.io.outputs import check_output_file
        from lunarloc.mapping.lac_map import LacMapper

        check_output_file(lac_map, overwrite)
        mapper = LacMapper()
    ref = load_reference(reference, cfg.loop.aggregation)
    with tqdm(unit="frame", desc="run", dynamic_ncols=True) as bar:  # closed before an error prints

        def prog(n, total):
            bar.total = total
            bar.n = n
            if n % 50 == 0 or n == total:
                bar.refresh()

        res = run(
            ArchiveSource(archive, cfg.odometry, cfg.detector.pairs),
            ref,
            cfg,
            progress=prog,
            mapper=mapper,
        )
    figures: list[Path] = []
    if plot:
        from lunarloc.viz import plot_run
    try:  # the figures before summary.json, which marks a complete run folder
        s = write_run(
            res,
            out,
            before_summary=(lambda s: figures.extend(plot_run(out, summary=s))) if plot else None,
        )
    except BaseException:
        from lunarloc.io.outputs import remove_partial_outputs

        # what this run wrote (the folder held no run: checked above), temporaries too
        remove_partial_outputs(out)
        raise
    if mapper is not None:
        import numpy as np

        from lunarloc.mapping.lac_map import save_lac_map

        est = mapper.grid()
        for p in save_lac_map(est, lac_map):
            typer.echo(f"wrote {p}")
        typer.echo(
            f"LAC map: {int(est.observed.sum())} cells seen, {int(est.interpolated.sum())} "
            f"interpolated, {int(np.sum(est.array[:, :, 3] >= 0.5))} rock cells ({len(est.rocks)} "
            "rocks)"
        )
    from lunarloc.pipeline.reference import reference_summary

    _print_summary(s, f"{archive.name} in {reference.name}")
    typer.echo(f"reference: {reference_summary(reference, ref)}")
    typer.echo(f"odometry: {res.config['info']['odometry_source']}")
    for p in figures:
        typer.echo(f"wrote {p}")
    typer.echo(f"wrote {out}/ (trajectory.tum, attempts.csv, summary.json, config.json, ...)")


@app.command("plot")
def plot_cmd(
    outdir: Path = typer.Argument(
        ..., help="A run folder written by `lunarloc run` or `lunarloc demo`."
    ),
    figdir: Optional[Path] = typer.Option(
        None, "--figdir", help="Where to write the PNGs (default: OUTDIR)."
    ),
) -> None:
    """Regenerate the figures (map.png, error.png, frame.png) of a run (replacing earlier ones:
    regenerating them is this command's purpose)."""
    from lunarloc.io.outputs import check_output_dir
    from lunarloc.viz import plot_run

    check_output_dir(figdir if figdir is not None else outdir, True, ())

    for p in plot_run(outdir, figdir):
        typer.echo(f"wrote {p}")


@app.command("demo")
def demo_cmd(
    out: Path = typer.Option(Path("demo-output"), "--out", help="Output folder."),
    config: Optional[Path] = typer.Option(
        None,
        "--config",
        help="A demo's config.json (run configuration and scenario); options given override it.",
    ),
    seed: Optional[int] = typer.Option(None, "--seed", help="Site seed (default 7)."),
    duration: Optional[float] = typer.Option(
        None, "--duration", help="Vehicle traverse length, seconds (default 90)."
    ),
    reference_duration: Optional[float] = typer.Option(
        None, "--reference-duration", help="Reference traverse length, seconds (default 120)."
    ),
    width: Optional[int] = typer.Option(
        None, "--width", help="Image width (height = 9/16 of it; default 640)."
    ),
    image_rate: Optional[float] = typer.Option(
        None, "--image-rate", help="Camera rate of both traverses, Hz (default 2)."
    ),
    n_rocks: Optional[int] = typer.Option(
        None, "--rocks", min=0, max=100_000, help="Rocks on the site (default: the LAC map's 386)."
    ),
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """End to end on generated data: simulate a site, a reference and a drifting vehicle
    traverse, build the reference map from images, run the loop, print a table, write figures."""
    from dataclasses import replace

    from lunarloc.core.errors import ConfigError
    from lunarloc.io.outputs import check_output_dir
    from lunarloc.pipeline.scenario import (
        ScenarioConfig,
        demo_run_config,
        run_scenario,
        scenario_problems,
    )

    positive(duration, "--duration", 3600.0, "s")
    positive(reference_duration, "--reference-duration", 3600.0, "s")
    number(width, "--width", 64, 4096, unit="px")
    positive(image_rate, "--image-rate", 10.0, "Hz")
    run_cfg, extra = _run_config(config, demo_run_config(), ("scenario",))
    scen = ScenarioConfig.from_dict(extra["scenario"]) if "scenario" in extra else ScenarioConfig()
    given = {
        "seed": seed,
        "n_rocks": n_rocks,
        "duration_s": duration,
        "reference_duration_s": reference_duration,
        "width": width,
        "image_rate_hz": image_rate,
    }
    try:
        scen = replace(scen, **{k: v for k, v in given.items() if v is not None})
    except ConfigError as exc:
        raise ConfigError(f"scenario: {exc}") from None
    check_output_dir(out, overwrite)
    check_output_dir(Path(out) / "data", overwrite, DEMO_DATA_FILES, marker=None)

    t0 = time.perf_counter()
    try:
        s = run_scenario(scen, out, log=lambda msg: typer.echo(f"[demo] {msg}"), run_config=run_cfg)
    # a failed stage keeps its data for a look (no summary.json: not complete)
    except KeyboardInterrupt:
        from lunarloc.io.outputs import remove_partial_outputs

        # both folders held none of these names (checked above): what this demo wrote, and
        # temporaries
        remove_partial_outputs(out)
        remove_partial_outputs(Path(out) / "data", DEMO_DATA_FILES)
        raise
    _print_summary(s, "demo: vehicle traverse localized in the image-built reference map")
    typer.echo(
        f"demo finished in {time.perf_counter() - t0:.0f} s; outputs and figures in {out}/ "
        f"(config.json repeats it: lunarloc demo --config {out}/config.json)"
    )
    problems = scenario_problems(s)
    if problems:
        from lunarloc.core.errors import CheckFailedError

        raise CheckFailedError("demo: " + "; ".join(problems))


DEMO_DATA_FILES = ("rocks.csv", "reference.lac", "vehicle.lac", "reference_map.csv")


@bench_app.command("loop")
def bench_loop_cmd(
    data: Path = typer.Option(..., "--data", help="lunarloc-data folder (csv/traverse_N.csv)."),
    out: Path = typer.Option(
        Path("bench-output/loop"), "--out", help="Folder for loop.json and per-traverse runs."
    ),
    config: Optional[Path] = CONFIG_OPT,
    heading_drift: Optional[float] = typer.Option(
        None, "--heading-drift", help="Simulated heading drift, deg per metre (default 0.05)."
    ),
    drift: Optional[float] = typer.Option(
        None, "--drift", hidden=True, help="Same as --heading-drift."
    ),
    scale_error: Optional[float] = typer.Option(
        None, "--scale-error", help="Simulated odometry scale error (default 0.02 = 2%)."
    ),
    traverses: Optional[str] = typer.Option(
        None, "--traverses", help="Comma-separated vehicle traverses (default all)."
    ),
    min_length: float = typer.Option(
        5.0, "--min-length", help="Skip vehicle traverses shorter than this (m)."
    ),
    odometry_bounds: bool = typer.Option(
        False,
        "--odometry-bounds/--no-odometry-bounds",
        help="Tell the localizer the simulated drift as its odometry's bounds "
        "(localization.distortion.scale_error, heading_drift_deg_per_m), as bench pairs does.",
    ),
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """The online loop on the real LunarLoc traverses (world-frame detections, no images) with
    simulated odometry drift; each traverse is localized against a map of all the others."""
    from rich.table import Table

    from lunarloc.pipeline.bench import bench_loop
    from lunarloc.config.run import RunConfig
    from lunarloc.core.errors import ConfigError
    from lunarloc.pipeline.evaluation import find_traverses
    from lunarloc.io.outputs import check_output_dir

    # one name across bench commands; --drift an alias
    heading_drift = heading_drift if drift is None else drift
    number(heading_drift, "--heading-drift", 0.0, 10.0, unit="deg/m")
    number(scale_error, "--scale-error", -0.5, 0.5)
    number(min_length, "--min-length", 0.0, 1e6, unit="m")
    try:
        wanted = [int(x) for x in traverses.split(",")] if traverses else None
    except ValueError:
        raise ConfigError(
            f"--traverses must be comma-separated traverse numbers, got {traverses!r}"
        ) from None
    cfg, _ = _run_config(config, RunConfig.for_detections())
    cfg = cfg.with_options(
        odometry__heading_drift_deg_per_m=heading_drift, odometry__scale_error=scale_error
    )
    if odometry_bounds:
        cfg = cfg.with_options(
            localization__distortion__scale_error=abs(cfg.odometry.scale_error),
            localization__distortion__heading_drift_deg_per_m=cfg.odometry.heading_drift_deg_per_m,
        )
    check_output_dir(out, overwrite, ("loop.json",), marker=None)
    for k in wanted or find_traverses(data):
        check_output_dir(out / f"traverse_{k}", overwrite)
    con = console()
    o = cfg.odometry
    table = Table(
        title=f"online loop on real traverses (drift {o.heading_drift_deg_per_m} deg/m, scale "
        f"{o.scale_error:+.1%})"
    )
    for col in (
        "vehicle",
        "length m",
        "ref lm",
        "attempts",
        "fixes",
        "odo RMSE m",
        "odo max m",
        "corr RMSE m",
        "corr max m",
        "worst fix cm",
        "RT fraction",
    ):
        table.add_column(col, justify="right")

    def row(s: dict) -> None:
        mx = s["max_accepted_fix_error_m"]
        table.add_row(
            str(s["vehicle"]),
            f"{s['path_length_m']:.1f}",
            str(s["reference_landmarks"]),
            str(s["attempts"]),
            str(s["fixes"]),
            f"{s['ate_odometry']['rmse_m']:.3f}",
            f"{s['ate_odometry']['max_m']:.3f}",
            f"{s['ate_corrected']['rmse_m']:.3f}",
            f"{s['ate_corrected']['max_m']:.3f}",
            "-" if mx is None else f"{mx * 100:.1f}",
            f"{s['real_time_fraction']:.3f}",
        )
        con.print(
            f"traverse {s['vehicle']}: corrected RMSE {s['ate_corrected']['rmse_m']:.3f} m "
            f"(odometry {s['ate_odometry']['rmse_m']:.3f} m), {s['fixes']} fixes"
        )

    bench_loop(data, out, cfg, traverses=wanted, min_length_m=min_length, on_traverse=row)
    con.print(table)
    con.print(f"wrote {out / 'loop.json'}")
