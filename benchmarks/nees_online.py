"""Is the online loop's stated uncertainty honest? NEES shares of the loop's fixes on the real
traverses and of OnlineLocalizer's covariance along image-built simulated runs.

Usage
-----
    python benchmarks/nees_online.py --data ../shared/data/lunarloc-data [--traverses 3 5]
        [--json OUT.json]
    python benchmarks/nees_online.py --runs bench-output/lac-leaderboard/site304_640x360 ...

``--data``: the loop as ``lunarloc bench loop`` runs it (each traverse against a map of all the
others, simulated drift 0.05 deg/m and 2 %), every successful localization judged against the
truth at the rover under the covariance it is stated with (``Attempt.fix_covariance_xyz``) and
under localize()'s own covariance there (before the loop's model): per traverse and in all.

``--runs``: run folders of ``benchmarks/bench_lac_leaderboard.py`` (``trace.npz``: per tick the
true and estimated positions, localized, the stated covariance and the gate model's sigma;
``attempts.json``: the component's fixes): the NEES of every localized tick under the stated
covariance and under the gate model's sigma (what the component stated before), and of the
fixes the component kept.

NEES: squared Mahalanobis distance of the position error, 3 dof; calibrated: 60-80 % under 3.53,
at least 99 % under 14.16. CPU time is reported (the machine may be loaded).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from lunarloc.pipeline.nees_online import loop_fix_records, nees, nees_shares, trace_nees


def _fmt(v) -> str:
    n, a, b = nees_shares(v)
    return f"{n:4d} cases  {a:6.1%} < 3.53  {b:6.1%} < 14.16" if n else "   0 cases"


def loop_part(data: str, traverses, out_json: str | None) -> None:
    t0 = time.process_time()
    recs = loop_fix_records(data, traverses)
    cpu = time.process_time() - t0
    if out_json:
        Path(out_json).write_text(json.dumps(recs))
    print(f"the loop's fixes on the real traverses ({cpu:.0f} s CPU)")
    print(f"{'vehicle':>8}  {'stated covariance':<42}  localize()'s own covariance")
    for v in sorted({r["vehicle"] for r in recs}):
        rs = [r for r in recs if r["vehicle"] == v]
        print(
            f"{v:>8}  {_fmt([r['nees'] for r in rs]):<42}  {_fmt([r['nees_localize'] for r in rs])}"
        )
    print(
        f"{'all':>8}  {_fmt([r['nees'] for r in recs]):<42}  {_fmt([r['nees_localize'] for r in recs])}"
    )
    acc = [r for r in recs if r["accepted"]]
    print(
        f"{'accepted':>8}  {_fmt([r['nees'] for r in acc]):<42}  {_fmt([r['nees_localize'] for r in acc])}"
    )


def runs_part(folders) -> None:
    print("OnlineLocalizer along image-built runs (localized ticks)")
    for d in map(Path, folders):
        z = np.load(d / "trace.npz")
        stated = trace_nees(z)
        loc = np.asarray(z["localized"], bool)
        e = np.asarray(z["est_xyz"]) - np.asarray(z["truth_xyz"])
        line = f"{d.name}: stated covariance {_fmt(stated)}"
        if "gate_sigma_m" in z.files:
            g = np.asarray(z["gate_sigma_m"])[loc]
            line += f" | gate model {_fmt(np.sum(e[loc] ** 2, axis=1) / g**2)}"
        print(line)
        sig = np.sqrt(np.diagonal(np.asarray(z["covariance_xyz"])[loc], axis1=1, axis2=2))
        print(
            f"   median |error| x/y/z {np.round(np.median(np.abs(e[loc]), axis=0) * 100, 2)} cm, "
            f"median stated sigma {np.round(np.median(sig, axis=0) * 100, 2)} cm"
        )
        att = d / "attempts.json"
        if att.exists():
            truth = np.asarray(z["truth_xyz"])
            fixes = [a for a in json.loads(att.read_text()) if a["fix_covariance_xyz"]]
            E = [np.array(a["fix_xyz"]) - truth[a["frame"] - 1] for a in fixes]
            C = [a["fix_covariance_xyz"] for a in fixes]
            print(f"   the component's fixes: {_fmt(nees(E, C))}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", help="lunarloc-data folder: the loop's fixes on the real traverses")
    ap.add_argument("--traverses", type=int, nargs="+", help="vehicle traverses (default all)")
    ap.add_argument("--json", help="write the loop's fix records here")
    ap.add_argument("--runs", nargs="+", help="bench_lac_leaderboard.py run folders")
    a = ap.parse_args(argv)
    if not a.data and not a.runs:
        ap.error("give --data and/or --runs")
    if a.data:
        loop_part(a.data, a.traverses, a.json)
    if a.runs:
        runs_part(a.runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
