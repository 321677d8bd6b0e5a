"""Cost of localizing a 150-landmark window against references of 100 to 100,000 rocks.

Uniform synthetic rock fields at the LAC density (0.55 rocks per square metre, smooth
terrain; ``lunarloc.sim.fields``); per field, vehicle windows of 150 landmarks (85 %
of the rocks around a random rock detected, 1.5 cm noise per axis, 15 % spurious
landmarks, any yaw, tilt up to 0.5 deg). At 100 rocks the window is 60 landmarks (a
150-landmark window does not fit).

Two searches, each size in a fresh subprocess (the compiled kernels warmed first, so
compile time is not counted; peak memory is the rise of the process's peak RSS over
its level before the call, via /proc/self/clear_refs; the process's own level, Python with
numpy, scipy and the loaded kernels, is reported as ``rss_before_mb``):

* ``full``: :func:`lunarloc.localization.localize.localize` on the whole reference (before);
  sizes whose N^2 reference-pair index would exceed the memory limit are skipped
  with the estimate, and larger sizes stop once one exceeds the time limit.
* ``indexed``: :func:`lunarloc.localization.large.localize_large` (after). Its time is
  split into building the reference index (once per reference map) and the query.

Per size also ``--null-trials`` windows cut from an UNRELATED field of the same size: each
must be refused ("unrelated accepted" counts confident answers there).
Right = success, every vehicle landmark placed within 0.2 m of where the known transform
puts it, and the rotation within 1 deg.
The fitted exponent is the least-squares slope of log(time) on log(N_ref) over the
sizes from 1,000 rocks.

``--stress N`` instead runs the indexed search on harder windows (50 % / 30 % of the rocks
detected, 40 % outliers, 60 landmarks, 2.5 cm noise) against one N-rock field.

Usage: python benchmarks/scaling.py [--sizes 100,300,...] [--trials 3] [--out scaling.json]
       python benchmarks/scaling.py --stress 20000 --trials 3
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time

SIZES = [100, 300, 1000, 3000, 10000, 20000, 30000, 100000]


def _rss_mb(field: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def child(n: int, method: str, trials: int, seed: int, null_trials: int = 0) -> dict:
    import numpy as np

    from lunarloc.sim.fields import uniform_rock_field, vehicle_window
    from lunarloc.pipeline.evaluation import _warm_up
    from lunarloc.core.geometry import rotation_angle, transform_points
    from lunarloc.localization.config import LocalizationConfig
    from lunarloc.localization.localize import localize
    from lunarloc.localization.large import build_index, localize_large

    cfg = LocalizationConfig()
    _warm_up(cfg)  # load the compiled kernels: compile time is not run time
    rng = np.random.default_rng(seed)
    ref = uniform_rock_field(rng, n)
    n_win = 150 if n >= 300 else 60
    wins = [vehicle_window(rng, ref, n_win) for _ in range(trials)]
    # null trials: windows cut from an unrelated field of the same size must be refused
    other = uniform_rock_field(np.random.default_rng(seed + 1000), n)
    nulls = [vehicle_window(rng, other, n_win) for _ in range(null_trials)]
    out = {
        "n_ref": n,
        "method": method,
        "n_veh": n_win,
        "trials": [],
        "null_accepted": 0,
        "null_trials": null_trials,
        "rss_before_mb": _rss_mb("VmRSS"),
    }
    index = None
    if method == "indexed":
        _reset_peak()
        before = _rss_mb("VmRSS")
        t0, c0 = time.perf_counter(), time.process_time()
        index = build_index(ref, cfg)
        out["index_s"] = time.perf_counter() - t0
        out["index_cpu_s"] = time.process_time() - c0
        out["index_peak_mb"] = _rss_mb("VmHWM") - before
        out["index_triangles"] = index.num_triangles
        out["index_mb"] = index.nbytes / 2**20
        out["max_side_m"] = index.max_side_m
    for w in nulls:
        r = (
            localize(ref, w.vehicle, cfg)
            if method == "full"
            else localize_large(ref, w.vehicle, cfg, index=index, search="indexed")
        )
        out["null_accepted"] += bool(r.success)
    for w in wins:
        _reset_peak()
        before = _rss_mb("VmRSS")
        t0, c0 = time.perf_counter(), time.process_time()
        if method == "full":
            r = localize(ref, w.vehicle, cfg)
            considered = r.num_associations
        else:
            r = localize_large(ref, w.vehicle, cfg, index=index, search="indexed")
            considered = r.considered
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        peak = _rss_mb("VmHWM") - before
        if np.all(np.isfinite(r.T_ref_veh)):
            # error where it matters: at the vehicle map's landmarks (not the far-away origin)
            P = w.vehicle.positions_xyz
            err_m = float(
                np.max(
                    np.linalg.norm(
                        transform_points(r.T_ref_veh, P) - transform_points(w.T_ref_veh, P), axis=1
                    )
                )
            )
            err_deg = math.degrees(rotation_angle(r.T_ref_veh[:3, :3] @ w.T_ref_veh[:3, :3].T))
        else:
            err_m = err_deg = float("nan")
        right = bool(r.success and err_m < 0.2 and err_deg < 1.0)
        out["trials"].append(
            {
                "time_s": dt,
                "cpu_s": cpu,
                "peak_mb": peak,
                "considered": int(considered),
                "success": bool(r.success),
                "right": right,
                "err_m": err_m,
                "inliers": r.num_inliers,
                "reason": r.reason,
                "candidates": len(getattr(r, "candidates", [])),
            }
        )
    return out


# harder vehicle windows: (detection probability, outlier fraction, landmarks, noise per axis m)
STRESS = [
    (0.5, 0.15, 150, 0.015),
    (0.85, 0.4, 150, 0.015),
    (0.85, 0.15, 60, 0.015),
    (0.85, 0.15, 150, 0.025),
    (0.3, 0.15, 80, 0.015),
]


def stress(n: int, trials: int, seed: int) -> None:
    """The indexed search on harder windows (missed detections, more outliers, fewer
    landmarks, more noise) against an n-rock field; prints right/accepted per variant."""
    import numpy as np

    from lunarloc.sim.fields import uniform_rock_field, vehicle_window
    from lunarloc.pipeline.evaluation import _warm_up
    from lunarloc.core.geometry import transform_points
    from lunarloc.localization.large import build_index, localize_large

    _warm_up(None)
    ref = uniform_rock_field(np.random.default_rng(seed), n)
    index = build_index(ref)
    print("| detected | outliers | landmarks | noise (m) | right | accepted | median time (s) |")
    print("|---:|---:|---:|---:|---|---|---:|")
    for dp, of, nv, noise in STRESS:
        right = accepted = 0
        times = []
        for t in range(trials):
            w = vehicle_window(
                np.random.default_rng([seed, t]),
                ref,
                nv,
                outlier_fraction=of,
                detect_prob=dp,
                noise_m=noise,
            )
            t0 = time.perf_counter()
            r = localize_large(ref, w.vehicle, index=index, search="indexed")
            times.append(time.perf_counter() - t0)
            P = w.vehicle.positions_xyz
            err = np.max(
                np.linalg.norm(
                    transform_points(r.T_ref_veh, P) - transform_points(w.T_ref_veh, P), axis=1
                )
            )
            accepted += r.success
            right += bool(r.success and err < 0.2)
        print(
            f"| {dp:.0%} | {of:.0%} | {nv} | {noise} | {right}/{trials} | {accepted}/{trials} | {_median(times):.2f} |"
        )


def run_size(
    n: int, method: str, trials: int, seed: int, timeout_s: float, null_trials: int = 0
) -> dict:
    cmd = [
        sys.executable,
        __file__,
        "--child",
        str(n),
        "--method",
        method,
        "--trials",
        str(trials),
        "--seed",
        str(seed),
        "--null-trials",
        str(null_trials),
    ]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"n_ref": n, "method": method, "skipped": f"exceeded {timeout_s:.0f} s"}
    if p.returncode != 0:
        tail = (p.stderr.strip().splitlines() or ["?"])[-1]
        return {"n_ref": n, "method": method, "skipped": f"failed: {tail}"}
    return json.loads(p.stdout.strip().splitlines()[-1])


def _median(xs):
    xs = sorted(xs)
    return xs[len(xs) // 2] if len(xs) % 2 else 0.5 * (xs[len(xs) // 2 - 1] + xs[len(xs) // 2])


def fit_exponent(rows: list, key: str = "time_s", min_n: int = 1000) -> float:
    pts = [
        (math.log(r["n_ref"]), math.log(r[key]))
        for r in rows
        if "skipped" not in r and r["n_ref"] >= min_n and r.get(key, 0) > 0
    ]
    if len(pts) < 2:
        return float("nan")
    mx = sum(p[0] for p in pts) / len(pts)
    my = sum(p[1] for p in pts) / len(pts)
    return sum((x - mx) * (y - my) for x, y in pts) / sum((x - mx) ** 2 for x, _ in pts)


def summarise(r: dict) -> dict:
    if "skipped" in r:
        return r
    t = r["trials"]
    s = {
        "n_ref": r["n_ref"],
        "method": r["method"],
        "n_veh": r["n_veh"],
        "considered": int(_median([x["considered"] for x in t])),
        "time_s": _median([x["time_s"] for x in t]),
        "cpu_s": _median([x["cpu_s"] for x in t]),
        "peak_mb": max(x["peak_mb"] for x in t),
        "right": sum(x["right"] for x in t),
        "trials": len(t),
        "wrong_accepted": sum(x["success"] and not x["right"] for x in t),
        "reasons": sorted({x["reason"] for x in t if not x["right"]}),
        "null_accepted": r.get("null_accepted", 0),
        "null_trials": r.get("null_trials", 0),
        "rss_before_mb": r.get("rss_before_mb"),
    }
    for k in (
        "index_s",
        "index_cpu_s",
        "index_peak_mb",
        "index_triangles",
        "index_mb",
        "max_side_m",
    ):
        if k in r:
            s[k] = r[k]
    return s


def table(rows: list) -> str:
    lines = [
        "| method | reference rocks | associations considered | wall time (s, median) | CPU time (s) | "
        "index build (s, once per map) | peak memory (MB) | right | unrelated accepted |",
        "|---|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in rows:
        if "skipped" in r:
            lines.append(
                f"| {r['method']} | {r['n_ref']:,} | - | - | - | - | - | skipped: {r['skipped']} | - |"
            )
            continue
        idx = f"{r['index_s']:.2f}" if "index_s" in r else "-"
        cpu = f"{r['cpu_s']:.3f}"
        mem = max(r["peak_mb"], r.get("index_peak_mb", 0.0))
        lines.append(
            f"| {r['method']} | {r['n_ref']:,} | {r['considered']:,} | {r['time_s']:.3f} | {cpu} | {idx} | "
            f"{mem:.0f} | {r['right']}/{r['trials']} | {r['null_accepted']}/{r['null_trials']} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)))
    ap.add_argument("--methods", default="full,indexed")
    ap.add_argument("--trials", type=int, default=3)
    ap.add_argument(
        "--null-trials", type=int, default=2, help="unrelated windows per size (must be refused)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--time-limit", type=float, default=120.0, help="stop a method's larger sizes past this (s)"
    )
    ap.add_argument(
        "--memory-limit-gb", type=float, default=4.0, help="skip full searches estimated above this"
    )
    ap.add_argument("--out", default="scaling.json")
    ap.add_argument(
        "--stress", type=int, metavar="N", help="only the harder-window variants on an N-rock field"
    )
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--method", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.method, args.trials, args.seed, args.null_trials)))
        return
    if args.stress:
        stress(args.stress, args.trials, args.seed)
        return
    sizes = [int(s) for s in args.sizes.split(",")]
    rows = []
    for method in args.methods.split(","):
        stop = None
        for n in sizes:
            # the full search's reference-pair index holds N^2 ordered pairs of ~40 bytes
            est_gb = 40.0 * n * n / 1e9
            if stop:
                r = {"n_ref": n, "method": method, "skipped": stop}
            elif method == "full" and est_gb >= args.memory_limit_gb:
                r = {
                    "n_ref": n,
                    "method": method,
                    "skipped": f"N^2 pair index ~{est_gb:.0f} GB > {args.memory_limit_gb:g} GB",
                }
            else:
                r = summarise(
                    run_size(
                        n,
                        method,
                        args.trials,
                        args.seed,
                        args.time_limit * (args.trials + 2 + args.null_trials),
                        args.null_trials,
                    )
                )
                if "skipped" not in r and r["time_s"] > args.time_limit:
                    stop = f"{n:,} rocks already took {r['time_s']:.0f} s > {args.time_limit:g} s"
            print(json.dumps(r), flush=True)
            rows.append(r)
    result = {
        "rows": rows,
        "cpu_count": os.cpu_count(),
        "load_avg": os.getloadavg(),
        "exponents": {
            m: fit_exponent([r for r in rows if r["method"] == m]) for m in args.methods.split(",")
        },
        "cpu_exponents": {
            m: fit_exponent([r for r in rows if r["method"] == m], "cpu_s")
            for m in args.methods.split(",")
        },
        "index_build_exponent": fit_exponent(
            [r for r in rows if r["method"] == "indexed"], "index_s"
        ),
    }
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(table(rows))
    print(
        "fitted exponent of wall time (N_ref >= 1000): "
        + ", ".join(f"{m} {e:.2f}" for m, e in result["exponents"].items())
    )
    print(
        "fitted exponent of CPU time (N_ref >= 1000): "
        + ", ".join(f"{m} {e:.2f}" for m, e in result["cpu_exponents"].items())
    )
    print(f"fitted exponent of the index build time: {result['index_build_exponent']:.2f}")


if __name__ == "__main__":
    main()
