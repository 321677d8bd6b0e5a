"""The 136 real traverse pairs of the LunarLoc dataset with the search forced to the
rock-triangle index (``localize_large(..., search="indexed")``) instead of the full
search: a robustness check of the index on real maps (real detection noise, real rock
density, partial overlap), against ``lunarloc bench pairs`` (full search) on the same
pairs and vehicle transforms.

The real references hold only ~150-450 rocks, so this measures whether the index finds
the region and whether its refusals stay honest, not speed.

Usage: python benchmarks/indexed_real_pairs.py [--data ../shared/data/lunarloc-data]
"""

from __future__ import annotations

import argparse
import itertools
import json

import lunarloc.pipeline.evaluation as ev
from lunarloc.localization.large import localize_large


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", default="../shared/data/lunarloc-data")
    ap.add_argument("--out", default="indexed_real_pairs.json")
    args = ap.parse_args()
    paths = ev.find_traverses(args.data)
    pairs = list(ev.PAPER_PAIRS) + [
        p for p in itertools.combinations(sorted(paths), 2) if p not in ev.PAPER_PAIRS
    ]
    # run_pair calls evaluation.localize; route it through the indexed search
    ev.localize = lambda ref, veh, cfg=None, **kw: localize_large(
        ref, veh, cfg, search="indexed", **kw
    )
    s = ev.bench_pairs(args.data, pairs)
    d = s.to_dict()
    bad = [
        f"{r.reference}-{r.vehicle}: {r.reason}" for r in s.results if not (r.success and r.correct)
    ]
    print(
        f"indexed search on {d['pairs']} real pairs: correct and accepted {d['success_and_correct']}, "
        f"confident-wrong {d['confident_wrong']}, median time {d['median_time_s']:.3f} s"
    )
    for line in bad:
        print("  not localized:", line)
    with open(args.out, "w") as f:
        json.dump(d, f, indent=1)


if __name__ == "__main__":
    main()
