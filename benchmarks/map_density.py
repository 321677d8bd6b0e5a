"""What limits the landmark count of an image-built reference map (issue 11, item 3).

Usage
-----
    python benchmarks/map_density.py --archive DIR/traverse_0.lac --rocks DIR/rocks.csv
        --det before=det_before.csv --det after=det_after.csv [--every 1 2 4]
        [--min-sightings 2 3 5] [--json OUT.json]

Each ``--det NAME=CSV`` is a detections CSV of the archive written by ``lunarloc detect``
with ground-truth poses (e.g. one from the detector before a change and one after).
For every detections file, every camera-rate divisor ``--every`` (keep every N-th
image frame: the archive's rate / N) and every DBSCAN minimum ``--min-sightings``, the
map is built as ``lunarloc map`` builds it (``AggregationConfig``, radius unchanged) and
judged against the site's ground truth:

* landmarks, and how many lie within max(0.15 m, r) of a true rock ("on rock");
* coverage: the true rocks the traverse saw (within 6 m, the detector's range, of a left camera, in its
  70-degree field of view, at some image frame) by radius band, and how many of those
  have a landmark;
* sightings per detected rock (how many frames see each true rock that has one).

The numbers say which factor bounds the count: too few rocks in view (coverage),
too few detections per rock (recall x camera rate against min-sightings), or too few
rocks detected at all (recall).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

BANDS = [(0.0, 0.05), (0.05, 0.1), (0.1, 0.2), (0.2, 10.0)]


def _seen_rocks(
    archive: Path, rocks: np.ndarray, max_range_m: float = 6.0, hfov_deg: float = 70.0
) -> np.ndarray:
    """Boolean (N,): rocks within max_range_m of the FrontLeft camera and inside its
    horizontal field of view at some image frame (occlusion ignored)."""
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.perception.camera import PinholeCamera, ipex_rig

    T_rc = ipex_rig(PinholeCamera())["FrontLeft"].T_rover_optical
    seen = np.zeros(len(rocks), bool)
    half = np.radians(hfov_deg) / 2
    with LacArchive(archive) as ar:
        for rec in ar.iter_frames(semantic=False):
            if "FrontLeft" not in rec.grayscale:
                continue
            s = rec.state
            T = pose_to_matrix(s["x"], s["y"], s["z"], s["roll"], s["pitch"], s["yaw"]) @ T_rc
            p = (rocks[:, :3] - T[:3, 3]) @ T[:3, :3]  # optical frame: z forward, x right
            ok = (
                (p[:, 2] > 0.5)
                & (np.hypot(p[:, 0], p[:, 2]) < max_range_m)
                & (np.abs(np.arctan2(p[:, 0], p[:, 2])) < half)
            )
            seen |= ok
    return seen


def evaluate(trav, rocks: np.ndarray, seen: np.ndarray, every: int, min_sightings: int) -> dict:
    from lunarloc.io.maps import AggregationConfig, Traverse, traverse_map

    keep_frames = np.asarray(trav.frames)[::every]
    sel = np.isin(trav.detection_frame, keep_frames)
    sub = Traverse(
        keep_frames,
        np.asarray(trav.rover_xyz)[::every],
        trav.detections_xyz[sel],
        trav.detection_frame[sel],
    )
    lm = traverse_map(sub, replace(AggregationConfig(), min_sightings=min_sightings))
    P = lm.positions_xyz
    d = (
        np.linalg.norm(P[:, None, :] - rocks[None, :, :3], axis=2)
        if len(P)
        else np.zeros((0, len(rocks)))
    )
    j = d.argmin(axis=1) if len(P) else np.zeros(0, int)
    on = d[np.arange(len(P)), j] <= np.maximum(0.15, rocks[j, 3]) if len(P) else np.zeros(0, bool)
    mapped = np.zeros(len(rocks), bool)
    mapped[j[on]] = True
    # sightings of each true rock: detections within max(0.15, r) of it, distinct frames
    D = sub.detections_xyz
    dd = (
        np.linalg.norm(D[:, None, :] - rocks[None, :, :3], axis=2)
        if len(D)
        else np.zeros((0, len(rocks)))
    )
    near = dd <= np.maximum(0.15, rocks[:, 3])[None, :]
    frames_per_rock = np.array(
        [len(np.unique(sub.detection_frame[near[:, k]])) for k in range(len(rocks))]
    )
    out = {
        "every": every,
        "min_sightings": min_sightings,
        "detections": int(len(D)),
        "landmarks": int(len(P)),
        "on_rock": int(on.sum()),
        "bands": {},
    }
    for lo, hi in BANDS:
        b = (rocks[:, 3] >= lo) & (rocks[:, 3] < hi)
        det_b = b & (frames_per_rock > 0)
        out["bands"][f"{lo:g}-{hi:g}"] = {
            "seen": int((b & seen).sum()),
            "detected": int(det_b.sum()),
            "mapped": int((b & mapped).sum()),
            "median_frames_per_detected_rock": float(np.median(frames_per_rock[det_b]))
            if det_b.any()
            else 0.0,
        }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--archive", type=Path, required=True)
    ap.add_argument("--rocks", type=Path, required=True)
    ap.add_argument(
        "--det", action="append", required=True, help="NAME=detections.csv (ground-truth poses)"
    )
    ap.add_argument("--every", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--min-sightings", type=int, nargs="+", default=[2, 3, 5])
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    from lunarloc.io.maps import load_traverse
    from lunarloc.sim.site import load_rocks_csv

    rocks = load_rocks_csv(a.rocks)[:, 1:5]
    seen = _seen_rocks(a.archive, rocks)
    rows = []
    for spec in a.det:
        name, path = spec.split("=", 1)
        trav = load_traverse(path)
        for every in a.every:
            for ms in a.min_sightings:
                r = evaluate(trav, rocks, seen, every, ms)
                r["detector"] = name
                rows.append(r)
    band_names = [f"{lo:g}-{hi:g}" for lo, hi in BANDS]
    print(
        "rocks seen within 6 m (by radius band "
        + ", ".join(band_names)
        + "): "
        + ", ".join(str(rows[0]["bands"][b]["seen"]) for b in band_names)
    )
    print(
        "detector | every | min_sightings | detections | landmarks | on rock | mapped/seen per band | frames per detected rock"
    )
    for r in rows:
        bands = " ".join(f"{r['bands'][b]['mapped']}/{r['bands'][b]['seen']}" for b in band_names)
        fpr = " ".join(
            f"{r['bands'][b]['median_frames_per_detected_rock']:.0f}" for b in band_names
        )
        print(
            f"{r['detector']} | {r['every']} | {r['min_sightings']} | {r['detections']} | {r['landmarks']} | "
            f"{r['on_rock']} | {bands} | {fpr}"
        )
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
