"""Benchmark of the perception front end on simulated traverses (ground truth known).

Usage
-----
    python benchmarks/bench_perception.py ARCHIVE.lac [ARCHIVE.lac ...] [--every N]
        [--segmenter classical|fastsam --weights PATH] [--no-centre-correction]
        [--centre-method METHOD] [--config RUN_CONFIG.json] [--breakdown] [--json OUT.json]
    python benchmarks/bench_perception.py --simulate SEED [SEED ...] [--lighting sun|lamps|sun+lamps]
        [--sun-elevation DEG] [--duration S] [--width W --height H] ...   # renders first (front pair)
    python benchmarks/bench_perception.py --lac-real DIR [--figure PNG]  # the real LAC frame
    python benchmarks/bench_perception.py --speed ARCHIVE.lac             # time one front pair
    python benchmarks/bench_perception.py ARCHIVE.lac ... --misses MISSES.csv  # where each miss is lost, rocks missed most
    python benchmarks/bench_perception.py --pool RUN1.json RUN2.json ...  # pool earlier runs' sites, with intervals
    python benchmarks/bench_perception.py --real-labels [DIR] [--misses M.csv]  # the labelled real LAC pairs

Archives must come from `lunarloc simulate` (they hold ``custom/rocks.csv`` and the
semantic images). The image size and field of view are read from each archive
(``initial.toml``); the detector's pixel-sized parameters, tuned at 1280x720, are
scaled to the archive's width (``lunarloc.config.run.scaled_detector_config``).
Detections use the ground-truth rover pose, so the errors measured are those of
perception alone.

Metrics
-------
* A ground-truth rock is *visible* in a left image when it covers at least
  ``--min-gt-px`` pixels there and none of them is within 2 px of the border (the
  method rejects masks cut by the border by design). Its range is the distance from
  the camera to its centre.
* A detection matches a rock when its 3D centroid is within max(0.15 m, rock radius)
  of the rock's centre; matching is one-to-one per frame, greedy by distance; a
  detection may match any rock (visible or not, e.g. one occluded at the border).
* Recall by size band (true radius) and range band, over visible rocks; precision by
  estimated-radius band and range band (detection depth), over detections.
* Centroid error of matched detections: 3D and horizontal (median, p90), for the
  visible-surface centroid and the centre-corrected one.
* 90 % intervals of the targets' figures (precision within 5 m, the two recalls, the
  median centre error), per lighting, by a bootstrap over sites (`site_bootstrap`): a
  rock is seen in several frames and terrain fools the detector frame after frame, so
  the sites, not the sightings, are the independent draws. With four sites an interval
  is often 0.1 wide; pool more sites to judge a target.
* Time per frame per stage (segment, filter, stereo), both left images of a frame.
  With the classical segmenter "stereo" is the half-resolution SGBM + ground height
  map that segmentation itself uses, so images/s counts all three stages.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lunarloc.core.errors import InputError
from lunarloc.perception.detector import CentreMethod, Detector, DetectorConfig
from lunarloc.pipeline.perception_eval import (
    FP_CAUSES,
    MISS_FIELDS,
    RANGE_BANDS,
    SIZE_BANDS,
    Accumulator,
    format_pooled,
    lighting_label,
    misses_by_rock,
    pair_speed,
    pool_runs,
    pooled_rows,
    run_archive,
)


def print_pooled(pooled: dict[str, dict[str, dict]]) -> dict:
    """One row per lighting: the pooled figures with their 90 % site-bootstrap intervals."""
    rows = pooled_rows(pooled)
    print("\n".join(format_pooled(rows)))
    return rows


def print_breakdown(groups: dict[str, dict]) -> None:
    """The centre error's parts per lighting, over all target matches and by true radius and
    range band (cm)."""
    print(
        "centre error of target matches (cm): n, median, p90, horizontal median, along-ray (+ far), |lateral|, "
        "vertical (+ high), est/true radius, median with the true radius"
    )
    for name, s in groups.items():
        print(
            f"{name}: median {100 * s['centroid_err_target_median_m']:.1f}, horizontal "
            f"{100 * s['centroid_err_target_xy_median_m']:.1f}"
        )
        for band, b in s["centre_breakdown"].items():
            o = b["true_radius_oracle_median_m"]
            print(
                f"  {band:>14} {b['n']:4d} {100 * b['median_m']:5.1f} {100 * b['p90_m']:5.1f} "
                f"{100 * b['xy_median_m']:5.1f} {100 * b['along_median_m']:+5.1f} {100 * b['lateral_abs_median_m']:4.1f} "
                f"{100 * b['vertical_median_m']:+5.1f} {b['radius_ratio_median']:5.2f} "
                + ("-" if o is None else f"{100 * o:5.1f}")
            )


def print_summary(s: dict) -> None:
    def band(b):
        return f"{b[0]:g}-{b[1]:g}" if b[1] < 10 else f">={b[0]:g}"

    print(f"frames {s['frames']}, detections {s['detections']}")
    print("recall (hit/visible) by true radius [m] x range [m]")
    print("radius \\ range " + "".join(f"{band(r):>16}" for r in RANGE_BANDS))
    for i, sb in enumerate(SIZE_BANDS):
        row = s["recall_by_size_range"][i]
        print(
            f"{band(sb):>14} "
            + "".join(f"{(h / t if t else float('nan')):>8.2f} ({h:>3}/{t:>3})" for h, t in row)
        )
    print("precision (tp/detections) by estimated radius [m] x depth [m]")
    for i, sb in enumerate(SIZE_BANDS):
        row = s["precision_by_estsize_range"][i]
        print(
            f"{band(sb):>14} "
            + "".join(f"{(h / t if t else float('nan')):>8.2f} ({h:>3}/{t:>3})" for h, t in row)
        )
    for k, v in s.items():
        if k not in ("recall_by_size_range", "precision_by_estsize_range", "centre_breakdown"):
            if k != "by_lighting":
                print(f"{k}: {v}")


def print_groups(groups: dict[str, dict]) -> None:
    """One row per lighting: the issue's targets side by side."""
    hdr = (
        "lighting",
        "frames",
        "P(<=5m)",
        "R(r>=.1,<=5m)",
        "R(.05-.1,<=3m)",
        "R(.025-.05,<=3m)",
        "err50 cm",
        "err90 cm",
        "frames/s",
        "CPU ms/frame",
    )
    print(" | ".join(hdr))
    for name, s in groups.items():
        print(
            " | ".join(
                [
                    name,
                    str(s["frames"]),
                    f"{s['precision_range<=5']:.2f}",
                    f"{s['target_recall_r>=0.1_range<=5']:.2f}",
                    f"{s['recall_0.05<=r<0.1_range<=3']:.2f}",
                    f"{s.get('recall_0.025<=r<0.05_range<=3', float('nan')):.2f} ({s.get('recall_0.025<=r<0.05_range<=3_counts', ['-', '-'])[1]})",
                    f"{100 * s['centroid_err_target_median_m']:.1f}",
                    f"{100 * s['centroid_err_target_p90_m']:.1f}",
                    f"{s['frames_per_s']:.1f}",
                    f"{s['cpu_ms_per_frame']:.0f}",
                ]
            )
        )
    ci = {
        name: s["site_bootstrap_ci90"] for name, s in groups.items() if s.get("site_bootstrap_ci90")
    }
    if ci:
        print(
            "90 % intervals, the sites resampled (bootstrap): P(<=5m) | R(r>=.1,<=5m) | R(.05-.1,<=3m) | err50 cm"
        )
        for name, c in ci.items():

            def iv(k, scale=1.0, fmt="{:.3f}"):
                return (
                    "-"
                    if k not in c
                    else "[" + ", ".join(fmt.format(scale * v) for v in c[k]) + "]"
                )

            print(
                f"{name} ({groups[name]['sites']} sites): "
                + " | ".join(
                    [
                        iv("precision_range<=5"),
                        iv("target_recall_r>=0.1_range<=5"),
                        iv("recall_0.05<=r<0.1_range<=3"),
                        iv("centroid_err_target_median_m", 100.0, "{:.1f}"),
                    ]
                )
            )
    print("false positives within 5 m by cause: " + ", ".join(FP_CAUSES))
    for name, s in groups.items():
        c = s.get("false_positives_within_5m_by_cause", {})
        print(f"{name}: " + " ".join(str(c.get(k, 0)) for k in FP_CAUSES))


def lac_real_frame(
    folder: Path, figure: Path | None = None, cfg: DetectorConfig | None = None
) -> list:
    """Detect rocks on the real LAC frame (FrontLeft/FrontRight_99.png, pose_99.json; the
    lander stands at the site centre, the map origin); print the detections and draw
    them (kept masks green, rejected ones coloured by filter) into `figure`. `cfg`: the
    detector configuration (default DetectorConfig())."""
    import cv2

    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.perception.detector import debug_overlay

    left = cv2.imread(str(folder / "FrontLeft_99.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(folder / "FrontRight_99.png"), cv2.IMREAD_GRAYSCALE)
    if left is None or right is None:
        raise SystemExit(f"no FrontLeft_99.png / FrontRight_99.png in {folder}")
    p = json.loads((folder / "pose_99.json").read_text())
    T = pose_to_matrix(*[float(p[k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")])
    det = Detector(cfg or DetectorConfig(), PinholeCamera(left.shape[1], left.shape[0], 70.0))
    T_ro = ipex_rig(det.camera)["FrontLeft"].T_rover_optical
    det.detect_pair(left, right, T_ro, T, "FrontLeft")  # warm-up (OpenCV allocations)
    t0 = time.perf_counter()
    pr = det.detect_pair(left, right, T_ro, T, "FrontLeft", keep_depth=True, lander_xy=np.zeros(2))
    dt = time.perf_counter() - t0
    print(f"real LAC frame 99: {len(pr.detections)} detections in {1000 * dt:.0f} ms (wall)")
    for d in pr.detections:
        print(
            f"  u,v {d.uv[0]:6.0f} {d.uv[1]:5.0f}  depth {d.depth_m:5.2f} m  radius {d.radius_m:5.3f} m  "
            f"map {d.p_map[0]:6.2f} {d.p_map[1]:6.2f} {d.p_map[2]:6.2f}"
        )
    counts: dict[str, int] = {}
    for r in pr.records:
        if r.reason is not None:
            counts[r.reason.value] = counts.get(r.reason.value, 0) + 1
    print("  rejected masks by filter:", counts)
    if figure is not None:
        figure.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(figure), debug_overlay(left, pr)[:, : left.shape[1]])
        print(f"  figure -> {figure}")
    return pr.detections


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("archives", nargs="*", type=Path)
    ap.add_argument(
        "--simulate", type=int, nargs="*", default=[], help="site seeds to render first"
    )
    ap.add_argument("--duration", type=float, default=60.0, help="seconds per simulated traverse")
    ap.add_argument("--image-rate", type=float, default=0.5, help="simulated camera rate, Hz")
    ap.add_argument("--width", type=int, default=1280, help="simulated image width, px")
    ap.add_argument("--height", type=int, default=720, help="simulated image height, px")
    ap.add_argument(
        "--lighting", default="sun+lamps", help="simulated lighting: sun | lamps | sun+lamps"
    )
    ap.add_argument(
        "--sun-elevation",
        type=float,
        default=12.0,
        help="simulated sun elevation, degrees (<= 0: night)",
    )
    ap.add_argument("--out-dir", type=Path, default=Path("bench-output/perception"))
    ap.add_argument("--every", type=int, default=1, help="use every N-th camera frame")
    ap.add_argument(
        "--segmenter", default=None, help="classical | fastsam (default: the config's, classical)"
    )
    ap.add_argument("--weights", default=None)
    ap.add_argument("--no-centre-correction", action="store_true")
    ap.add_argument(
        "--centre-method",
        default=None,
        help=" | ".join(m.value for m in CentreMethod) + " (default: the config's)",
    )
    ap.add_argument(
        "--breakdown",
        action="store_true",
        help="print the centre error by true radius and range band, split along / across the ray / vertical",
    )
    ap.add_argument("--min-gt-px", type=int, default=50)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--lac-real", type=Path, default=None, help="run the real LAC frame in this folder and stop"
    )
    ap.add_argument(
        "--figure", type=Path, default=None, help="with --lac-real: draw the detections here"
    )
    ap.add_argument(
        "--speed", action="store_true", help="time the detector on one front pair of each archive"
    )
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="a run configuration (config.json, `lunarloc config`): its detector section is benchmarked",
    )
    ap.add_argument(
        "--pool",
        type=Path,
        nargs="+",
        default=None,
        metavar="JSON",
        help="pool the per-site counts of earlier --json outputs (other sites, or other lightings) and "
        "print each lighting's figures with 90 %% intervals, the sites resampled; detects nothing",
    )
    ap.add_argument(
        "--misses",
        type=Path,
        default=None,
        help="write each missed sighting of a rock r >= 0.1 m within 5 m, with the stage where it was "
        "lost (the mask overlapping it most: its reject reason, or kept but off-centre; or no blob), to "
        "this CSV, and print the counts by stage and the rocks missed most",
    )
    ap.add_argument(
        "--real-labels",
        type=Path,
        nargs="?",
        const=Path(""),
        default=None,
        metavar="DIR",
        help="score the hand-labelled real LAC pairs (tests/data/lac_real_labels.json; images in DIR, default "
        "$LUNARLOC_LAC_REAL or ../shared/data/lac-real) with benchmarks/real_labels.py, with --config, "
        "--misses and --json passed on, and stop",
    )
    ap.add_argument(
        "--small-rocks",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the small-rock stage on or off (DetectorConfig.small_rocks.enabled; on by default)",
    )
    a = ap.parse_args(argv)
    if a.small_rocks is not None and a.real_labels is None:
        ap.error(
            "--[no-]small-rocks goes with --real-labels; for archives give --config with "
            '{"detector": {"small_rocks": {"enabled": false}}}'
        )
    if a.real_labels is not None:
        import real_labels

        args = ["--data", str(a.real_labels)] if str(a.real_labels) not in ("", ".") else []
        for flag, v in (("--config", a.config), ("--misses", a.misses), ("--json", a.json)):
            args += [flag, str(v)] if v is not None else []
        if a.small_rocks is not None:
            args += ["--small-rocks" if a.small_rocks else "--no-small-rocks"]
        return real_labels.main(args)
    base = DetectorConfig()
    if a.config is not None:
        from lunarloc.config.run import load_config_file

        base = load_config_file(a.config)[0].detector
    if a.centre_method:
        base = replace(base, centre=replace(base.centre, method=CentreMethod(a.centre_method)))
    if a.pool is not None:
        try:
            pooled = print_pooled(pool_runs(a.pool))
        except InputError as e:
            raise SystemExit(f"--pool: {e}") from None
        if a.json:
            a.json.parent.mkdir(parents=True, exist_ok=True)
            a.json.write_text(json.dumps(pooled, indent=2))
        return 0
    if a.lac_real is not None:
        lac_real_frame(a.lac_real, a.figure, base)
        return 0
    if a.speed:
        for p in a.archives:
            print(p, json.dumps({k: round(v, 1) for k, v in pair_speed(p, cfg=base).items()}))
        return 0
    archives = list(a.archives)
    for seed in a.simulate:
        from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse

        from lunarloc.sim.render import RenderConfig

        sc = SimulationConfig(
            duration_s=a.duration,
            image_rate_hz=a.image_rate,
            width=a.width,
            height=a.height,
            cameras=("FrontLeft", "FrontRight"),
            render=RenderConfig(sun_elevation_deg=a.sun_elevation, lighting=a.lighting),
        )
        size = "" if (a.width, a.height) == (1280, 720) else f"_{a.width}x{a.height}"
        light = f"_{a.lighting.replace('+', '_')}_el{a.sun_elevation:g}"
        p = a.out_dir / f"site{seed}{light}_traverse0{size}.lac"
        if not p.exists():
            a.out_dir.mkdir(parents=True, exist_ok=True)
            t0 = time.time()
            simulate_traverse(simulate_site(seed, sc), p, 0, sc)
            print(f"rendered {p} in {time.time() - t0:.0f} s", file=sys.stderr)
        archives.append(p)
    if not archives:
        ap.error("give archives or --simulate SEED")
    cfg = replace(
        base,
        segmenter=a.segmenter or base.segmenter,
        weights=a.weights or base.weights,
        centre=replace(
            base.centre, correction=base.centre.correction and not a.no_centre_correction
        ),
    )
    acc = Accumulator()
    acc.min_gt_px = a.min_gt_px
    det = None
    configs = {}  # the detector config used at each image size (pixel parameters scaled)
    groups: dict[str, Accumulator] = {}
    misses: list[dict] = []
    for p in archives:
        g = groups.setdefault(lighting_label(p), Accumulator())
        g.min_gt_px = a.min_gt_px
        if a.misses is not None:
            g.misses = misses
        det = run_archive(p, cfg, a.every, g, det, progress=lambda s: print(s, file=sys.stderr))
        configs[f"{det.camera.width}x{det.camera.height}"] = det.config.to_dict()
    for g in groups.values():  # the total over all archives
        acc.merge(g)
    s = acc.summary()
    s["by_lighting"] = {k: g.summary() for k, g in groups.items()}
    s["archives"] = [str(p) for p in archives]
    s["config"] = configs[next(iter(configs))] if len(configs) == 1 else configs
    print_summary(s)
    print_groups({**s["by_lighting"], "all": s})
    if a.breakdown:
        print_breakdown({**s["by_lighting"], "all": s})
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(s, indent=2, default=str))
    if a.misses is not None:
        write_misses(a.misses, misses)
    return 0


def write_misses(path: Path, rows: list[dict]) -> None:
    """The missed target sightings as CSV (MISS_FIELDS), and their counts by stage."""
    import csv
    from collections import Counter

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=MISS_FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})
    counts = Counter(r["stage"] for r in rows)
    print(
        f"missed target sightings: {len(rows)} -> {path}; by stage: "
        + ", ".join(f"{k} {v}" for k, v in counts.most_common())
    )
    rules = Counter(r.get("tentative_rules") or "?" for r in rows if r["stage"] == "tentative")
    if rules:
        print(
            "tentatives never confirmed, by the rules that made them tentative: "
            + ", ".join(f"{k} {v}" for k, v in rules.most_common())
        )
    judged = Counter(r.get("rejected_by") or "?" for r in rows if r["stage"] == "not_a_rock")
    if judged:
        print(
            "judged no rock, by the rules that fired or the verifier: "
            + ", ".join(f"{k} {v}" for k, v in judged.most_common())
        )
    groups = misses_by_rock(rows)
    if groups:
        print("rocks missed most (archive, rock id, radius, range, sightings missed, stages):")
        for g in groups[:10]:
            print(
                f"  {g['archive']}  rock {g['rock_id']}  r {g['radius_m']:.2f} m  {g['range_min_m']:.1f}-"
                f"{g['range_max_m']:.1f} m  {g['missed']} x  "
                + ", ".join(f"{k} {v}" for k, v in g["stages"])
            )


if __name__ == "__main__":
    sys.exit(main())
