"""Localization against the ground-truth LAC geometric map of simulated sites.

For each simulated site (``lunarloc.sim.simulate.simulate_site``), the reference is its
LAC geometric map (``overhead.site_geometric_map``: 0.15 m cells, rocks grouped by
``overhead.grid_landmarks``). Vehicle maps are landmark-level stand-ins for image-built
maps: the visible centres of the rocks a detector can see (radius >= 5 cm,
``pipeline.rocks_to_reference``) within `--radius` m of a random point, 20 % of them
missed, 2 cm noise, 10 % spurious landmarks, in a random frame (roll/pitch up to 0.5 deg).
Reports success, the error at the vehicle map's centroid and at its farthest landmark,
the predicted error, coverage, and time (measured on a shared machine: see the load).

Usage: python benchmarks/overhead_sites.py [--sites 5] [--areas 6] [--radius 6] [--odometry-bounds SCALE DEG_PER_M]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from lunarloc.sim.simulate import simulate_site
from lunarloc.pipeline.evaluation import random_vehicle_transform
from lunarloc.core.geometry import transform_points
from lunarloc.localization.config import LocalizationConfig
from lunarloc.localization.localize import localize
from lunarloc.io.maps import LandmarkMap
from lunarloc.io.overhead import grid_landmarks, site_geometric_map
from lunarloc.pipeline.reference import rocks_to_reference


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--sites", type=int, default=5)
    ap.add_argument("--areas", type=int, default=6)
    ap.add_argument("--radius", type=float, default=6.0)
    ap.add_argument(
        "--odometry-bounds",
        type=float,
        nargs=2,
        default=None,
        metavar=("SCALE", "DEG_PER_M"),
        help="state the vehicle maps' odometry bounds (0 0: rigid, as these stand-ins are); "
        "default: none stated, the distortion is fitted from the maps",
    )
    args = ap.parse_args()
    cfg = (
        LocalizationConfig()
        if args.odometry_bounds is None
        else LocalizationConfig(
            odometry_scale_error=args.odometry_bounds[0],
            odometry_heading_drift_deg_per_m=args.odometry_bounds[1],
        )
    )
    rng = np.random.default_rng(0)
    rows = []
    localize(
        LandmarkMap(rng.normal(size=(30, 3))), LandmarkMap(rng.normal(size=(10, 3)))
    )  # compile
    for seed in range(args.sites):
        site = simulate_site(seed)
        ref = grid_landmarks(site_geometric_map(site))
        truth = rocks_to_reference(site.rocks.table())
        for _ in range(args.areas):
            c = rng.uniform(-9, 9, 2)
            sel = np.flatnonzero(
                np.linalg.norm(truth.positions_xyz[:, :2] - c, axis=1) < args.radius
            )
            sel = sel[rng.random(len(sel)) > 0.2]
            if len(sel) < 5:
                continue
            P = truth.positions_xyz[sel] + rng.normal(0, 0.02, (len(sel), 3))
            n_sp = max(1, len(sel) // 10)
            spur = np.c_[
                c + rng.uniform(-args.radius, args.radius, (n_sp, 2)), rng.normal(0, 0.2, n_sp)
            ]
            world = np.vstack([P, spur])
            T_veh_world = random_vehicle_transform(rng, max_tilt_deg=0.5)
            veh = LandmarkMap(transform_points(T_veh_world, world))
            t0 = time.perf_counter()
            r = localize(ref, veh, cfg)
            dt = time.perf_counter() - t0
            if np.all(np.isfinite(r.T_ref_veh)):
                est = transform_points(r.T_ref_veh @ T_veh_world, P)
                e = np.linalg.norm(est - P, axis=1)
                centre = transform_points(r.T_ref_veh @ T_veh_world, P.mean(axis=0)[None])[0]
                err_c, err_max = float(np.linalg.norm(centre - P.mean(axis=0))), float(e.max())
            else:
                err_c = err_max = float("nan")
            rows.append(
                (
                    seed,
                    len(ref),
                    len(veh),
                    r.success,
                    r.num_inliers,
                    err_c,
                    err_max,
                    r.predicted_error_m,
                    dt,
                    r.predicted_rotation_deg,
                    r.distortion_fit,
                )
            )
            print(
                f"site {seed} ({len(ref)} grid rocks) vehicle {len(veh):3d}: success {r.success!s:5s} "
                f"inliers {r.num_inliers:3d} err centre {err_c * 100:5.1f} cm, max {err_max * 100:5.1f} cm, "
                f"predicted {r.predicted_error_m * 100:5.1f} cm, {dt:.2f} s  {'' if r.success else r.reason[:70]}",
                flush=True,
            )
    ok = [r for r in rows if r[3]]
    wrong = [r for r in ok if r[6] >= 0.10]
    accuracy = (
        (
            f"error at the centroid median {np.median([r[5] for r in ok]) * 100:.1f} cm, max "
            f"{max(r[5] for r in ok) * 100:.1f} cm, max anywhere {max(r[6] for r in ok) * 100:.1f} cm; the predicted "
            f"error covers the max error in {np.mean([r[6] <= r[7] for r in ok]):.0%} (1 sigma) / "
            f"{np.mean([r[6] <= 3 * r[7] for r in ok]):.0%} (3 sigma)"
        )
        if ok
        else "none to measure"
    )
    fits = [r[10] for r in rows if r[10] and np.isfinite(r[10]["sigma_m"])]
    if fits:  # no bounds stated: what the predicted error is made of (medians over the fitted maps)
        med = {
            k: np.median([f[k] for f in fits])
            for k in (
                "shift_m",
                "sigma_m",
                "floor_sigma_m",
                "rotation_shift_deg",
                "rotation_sigma_deg",
                "rotation_floor_sigma_deg",
            )
        }
        print(
            f"bend fitted on {len(fits)} maps, medians: predicted {np.median([r[7] for r in rows]) * 100:.1f} cm / "
            f"{np.median([r[9] for r in rows]):.2f} deg; shift {med['shift_m'] * 100:.1f} cm / "
            f"{med['rotation_shift_deg']:.2f} deg, bend's own sigma {med['sigma_m'] * 100:.1f} cm / "
            f"{med['rotation_sigma_deg']:.2f} deg, floor {med['floor_sigma_m'] * 100:.1f} cm / "
            f"{med['rotation_floor_sigma_deg']:.2f} deg; true max error {np.median([r[6] for r in rows]) * 100:.1f} cm"
        )
    print(
        f"{len(ok)} of {len(rows)} localized, {len(wrong)} of them more than 10 cm off anywhere on the vehicle map;"
        f" {accuracy}; time median {np.median([r[8] for r in rows]):.2f} s (load average {os.getloadavg()[0]:.1f})"
    )


if __name__ == "__main__":
    main()
