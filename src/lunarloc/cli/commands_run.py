"""`lunarloc run`, `lunarloc plot`, `lunarloc demo`, `lunarloc bench loop`."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import typer

from lunarloc.cli.app import app, console
from lunarloc.cli.commands_core import bench_app


def _loop_config(every_m: float, every_s: float, window_m: float, fix: str = "landmarks"):
    from lunarloc.errors import ConfigError
    from lunarloc.pipeline import LoopConfig

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
    archive: Path = typer.Argument(..., help="Vehicle traverse .lac archive (stereo images; any custom records)."),
    reference: Path = typer.Option(..., "--reference", "-r",
                                   help="Reference map: landmark CSV/.npz, traverse CSV, or rocks.csv (id,x,y,z,radius)."),  # fmt: skip
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
) -> None:
    """Online localization over a traverse: detect, map, localize against REFERENCE, fuse."""
    from tqdm import tqdm

    from lunarloc.pipeline import load_reference, run_online, scaled_detector_config, write_outputs
    from lunarloc.perception.detector import DetectorConfig

    from lunarloc.odometry import default_odometry_source, parse_odometry_source

    if odometry is not None:
        parse_odometry_source(odometry)  # fail on a bad name before any work
    cfg = _loop_config(every_m, every_s, window_m, fix)
    ref = load_reference(reference, cfg.aggregation)
    base = DetectorConfig(segmenter=segmenter, weights=str(weights) if weights else None)
    from lunarloc.data.lac import LacArchive
    from lunarloc.pipeline import _camera_of

    with LacArchive(archive) as ar:
        width = _camera_of(ar.configured_cameras).width
        odometry = odometry or default_odometry_source(ar)
    det_cfg = scaled_detector_config(width, base)
    bar = tqdm(unit="frame", desc="run", dynamic_ncols=True)

    def prog(n, total):
        bar.total = total
        bar.n = n
        if n % 50 == 0 or n == total:
            bar.refresh()

    res = run_online(archive, ref, cfg, det_cfg, progress=prog, odometry_source=odometry)
    bar.close()
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
    """Regenerate the figures (map.png, error.png, frame.png) of a run."""
    from lunarloc.viz import plot_run

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
    n_rocks: int = typer.Option(800, "--rocks", help="Rocks on the site (LAC map: 386; the demo uses a rock-rich site)."),
) -> None:
    """End to end on generated data: simulate a site, a reference and a drifting vehicle
    traverse, build the reference map from images, run the loop, print a table, write figures."""
    from lunarloc.scenario import ScenarioConfig, run_scenario, scenario_problems

    t0 = time.perf_counter()
    cfg = ScenarioConfig(seed=seed, n_rocks=n_rocks, duration_s=duration, reference_duration_s=reference_duration,
                         width=width, image_rate_hz=image_rate)  # fmt: skip
    s = run_scenario(cfg, out, log=lambda msg: typer.echo(f"[demo] {msg}"))
    _print_summary(s, "demo: vehicle traverse localized in the image-built reference map")
    typer.echo(f"demo finished in {time.perf_counter() - t0:.0f} s; outputs and figures in {out}/")
    problems = scenario_problems(s)
    if problems:
        typer.secho("demo check failed: " + "; ".join(problems), err=True, fg=typer.colors.RED)
        raise typer.Exit(1)


@bench_app.command("loop")
def bench_loop_cmd(
    data: Path = typer.Option(..., "--data", help="lunarloc-data folder (csv/traverse_N.csv)."),
    out: Path = typer.Option(Path("bench-output/loop"), "--out", help="Folder for loop.json and per-traverse runs."),
    heading_drift: float = typer.Option(0.05, "--heading-drift", help="Simulated heading drift, deg per metre."),
    scale_error: float = typer.Option(0.02, "--scale-error", help="Simulated odometry scale error (0.02 = 2%)."),
    traverses: Optional[str] = typer.Option(None, "--traverses", help="Comma-separated vehicle traverses (default all)."),
    min_length: float = typer.Option(5.0, "--min-length", help="Skip vehicle traverses shorter than this (m)."),
) -> None:
    """The online loop on the real LunarLoc traverses (world-frame detections, no images) with
    simulated odometry drift; each traverse is localized against a map of all the others."""
    import numpy as np
    from rich.table import Table

    from lunarloc.evaluation import DriftModel, find_traverses
    from lunarloc.maps import aggregate_detections, load_traverse
    from lunarloc.pipeline import run_traverse_csv, write_outputs

    paths = find_traverses(data)
    trav = {k: load_traverse(p) for k, p in paths.items()}
    wanted = [int(x) for x in traverses.split(",")] if traverses else sorted(trav)
    drift = DriftModel(heading_drift, scale_error)
    con = console()
    table = Table(title=f"online loop on real traverses (drift {heading_drift} deg/m, scale {scale_error:+.1%})")
    for col in ("vehicle", "length m", "ref lm", "attempts", "fixes", "odo RMSE m", "odo max m", "corr RMSE m",
                "corr max m", "worst fix cm", "RT fraction"):  # fmt: skip
        table.add_column(col, justify="right")
    rows = []
    for v in wanted:
        if v not in trav:
            raise typer.BadParameter(f"traverse {v} not in {data}")
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
    out.mkdir(parents=True, exist_ok=True)
    (out / "loop.json").write_text(json.dumps(rows, indent=1))
    con.print(f"wrote {out / 'loop.json'}")
