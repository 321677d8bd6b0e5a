"""Where does the error at the rover come from, and what reduces it?

For every one of the 136 real traverse pairs, the error of the estimated pose at the
vehicle's last position is split into the part explained by the rotation error times
the lever arm from the inliers' centroid, and the rest. Variants show what each
ingredient buys: the clique alone (Arun on the maximum clique), + nearest-neighbour
refinement (more inliers), + robust re-weighting (better use of landmark centres), and
more landmarks (fewer sightings needed per landmark).

Usage: python benchmarks/error_budget.py [--data ../shared/data/lunarloc-data]
"""

from __future__ import annotations

import argparse

import numpy as np

from lunarloc.pipeline.evaluation import bench_pairs
from lunarloc.localization.config import LocalizationConfig
from lunarloc.io.maps import AggregationConfig

VARIANTS = {
    "clique only (Arun on the max clique)": (LocalizationConfig(refine=False), None),
    "+ NN refinement, no robust weights": (LocalizationConfig(robust_scale_m=1e3), None),
    "+ robust (Cauchy IRLS) = default": (LocalizationConfig(), None),
    "default, more landmarks (min_sightings 3)": (
        LocalizationConfig(),
        AggregationConfig(min_sightings=3),
    ),
}


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", default="../shared/data/lunarloc-data")
    args = ap.parse_args()
    print(
        "variant | correct (<10 cm, <1 deg) | err@rover cm median/p90/max | err@origin cm median/max | "
        "rot deg median/max | rotation x lever share of err@rover (median) | lever m median"
    )
    for name, (cfg, agg) in VARIANTS.items():
        s = bench_pairs(args.data, loc_config=cfg, agg_config=agg)
        r = [x for x in s.results if np.isfinite(x.err_rover_m)]
        er = np.array([x.err_rover_m for x in r]) * 100
        eo = np.array([x.err_origin_m for x in r]) * 100
        rot = np.array([x.rot_err_deg for x in r])
        share = np.array(
            [min(x.rotation_part_m / x.err_rover_m, 9.99) for x in r if x.err_rover_m > 0]
        )
        lever = np.array([x.lever_m for x in r])
        print(
            f"{name} | {s.n_correct}/{s.n_pairs} | {np.median(er):.1f}/{np.percentile(er, 90):.1f}/{er.max():.1f} | "
            f"{np.median(eo):.2f}/{eo.max():.2f} | {np.median(rot):.3f}/{rot.max():.3f} | {np.median(share):.2f} | "
            f"{np.median(lever):.1f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
