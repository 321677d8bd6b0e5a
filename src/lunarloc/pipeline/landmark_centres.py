"""The centre error of a map's landmarks against the true rock centres, next to that of
the single detections they were clustered from: the logic behind
``benchmarks/landmark_centres.py`` (which prints the table).

Each traverse's detections are clustered as ``lunarloc map`` clusters them
(:func:`lunarloc.io.maps.traverse_map`, ``AggregationConfig`` with the given minimum
sightings), and both the detections (per frame) and the landmarks are matched one-to-one
to the true rocks within max(0.15 m, r) (:func:`lunarloc.pipeline.perception_eval.match`).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from lunarloc.config.run import scaled_detector_config
from lunarloc.io.lac.archive import LacArchive
from lunarloc.io.maps import AggregationConfig, Traverse, load_traverse, traverse_map
from lunarloc.perception.camera import STEREO_PAIRS, camera_from_archive
from lunarloc.perception.detector import Detector, DetectorConfig, detect_archive
from lunarloc.pipeline.perception_eval import lander_xy, lighting_label, match
from lunarloc.sim.site import load_rocks_csv


class Errors:
    """Matched centre errors (3D, horizontal, |vertical|), target and all."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float, float, bool]] = []  # (3d, xy, |z|, target)
        self.items = 0

    def add(self, est: np.ndarray, rocks: np.ndarray, near: np.ndarray | None = None) -> int:
        """Match `est` (N, 3) to `rocks` (M, 5: id x y z r); `near` (N,) marks the estimates
        whose rock counts as target range (None: all). Returns the number matched."""
        est = np.asarray(est, float).reshape(-1, 3)
        self.items += len(est)
        m = match(est, rocks[:, 1:4], rocks[:, 4])
        for i, j, _ in m:
            e = est[i] - rocks[j, 1:4]
            target = rocks[j, 4] >= 0.1 and (near is None or bool(near[i]))
            self.rows.append(
                (float(np.linalg.norm(e)), float(np.linalg.norm(e[:2])), abs(float(e[2])), target)
            )
        return len(m)

    def summary(self) -> dict:
        a = np.asarray(self.rows, float).reshape(-1, 4)
        out = {"items": self.items, "matched": int(len(a))}
        for name, sel in (("target", a[:, 3] > 0), ("all", np.ones(len(a), bool))):
            b = a[sel]
            out[name] = {"n": int(len(b))}
            for k, col in (("3d", 0), ("xy", 1), ("z_abs", 2)):
                out[name][f"{k}_median_m"] = float(np.median(b[:, col])) if len(b) else float("nan")
                out[name][f"{k}_p90_m"] = (
                    float(np.percentile(b[:, col], 90)) if len(b) else float("nan")
                )
        return out


def traverse_landmarks(
    frames: np.ndarray,
    rover_xyz: np.ndarray,
    dets: np.ndarray,
    det_frame: np.ndarray,
    min_sightings: int,
) -> np.ndarray:
    """The landmarks ``lunarloc map`` clusters from these detections (at least
    `min_sightings` sightings each), map frame (L, 3)."""
    trav = Traverse(
        np.asarray(frames),
        np.asarray(rover_xyz, float).reshape(-1, 3),
        np.asarray(dets, float).reshape(-1, 3),
        np.asarray(det_frame),
    )
    return traverse_map(
        trav, replace(AggregationConfig(), min_sightings=min_sightings)
    ).positions_xyz


def archive_traverse(path: Path, base_cfg: DetectorConfig) -> tuple:
    """A simulated archive's detections as ``bench_perception.py`` makes them (ground-truth
    poses, `base_cfg` scaled to the archive's width, the lander dropped): (frames,
    rover_xyz, detections (D, 3), their frames, their camera ranges, rocks (M, 5: id x y z
    r), lighting label)."""

    with LacArchive(path) as ar:
        t = ar.custom("rocks")
        rocks = np.column_stack([t["id"], t["x"], t["y"], t["z"], t["radius"]])
        frames = [
            int(f)
            for f in ar.frame_numbers
            if ar.camera_row(STEREO_PAIRS[0][0], int(f)) is not None
        ]
        cam = camera_from_archive(ar)
        det = Detector(scaled_detector_config(cam.width, base=base_cfg), cam)
        F, X, D, DF, R = [], [], [], [], []
        for fd in detect_archive(
            ar, det.config, "ground-truth", detector=det, frames=frames, lander_xy=lander_xy(ar)
        ):
            F.append(fd.frame)
            X.append(np.asarray(fd.T_map_rover, float)[:3, 3])
            for pair in fd.pairs:
                for d in pair.detections:
                    D.append(d.p_map)
                    DF.append(fd.frame)
                    R.append(float(np.linalg.norm(d.p_optical)))
        return F, X, D, DF, R, rocks, lighting_label(path)


def csv_traverse(det_path: Path, rocks_path: Path) -> tuple:
    """A detections CSV written by ``lunarloc detect --pose ground-truth`` and its rocks.csv,
    as :func:`archive_traverse`'s tuple (ranges from the rover; the label is the path)."""

    tr = load_traverse(det_path)
    pos = {int(f): p for f, p in zip(tr.frames, tr.rover_xyz)}
    rng = [
        float(np.linalg.norm(p - pos[int(f)]))
        for p, f in zip(tr.detections_xyz, tr.detection_frame)
    ]
    return (
        tr.frames,
        tr.rover_xyz,
        tr.detections_xyz,
        tr.detection_frame,
        rng,
        load_rocks_csv(rocks_path),
        str(det_path),
    )


def evaluate(traverses, min_sightings: list[int]) -> dict:
    """{group: {"detections": summary, "landmarks_ms<M>": summary}} over `traverses`
    (iterable of archive_traverse / csv_traverse tuples)."""
    groups: dict[str, dict] = {}
    for F, X, D, DF, R, rocks, label in traverses:
        D, DF, R = np.asarray(D, float).reshape(-1, 3), np.asarray(DF), np.asarray(R, float)
        for g in (label, "all"):
            acc = groups.setdefault(
                g, {"detections": Errors(), **{f"landmarks_ms{m}": Errors() for m in min_sightings}}
            )
            for f in np.unique(DF):
                sel = DF == f
                acc["detections"].add(D[sel], rocks, R[sel] <= 5.0)
            for m in min_sightings:
                acc[f"landmarks_ms{m}"].add(traverse_landmarks(F, X, D, DF, m), rocks)
    order = [g for g in groups if g != "all"] + ["all"]
    return {g: {k: e.summary() for k, e in groups[g].items()} for g in order if g in groups}
