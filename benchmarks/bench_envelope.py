"""The operating envelope: how much driving a first fix needs, and how many fixes per 100 m
follow, on simulated LAC sites (386 rocks, the LAC's density; the site's rocks.csv as the
reference map, as a map from above would be), front stereo pair, with the default run.

For each site it runs exactly what a user would (`lunarloc simulate`, then `lunarloc run`),
unless the run folder exists already (`--reuse`), and reads the run folder:

- distance to first fix: the ground-truth path length driven before the first accepted fix;
- the local map then: the landmarks in the rover's window and the reference landmarks
  inside it at that attempt (the "overlap" the fix used), and the inliers;
- fixes per 100 m over the whole traverse, the worst accepted fix error.

    python benchmarks/bench_envelope.py --out /tmp/env --sites 301 302 303 --width 640 --duration 90
    python benchmarks/bench_envelope.py --out /tmp/env --sites 301 --width 1280 --duration 90
    python benchmarks/bench_envelope.py --out /tmp/env --sites 305 --width 640 --duration 90 --rovers 2

With ``--rovers 2`` the site has two traverses, run together with ``--share-maps`` and no
reference map: a fix there comes only from the other rover's live map.
Rendering dominates (minutes per site on a shared 2-core machine); size the runs to fit.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np


def _cli(*args: str) -> None:
    cmd = [sys.executable, "-m", "lunarloc", *args]
    print("$", " ".join(cmd[2:]), flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)


def _arc_at(tum: Path, times_s: np.ndarray) -> np.ndarray:
    """Ground-truth path length (m) driven by each time in `times_s`."""
    a = np.loadtxt(tum, ndmin=2)
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(a[:, 1:3], axis=0), axis=1))]
    return np.interp(times_s, a[:, 0], arc)


def analyse_run(run: Path) -> dict:
    """The envelope figures of one rover's run folder."""
    s = json.loads((run / "summary.json").read_text())
    with open(run / "attempts.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    acc = [r for r in rows if r["accepted"] == "True"]
    out = {
        "run": str(run),
        "path_m": s["path_length_m"],
        "duration_s": s["duration_s"],
        "reference_landmarks": s["reference_landmarks"],
        "attempts": len(rows),
        "fixes": len(acc),
        "fixes_per_100m": round(100.0 * len(acc) / s["path_length_m"], 1)
        if s["path_length_m"] > 0
        else None,
        "worst_fix_cm": None
        if s.get("max_accepted_fix_error_m") is None
        else round(100 * s["max_accepted_fix_error_m"], 1),
        "first_fix_m": None,
        "first_fix_s": None,
        "local_landmarks_at_first_fix": None,
        "reference_in_window_at_first_fix": None,
        "inliers_at_first_fix": None,
        "first_attempt_m": None,
    }
    gt = run / "trajectory_groundtruth.tum"
    if rows and gt.is_file():
        out["first_attempt_m"] = round(
            float(_arc_at(gt, np.array([float(rows[0]["time_s"])]))[0]), 2
        )
    if acc and gt.is_file():
        f = acc[0]
        t = float(f["time_s"])
        out.update(
            first_fix_s=t,
            first_fix_m=round(float(_arc_at(gt, np.array([t]))[0]), 2),
            local_landmarks_at_first_fix=int(f["landmarks"]),
            reference_in_window_at_first_fix=int(f["reference_landmarks"]),
            inliers_at_first_fix=int(f["inliers"]),
        )
    return out


def _runs(folder: Path) -> list[Path]:
    if (folder / "summary.json").is_file():
        return [folder]
    return sorted(p.parent for p in folder.glob("*/summary.json"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--sites", type=int, nargs="+", required=True)
    ap.add_argument("--width", type=int, default=640, help="image width (height 9/16 of it)")
    ap.add_argument("--duration", type=float, default=90.0, help="traverse length, seconds")
    ap.add_argument(
        "--rovers", type=int, default=1, help="2: two traverses run with --share-maps, no reference"
    )
    ap.add_argument(
        "--reuse",
        action="store_true",
        help="analyse existing folders, simulate/run only what is missing",
    )
    a = ap.parse_args(argv)
    results = []
    for seed in a.sites:
        tag = f"s{seed}_{a.width}" + ("" if a.rovers == 1 else f"_{a.rovers}r")
        d = a.out / tag
        if not (a.reuse and all((d / f"traverse_{i}.lac").is_file() for i in range(a.rovers))):
            _cli(
                "simulate",
                "--seed",
                str(seed),
                "--traverses",
                str(a.rovers),
                "--duration",
                f"{a.duration:g}",
                "--width",
                str(a.width),
                "--height",
                str(a.width * 9 // 16),
                "--front-only",
                "--no-semantic",
                "--out",
                str(d),
                "--overwrite",
            )
        run = d / "run"
        if not (a.reuse and _runs(run)):
            archives = [str(d / f"traverse_{i}.lac") for i in range(a.rovers)]
            ref = ["-r", str(d / "rocks.csv")] if a.rovers == 1 else ["--share-maps"]
            _cli("run", *archives, *ref, "-o", str(run), "--no-plot", "--overwrite")
        for r in _runs(run):
            res = {"site": seed, "width": a.width, "rovers": a.rovers, **analyse_run(r)}
            results.append(res)
            print(json.dumps(res), flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    name = f"envelope_{a.width}_{a.rovers}r.json"
    (a.out / name).write_text(json.dumps(results, indent=1))
    print(
        "| site | px | rovers | path m | first fix after m | local / ref-in-window landmarks then | inliers | fixes | per 100 m | worst fix cm |"
    )
    for r in results:
        ff = "none" if r["first_fix_m"] is None else f"{r['first_fix_m']:.1f}"
        lw = (
            "-"
            if r["first_fix_m"] is None
            else f"{r['local_landmarks_at_first_fix']} / {r['reference_in_window_at_first_fix']}"
        )
        print(
            f"| {r['site']} | {r['width']} | {r['rovers']} | {r['path_m']:.1f} | {ff} | {lw} | "
            f"{r['inliers_at_first_fix'] if r['inliers_at_first_fix'] is not None else '-'} | {r['fixes']}/{r['attempts']} | "
            f"{r['fixes_per_100m']} | {r['worst_fix_cm'] if r['worst_fix_cm'] is not None else '-'} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
