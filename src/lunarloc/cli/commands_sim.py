"""`lunarloc simulate`: a procedural site, its ground-truth rocks and traverse archives."""

from __future__ import annotations

from pathlib import Path

import typer

from lunarloc.cli.app import app
from lunarloc.sim.render import Lighting, SemanticFormat
from lunarloc.cli.checks import OVERWRITE_OPT, number, positive


@app.command("simulate")
def simulate(
    out: Path = typer.Option(..., "--out", help="Output folder (rocks.csv, traverse_<i>.lac)."),
    seed: int = typer.Option(0, "--seed", help="Site seed (same seed, same site)."),
    traverses: int = typer.Option(
        1, "--traverses", min=0, max=1000, help="Number of traverse archives."
    ),
    duration: float = typer.Option(120.0, "--duration", help="Traverse length in seconds."),
    width: int = typer.Option(1280, "--width", help="Image width in pixels."),
    height: int = typer.Option(720, "--height", help="Image height in pixels."),
    image_rate: float = typer.Option(
        2.0, "--image-rate", help="Camera rate in Hz (divides 20 Hz, at most 10)."
    ),
    sun_elevation: float = typer.Option(
        12.0,
        "--sun-elevation",
        min=-90.0,
        max=90.0,
        help="Sun elevation in degrees (5-30 typical; <= 0: below the horizon, night).",
    ),
    sun_azimuth: float = typer.Option(
        135.0, "--sun-azimuth", help="Sun azimuth in degrees from the site +x axis."
    ),
    lighting: Lighting = typer.Option(
        Lighting.SUN_LAMPS,
        "--lighting",
        help="What lights the scene: the sun, the rover's lamps, or both.",
    ),
    lamp_intensity: float = typer.Option(
        1.0,
        "--lamp-intensity",
        min=0.0,
        max=1.0,
        help="Lamp intensity 0-1 (the archive's light_intensity).",
    ),
    semantic_format: SemanticFormat = typer.Option(
        SemanticFormat.IDS,
        "--semantic",
        help="Semantic images as per-rock ids (uint16) or in the LAC palette (RGB).",
    ),
    front_only: bool = typer.Option(
        False, "--front-only", help="Record only the front stereo pair."
    ),
    no_semantic: bool = typer.Option(False, "--no-semantic", help="Do not store semantic images."),
    lac_style: bool = typer.Option(
        False,
        "--lac-style",
        help="A site that looks like the LAC's real frames: crater rims that tilt the rover "
        "10-25 deg, small craters, hummocks and 600 extra rocks of 2-5 cm (docs/rendering.md).",
    ),
    example_images: Path | None = typer.Option(
        None,
        "--example-images",
        help="Only write the two example images (FrontLeft grayscale + semantic) here.",
    ),
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """Simulate a lunar site: write its ground-truth rock map and N traverse archives."""
    from lunarloc.core.errors import require
    from lunarloc.io.outputs import check_output_dir

    for module in ("trimesh", "embreex.rtcore_scene", "embreex.mesh_construction"):
        require(module, "sim", "the ray-cast renderer")  # before any output exists
    positive(duration, "--duration", 24 * 3600.0, "s")
    number(width, "--width", 16, 8192, unit="px")
    number(height, "--height", 16, 8192, unit="px")
    positive(image_rate, "--image-rate", 10.0, "Hz")
    number(sun_elevation, "--sun-elevation", -90.0, 90.0, unit="deg")
    number(sun_azimuth, "--sun-azimuth", -360.0, 360.0, unit="deg")
    if example_images is not None:
        check_output_dir(example_images, True, ())
    else:
        check_output_dir(
            out,
            overwrite,
            ("rocks.csv", "simulation.json", *(f"traverse_{i}.lac" for i in range(traverses))),
            marker=None,
        )
    from dataclasses import replace

    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    from lunarloc.sim.render import RenderConfig
    from lunarloc.sim.site import SiteConfig
    from lunarloc.sim.simulate import (
        ALL_CAMERAS,
        SimulationConfig,
        simulate_dataset,
        write_example_images,
    )

    cfg = SimulationConfig(
        duration_s=duration,
        image_rate_hz=image_rate,
        width=width,
        height=height,
        cameras=("FrontLeft", "FrontRight") if front_only else ALL_CAMERAS,
        semantic=not no_semantic,
        semantic_format=semantic_format,
        site=SiteConfig.lac_style() if lac_style else SiteConfig(),
        render=replace(
            RenderConfig.lac_style() if lac_style else RenderConfig(),
            sun_elevation_deg=sun_elevation,
            sun_azimuth_deg=sun_azimuth,
            lighting=lighting,
            lamp_intensity=lamp_intensity,
        ),
    )
    if example_images is not None:
        for p in write_example_images(example_images, seed, config=cfg):
            typer.echo(f"wrote {p}")
        return
    n_frames = int(round(duration * cfg.rover.rate_hz)) + 1
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn()
    ) as bar:
        tasks = [bar.add_task(f"traverse_{i}.lac", total=n_frames) for i in range(traverses)]

        def on_progress(i: int, n: int) -> None:
            bar.update(tasks[i], completed=n)

        paths = simulate_dataset(seed, traverses, out, cfg, progress=on_progress)
    typer.echo(f"wrote {out / 'rocks.csv'}")
    for p in paths:
        typer.echo(f"wrote {p} ({p.stat().st_size / 1e6:.1f} MB)")
