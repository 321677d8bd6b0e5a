"""Where the detector loses rocks of r >= 0.1 m within 5 m: the missed sightings of
``bench_perception.py --misses`` tabulated by stage against range, radius, sun, rover tilt
and the share of the rock's disc that shows in the image, each band with the count of all
target sightings in it (the denominators, from the archives' semantic images).

Usage
-----
    python benchmarks/bench_perception.py ARCHIVE.lac ... --misses M.csv
    python benchmarks/miss_table.py M.csv ARCHIVE.lac ...

A target sighting is a rock of true radius >= 0.1 m whose centre is within 5 m of the left
camera and that covers at least ``--min-gt-px`` (50, as bench_perception.py) pixels of the
left image, none within 2 px of its border. Its *visible share* is its pixel count over the
area of a disc of its radius at its range (pi (fx r / range)^2): a rock behind a crater rim
or another rock, or a low rock mostly buried, shows well under half of it. The rover's tilt
is the angle of its z axis from vertical (frames.csv roll and pitch). Prints Markdown tables.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import math
import sys
from collections import Counter
from pathlib import Path

import numpy as np

BANDS = {
    "range (m)": [0.0, 2.0, 3.0, 4.0, 5.0001],
    "radius (m)": [0.1, 0.15, 0.2, 10.0],
    "tilt (deg)": [0.0, 5.0, 10.0, 15.0, 90.0],
    "visible share": [0.0, 0.25, 0.5, 100.0],
}


def band(v: float, edges: list[float]) -> str:
    """The band of `v` ("lo-hi", the last one ">= lo"), prefixed by its index for sorting."""
    last = len(edges) - 2
    for i, (lo, hi) in enumerate(itertools.pairwise(edges)):
        if lo <= v < hi:
            return f"{i}|" + (f">= {lo:g}" if i == last else f"{lo:g}-{hi:.4g}")
    return "9|other"


def target_sightings(path: Path, min_gt_px: int) -> dict[tuple[int, str, int], dict]:
    """(frame, camera, rock id) -> range, radius, tilt, visible share, sun of every target
    sighting of the archive's left cameras."""
    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.camera import camera_from_archive
    from lunarloc.perception.detector import mounts_from_archive_row
    from lunarloc.pipeline.perception_eval import lighting_label
    from lunarloc.sim.render import semantic_to_rock_id

    sun = lighting_label(path)
    out = {}
    with LacArchive(path) as ar:
        cam = camera_from_archive(ar)
        t = ar.custom("rocks")
        ids = np.asarray(t["id"]).astype(int)
        centres = np.column_stack([t["x"], t["y"], t["z"]])
        radii = np.asarray(t["radius"], float)
        index = {int(i): k for k, i in enumerate(ids)}
        for rec in ar.iter_frames(semantic=True):
            s = rec.state
            T = pose_to_matrix(s["x"], s["y"], s["z"], s["roll"], s["pitch"], s["yaw"])
            tilt = math.degrees(math.acos(math.cos(s["roll"]) * math.cos(s["pitch"])))
            mounts = mounts_from_archive_row(rec.cameras, cam) if rec.cameras else {}
            for name, sem in rec.semantic.items():
                if not name.endswith("Left") or name not in mounts:
                    continue
                rid = semantic_to_rock_id(sem)
                border = np.concatenate(
                    [rid[:2].ravel(), rid[-2:].ravel(), rid[:, :2].ravel(), rid[:, -2:].ravel()]
                )
                edge = set(np.unique(border).tolist())
                cam_pos = (T @ mounts[name].T_rover_optical)[:3, 3]
                vis, counts = np.unique(rid[rid >= 0], return_counts=True)
                for r, n in zip(vis.tolist(), counts.tolist()):
                    if n < min_gt_px or r in edge or r not in index:
                        continue
                    j = index[r]
                    rng = float(np.linalg.norm(centres[j] - cam_pos))
                    if radii[j] < 0.1 or rng > 5.0:
                        continue
                    disc = math.pi * (cam.fx * radii[j] / rng) ** 2
                    out[(int(rec.frame), name, int(r))] = {
                        "range (m)": rng,
                        "radius (m)": float(radii[j]),
                        "tilt (deg)": tilt,
                        "visible share": n / disc,
                        "sun": sun,
                    }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("misses", type=Path, help="the CSV of bench_perception.py --misses")
    ap.add_argument("archives", type=Path, nargs="+", help="the archives it was measured on")
    ap.add_argument("--min-gt-px", type=int, default=50)
    a = ap.parse_args(argv)
    rows = list(csv.DictReader(a.misses.open()))
    sightings: dict[str, dict] = {}
    for p in a.archives:
        sightings[p.name] = target_sightings(p, a.min_gt_px)
    missed = []
    for r in rows:
        key = (int(r["frame"]), r["camera"], int(r["rock_id"]))
        s = sightings.get(r["archive"], {}).get(key)
        if s is None:
            print(f"warning: {r['archive']} {key} is not a target sighting here", file=sys.stderr)
            continue
        missed.append((r["stage"], s))
    every = [s for per in sightings.values() for s in per.values()]
    stages = [k for k, _ in Counter(st for st, _ in missed).most_common()]
    print(
        f"{len(missed)} of {len(every)} target sightings missed; by stage: "
        + ", ".join(f"{k} {sum(st == k for st, _ in missed)}" for k in stages)
    )
    keys = {k: (lambda s, e=e, k=k: band(s[k], e)) for k, e in BANDS.items()}
    keys["sun"] = lambda s: s["sun"]
    for name, fn in keys.items():
        print(f"\n| {name} | " + " | ".join(stages) + " | missed / all |")
        print("| --- " * (len(stages) + 2) + "|")
        for v in sorted({fn(s) for s in every}):
            sel = [st for st, s in missed if fn(s) == v]
            n_all = sum(fn(s) == v for s in every)
            cells = " | ".join(str(sel.count(k)) for k in stages)
            print(f"| {v.split('|')[-1]} | {cells} | {len(sel)} / {n_all} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
