"""The centre error of a map's landmarks against the true rock centres, next to that of
the single detections they were clustered from (issue 11: is the localisation-relevant
centre, the landmark, within 3 cm even where single detections are not?).

Usage
-----
    python benchmarks/landmark_centres.py ARCHIVES.lac... [--config RUN.json]
        [--min-sightings 3 5] [--json OUT.json]
    python benchmarks/landmark_centres.py --det DET.csv --rocks ROCKS.csv [--det ... --rocks ...]
        [--min-sightings 3 5] [--json OUT.json]

With archives (rendered with ``custom/rocks.csv``), the detector runs over each one as
``bench_perception.py`` runs it (``detect_archive``, ground-truth poses, the run
configuration's detector scaled to the archive's width, the lander dropped). With
``--det``/``--rocks`` pairs, detections CSVs written by ``lunarloc detect --pose
ground-truth`` are read instead (e.g. the multi-session reference traverses).

Each traverse's detections are clustered as ``lunarloc map`` clusters them
(:func:`lunarloc.io.maps.traverse_map`, ``AggregationConfig`` with the given minimum
sightings). Reported, for the rocks of radius >= 0.1 m ("target") and for all rocks:

* detections: each frame's detections matched one-to-one to the true rocks within
  max(0.15 m, r) (as ``bench_perception.py`` matches them); median and p90 of the 3D,
  horizontal and |vertical| centre errors. With archives only rocks within 5 m of the
  camera count (the issue's target); with CSVs within 5 m of the rover.
* landmarks: the map's landmarks matched one-to-one to the true rocks the same way;
  the same errors, and how many landmarks lie on a rock.

Groups: per archive lighting (from its description) and "all"; with CSVs, per file.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_perception import _lander_xy, lighting_label, match  # noqa: E402


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
            self.rows.append((float(np.linalg.norm(e)), float(np.linalg.norm(e[:2])), abs(float(e[2])), target))
        return len(m)

    def summary(self) -> dict:
        a = np.asarray(self.rows, float).reshape(-1, 4)
        out = {"items": self.items, "matched": int(len(a))}
        for name, sel in (("target", a[:, 3] > 0), ("all", np.ones(len(a), bool))):
            b = a[sel]
            out[name] = {"n": int(len(b))}
            for k, col in (("3d", 0), ("xy", 1), ("z_abs", 2)):
                out[name][f"{k}_median_m"] = float(np.median(b[:, col])) if len(b) else float("nan")
                out[name][f"{k}_p90_m"] = float(np.percentile(b[:, col], 90)) if len(b) else float("nan")
        return out


def _landmarks(frames: np.ndarray, rover_xyz: np.ndarray, dets: np.ndarray, det_frame: np.ndarray,
               min_sightings: int) -> np.ndarray:
    from lunarloc.io.maps import AggregationConfig, Traverse, traverse_map

    trav = Traverse(np.asarray(frames), np.asarray(rover_xyz, float).reshape(-1, 3), np.asarray(dets, float).reshape(-1, 3),
                    np.asarray(det_frame))
    return traverse_map(trav, replace(AggregationConfig(), min_sightings=min_sightings)).positions_xyz


def _archive_traverse(path: Path, base_cfg):
    """(frames, rover_xyz, detections (D, 3), their frames, their camera ranges, rocks, label)."""
    from lunarloc.config.run import scaled_detector_config
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.camera import STEREO_PAIRS
    from lunarloc.perception.camera import camera_from_archive
    from lunarloc.perception.detector import Detector, detect_archive

    with LacArchive(path) as ar:
        t = ar.custom("rocks")
        rocks = np.column_stack([t["id"], t["x"], t["y"], t["z"], t["radius"]])
        frames = [int(f) for f in ar.frame_numbers if ar.camera_row(STEREO_PAIRS[0][0], int(f)) is not None]
        cam = camera_from_archive(ar)
        det = Detector(scaled_detector_config(cam.width, base=base_cfg), cam)
        F, X, D, DF, R = [], [], [], [], []
        for fd in detect_archive(ar, det.config, "ground-truth", detector=det, frames=frames, lander_xy=_lander_xy(ar)):
            F.append(fd.frame)
            X.append(np.asarray(fd.T_map_rover, float)[:3, 3])
            for pair in fd.pairs:
                for d in pair.detections:
                    D.append(d.p_map)
                    DF.append(fd.frame)
                    R.append(float(np.linalg.norm(d.p_optical)))
        return F, X, D, DF, R, rocks, lighting_label(path)


def _csv_traverse(det_path: Path, rocks_path: Path):
    from lunarloc.sim.site import load_rocks_csv
    from lunarloc.io.maps import load_traverse

    tr = load_traverse(det_path)
    pos = {int(f): p for f, p in zip(tr.frames, tr.rover_xyz)}
    rng = [float(np.linalg.norm(p - pos[int(f)])) for p, f in zip(tr.detections_xyz, tr.detection_frame)]
    return (tr.frames, tr.rover_xyz, tr.detections_xyz, tr.detection_frame, rng, load_rocks_csv(rocks_path),
            str(det_path))


def evaluate(traverses, min_sightings: list[int]) -> dict:
    """{group: {"detections": summary, "landmarks_ms<M>": summary}} over `traverses`
    (iterable of _archive_traverse / _csv_traverse tuples)."""
    groups: dict[str, dict] = {}
    for F, X, D, DF, R, rocks, label in traverses:
        D, DF, R = np.asarray(D, float).reshape(-1, 3), np.asarray(DF), np.asarray(R, float)
        for g in (label, "all"):
            acc = groups.setdefault(g, {"detections": Errors(), **{f"landmarks_ms{m}": Errors() for m in min_sightings}})
            for f in np.unique(DF):
                sel = DF == f
                acc["detections"].add(D[sel], rocks, R[sel] <= 5.0)
            for m in min_sightings:
                acc[f"landmarks_ms{m}"].add(_landmarks(F, X, D, DF, m), rocks)
    order = [g for g in groups if g != "all"] + ["all"]
    return {g: {k: e.summary() for k, e in groups[g].items()} for g in order if g in groups}


def print_table(res: dict) -> None:
    def cm(x):
        return f"{100 * x:4.1f}"

    print("group | what | items | matched | target n: 3D median/p90, horizontal median/p90, |z| median (cm) | all n: 3D median")
    for g, v in res.items():
        for k, s in v.items():
            t, a = s["target"], s["all"]
            print(f"{g} | {k} | {s['items']} | {s['matched']} | {t['n']}: {cm(t['3d_median_m'])}/{cm(t['3d_p90_m'])}, "
                  f"{cm(t['xy_median_m'])}/{cm(t['xy_p90_m'])}, {cm(t['z_abs_median_m'])} | {a['n']}: {cm(a['3d_median_m'])}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("archives", nargs="*", type=Path)
    ap.add_argument("--det", type=Path, action="append", default=[], help="detections CSV (ground-truth poses)")
    ap.add_argument("--rocks", type=Path, action="append", default=[], help="rocks.csv of each --det, in order")
    ap.add_argument("--config", type=Path, default=None, help="run configuration JSON (its detector section)")
    ap.add_argument("--min-sightings", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    if len(a.det) != len(a.rocks):
        ap.error("give one --rocks per --det")
    if not a.archives and not a.det:
        ap.error("give archives or --det/--rocks pairs")
    from lunarloc.config.run import RunConfig, load_config_file

    cfg = (load_config_file(a.config)[0] if a.config else RunConfig()).detector
    trs = [_archive_traverse(p, cfg) for p in a.archives] + [_csv_traverse(d, r) for d, r in zip(a.det, a.rocks)]
    res = evaluate(trs, a.min_sightings)
    print_table(res)
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
