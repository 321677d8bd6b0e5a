"""`lunarloc detect`: stereo images of a `.lac` archive -> rock detections CSV."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from lunarloc.cli.app import app
from lunarloc.cli.checks import ODOMETRY_METAVAR, OVERWRITE_OPT, enum_value
from lunarloc.perception.detector import PoseSource
from lunarloc.perception.segment import SegmenterKind


@app.command("detect")
def detect(
    archive: Path = typer.Argument(..., help="input .lac archive (front/rear stereo images)"),
    output: Path = typer.Option(
        ..., "-o", "--output", help="detections CSV (frame,x,y,z,detections,boulders)"
    ),
    config: Optional[Path] = typer.Option(
        None,
        "--config",
        help="run configuration (a config.json written by detect or run); options given override "
        "it",
    ),
    segmenter: Optional[SegmenterKind] = typer.Option(
        None, "--segmenter", help="default from the config: classical"
    ),
    weights: Optional[Path] = typer.Option(
        None, "--weights", help="FastSAM checkpoint (.pt) for --segmenter fastsam"
    ),
    pose: PoseSource = typer.Option(
        PoseSource.GROUND_TRUTH.value, "--pose", help="rover pose for the map frame"
    ),
    odometry: Optional[str] = typer.Option(
        None,
        "--odometry",
        metavar=ODOMETRY_METAVAR,
        help="place detections with this odometry source instead of --pose: "
        "visual | imu | record:NAME | ground-truth (evaluation only)",
    ),
    debug_dir: Optional[Path] = typer.Option(
        None, "--debug-dir", help="write overlay images (masks by filter, depth) here"
    ),
    every: int = typer.Option(
        1, "--every", min=1, max=1_000_000, help="process every N-th camera frame"
    ),
    no_centre_correction: bool = typer.Option(
        False,
        "--no-centre-correction",
        help="keep the visible-surface centroid (no sphere-centre shift)",
    ),
    overwrite: bool = OVERWRITE_OPT,
    lander_xy: Optional[str] = typer.Option(
        None,
        "--lander-xy",
        help="X,Y: the lander's centre in the map frame (m); detections on it are dropped "
        "(default: from the archive's initial.toml)",
    ),
) -> None:
    """Segment rocks in the left images, lift them to 3D with stereo, write the traverse CSV
    and its configuration (OUTPUT.config.json)."""
    from tqdm import tqdm

    from lunarloc.config.run import RunConfig, load_config_file
    from lunarloc.io.inputs import check_input_file
    from lunarloc.io.outputs import check_output_dir, check_output_file, make_dir
    from lunarloc.perception.camera import STEREO_PAIRS
    from lunarloc.pipeline.runner import detect as detect_pipeline

    pose, segmenter = enum_value(pose), enum_value(segmenter)
    if weights is not None:
        check_input_file(weights, None, "FastSAM weights")
    check_input_file(archive, None, ".lac archive")
    config_path = output.with_suffix(output.suffix + ".config.json")
    check_output_file(output, overwrite, "detections CSV")  # all output checks before any work
    check_output_file(config_path, overwrite, "detection config")
    if debug_dir is not None:
        check_output_dir(debug_dir, True, ())
    cfg = load_config_file(config)[0] if config is not None else RunConfig()
    cfg = cfg.with_options(
        detector__segmenter=segmenter,
        detector__weights=str(weights) if weights else None,
        detector__centre_correction=False if no_centre_correction else None,
        odometry__source=odometry,
    )
    lander = None
    if lander_xy is not None:
        import math

        from lunarloc.core.errors import ConfigError

        try:
            lander = [float(v) for v in lander_xy.split(",")]
        except ValueError:
            lander = []
        if len(lander) != 2 or not all(math.isfinite(v) and abs(v) < 1e7 for v in lander):
            raise ConfigError(f"--lander-xy takes X,Y in metres (finite), got {lander_xy!r}")
    if debug_dir is not None:
        make_dir(debug_dir)
    with tqdm(
        unit="frame", desc="detect", dynamic_ncols=True
    ) as bar:  # closed before an error prints

        def prog(n, total, detections):
            bar.total = total
            bar.update(n - bar.n)
            bar.set_postfix(det=detections)

        res = detect_pipeline(
            archive,
            output,
            cfg,
            pose=pose,
            every=every,
            debug_dir=debug_dir,
            lander_xy=lander,
            progress=prog,
        )
    typer.echo(
        f"{res.frames} frames, {res.detections} detections placed with {res.pose_label} poses -> "
        f"{output} ({res.frames_per_s:.2f} frames/s; per frame: "
        + ", ".join(f"{k} {1000 * v:.0f} ms" for k, v in res.per_frame_s().items())
        + f"; {len(STEREO_PAIRS)} pairs max)"
    )
