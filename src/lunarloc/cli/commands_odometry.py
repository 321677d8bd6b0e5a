"""`lunarloc odometry`: an archive's odometry from one source, as TUM, with its drift."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

import numpy as np

from lunarloc.cli.app import app, console
from lunarloc.cli.checks import (
    JSON_OUT_OPT,
    JSON_STDOUT_OPT,
    ODOMETRY_METAVAR,
    OVERWRITE_OPT,
    write_json_out,
)


@app.command("odometry")
def odometry_cmd(
    archive: Path = typer.Argument(..., help="A .lac archive.", exists=True, dir_okay=False),
    source: Optional[str] = typer.Option(
        None,
        "--source",
        "-s",
        metavar=ODOMETRY_METAVAR,
        help="visual | imu | record:NAME | ground-truth (evaluation only). "
        "Default: visual when the archive has front stereo pairs, else imu.",
    ),
    out: Optional[Path] = typer.Option(
        None, "-o", "--out", help="Write the trajectory here (TUM: t x y z qx qy qz qw)."
    ),
    as_json: bool = JSON_STDOUT_OPT,
    json_out: Optional[Path] = JSON_OUT_OPT,
    kitti: Optional[Path] = typer.Option(
        None, "--kitti", help="Also write the trajectory as a KITTI pose file."
    ),
    overwrite: bool = OVERWRITE_OPT,
) -> None:
    """Odometry of ARCHIVE from SOURCE, and its drift against the archive's ground truth."""
    from tqdm import tqdm

    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.odometry.source import (
        archive_odometry,
        default_odometry_source,
        ground_truth_poses,
        odometry_drift,
    )
    from lunarloc.odometry.source import parse_odometry_source
    from lunarloc.io.trajectory import write_kitti, write_tum

    from lunarloc.core.errors import InputError
    from lunarloc.io.outputs import check_output_file

    if source is not None:
        parse_odometry_source(source)
    for path in (out, json_out, kitti):  # before the work: an existing output needs --overwrite
        if path is not None:
            check_output_file(path, overwrite)
    to_stdout = as_json
    con = console(stderr=to_stdout)  # with --json, stdout holds the JSON object alone
    with LacArchive(archive) as ar:
        source = source or default_odometry_source(ar)
        # on stderr
        bar = tqdm(unit="pair", desc=f"odometry {source}", dynamic_ncols=True, disable=None)

        def prog(n, total):
            bar.total = total
            bar.n = n
            if n % 20 == 0 or n == total:
                bar.refresh()

        traj = archive_odometry(ar, source, progress=prog)
        bar.close()
        drift = odometry_drift(traj.T_map_rover, ground_truth_poses(ar))
    drift = {
        "archive": str(archive),
        "source": traj.label,
        "evaluation_only": traj.evaluation_only,
        "measured_frames": int(traj.measured.sum()) if traj.measured is not None else None,
        "failures": traj.failures,
        **drift,
    }
    if not np.all(np.isfinite(traj.T_map_rover)):  # never written as a result
        raise InputError(
            f"{archive}: the {traj.label} odometry is not finite (a non-finite value in the "
            "archive?)"
        )
    bad = [k for k, v in drift.items() if isinstance(v, float) and not math.isfinite(v)]
    if bad:
        raise InputError(f"{archive}: drift figures {', '.join(bad)} are not finite")
    if out is not None:
        write_tum(out, traj.times_s, traj.T_map_rover)
    if kitti is not None:
        kitti.parent.mkdir(parents=True, exist_ok=True)
        write_kitti(kitti, traj.T_map_rover)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
    if to_stdout or json_out is not None:
        write_json_out(drift, json_out, to_stdout)
    pct = "-" if drift["final_error_pct"] is None else f"{drift['final_error_pct']:.2f} %"
    con.print(
        f"[bold]{archive.name}[/bold]: odometry {traj.label}, {drift['frames']} frames, "
        f"path {drift['path_length_m']:.2f} m (ground truth)"
    )
    con.print(f"  final error   : {drift['final_error_m']:.3f} m ({pct} of the path)")
    con.print(
        f"  heading error : {drift['heading_error_deg']:.3f} deg at the end (max "
        f"{drift['max_heading_error_deg']:.3f} deg)"
    )
    con.print(f"  RMSE          : {drift['rmse_m']:.3f} m (max {drift['max_error_m']:.3f} m)")
    if traj.failures:
        con.print(f"  visual odometry fell back to the IMU prior on {traj.failures} image pair(s)")
    for p in (out, kitti, json_out):
        if p is not None:
            con.print(f"wrote {p}")
