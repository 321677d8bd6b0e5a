"""Reference maps: what the rover localizes against (frame ``map``).

``load_reference(path)`` reads any supported reference file; ``build_reference_map`` builds one
from the images of an earlier traverse ("a map from a previous session", LunarLoc);
``reference_from_traverses`` merges the detections of several real traverses (the reference
of ``lunarloc bench loop``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from lunarloc.core.errors import InputError
from lunarloc.io.maps import (
    ROCK_COLUMNS,
    AggregationConfig,
    LandmarkMap,
    aggregate_detections,
    load_map,
)

log = logging.getLogger(__name__)
log.addHandler(logging.NullHandler())

__all__ = [
    "ROCK_COLUMNS",
    "rocks_to_reference",
    "load_reference",
    "reference_summary",
    "build_reference_map",
    "reference_from_traverses",
]


def rocks_to_reference(
    rocks: np.ndarray, min_radius_m: float = 0.05, top_offset: float = 0.025
) -> LandmarkMap:
    """Reference landmark map from a ground-truth rock list ``(N, 5) id, x, y, z, radius``.

    A vision detection of a rock lands on the centre of its *visible* part: horizontally
    the rock's centre (the detector shifts the surface centroid back by the estimated
    radius), vertically near the ellipsoid centre (the detector places it below the
    visible top by a share of the radius). Measured on simulated LAC-look sites with the
    current detector (3,619 detections of rocks of 5 cm radius and more on sites 280-285,
    placed with their true poses), detections sit ``+0.025 x radius`` above the ellipsoid
    centre (median), so landmarks are placed at ``z + top_offset * radius`` (docs/lac-map.md,
    "The corrected poses' height"). Rocks smaller than `min_radius_m` are dropped: the
    detector does not see them (its size floor is a radius of about 6 cm), and keeping
    them would only add chance associations.
    """
    r = np.asarray(rocks, float)
    if r.ndim != 2 or r.shape[1] < 5:
        raise InputError(f"rock list must be (N, 5) id,x,y,z,radius; got shape {r.shape}")
    keep = r[:, 4] >= min_radius_m
    if not keep.all():
        log.info(
            "reference: %d of %d rocks kept; %d under %g cm radius dropped (below the detector's "
            "size floor)",
            int(keep.sum()),
            len(r),
            int((~keep).sum()),
            min_radius_m * 100,
        )
    r = r[keep]
    pos = r[:, 1:4].copy()
    pos[:, 2] += top_offset * r[:, 4]
    return LandmarkMap(pos, sizes=2 * r[:, 4], frame="rocks")


def reference_summary(path: str | Path, reference: LandmarkMap, min_radius_m: float = 0.05) -> str:
    """How many landmarks `reference` (loaded from `path` by :func:`load_reference`) holds and,
    for a rock list, how many rocks were dropped and why: e.g. ``177 landmarks (386 rocks, 209
    under 5 cm radius dropped: below the detector's size floor)``."""
    path = Path(path)
    n = len(reference)
    if path.suffix.lower() == ".csv" and _is_rock_csv(path):
        total = len(load_rock_csv(path))
        if total > n:
            return (
                f"{n} landmarks ({total} rocks, {total - n} under {min_radius_m * 100:g} cm radius "
                "dropped: below the detector's size floor)"
            )
    return f"{n} landmarks"


def _is_rock_csv(path: Path) -> bool:
    from lunarloc.io.maps import _first_line

    return _first_line(path).split(",")[:5] == ROCK_COLUMNS


def load_reference(
    path: str | Path,
    config: AggregationConfig | None = None,
    min_radius_m: float = 0.05,
    dem: str | Path | None = None,
) -> LandmarkMap:
    """A reference map from a landmark CSV/.npz, a traverse CSV, a rock list (``rocks.csv``:
    ``id,x,y,z,radius``, converted by :func:`rocks_to_reference`), a LAC geometric map
    (``.npy``, rocks grouped by :func:`lunarloc.io.overhead.grid_landmarks`) or a rock catalogue
    (``x,y[,z],radius[,sigma_m]``; heights from the LAC map `dem` when it has no ``z``).
    Raises InputError when empty."""
    from lunarloc.io import overhead
    from lunarloc.io.inputs import check_input_file

    path = check_input_file(path, None, "reference map")
    if path.suffix.lower() == ".npy":
        ref = overhead.grid_landmarks(overhead.load_lac_grid(path), frame=path.stem)
    elif path.suffix.lower() == ".csv" and overhead.is_rock_catalogue(path):
        ref = overhead.load_rock_catalogue(path, dem)
    elif path.suffix.lower() == ".csv" and _is_rock_csv(path):
        ref = rocks_to_reference(load_rock_csv(path), min_radius_m)
    else:
        ref = load_map(path, config)
    if len(ref) < 3:
        raise InputError(f"{path}: reference map has {len(ref)} landmark(s); at least 3 are needed")
    return ref


def load_rock_csv(path: Path) -> np.ndarray:
    """(N, 5) id, x, y, z, radius from a rock list CSV; FileFormatError naming file and line."""
    from lunarloc.io.maps import read_numeric_csv

    _, header, table = read_numeric_csv(path, tuple(ROCK_COLUMNS), "rock list CSV")
    return table[:, [header.index(c) for c in ROCK_COLUMNS]]


def build_reference_map(
    archive_path: str | Path,
    config=None,
    progress: Callable[[int, int], None] | None = None,
) -> LandmarkMap:
    """Landmark map of an earlier traverse, built from its images with its (ground-truth)
    poses: the "map from a previous session" of LunarLoc (frame ``map``).

    config : :class:`lunarloc.config.run.RunConfig` (its detector, scaled to the archive's image
        width, and its loop's aggregation); default ``RunConfig()``."""
    from lunarloc.config.run import RunConfig
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.camera import camera_from_archive
    from lunarloc.perception.detector import Detector, detect_archive

    cfg = config or RunConfig()
    with LacArchive(archive_path) as ar:
        cam = camera_from_archive(ar)
        det = Detector(cfg.detector_for(cam.width), cam)
        pts, frames = [], []
        lefts = [l for l, _ in det.config.pairs if l in ar.cameras]
        total = len({int(f) for c in lefts for f in ar.camera_frames(c)["frame"]})
        for n, fd in enumerate(
            detect_archive(ar, det.config, "ground-truth", detector=det), start=1
        ):
            p = fd.positions_map()
            pts.append(p)
            frames.append(np.full(len(p), fd.frame))
            if progress:
                progress(n, total)
    if not pts:
        raise InputError(f"{archive_path}: no stereo image frames to build a reference map from")
    P = np.concatenate(pts)
    lm = aggregate_detections(P, np.concatenate(frames), cfg.loop.aggregation, frame="map")
    log.info("reference map from %s: %d detections -> %d landmarks", archive_path, len(P), len(lm))
    return lm


def reference_from_traverses(
    traverses: Mapping[int, object],
    exclude: int | None = None,
    config: AggregationConfig | None = None,
) -> LandmarkMap:
    """One reference map from the world-frame detections of several traverses
    (``{number: Traverse}``), all but `exclude`: each rock seen on any of them becomes one
    landmark. Frame numbers restart on every traverse, so each traverse's frames are kept
    apart (a rock needs its sightings from distinct frames, see
    :func:`lunarloc.io.maps.aggregate_detections`)."""
    keys = [k for k in traverses if k != exclude]
    if not keys:
        raise InputError("no traverse left to build the reference from")
    D = np.concatenate([traverses[k].detections_xyz for k in keys])
    offsets = np.concatenate(
        [np.full(len(traverses[k].detection_frame), i, np.int64) for i, k in enumerate(keys)]
    )
    frames = np.concatenate([traverses[k].detection_frame for k in keys]).astype(np.int64)
    span = int(frames.max()) + 1 if len(frames) else 1
    return aggregate_detections(D, frames + span * offsets, config, frame="map")
