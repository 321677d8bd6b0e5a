"""Scoring the rock detector on the hand-labelled real LAC pairs (tests/data/lac_real_labels.json,
made as tests/data/README.md says): the logic behind ``benchmarks/real_labels.py``.

Each pair runs once through `Detector.detect_pair` with the IPEx front-left mount; frame 99 with
its ground-truth pose and the lander at the site centre, the ipex frames with no pose (their roll
and pitch are unknown: the rover frame is the detector's only frame). A detection is *on* a rock
when its image point lies in the rock's box grown by GROW_PX and its depth is within a factor
DEPTH_RATIO of the rock's range; a rock is found when a detection is on it. Recall counts certain
rocks with range <= recall_range_m (6 m); detections on uncertain rocks are ignored; every other
detection is false, and those on a no-fire region (lander, rover shadow) are counted apart. For
each missed rock, the stage that lost it (:func:`lunarloc.pipeline.perception_eval.miss_stage`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from lunarloc.core.errors import InputError, MissingFileError, import_cv2
from lunarloc.core.geometry import pose_to_matrix
from lunarloc.perception.camera import PinholeCamera, ipex_rig
from lunarloc.perception.detector import Detector, DetectorConfig
from lunarloc.pipeline.perception_eval import miss_stage

GROW_PX = 4
DEPTH_RATIO = 1.6


def load_labels(path: Path) -> dict:
    """The labels file (tests/data/lac_real_labels.json's layout: camera, recall_range_m,
    frames)."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read the labels {path}: {e}") from None


def _in_poly(uv, poly) -> bool:
    cv2 = import_cv2()
    return (
        cv2.pointPolygonTest(np.asarray(poly, np.float32), (float(uv[0]), float(uv[1])), False) >= 0
    )


def on_rock(det_uv, det_depth: float, rock: dict, grow: int = GROW_PX) -> bool:
    """A detection at image point `det_uv` and depth `det_depth` (m) is on `rock`: inside its box
    grown by `grow` px, at a depth within a factor DEPTH_RATIO of its range (when both are
    known)."""
    x0, y0, x1, y1 = rock["box"]
    u, v = det_uv
    if not (x0 - grow <= u <= x1 + grow and y0 - grow <= v <= y1 + grow):
        return False
    r = rock.get("range_m")
    return (
        r is None or not np.isfinite(det_depth) or 1.0 / DEPTH_RATIO <= det_depth / r <= DEPTH_RATIO
    )


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
            where = next(
                (z["what"] for z in frame.get("no_fire", []) if _in_poly(d.uv, z["polygon"])), ""
            )
        for r in hit:
            found.add(r["id"])
        det_rows.append(
            dict(
                uv=[round(float(d.uv[0]), 1), round(float(d.uv[1]), 1)],
                depth_m=round(float(d.depth_m), 2),
                radius_m=round(float(d.radius_m), 3),
                kind=kind,
                no_fire=where,
                rocks=[r["id"] for r in hit],
            )
        )
    target = [
        r
        for r in rocks
        if r["certain"] and r["range_m"] is not None and r["range_m"] <= recall_range_m
    ]
    return dict(
        frame=frame["name"],
        rocks=[
            dict(id=r["id"], width_m=r["width_m"], range_m=r["range_m"], found=r["id"] in found)
            for r in target
        ],
        detections=det_rows,
    )


def summarize(frames: list[dict]) -> dict:
    """Recall (all, >= 8 cm, < 8 cm, by range band: [found, total, ratio]) and the detections'
    counts and precision over frames scored by :func:`score_frame`."""
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
    by_range = {
        f"{a}-{b} m": rec([r for r in rocks if a <= r["range_m"] < b])
        for a, b in ((0, 2), (2, 4), (4, 6.01))
    }
    return dict(
        recall_all=rec(rocks),
        recall_ge_8cm=rec(big),
        recall_lt_8cm=rec(small),
        recall_by_range=by_range,
        detections=len(dets),
        on_rocks=on,
        on_uncertain=len(dets) - len(judged),
        false=len(judged) - on,
        precision=round(on / len(judged), 3) if judged else None,
        on_no_fire=sum(bool(d["no_fire"]) for d in dets),
    )


def run(
    data_dir: Path,
    labels: dict,
    cfg: DetectorConfig | None = None,
    frames_wanted=None,
    misses: list | None = None,
    figure_dir: Path | None = None,
) -> dict:
    """The detector (`cfg`, default DetectorConfig()) on each labelled pair under `data_dir`
    (`frames_wanted`: their names, default all): {"summary": :func:`summarize`'s, "frames": each
    frame's :func:`score_frame`}. Each missed rock's stage is appended to `misses` when a list is
    given; the drawn frames (:func:`draw`) are written to `figure_dir` when given."""
    cv2 = import_cv2()
    cam = labels["camera"]
    det = Detector(
        cfg or DetectorConfig(), PinholeCamera(cam["width_px"], cam["height_px"], cam["hfov_deg"])
    )
    T_ro = ipex_rig(det.camera)["FrontLeft"].T_rover_optical
    out = []
    wall = []
    for fr in labels["frames"]:
        if frames_wanted and fr["name"] not in frames_wanted:
            continue
        L = cv2.imread(str(data_dir / fr["left"]), cv2.IMREAD_GRAYSCALE)
        R = cv2.imread(str(data_dir / fr["right"]), cv2.IMREAD_GRAYSCALE)
        if L is None or R is None:
            raise MissingFileError(f"{fr['name']}: images not found under {data_dir}")
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
                if (
                    not r["certain"]
                    or r["range_m"] is None
                    or r["range_m"] > labels["recall_range_m"]
                    or r["id"] in found
                ):
                    continue
                px = np.zeros(L.shape, bool)
                x0, y0, x1, y1 = r["box"]
                px[y0 : y1 + 1, x0 : x1 + 1] = True
                misses.append(
                    dict(
                        frame=fr["name"],
                        rock_id=r["id"],
                        width_m=r["width_m"],
                        range_m=r["range_m"],
                        **miss_stage(pr, px),
                    )
                )
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
