"""Confident-wrong poses on distorted vehicle maps: families of odometry distortion on
the 17 real LunarLoc traverses (all 136 pairs per family).

Families (the vehicle map of the second traverse of each pair, in a random frame):
* scale: the whole map scaled about its centroid by 0.5-3 % (either sign), as an
  odometry scale error makes it;
* heading drift 0.025-0.1 deg/m (plus 1 % scale in one family) over windows of the last
  10-60 m of the path (what an online rover localizes).

Each family runs with the odometry bounds given to the localizer
(``LocalizationConfig.odometry_scale_error`` / ``odometry_heading_drift_deg_per_m`` set
to the family's magnitudes, as a rover's odometry specification would state them) and,
with ``--without-bounds``, also without: the localizer then fits a bent and scaled model of
the vehicle map to its inliers (``lunarloc.localization.bending.bending_fit``) and adds what that model
moves, and cannot exclude, at the rover to the predicted error. The pose is judged at the rover's last position (``query_xyz``; the
path goes in as ``path_xyz``). Reported per family: pairs correct (a rigid pose within
10 cm / 1 deg at the rover exists and was found), localized (success claimed),
confident-wrong (claimed but not correct: must be 0), and coverage of the predicted
1-sigma errors (share of localized pairs within 1 and 3 sigma).

Usage: python benchmarks/distortion_families.py [--data ../shared/data/lunarloc-data]
       [--out distortion.json] [--quick] [--without-bounds | --only-without-bounds]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from lunarloc.pipeline.evaluation import DriftModel, bench_pairs
from lunarloc.localization.config import LocalizationConfig

SCALES = (0.005, 0.01, 0.02, 0.03, -0.01, -0.03)
DRIFTS = ((0.025, 0.0), (0.05, 0.0), (0.1, 0.0), (0.05, 0.01))
WINDOWS = (10.0, 30.0, 60.0)


def families(quick: bool = False):
    """(name, DriftModel, window_m, scale_about_centroid) of every family."""
    out = [
        (f"scale {s:+.1%}", DriftModel(), None, 1.0 + s)
        for s in (SCALES[1::2] if quick else SCALES)
    ]
    for d, sc in DRIFTS[1:3] if quick else DRIFTS:
        for w in (30.0,) if quick else WINDOWS:
            name = f"drift {d:g} deg/m" + (f" scale {sc:+.0%}" if sc else "") + f" window {w:g} m"
            out.append((name, DriftModel(d, sc), w, 1.0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", default="../shared/data/lunarloc-data")
    ap.add_argument("--out", default="distortion.json")
    ap.add_argument("--quick", action="store_true", help="a subset of the families")
    ap.add_argument(
        "--without-bounds",
        action="store_true",
        help="also run every family without telling the localizer the odometry bounds",
    )
    ap.add_argument(
        "--only-without-bounds",
        action="store_true",
        help="run every family only without the odometry bounds (the localizer fits the distortion)",
    )
    args = ap.parse_args()
    rows = []
    t0 = time.perf_counter()
    for name, drift, window, scale in families(args.quick):
        for bounds in (
            (False,)
            if args.only_without_bounds
            else (True, False)
            if args.without_bounds
            else (True,)
        ):
            cfg = LocalizationConfig(  # without bounds (None) the localizer fits the distortion from the maps
                odometry_scale_error=max(abs(drift.scale_error), abs(scale - 1.0))
                if bounds
                else None,
                odometry_heading_drift_deg_per_m=drift.heading_drift_deg_per_m if bounds else None,
            )
            summary = bench_pairs(
                args.data, loc_config=cfg, drift=drift, window_m=window, scale_about_centroid=scale
            )
            d = summary.to_dict()
            row = {
                "family": name,
                "bounds_given": bounds,
                "pairs": d["pairs"],
                "correct": d["correct"],
                "localized": d["success"],
                "confident_wrong": d["confident_wrong"],
                "wrong_pairs": [
                    f"{r.reference}-{r.vehicle}" for r in summary.results if r.confident_wrong
                ],
                "coverage": d["coverage"],
                "median_time_s": d["median_time_s"],
            }
            rows.append(row)
            cov = d["coverage"]
            cov_s = (
                f"cover 1s {cov['position_1sigma']:.0%} 3s {cov['position_3sigma']:.0%}"
                if cov["n"]
                else ""
            )
            print(
                f"{name:42s} bounds {'yes' if bounds else 'no ':3s}: correct {d['correct']:3d} localized "
                f"{d['success']:3d} confident-wrong {d['confident_wrong']:2d} {cov_s}",
                flush=True,
            )
    total_wrong = sum(r["confident_wrong"] for r in rows if r["bounds_given"])
    without = [r["confident_wrong"] for r in rows if not r["bounds_given"]]
    print(
        f"confident-wrong with bounds given: {total_wrong}"
        + (f"; without: {sum(without)}" if without else "")
        + f"  ({time.perf_counter() - t0:.0f} s)"
    )
    Path(args.out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
