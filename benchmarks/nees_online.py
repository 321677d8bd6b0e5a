"""Is the online loop's stated uncertainty honest? NEES shares of the loop's fixes on the real
traverses and of OnlineLocalizer's covariance along image-built simulated runs.

Usage
-----
    python benchmarks/nees_online.py --data ../shared/data/lunarloc-data [--traverses 3 5]
        [--json OUT.json]
    python benchmarks/nees_online.py --sites SITES/seed_286 SITES/seed_287 ... [--json OUT.json]
    python benchmarks/nees_online.py --runs bench-output/lac-leaderboard/site304_640x360 ...

``--data``: the loop as ``lunarloc bench loop`` runs it (each traverse against a map of all the
others, simulated drift 0.05 deg/m and 2 %), every successful localization judged against the
truth at the rover under the covariance it is stated with (``Attempt.fix_covariance_xyz``) and
under localize()'s own covariance there (before the loop's model): per traverse and in all.
Each fix's heading is judged too: its error against the yaw sigma stated for it (1-dof NEES).

``--sites``: the image loop (``RunConfig()``) on recorded LAC-look sites
(``benchmarks/bench_lac_map.py simulate`` folders: ``traverse.lac``, ``rocks.csv``), the same
records per site (the detector runs on every stereo pair: about 25-50 s CPU a site).

``--runs``: run folders of ``benchmarks/bench_lac_leaderboard.py`` (``trace.npz``: per tick the
true and estimated positions, localized, the stated covariance and the gate model's sigma;
``attempts.json``: the component's fixes): the NEES of every localized tick under the stated
covariance and under the gate model's sigma (what the component stated before), and of the
fixes the component kept (position and, where the trace holds the true heading, yaw).

NEES: squared Mahalanobis distance of the position error, 3 dof; calibrated: 60-80 % under 3.53,
at least 99 % under 14.16; a heading's (1 dof): 60-80 % under 1.0, at least 99 % under 9.0. CPU
time is reported (the machine may be loaded).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from lunarloc.pipeline.nees_online import (
    loop_fix_records,
    nees,
    nees_shares,
    site_fix_records,
    trace_nees,
    yaw_nees_shares,
)


def _fmt(v) -> str:
    n, a, b = nees_shares(v)
    return f"{n:4d} cases  {a:6.1%} < 3.53  {b:6.1%} < 14.16" if n else "   0 cases"


def _fmt_yaw(v) -> str:
    n, a, b = yaw_nees_shares(v)
    return f"{a:6.1%} < 1  {b:6.1%} < 9" if n else "-"


def _table(recs, key: str) -> None:
    own = "localize()'s own covariance"
    print(f"{key:>8}  {'stated covariance':<42}  {own:<42}  yaw stated (1 dof)    yaw own")
    groups = [(g, [r for r in recs if r[key] == g]) for g in sorted({r[key] for r in recs})]
    groups += [("all", recs), ("accepted", [r for r in recs if r["accepted"]])]
    for g, rs in groups:
        print(
            f"{g:>8}  {_fmt([r['nees'] for r in rs]):<42}  "
            f"{_fmt([r['nees_localize'] for r in rs]):<42}  {_fmt_yaw([r['nees_yaw'] for r in rs])}"
            f"  {_fmt_yaw([r.get('nees_yaw_localize', np.nan) for r in rs])}"
        )


def loop_part(data: str, traverses, out_json: str | None) -> None:
    t0 = time.process_time()
    recs = loop_fix_records(data, traverses)
    cpu = time.process_time() - t0
    if out_json:
        Path(out_json).write_text(json.dumps(recs))
    print(f"the loop's fixes on the real traverses ({cpu:.0f} s CPU)")
    _table(recs, "vehicle")


def sites_part(sites, out_json: str | None) -> None:
    t0 = time.process_time()
    recs = site_fix_records(sites)
    cpu = time.process_time() - t0
    if out_json:
        Path(out_json).write_text(json.dumps(recs))
    print(f"the image loop's fixes on recorded sites ({cpu:.0f} s CPU)")
    _table(recs, "site")


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
            line = f"   the component's fixes: {_fmt(nees(E, C))}"
            if "truth_yaw_rad" in z.files and fixes and "fix_yaw_rad" in fixes[0]:
                ty = np.asarray(z["truth_yaw_rad"])
                ey = [_wrap(a["fix_yaw_rad"] - ty[a["frame"] - 1]) for a in fixes]
                line += f", yaw {_fmt_yaw([(e / a['fix_sigma_yaw_rad']) ** 2 for e, a in zip(ey, fixes)])}"
            print(line)
        if "truth_yaw_rad" in z.files:
            ey = _wrap(np.asarray(z["est_yaw_rad"]) - np.asarray(z["truth_yaw_rad"]))[loc]
            print(
                f"   the stated yaw variance: {_fmt_yaw(ey**2 / np.asarray(z['yaw_variance_rad2'])[loc])}"
            )


def _wrap(a):
    return (np.asarray(a, float) + np.pi) % (2 * np.pi) - np.pi


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", help="lunarloc-data folder: the loop's fixes on the real traverses")
    ap.add_argument("--traverses", type=int, nargs="+", help="vehicle traverses (default all)")
    ap.add_argument(
        "--sites", nargs="+", help="recorded LAC-look site folders: the image loop's fixes"
    )
    ap.add_argument("--json", help="write the fix records (--data or --sites) here")
    ap.add_argument("--runs", nargs="+", help="bench_lac_leaderboard.py run folders")
    a = ap.parse_args(argv)
    if not a.data and not a.runs and not a.sites:
        ap.error("give --data, --sites and/or --runs")
    if a.data and a.sites and a.json:
        ap.error("--json with one of --data, --sites")
    if a.data:
        loop_part(a.data, a.traverses, a.json)
    if a.sites:
        sites_part(a.sites, a.json)
    if a.runs:
        runs_part(a.runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
