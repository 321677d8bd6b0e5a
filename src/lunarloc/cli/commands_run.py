"""`lunarloc run`, `lunarloc plot`, `lunarloc demo`, `lunarloc bench loop`."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from lunarloc.cli.app import app, console
from lunarloc.cli.checks import OVERWRITE_OPT, choice, number, positive
from lunarloc.cli.commands_core import bench_app


def _loop_config(every_m: float, every_s: float, window_m: float, fix: str = "landmarks"):
    from lunarloc.errors import ConfigError
    from lunarloc.pipeline import FixKind, LoopConfig

    positive(every_m, "--every-m", 1e6, "m")
    positive(every_s, "--every-s", 1e7, "s")
    positive(window_m, "--window-m", 1e6, "m")
    choice(fix, FixKind, "--fix")
    try:
        return LoopConfig.for_images(localize_every_m=every_m, localize_every_s=every_s, window_m=window_m, fix_kind=fix)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def _print_summary(s: dict, title: str) -> None:
    from rich.table import Table

    t = Table(title=title)
    t.add_column("")
    t.add_column("odometry", justify="right")
    t.add_column("corrected", justify="right")
    t.add_column("online", justify="right")
    if "ate_odometry" in s:
        for key, lab in (("rmse_m", "ATE RMSE (m)"), ("max_m", "ATE max (m)")):
            t.add_row(lab, *(f"{s[f'ate_{n}'][key]:.3f}" for n in ("odometry", "corrected", "online")))
        t.add_row("final error (m)", f"{s['final_error_odometry_m']:.3f}", f"{s['final_error_corrected_m']:.3f}", "")
    con = console()
    con.print(t)
    mx = s.get("max_accepted_fix_error_m")
    con.print(
        f"path {s['path_length_m']:.1f} m in {s['duration_s']:.0f} s; attempts {s['attempts']}, localized "
        f"{s['localized']}, fixes {s['fixes']} (gate rejected {s['rejected_by_gate']})"
        + (f", worst accepted fix {mx * 100:.1f} cm" if mx is not None else "")
    )
    per = ", ".join(f"{k} {v:.1f} ms" for k, v in s["time_per_image_frame_ms"].items())
    rt = s.get("real_time_fraction")
    con.print(f"time per image frame: {per}; real-time fraction {rt:.3f} ({1 / rt:.1f}x faster than real time)" if rt else per)


@app.command("run")
def run_cmd(
    archives: list[Path] = typer.Argument(..., help="Vehicle traverse .lac archive (stereo images; any custom records); "
                                          "several: rovers of one site on one clock (docs/multi-rover.md)."),  # fmt: skip
    reference: Optional[Path] = typer.Option(None, "--reference", "-r",
                                             help="Reference map: landmark CSV/.npz, traverse CSV, or rocks.csv (id,x,y,z,radius)."),  # fmt: skip
    share_maps: bool = typer.Option(False, "--share-maps", help="Several archives: also localize against the other rovers' live maps."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder."),
    segmenter: str = typer.Option("classical", "--segmenter", help="classical | fastsam"),
    weights: Optional[Path] = typer.Option(None, "--weights", help="FastSAM checkpoint for --segmenter fastsam."),
    every_m: float = typer.Option(1.5, "--every-m", help="Localize after this many metres of travel ..."),
    every_s: float = typer.Option(20.0, "--every-s", help="... or this many seconds."),
    window_m: float = typer.Option(8.0, "--window-m", help="Local map: detections of the last N metres."),
    fix: str = typer.Option("landmarks", "--fix", help="How fixes enter the pose graph: landmarks | pose."),
    plot: bool = typer.Option(True, "--plot/--no-plot", help="Write the figures into OUT."),
    odometry: Optional[str] = typer.Option(
        None, "--odometry",
        help="Odometry source: visual | imu | record:NAME | ground-truth (evaluation only). "
        "Default: visual when the archive has front stereo pairs, else imu.",
    ),  # fmt: skip
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """Online localization over a traverse: detect, map, localize against REFERENCE, fuse.
    Several archives play on one mission clock, each rover also using the others' maps with --share-maps."""
    if len(archives) > 1 or share_maps:
        from lunarloc.cli.commands_multirover import run_several

        return run_several(archives, reference, out, share_maps, segmenter, weights,
                           _loop_config(every_m, every_s, window_m, fix), odometry, plot, overwrite)  # fmt: skip
    archive = archives[0]
    if reference is None:
        from lunarloc.errors import ConfigError

        raise ConfigError("--reference is required with one archive (several archives can use --share-maps instead)")
    from tqdm import tqdm

    from lunarloc.inputs import check_input_file
    from lunarloc.outputs import check_output_dir
    from lunarloc.pipeline import load_reference, run_online, scaled_detector_config, write_outputs
    from lunarloc.perception.detector import DetectorConfig
    from lunarloc.perception.segment import SegmenterKind

    choice(segmenter, SegmenterKind, "--segmenter")
    if weights is not None:
        check_input_file(weights, None, "FastSAM weights")
    check_input_file(archive, None, ".lac archive")
    from lunarloc.odometry import default_odometry_source, parse_odometry_source

    if odometry is not None:
        parse_odometry_source(odometry)  # fail on a bad name before any work
    cfg = _loop_config(every_m, every_s, window_m, fix)
    check_output_dir(out, overwrite)  # a previous run is refused, or cleared with --overwrite
    ref = load_reference(reference, cfg.aggregation)
    base = DetectorConfig(segmenter=segmenter, weights=str(weights) if weights else None)
    from lunarloc.data.lac import LacArchive
    from lunarloc.pipeline import _camera_of

    with LacArchive(archive) as ar:
        width = _camera_of(ar.configured_cameras).width
        odometry = odometry or default_odometry_source(ar)
    det_cfg = scaled_detector_config(width, base)
    with tqdm(unit="frame", desc="run", dynamic_ncols=True) as bar:  # closed before an error prints

        def prog(n, total):
            bar.total = total
            bar.n = n
            if n % 50 == 0 or n == total:
                bar.refresh()

        res = run_online(archive, ref, cfg, det_cfg, progress=prog, odometry_source=odometry)
    s = write_outputs(res, out)
    _print_summary(s, f"{archive.name} in {reference.name} ({len(ref)} landmarks)")
    typer.echo(f"odometry: {res.config['odometry_source']}")
    if plot:
        from lunarloc.viz import plot_run

        for p in plot_run(out):
            typer.echo(f"wrote {p}")
    typer.echo(f"wrote {out}/ (trajectory.tum, attempts.csv, summary.json, ...)")


@app.command("plot")
def plot_cmd(
    outdir: Path = typer.Argument(..., help="A run folder written by `lunarloc run` or `lunarloc demo`."),
    figdir: Optional[Path] = typer.Option(None, "--figdir", help="Where to write the PNGs (default: OUTDIR)."),
) -> None:
    """Regenerate the figures (map.png, error.png, frame.png) of a run (replacing earlier ones:
    regenerating them is this command's purpose)."""
    from lunarloc.outputs import check_output_dir
    from lunarloc.viz import plot_run

    check_output_dir(figdir if figdir is not None else outdir, True, ())

    for p in plot_run(outdir, figdir):
        typer.echo(f"wrote {p}")


@app.command("demo")
def demo_cmd(
    out: Path = typer.Option(Path("demo-output"), "--out", help="Output folder."),
    seed: int = typer.Option(7, "--seed", help="Site seed."),
    duration: float = typer.Option(90.0, "--duration", help="Vehicle traverse length, seconds."),
    reference_duration: float = typer.Option(100.0, "--reference-duration", help="Reference traverse length, seconds."),
    width: int = typer.Option(640, "--width", help="Image width (height = 9/16 of it)."),
    image_rate: float = typer.Option(2.0, "--image-rate", help="Camera rate of both traverses, Hz."),
    n_rocks: int = typer.Option(800, "--rocks", min=0, max=100_000,
                                help="Rocks on the site (LAC map: 386; the demo uses a rock-rich site)."),  # fmt: skip
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """End to end on generated data: simulate a site, a reference and a drifting vehicle
    traverse, build the reference map from images, run the loop, print a table, write figures."""
    from lunarloc.outputs import check_output_dir

    positive(duration, "--duration", 3600.0, "s")
    positive(reference_duration, "--reference-duration", 3600.0, "s")
    number(width, "--width", 64, 4096, unit="px")
    positive(image_rate, "--image-rate", 10.0, "Hz")
    check_output_dir(out, overwrite)
    check_output_dir(Path(out) / "data", overwrite, DEMO_DATA_FILES, marker=None)

    from lunarloc.scenario import ScenarioConfig, run_scenario, scenario_problems

    t0 = time.perf_counter()
    cfg = ScenarioConfig(seed=seed, n_rocks=n_rocks, duration_s=duration, reference_duration_s=reference_duration,
                         width=width, image_rate_hz=image_rate)  # fmt: skip
    s = run_scenario(cfg, out, log=lambda msg: typer.echo(f"[demo] {msg}"))
    _print_summary(s, "demo: vehicle traverse localized in the image-built reference map")
    typer.echo(f"demo finished in {time.perf_counter() - t0:.0f} s; outputs and figures in {out}/")
    problems = scenario_problems(s)
    if problems:
        from lunarloc.errors import CheckFailedError

        raise CheckFailedError("demo: " + "; ".join(problems))


DEMO_DATA_FILES = ("rocks.csv", "reference.lac", "vehicle.lac", "reference_map.csv")


@bench_app.command("loop")
def bench_loop_cmd(
    data: Path = typer.Option(..., "--data", help="lunarloc-data folder (csv/traverse_N.csv)."),
    out: Path = typer.Option(Path("bench-output/loop"), "--out", help="Folder for loop.json and per-traverse runs."),
    heading_drift: float = typer.Option(0.05, "--heading-drift", help="Simulated heading drift, deg per metre."),
    scale_error: float = typer.Option(0.02, "--scale-error", help="Simulated odometry scale error (0.02 = 2%)."),
    traverses: Optional[str] = typer.Option(None, "--traverses", help="Comma-separated vehicle traverses (default all)."),
    min_length: float = typer.Option(5.0, "--min-length", help="Skip vehicle traverses shorter than this (m)."),
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """The online loop on the real LunarLoc traverses (world-frame detections, no images) with
    simulated odometry drift; each traverse is localized against a map of all the others."""
    import numpy as np
    from rich.table import Table

    from lunarloc.evaluation import DriftModel, find_traverses
    from lunarloc.maps import aggregate_detections, load_traverse
    from lunarloc.errors import ConfigError
    from lunarloc.outputs import atomic_open, check_output_dir
    from lunarloc.pipeline import run_traverse_csv, write_outputs

    number(heading_drift, "--heading-drift", 0.0, 10.0, unit="deg/m")
    number(scale_error, "--scale-error", -0.5, 0.5)
    number(min_length, "--min-length", 0.0, 1e6, unit="m")
    try:
        wanted_arg = [int(x) for x in traverses.split(",")] if traverses else None
    except ValueError:
        raise ConfigError(f"--traverses must be comma-separated traverse numbers, got {traverses!r}") from None
    paths = find_traverses(data)
    check_output_dir(out, overwrite, ("loop.json",), marker=None)
    for k in wanted_arg or paths:
        check_output_dir(out / f"traverse_{k}", overwrite)
    trav = {k: load_traverse(p) for k, p in paths.items()}
    wanted = wanted_arg or sorted(trav)
    drift = DriftModel(heading_drift, scale_error)
    con = console()
    table = Table(title=f"online loop on real traverses (drift {heading_drift} deg/m, scale {scale_error:+.1%})")
    for col in ("vehicle", "length m", "ref lm", "attempts", "fixes", "odo RMSE m", "odo max m", "corr RMSE m",
                "corr max m", "worst fix cm", "RT fraction"):  # fmt: skip
        table.add_column(col, justify="right")
    rows = []
    for v in wanted:
        if v not in trav:
            raise ConfigError(f"--traverses: traverse {v} not in {data} (have {', '.join(map(str, trav))})")
        if trav[v].path_length < min_length:
            continue
        others = [k for k in trav if k != v]
        D = [trav[k].detections_xyz for k in others]
        F = [trav[k].detection_frame + 1_000_000 * k for k in others]
        ref = aggregate_detections(np.concatenate(D), np.concatenate(F), frame="ref")
        res = run_traverse_csv(trav[v], ref, drift)
        s = write_outputs(res, out / f"traverse_{v}")
        s["vehicle"] = v
        rows.append(s)
        mx = s["max_accepted_fix_error_m"]
        table.add_row(str(v), f"{s['path_length_m']:.1f}", str(len(ref)), str(s["attempts"]), str(s["fixes"]),
                      f"{s['ate_odometry']['rmse_m']:.3f}", f"{s['ate_odometry']['max_m']:.3f}",
                      f"{s['ate_corrected']['rmse_m']:.3f}", f"{s['ate_corrected']['max_m']:.3f}",
                      "-" if mx is None else f"{mx * 100:.1f}", f"{s['real_time_fraction']:.3f}")  # fmt: skip
        con.print(f"traverse {v}: corrected RMSE {s['ate_corrected']['rmse_m']:.3f} m "
                  f"(odometry {s['ate_odometry']['rmse_m']:.3f} m), {s['fixes']} fixes")  # fmt: skip
    con.print(table)
    with atomic_open(out / "loop.json", "w") as fh:
        fh.write(json.dumps(rows, indent=1))
    con.print(f"wrote {out / 'loop.json'}")
