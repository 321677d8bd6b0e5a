"""Calibration of the localizer's claims: claimed, right, confident-wrong and the
NEES shares per family of maps, configuration (the CLI's default: no odometry bounds stated;
the maps stated rigid) and search (full, indexed, auto). The families and the judging are in
:mod:`lunarloc.pipeline.calibration`; this prints the table, and with ``--json PATH`` (or
``--out PATH``) writes every outcome as JSON there (no file by default).

With ``--data`` (the lunarloc-data folder) it also runs the real families
(:data:`lunarloc.pipeline.calibration.REAL_FAMILIES`: the 136 pairs of the 17 traverses under
random rigid motions, built from the ground-truth poses or by a distorting odometry), with the
CLI's default configuration (what ``lunarloc localize A B`` does with the files: no bounds stated,
the vehicle file's pose provenance: the dataset's schema for the ground-truth-posed maps, rigid;
``odometry`` as lunarloc writes it for the distorted ones, the prior) and with the odometry's
bounds stated as they are, judged at the rover (NEES of its position, 3 dof); and the paper's five
pairs among them. ``--real-configs`` also takes "no provenance" (a file that says nothing: the
prior) and "claimed rigid" (every file says ground truth, the distorted ones falsely).

Usage: python benchmarks/calibration.py [--per-family 8] [--families lattice,motifs]
       [--searches full,indexed,auto] [--configs "cli default,stated rigid"]
       [--data ../shared/data/lunarloc-data] [--real-families all]
       [--real-configs "cli default,stated bounds,no provenance,claimed rigid"] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from lunarloc.pipeline.calibration import (
    CONFIGS,
    FAMILIES,
    NEES_68,
    NEES_997,
    REAL_CONFIGS,
    REAL_FAMILIES,
    SEARCHES,
    format_table,
    make_cases,
    run_cases,
    run_real,
    summarise,
)


def real_pairs(outcomes) -> dict:
    """The 136 real pairs under the CLI's default (what ``lunarloc localize A B`` does with two dataset
    traverse CSVs: no bounds stated, the files' ground-truth pose provenance), and the paper's five
    among them, from :func:`run_real`'s outcomes."""
    from lunarloc.pipeline.evaluation import PAPER_PAIRS

    rs = [o for o in outcomes if o.family == "real pairs" and o.config == "cli default"]
    paper = [o for o in rs if divmod(o.seed, 100) in PAPER_PAIRS]
    claims = [o for o in rs if o.claimed]
    d2 = np.array([o.nees for o in claims if math.isfinite(o.nees)])
    return {
        "pairs": len(rs),
        "claimed": len(claims),
        "right": sum(o.right for o in claims),
        "confident_wrong": sum(o.confident_wrong for o in rs),
        "paper_claimed": sum(o.claimed for o in paper),
        "paper_right": sum(o.claimed and o.right for o in paper),
        "nees_rover_68": float(np.mean(d2 <= NEES_68)) if len(d2) else None,
        "nees_rover_997": float(np.mean(d2 <= NEES_997)) if len(d2) else None,
        "refused": [f"{o.params['pair']}: {o.reason}" for o in rs if not o.claimed],
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--per-family", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--searches", default=",".join(SEARCHES))
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument(
        "--data", default=None, help="lunarloc-data folder: also the real families (136 pairs each)"
    )
    ap.add_argument(
        "--real-families",
        default="real pairs",
        help=f"with --data: comma-separated, 'all' for every one of {', '.join(REAL_FAMILIES)}",
    )
    ap.add_argument("--real-configs", default=",".join(REAL_CONFIGS))
    ap.add_argument(
        "--json",
        "--out",
        dest="out",
        default=None,
        metavar="PATH",
        help="write the rows and every outcome as JSON here (default: no file)",
    )
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    cases = make_cases(args.families.split(","), args.per_family, args.first_seed)
    outs = run_cases(
        cases,
        args.configs.split(","),
        args.searches.split(","),
        progress=lambda o: print(
            f"  {o.family} #{o.seed} {o.config} {o.search}: "
            f"{'claimed' if o.claimed else 'refused'}"
            f"{' WRONG' if o.confident_wrong else ''} err {o.err_m:.3f} m "
            f"pred {o.predicted_error_m:.3f} m NEES {o.nees:.2f} ({o.time_s:.1f} s)",
            flush=True,
        ),
    )
    rows = summarise(outs)
    print(format_table(rows))
    total_cw = sum(r["confident_wrong"] for r in rows)
    print(f"confident-wrong: {total_cw} of {len(outs)} runs ({time.perf_counter() - t0:.0f} s)")
    result = {"rows": rows, "outcomes": [o.to_dict() for o in outs]}
    if args.data:
        fams = list(REAL_FAMILIES) if args.real_families == "all" else args.real_families.split(",")
        routs = run_real(args.data, fams, args.real_configs.split(","))
        rrows = summarise(routs)
        print(format_table(rrows))
        print(
            f"confident-wrong on the real families: {sum(r['confident_wrong'] for r in rrows)} of {len(routs)} runs"
        )
        result["real_rows"] = rrows
        result["real_outcomes"] = [o.to_dict() for o in routs]
        rp = real_pairs(routs)
        result["real_pairs"] = rp
        print(
            f"136 real pairs, CLI default: claimed {rp['claimed']}, right {rp['right']}, confident-wrong "
            f"{rp['confident_wrong']}; paper pairs claimed {rp['paper_claimed']} of 5"
        )
    if args.out is not None:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1, default=float)


if __name__ == "__main__":
    main()
