"""Score the rock detector on the hand-labelled real LAC pairs (tests/data/lac_real_labels.json).

    python benchmarks/real_labels.py [--data DIR] [--labels JSON] [--config RUN_CONFIG.json] [--small-rocks]
        [--frames lac99 ipex179 ...] [--misses OUT.csv] [--figure-dir DIR] [--json OUT.json]

DIR defaults to $LUNARLOC_LAC_REAL or ../shared/data/lac-real. Each pair runs once through
`Detector.detect_pair` with the IPEx front-left mount; frame 99 with its ground-truth pose and the
lander at the site centre (as `bench_perception --lac-real`), the ipex frames with no pose (their
roll and pitch are unknown: the rover frame is the detector's only frame).

Scoring (see tests/data/README.md): a detection is *on* a rock when its image point lies in the
rock's box grown by GROW_PX and its depth is within a factor 1.6 of the rock's range; a rock is
found when a detection is on it. Recall counts certain rocks with range <= recall_range_m (6 m);
detections on uncertain rocks are ignored; every other detection is false, and those on a no-fire
region (lander, rover shadow) are counted apart. For each missed rock, the stage that lost it
(`lunarloc.pipeline.perception_eval.miss_stage`: the mask overlapping its box most and that mask's reject reason,
or no blob with the share of the box that has a height and the highest height there).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

GROW_PX = 4
DEPTH_RATIO = 1.6
LABELS = HERE.parent / "tests" / "data" / "lac_real_labels.json"


def default_data_dir() -> Path:
    return Path(os.environ.get("LUNARLOC_LAC_REAL", HERE.parent.parent / "shared" / "data" / "lac-real"))


def load_labels(path: Path = LABELS) -> dict:
    return json.loads(Path(path).read_text())


def _in_poly(uv, poly) -> bool:
    import cv2

    return cv2.pointPolygonTest(np.asarray(poly, np.float32), (float(uv[0]), float(uv[1])), False) >= 0


def on_rock(det_uv, det_depth: float, rock: dict, grow: int = GROW_PX) -> bool:
    x0, y0, x1, y1 = rock["box"]
    u, v = det_uv
    if not (x0 - grow <= u <= x1 + grow and y0 - grow <= v <= y1 + grow):
        return False
    r = rock.get("range_m")
    return r is None or not np.isfinite(det_depth) or 1.0 / DEPTH_RATIO <= det_depth / r <= DEPTH_RATIO


def score_frame(frame: dict, dets: list, recall_range_m: float) -> dict:
    """Counts of one labelled frame for detections `dets` (objects with .uv, .depth_m)."""
    rocks = frame["rocks"]
    found = set()
    det_rows = []
    for d in dets:
        hit = [r for r in rocks if on_rock(d.uv, d.depth_m, r)]
        kind = "rock" if any(r["certain"] for r in hit) else ("uncertain" if hit else "false")
        where = ""
        if kind == "false":
            where = next((z["what"] for z in frame.get("no_fire", []) if _in_poly(d.uv, z["polygon"])), "")
        for r in hit:
            found.add(r["id"])
        det_rows.append(dict(uv=[round(float(d.uv[0]), 1), round(float(d.uv[1]), 1)], depth_m=round(float(d.depth_m), 2),
                             radius_m=round(float(d.radius_m), 3), kind=kind, no_fire=where,
                             rocks=[r["id"] for r in hit]))
    target = [r for r in rocks if r["certain"] and r["range_m"] is not None and r["range_m"] <= recall_range_m]
    return dict(frame=frame["name"], rocks=[dict(id=r["id"], width_m=r["width_m"], range_m=r["range_m"],
                                                  found=r["id"] in found) for r in target],
                detections=det_rows)


def summarize(frames: list[dict]) -> dict:
    rocks = [r for f in frames for r in f["rocks"]]
    dets = [d for f in frames for d in f["detections"]]

    def rec(sel):
        n = len(sel)
        k = sum(r["found"] for r in sel)
        return [k, n, round(k / n, 3) if n else None]

    big = [r for r in rocks if r["width_m"] >= 0.08]
    small = [r for r in rocks if r["width_m"] < 0.08]
    judged = [d for d in dets if d["kind"] != "uncertain"]
    on = sum(d["kind"] == "rock" for d in judged)
    by_range = {f"{a}-{b} m": rec([r for r in rocks if a <= r["range_m"] < b]) for a, b in ((0, 2), (2, 4), (4, 6.01))}
    return dict(recall_all=rec(rocks), recall_ge_8cm=rec(big), recall_lt_8cm=rec(small), recall_by_range=by_range,
                detections=len(dets), on_rocks=on, on_uncertain=len(dets) - len(judged),
                false=len(judged) - on, precision=round(on / len(judged), 3) if judged else None,
                on_no_fire=sum(bool(d["no_fire"]) for d in dets))


def run(data_dir: Path, labels: dict, cfg=None, frames_wanted=None, misses: list | None = None,
        figure_dir: Path | None = None) -> dict:
    import cv2

    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.perception.detector import Detector, DetectorConfig
    from lunarloc.pipeline.perception_eval import miss_stage

    cam = labels["camera"]
    det = Detector(cfg or DetectorConfig(), PinholeCamera(cam["width_px"], cam["height_px"], cam["hfov_deg"]))
    T_ro = ipex_rig(det.camera)["FrontLeft"].T_rover_optical
    out = []
    wall = []
    for fr in labels["frames"]:
        if frames_wanted and fr["name"] not in frames_wanted:
            continue
        L = cv2.imread(str(data_dir / fr["left"]), cv2.IMREAD_GRAYSCALE)
        R = cv2.imread(str(data_dir / fr["right"]), cv2.IMREAD_GRAYSCALE)
        if L is None or R is None:
            raise SystemExit(f"{fr['name']}: images not found under {data_dir}")
        T, lander = None, None
        if fr.get("pose"):
            p = json.loads((data_dir / fr["pose"]).read_text())
            T = pose_to_matrix(*[float(p[k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")])
            lander = np.zeros(2)  # the lander stands at the site centre
        t0 = time.perf_counter()
        pr = det.detect_pair(L, R, T_ro, T, "FrontLeft", keep_depth=True, lander_xy=lander)
        wall.append(time.perf_counter() - t0)
        s = score_frame(fr, pr.detections, labels["recall_range_m"])
        out.append(s)
        if misses is not None:
            found = {r["id"] for r in s["rocks"] if r["found"]}
            for r in fr["rocks"]:
                if not r["certain"] or r["range_m"] is None or r["range_m"] > labels["recall_range_m"] or r["id"] in found:
                    continue
                px = np.zeros(L.shape, bool)
                x0, y0, x1, y1 = r["box"]
                px[y0:y1 + 1, x0:x1 + 1] = True
                misses.append(dict(frame=fr["name"], rock_id=r["id"], width_m=r["width_m"], range_m=r["range_m"],
                                   **miss_stage(pr, px)))
        if figure_dir is not None:
            figure_dir.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(figure_dir / f"{fr['name']}.png"), draw(L, fr, s))
    summ = summarize(out)
    summ["wall_ms_per_pair_median"] = round(1000 * float(np.median(wall)), 1) if wall else None
    return dict(summary=summ, frames=out)


def draw(L: np.ndarray, frame: dict, scored: dict) -> np.ndarray:
    """The left image with the labels (rocks yellow, uncertain grey, no-fire blue) and the
    detections (green on a rock, red false, grey on an uncertain label)."""
    import cv2

    im = cv2.cvtColor(L, cv2.COLOR_GRAY2BGR)
    found = {r["id"] for r in scored["rocks"] if r["found"]}
    for z in frame.get("no_fire", []):
        cv2.polylines(im, [np.asarray(z["polygon"], np.int32)], True, (255, 128, 0), 1)
    for r in frame["rocks"]:
        x0, y0, x1, y1 = r["box"]
        col = (0, 220, 255) if r["certain"] else (150, 150, 150)
        if r["id"] in found:
            col = (0, 255, 0)
        cv2.rectangle(im, (x0 - 2, y0 - 2), (x1 + 2, y1 + 2), col, 1)
    for d in scored["detections"]:
        col = {"rock": (0, 255, 0), "false": (0, 0, 255), "uncertain": (160, 160, 160)}[d["kind"]]
        u, v = int(d["uv"][0]), int(d["uv"][1])
        cv2.drawMarker(im, (u, v), col, cv2.MARKER_CROSS, 12, 2)
    return im


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--labels", type=Path, default=LABELS)
    ap.add_argument("--config", type=Path, default=None, help="a run configuration whose detector section is used")
    ap.add_argument("--frames", nargs="*", default=None)
    ap.add_argument("--small-rocks", action="store_true",
                    help="turn the small-rock stage on (DetectorConfig.small_rocks.enabled; off by default)")
    ap.add_argument("--misses", type=Path, default=None, help="write each missed rock and its stage to this CSV")
    ap.add_argument("--figure-dir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    data = a.data or default_data_dir()
    cfg = None
    if a.config is not None:
        from lunarloc.config.run import load_config_file

        cfg = load_config_file(a.config)[0].detector
    if a.small_rocks:
        from dataclasses import replace

        from lunarloc.perception.detector import DetectorConfig
        from lunarloc.perception.small_rocks import SmallRockConfig

        base = cfg or DetectorConfig()
        cfg = replace(base, small_rocks=replace(base.small_rocks, enabled=True))
    misses: list | None = [] if a.misses is not None else None
    res = run(data, load_labels(a.labels), cfg, a.frames, misses, a.figure_dir)
    for f in res["frames"]:
        s = summarize([f])
        print(f"{f['frame']:9s} rocks {s['recall_all'][0]:2d}/{s['recall_all'][1]:2d}  >=8cm {s['recall_ge_8cm'][0]}/"
              f"{s['recall_ge_8cm'][1]}  detections {s['detections']:2d}: on rocks {s['on_rocks']}, false {s['false']}"
              f" (no-fire {s['on_no_fire']}), uncertain {s['on_uncertain']}")
    s = res["summary"]
    print("all: recall {0[0]}/{0[1]} = {0[2]}; >= 8 cm {1[0]}/{1[1]} = {1[2]}; < 8 cm {2[0]}/{2[1]} = {2[2]}".format(
        s["recall_all"], s["recall_ge_8cm"], s["recall_lt_8cm"]))
    print("     by range: " + ", ".join(f"{k} {v[0]}/{v[1]}" for k, v in s["recall_by_range"].items()))
    print(f"     detections {s['detections']}: on rocks {s['on_rocks']}, false {s['false']} (on no-fire regions "
          f"{s['on_no_fire']}), on uncertain labels {s['on_uncertain']}; precision {s['precision']}; "
          f"{s['wall_ms_per_pair_median']} ms per pair (wall, median)")
    if misses is not None:
        import csv
        from collections import Counter

        a.misses.parent.mkdir(parents=True, exist_ok=True)
        if misses:
            with open(a.misses, "w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(misses[0]))
                w.writeheader()
                for r in misses:
                    w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})
        print("missed rocks by stage: " + ", ".join(f"{k} {v}" for k, v in Counter(r['stage'] for r in misses).most_common()))
        for r in misses:
            print(f"  {r['rock_id']:7s} {r['width_m']:.3f} m wide at {r['range_m']:.2f} m: {r['stage']}"
                  + (f" ({r['tentative_rules']})" if r.get("tentative_rules") else "")
                  + (f" valid {r['valid_fraction']:.2f} max height {r['max_height_m']:.3f} m"
                     if r["stage"] == "no-blob" else f" overlap {r['overlap']:.2f}"))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
