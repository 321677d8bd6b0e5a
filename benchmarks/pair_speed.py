"""CPU time of the association on the 136 real traverse pairs, and the answers, for a
before/after comparison of search changes.

Each pair is built exactly as ``lunarloc bench pairs`` builds it (seed 0, same random
vehicle transform); ``localize`` is timed with ``time.process_time`` (CPU time of the whole
process, all threads), so the figure does not depend on how loaded the machine is, and
with wall time. A warm-up call first (compile time is never counted). The answer of each
pair (success, inliers, clique and competitor sizes, reason) goes to a JSON file;
``--compare OLD.json`` reports every pair whose answer differs.

Usage::

    python benchmarks/pair_speed.py --data ../shared/data/lunarloc-data --out /tmp/ps.json [--threads 1]
    python benchmarks/pair_speed.py ... --compare /tmp/ps_before.json
    python benchmarks/pair_speed.py ... --pairs 13-15 3-7 --repeat 5
"""

from __future__ import annotations

import argparse
import itertools
import json
import time

import numpy as np

import lunarloc.pipeline.evaluation as evaluation
from lunarloc.pipeline.evaluation import bench_pairs, find_traverses
from lunarloc.localization.config import LocalizationConfig
from lunarloc.localization.localize import localize


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", required=True)
    ap.add_argument("--out", required=True, help="JSON file of per-pair answers and times")
    ap.add_argument(
        "--threads", type=int, default=None, help="search threads (default: the config's)"
    )
    ap.add_argument("--pairs", nargs="*", help="pairs as A-B (default: all)")
    ap.add_argument("--repeat", type=int, default=1, help="calls per pair; the fastest is kept")
    ap.add_argument(
        "--unbounded",
        action="store_true",
        help="state no odometry bounds (the distortion is fitted "
        "from the maps, as a one-shot `lunarloc localize` does)",
    )
    ap.add_argument(
        "--compare", help="earlier JSON of this script: list pairs whose answer differs"
    )
    args = ap.parse_args()
    pairs = (
        [tuple(int(x) for x in p.split("-")) for p in args.pairs]
        if args.pairs
        else list(itertools.combinations(sorted(find_traverses(args.data)), 2))
    )
    # as `lunarloc bench pairs` runs them: the maps are rigid (ground-truth poses), and the
    # localizer is told so (odometry bounds 0); without bounds it fits the distortion instead
    bounds = dict(odometry_scale_error=0.0, odometry_heading_drift_deg_per_m=0.0)
    if args.unbounded:
        bounds = {}
    cfg = (
        LocalizationConfig(**bounds)
        if args.threads is None
        else LocalizationConfig(threads=args.threads, **bounds)
    )
    calls = []

    def timed_localize(*a, **k):  # bench_pairs' own loop, with each call's CPU and wall time kept
        cpus, walls = [], []
        for _ in range(args.repeat):
            c0, w0 = time.process_time(), time.perf_counter()
            r = localize(*a, **k)
            cpus.append(time.process_time() - c0)
            walls.append(time.perf_counter() - w0)
        calls.append((r, min(cpus), min(walls), len(a[0]), len(a[1])))
        return r

    evaluation.localize = timed_localize
    try:
        summary = bench_pairs(args.data, pairs, loc_config=cfg)
    finally:
        evaluation.localize = localize
    calls = calls[1:]  # the first call is bench_pairs' warm-up
    rows = []
    for p, (r, cpu_s, wall_s, n_ref, n_veh) in zip(summary.results, calls):
        rows.append(
            dict(
                pair=f"{p.reference}-{p.vehicle}",
                n_ref=n_ref,
                n_veh=n_veh,
                cpu_s=cpu_s,
                wall_s=wall_s,
                success=bool(r.success),
                inliers=sorted(map(list, r.inliers.tolist())),
                clique=r.clique_size,
                competitor=r.competitor_size,
                reason=r.reason,
                timings=r.timings,
            )
        )
    cpu = np.array([r["cpu_s"] for r in rows])
    wall = np.array([r["wall_s"] for r in rows])
    big = max(rows, key=lambda r: r["n_ref"] * r["n_veh"])
    print(
        f"{len(rows)} pairs, threads {cfg.threads}: CPU median {np.median(cpu):.4f} s, total {cpu.sum():.2f} s; "
        f"wall median {np.median(wall):.4f} s; largest {big['pair']}: CPU {big['cpu_s']:.3f} s, wall {big['wall_s']:.3f} s"
    )
    print(f"success {sum(r['success'] for r in rows)}")
    with open(args.out, "w") as f:
        json.dump(rows, f)
    if args.compare:
        old = {r["pair"]: r for r in json.load(open(args.compare))}
        diff = 0
        for r in rows:
            o = old.get(r["pair"])
            if o is None:
                continue
            keys = [
                k for k in ("success", "inliers", "clique", "competitor", "reason") if o[k] != r[k]
            ]
            if keys:
                diff += 1
                print(
                    f"  {r['pair']}: differs in {keys}: "
                    + "; ".join(f"{k} {o[k]!r} -> {r[k]!r}" for k in keys if k != "inliers")
                )
        ocpu = np.array([old[r["pair"]]["cpu_s"] for r in rows if r["pair"] in old])
        print(
            f"compared with {args.compare}: {diff} pairs differ; CPU median {np.median(ocpu):.4f} -> {np.median(cpu):.4f} s, "
            f"total {ocpu.sum():.2f} -> {cpu.sum():.2f} s"
        )


if __name__ == "__main__":
    main()
