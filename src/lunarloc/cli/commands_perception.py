"""`lunarloc detect`: stereo images of a `.lac` archive -> rock detections CSV."""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from lunarloc.cli.app import app
from lunarloc.cli.checks import OVERWRITE_OPT, choice


@app.command("detect")
def detect(
    archive: Path = typer.Argument(..., help="input .lac archive (front/rear stereo images)"),
    output: Path = typer.Option(..., "-o", "--output", help="detections CSV (frame,x,y,z,detections,boulders)"),
    segmenter: str = typer.Option("classical", "--segmenter", help="classical | fastsam"),
    weights: Path = typer.Option(None, "--weights", help="FastSAM checkpoint (.pt) for --segmenter fastsam"),
    pose: str = typer.Option("ground-truth", "--pose", help="rover pose for the map frame: ground-truth | odometry"),
    odometry: str = typer.Option(
        None, "--odometry",
        help="place detections with this odometry source instead of --pose: "
        "visual | imu | record:NAME | ground-truth (evaluation only)",
    ),  # fmt: skip
    debug_dir: Path = typer.Option(None, "--debug-dir", help="write overlay images (masks by filter, depth) here"),
    every: int = typer.Option(1, "--every", min=1, max=1_000_000, help="process every N-th camera frame"),
    no_centre_correction: bool = typer.Option(
        False, "--no-centre-correction", help="keep the visible-surface centroid (no sphere-centre shift)"
    ),
    overwrite: bool = OVERWRITE_OPT,
    lander_xy: str = typer.Option(
        None, "--lander-xy", help="X,Y: the lander's centre in the map frame (m); detections on it are dropped "
        "(default: from the archive's initial.toml)"
    ),
) -> None:
    """Segment rocks in the left images, lift them to 3D with stereo, write the traverse CSV."""
    from tqdm import tqdm

    from lunarloc.data.lac import LacArchive
    from lunarloc.perception.camera import STEREO_PAIRS
    from lunarloc.perception.detector import (
        Detector,
        DetectorConfig,
        PoseSource,
        debug_overlay,
        detect_archive,
        write_traverse_csv,
    )
    from lunarloc.inputs import check_input_file
    from lunarloc.outputs import atomic_open, check_output_dir, check_output_file, make_dir
    from lunarloc.perception.segment import SegmenterKind

    pose_src = PoseSource(choice(pose, PoseSource, "--pose"))
    choice(segmenter, SegmenterKind, "--segmenter")
    if weights is not None:
        check_input_file(weights, None, "FastSAM weights")
    check_input_file(archive, None, ".lac archive")
    config_path = output.with_suffix(output.suffix + ".config.json")
    check_output_file(output, overwrite, "detections CSV")  # all output checks before any work
    check_output_file(config_path, overwrite, "detection config")
    if debug_dir is not None:
        check_output_dir(debug_dir, True, ())
    from lunarloc.odometry import archive_odometry, parse_odometry_source

    if odometry is not None:
        parse_odometry_source(odometry)  # a bad name fails before any work
    cfg = DetectorConfig(
        segmenter=segmenter,
        weights=str(weights) if weights else None,
        centre_correction=not no_centre_correction,
    )
    lander = None
    if lander_xy is not None:
        import math

        from lunarloc.errors import ConfigError

        try:
            lander = [float(v) for v in lander_xy.split(",")]
        except ValueError:
            lander = []
        if len(lander) != 2 or not all(math.isfinite(v) and abs(v) < 1e7 for v in lander):
            raise ConfigError(f"--lander-xy takes X,Y in metres (finite), got {lander_xy!r}")
    if debug_dir is not None:
        make_dir(debug_dir)
    with LacArchive(archive) as ar:
        from lunarloc.perception.detector import _camera_from_archive
        from lunarloc.pipeline import scaled_detector_config

        camera = _camera_from_archive(ar)
        cfg = scaled_detector_config(camera.width, cfg)  # pixel parameters are tuned at 1280 px
        detector = Detector(cfg, camera)  # fails early (e.g. missing weights)
        lefts = [left for left, _ in cfg.pairs]
        frames = sorted(
            {int(f) for f in ar.frame_numbers for c in lefts if c in ar.cameras and ar.camera_row(c, int(f))}
        )[::every]
        stats = {"frames": 0, "detections": 0, "time": {}}
        t_start = time.perf_counter()
        poses, pose_label = None, pose_src.value
        if odometry is not None:
            traj = archive_odometry(ar, odometry)
            poses = dict(zip(traj.frames.tolist(), traj.T_map_rover))
            pose_label = traj.label
            stats["time"]["odometry"] = time.perf_counter() - t_start

        def frames_iter():
            with tqdm(total=len(frames), unit="frame", desc="detect", dynamic_ncols=True) as bar:  # closed before an error prints
                yield from _frames(bar)

        def _frames(bar):
            for fd in detect_archive(ar, cfg, pose_src, detector=detector, frames=frames,
                                     keep_depth=debug_dir is not None, poses=poses, lander_xy=lander):  # fmt: skip
                stats["frames"] += 1
                stats["detections"] += len(fd.detections)
                for k, v in fd.timings.items():
                    stats["time"][k] = stats["time"].get(k, 0.0) + v
                if debug_dir is not None:
                    import cv2

                    for pair in fd.pairs:
                        img = ar.grayscale(pair.camera, fd.frame)
                        cv2.imwrite(str(debug_dir / f"{pair.camera}_{fd.frame:06d}.png"), debug_overlay(img, pair))
                bar.update(1)
                bar.set_postfix(det=stats["detections"])
                yield fd

        gen = frames_iter()
        try:
            n = write_traverse_csv(output, gen)
        finally:
            gen.close()  # closes the progress bar before an error message is printed
    wall = time.perf_counter() - t_start
    with atomic_open(config_path, "w") as fh:
        fh.write(json.dumps({"archive": str(archive), "pose": pose_label, "detector": cfg.to_dict()},
                            indent=2, default=str))  # fmt: skip
    per = {k: v / max(stats["frames"], 1) for k, v in stats["time"].items()}
    typer.echo(
        f"{n} frames, {stats['detections']} detections placed with {pose_label} poses -> {output} "
        f"({n / wall if wall > 0 else 0:.2f} frames/s; per frame: "
        + ", ".join(f"{k} {1000 * v:.0f} ms" for k, v in per.items())
        + f"; {len(STEREO_PAIRS)} pairs max)"
    )
