"""Run folders: what ``lunarloc run``, ``demo`` and ``bench loop`` write, and reading them back.

A run folder holds (every file written to a temporary name and renamed, so an interrupted run
leaves no truncated file; ``summary.json``, written last, marks a complete run):

- ``trajectory.tum`` (corrected: the pose graph at the end of the run), ``trajectory_online.tum``
  (causal: what the rover knew at each frame), ``trajectory_odometry.tum``,
  ``trajectory_groundtruth.tum`` (when known); TUM lines ``t x y z qx qy qz qw``, frame ``map``;
- ``attempts.csv`` and ``attempts.json`` (every localization attempt);
- ``vehicle_map.csv`` (detections placed with the corrected poses), ``vehicle_map_odometry.csv``
  (both with a ``# pose: odometry:...`` line, their pose provenance), ``reference_map.csv``,
  ``rocks.csv`` (when known);
- ``example_frame.npz`` (one camera frame with its detections, when images were used);
- ``config.json`` (the run's :class:`~lunarloc.config.run.RunConfig`, read back by ``--config``,
  plus an ``info`` section: the source, camera and odometry actually used);
- ``summary.json``.

:func:`write_run` writes one, :func:`read_run` reads it into a :class:`RunFolder`.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from lunarloc.core.errors import FileFormatError

# their home is io.trajectory; kept importable here
from lunarloc.io.trajectory import read_tum, write_tum

__all__ = ["write_tum", "read_tum", "write_run", "read_run", "RunFolder", "to_json_ready"]


def to_json_ready(x):
    """Plain JSON values: NaN/inf become None, Enums their values, numpy scalars Python's."""
    if isinstance(x, dict):
        return {str(k): to_json_ready(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_json_ready(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return to_json_ready(x.item())
    if hasattr(x, "value") and not isinstance(x, (int, float, str)):
        return x.value
    return x


def write_run(result, outdir: str | Path, before_summary=None) -> dict:
    """Write a :class:`~lunarloc.online.loop.LoopResult` to the run folder `outdir` (see the module
    docstring); returns its summary. ``summary.json`` is written last and marks a complete
    folder: `before_summary(summary)`, when given, runs just before it (the figures,
    :func:`lunarloc.viz.plot_run` with ``summary=``), so a run interrupted while plotting
    never looks complete."""
    from lunarloc.io.maps import POSE_ODOMETRY, PoseProvenance, save_map
    from lunarloc.io.outputs import atomic_open, atomic_path, make_dir, write_text
    from lunarloc.io.maps import ROCK_COLUMNS

    out = make_dir(outdir)
    write_tum(out / "trajectory.tum", result.times, result.T_map_rover)
    write_tum(out / "trajectory_online.tum", result.times, result.T_map_rover_online)
    write_tum(out / "trajectory_odometry.tum", result.times, result.T_odo_rover)
    if result.T_map_rover_true is not None:
        write_tum(out / "trajectory_groundtruth.tum", result.times, result.T_map_rover_true)
    keys = result.attempt_columns()
    with atomic_open(out / "attempts.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        for a in result.attempts:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in a.row().items()})
    write_text(
        out / "attempts.json",
        json.dumps([to_json_ready(asdict(a)) for a in result.attempts], indent=1),
    )
    # both vehicle maps were placed by odometry (corrected by the loop's fixes, or raw): their files
    # say so, and lunarloc localize judges them with its odometry prior, not as rigid maps
    for lm, name, detail in (
        (result.vehicle_map, "vehicle_map.csv", "corrected by the loop"),
        (result.vehicle_map_odometry, "vehicle_map_odometry.csv", "raw"),
    ):
        save_map(replace(lm, pose_provenance=PoseProvenance(POSE_ODOMETRY, detail)), out / name)
    save_map(result.reference, out / "reference_map.csv")
    if result.rocks is not None:
        with atomic_path(out / "rocks.csv") as tmp:
            np.savetxt(
                tmp,
                result.rocks,
                delimiter=",",
                header=",".join(ROCK_COLUMNS),
                comments="",
                fmt=["%d", "%.5f", "%.5f", "%.5f", "%.5f"],
            )
    if result.example is not None:
        ex = result.example
        with atomic_path(out / "example_frame.npz") as tmp:
            np.savez_compressed(
                tmp,
                image=ex["image"],
                uv=ex["uv"],
                radius_px=ex["radius_px"],
                depth_m=ex["depth_m"],
                frame=ex["frame"],
                camera=ex["camera"],
            )
    write_text(out / "config.json", json.dumps(to_json_ready(result.config), indent=2, default=str))
    summary = result.summary()
    if before_summary is not None:
        before_summary(to_json_ready(summary))
    write_text(out / "summary.json", json.dumps(to_json_ready(summary), indent=2))
    return summary


@dataclass
class RunFolder:
    """A run folder read back (poses (F, 6) x, y, z, roll, pitch, yaw in ``map``)."""

    path: Path
    times: np.ndarray
    corrected: np.ndarray
    odometry: np.ndarray
    online: np.ndarray | None
    ground_truth: np.ndarray | None
    attempts: list[dict]
    summary: dict
    config: dict | None  # config.json as written (None when absent)
    reference_xyz: np.ndarray
    vehicle_xyz: np.ndarray
    vehicle_odometry_xyz: np.ndarray
    rocks: np.ndarray | None  # (N, 5) id, x, y, z, radius


RUN_FILES_NEEDED = ("trajectory.tum", "trajectory_odometry.tum", "attempts.json", "summary.json")


def read_run(outdir: str | Path, summary: dict | None = None) -> RunFolder:
    """Read a run folder written by :func:`write_run`; FileFormatError naming the folder when
    it is not one or a file is damaged. `summary`: the summary not yet written (figures drawn
    before ``summary.json``, see :func:`write_run`)."""
    outdir = Path(outdir)
    missing = [
        n
        for n in RUN_FILES_NEEDED
        if not (outdir / n).is_file() and not (n == "summary.json" and summary is not None)
    ]
    if missing:
        raise FileFormatError(f"{outdir}: not a lunarloc run folder (missing {', '.join(missing)})")
    try:
        return _read_run(outdir, summary)
    except (
        ValueError,
        IndexError,
    ) as exc:  # json, TUM or CSV contents; LunarLocErrors pass through
        if isinstance(exc, FileFormatError):
            raise
        raise FileFormatError(
            f"{outdir}: damaged run folder ({type(exc).__name__}: {str(exc)[:120]})"
        ) from None


def _read_run(outdir: Path, summary: dict | None = None) -> RunFolder:
    from lunarloc.io.maps import load_map

    def tum(name):
        return read_tum(outdir / name)[1] if (outdir / name).is_file() else None

    def xyz(name):
        return (
            load_map(outdir / name).positions_xyz if (outdir / name).is_file() else np.zeros((0, 3))
        )

    t, corrected = read_tum(outdir / "trajectory.tum")
    rocks = outdir / "rocks.csv"
    cfg = outdir / "config.json"
    return RunFolder(
        outdir,
        t,
        corrected,
        tum("trajectory_odometry.tum"),
        tum("trajectory_online.tum"),
        tum("trajectory_groundtruth.tum"),
        json.loads((outdir / "attempts.json").read_text()),
        summary if summary is not None else json.loads((outdir / "summary.json").read_text()),
        json.loads(cfg.read_text()) if cfg.is_file() else None,
        xyz("reference_map.csv"),
        xyz("vehicle_map.csv"),
        xyz("vehicle_map_odometry.csv"),
        np.loadtxt(rocks, delimiter=",", skiprows=1, ndmin=2) if rocks.is_file() else None,
    )
