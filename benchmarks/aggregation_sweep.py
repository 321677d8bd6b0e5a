"""Choose the landmark-aggregation parameters (DBSCAN radius, minimum sightings) by
measurement on the 17 real LunarLoc traverses.

For each setting it runs the all-pairs benchmark (136 pairs, seeded random vehicle
transforms) and reports: pairs localized correctly with success claimed, confident-wrong
pairs, median inliers, median and largest-pair association time, mean landmarks per map.

Usage: python benchmarks/aggregation_sweep.py [--data ../shared/data/lunarloc-data]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lunarloc.pipeline.evaluation import bench_pairs
from lunarloc.io.maps import AggregationConfig


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", default="../shared/data/lunarloc-data")
    ap.add_argument("--radii", default="0.05,0.1,0.2")
    ap.add_argument("--min-sightings", default="2,3,5,8")
    args = ap.parse_args()
    print(
        "radius_m min_sightings | ok/136 confident_wrong | median_inliers landmarks/map | median_s largest_pair_s"
    )
    for radius in (float(x) for x in args.radii.split(",")):
        for ms in (int(x) for x in args.min_sightings.split(",")):
            t0 = time.perf_counter()
            s = bench_pairs(
                args.data, agg_config=AggregationConfig(radius_m=radius, min_sightings=ms)
            )
            res = s.results
            big = max(res, key=lambda r: r.segs_ref * r.segs_veh)
            print(
                f"{radius:8.2f} {ms:13d} | {s.n_success_and_correct:6d} {s.n_confident_wrong:15d} | "
                f"{np.median([r.inliers for r in res]):14.0f} {np.mean([r.segs_veh for r in res]):13.0f} | "
                f"{np.median([r.time_s for r in res]):8.3f} {big.time_s:14.3f}   ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
