"""Pose-graph solve time, and agreement with another implementation of the graph.

A rover drives a long lawn-mower path with drifting odometry (scale error and heading
bias); every keyframe sees up to 8 landmarks and every 20th has a pose fix. The graph
is solved incrementally over a sliding window (as the online loop does) and once in
full at the end. With ``--compare OTHER.py`` (another ``fusion.py``, e.g. the previous
one: ``git show 255fd75:src/lunarloc/fusion/posegraph.py > /tmp/fusion_old.py``) the same script
runs on both and prints the largest difference of the final estimates.

Usage: python benchmarks/bench_fusion.py [--keyframes 600] [--window-m 10] [--compare OTHER.py]
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
import time

import numpy as np


def _module(path: str | None):
    if path is None:
        import lunarloc.fusion.posegraph as mod

        return mod
    spec = importlib.util.spec_from_file_location("fusion_other", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["fusion_other"] = mod
    spec.loader.exec_module(mod)
    return mod


def run(mod, K: int, window_m: float, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    yaw = np.where((np.arange(K) // 50) % 2 == 0, 0.0, math.pi) + rng.normal(0, 0.01, K)
    p = np.zeros((K, 3))
    for i in range(1, K):
        p[i] = p[i - 1] + 0.25 * np.array([math.cos(yaw[i - 1]), math.sin(yaw[i - 1]), 0.0])
        if i % 50 == 0:
            p[i, 1] += 2.0  # next lane
    oy = yaw + 4e-4 * np.arange(K)
    o = np.zeros((K, 3))
    for i in range(1, K):
        step = 1.03 * np.linalg.norm(p[i] - p[i - 1])
        o[i] = o[i - 1] + step * np.array([math.cos(oy[i - 1]), math.sin(oy[i - 1]), 0.0])
    lo, hi = p[:, :2].min(axis=0) - 3, p[:, :2].max(axis=0) + 3
    rocks = np.column_stack(
        [rng.uniform(lo, hi, (int(np.prod(hi - lo) / 2), 2)), np.zeros(int(np.prod(hi - lo) / 2))]
    )
    g = mod.PoseGraph()
    t_solve, n_solve = [], 0
    for i in range(K):
        g.add_keyframe(float(i), np.r_[o[i], oy[i]])
        near = rocks[np.linalg.norm(rocks[:, :2] - p[i, :2], axis=1) < 2.5][:8]
        c, s = math.cos(yaw[i]), math.sin(yaw[i])
        d = near - p[i]
        det = np.column_stack(
            [c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]]
        ) + rng.normal(0, 0.01, d.shape)
        g.add_landmark_observations(
            [(i, j) for j in range(len(near))],
            [i] * len(near),
            det,
            np.zeros((len(near), 2)),
            near,
            0.05,
        )
        if i % 20 == 19:
            g.add_fix(i, np.r_[p[i] + rng.normal(0, 0.02, 3), yaw[i]], 0.03, 0.005)
        if i % 5 == 4:
            t0 = time.perf_counter()
            g.solve(window_m)
            t_solve.append(time.perf_counter() - t0)
            n_solve += 1
    t0 = time.perf_counter()
    g.solve()
    t_full = time.perf_counter() - t0
    est = g.poses()
    rmse = math.sqrt(np.mean(np.sum((est[:, :3] - p) ** 2, axis=1)))
    odo = math.sqrt(np.mean(np.sum((o - p) ** 2, axis=1)))
    return {
        "poses": est,
        "scale": g.scale,
        "t_window": np.array(t_solve),
        "t_full": t_full,
        "rmse": rmse,
        "odo": odo,
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--keyframes", type=int, default=600)
    ap.add_argument("--window-m", type=float, default=10.0)
    ap.add_argument("--compare", default=None, help="another fusion.py to run the same scenario on")
    args = ap.parse_args()
    runs = {"lunarloc.fusion.posegraph": run(_module(None), args.keyframes, args.window_m)}
    if args.compare:
        runs[args.compare] = run(_module(args.compare), args.keyframes, args.window_m)
    for name, r in runs.items():
        tw = r["t_window"] * 1e3
        print(
            f"{name}: {args.keyframes} keyframes, RMSE {r['rmse']:.3f} m (odometry {r['odo']:.2f} m), scale {r['scale']:.4f}; "
            f"window solve ms median {np.median(tw):.1f} p90 {np.percentile(tw, 90):.1f} max {tw.max():.1f}; "
            f"full solve {r['t_full'] * 1e3:.0f} ms"
        )
    if args.compare:
        a, b = runs.values()
        dp = np.abs(a["poses"][:, :3] - b["poses"][:, :3]).max()
        dy = np.abs((a["poses"][:, 3] - b["poses"][:, 3] + math.pi) % (2 * math.pi) - math.pi).max()
        print(
            f"largest difference: position {dp:.2e} m, yaw {dy:.2e} rad, scale {abs(a['scale'] - b['scale']):.2e}"
        )


if __name__ == "__main__":
    main()
