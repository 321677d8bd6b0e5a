"""Calibration of the localizer's claims: claimed, right, confident-wrong and the
NEES shares per family of maps, configuration (the CLI's default: no odometry bounds stated;
the maps stated rigid) and search (full, indexed, auto). The families and the judging are in
:mod:`lunarloc.pipeline.calibration`; this prints the table and writes every outcome as JSON.

With ``--data`` (the lunarloc-data folder) it also runs the 136 real traverse pairs under
random rigid motions with the CLI's default configuration (what ``lunarloc localize A B``
does with two traverse CSVs), and the paper's five pairs among them.

Usage: python benchmarks/calibration.py [--per-family 8] [--families lattice,motifs]
       [--searches full,indexed,auto] [--configs "cli default,stated rigid"]
       [--data ../shared/data/lunarloc-data] [--out calibration.json]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from lunarloc.pipeline.calibration import (
    CONFIGS, FAMILIES, NEES_68, NEES_997, SEARCHES, format_table, make_cases, run_cases, summarise,
)


def real_pairs(data: str) -> dict:
    """The 136 real pairs, CLI default (no odometry bounds), and the paper's five among them."""
    from lunarloc.localization.localize import LocalizationConfig
    from lunarloc.pipeline.evaluation import PAPER_PAIRS, bench_pairs

    s = bench_pairs(data, loc_config=LocalizationConfig())
    paper = [r for r in s.results if (r.reference, r.vehicle) in PAPER_PAIRS]
    claims = [r for r in s.results if r.success]
    d2 = np.array([r.covariance_d2 for r in claims if math.isfinite(r.covariance_d2)])
    return {"pairs": s.n_pairs, "claimed": s.n_success, "right": s.n_success_and_correct,
            "confident_wrong": s.n_confident_wrong, "paper_claimed": sum(r.success for r in paper),
            "paper_right": sum(r.success and r.correct for r in paper),
            "nees_origin_68": float(np.mean(d2 <= NEES_68)) if len(d2) else None,
            "nees_origin_997": float(np.mean(d2 <= NEES_997)) if len(d2) else None,
            "refused": [f"{r.reference}-{r.vehicle}: {r.reason}" for r in s.results if not r.success]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--per-family", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--searches", default=",".join(SEARCHES))
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--data", default=None, help="lunarloc-data folder: also the 136 real pairs, CLI default")
    ap.add_argument("--out", default="calibration.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    cases = make_cases(args.families.split(","), args.per_family, args.first_seed)
    outs = run_cases(cases, args.configs.split(","), args.searches.split(","),
                     progress=lambda o: print(f"  {o.family} #{o.seed} {o.config} {o.search}: "
                                              f"{'claimed' if o.claimed else 'refused'}"
                                              f"{' WRONG' if o.confident_wrong else ''} err {o.err_m:.3f} m "
                                              f"pred {o.predicted_error_m:.3f} m NEES {o.nees:.2f} ({o.time_s:.1f} s)",
                                              flush=True))
    rows = summarise(outs)
    print(format_table(rows))
    total_cw = sum(r["confident_wrong"] for r in rows)
    print(f"confident-wrong: {total_cw} of {len(outs)} runs ({time.perf_counter() - t0:.0f} s)")
    result = {"rows": rows, "outcomes": [o.to_dict() for o in outs]}
    if args.data:
        rp = real_pairs(args.data)
        result["real_pairs"] = rp
        print(f"136 real pairs, CLI default: claimed {rp['claimed']}, right {rp['right']}, confident-wrong "
              f"{rp['confident_wrong']}; paper pairs claimed {rp['paper_claimed']} of 5")
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1, default=float)


if __name__ == "__main__":
    main()
