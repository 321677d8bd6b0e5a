"""How large a consistent set arises by chance between UNRELATED maps?

Null models with the rock density and structure of the real LunarLoc maps:
* real-disjoint: every pair of the 17 real traverse maps, with every reference
  landmark within 1 m of a vehicle landmark removed, so that no true correspondence
  is left (the vehicle is somewhere the reference never saw);
* real-mirrored (reported, not fitted): the vehicle map mirrored (x -> -x). This is
  pessimistic: both maps cover the same site, so any locally mirror-symmetric group
  of rocks matches itself;
* synthetic: independent uniform rock fields on the 27 m x 27 m site (z from a
  gentle random surface) with 20-450 landmarks per map;
* overhead (``--overhead N``): the rocks of the ground-truth LAC geometric maps of N
  simulated sites (quantised to 0.15 m cells, sigma = cell / sqrt(12), which raises the
  refinement radius and the RMSE limit) against unrelated synthetic vehicle maps of
  20-160 landmarks: the largest consistent set and the inlier count after refinement,
  and whether any was accepted.

For each pair the largest consistent set (exact maximum clique over all yaw bins) is
recorded against the number of putative associations m. The acceptance rule in
``lunarloc.localization.chance.chance_clique_size`` is an envelope over these maxima.

Usage: python benchmarks/chance_cliques.py [--data ../shared/data/lunarloc-data] [--out chance.json]
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lunarloc.pipeline.evaluation import find_traverses
from lunarloc.localization.config import LocalizationConfig, Mode
from lunarloc.localization.localize import localize
from lunarloc.io.maps import LandmarkMap, load_traverse, traverse_map


def synthetic_field(rng, n, size=27.0):
    xy = rng.uniform(-size / 2, size / 2, (n, 2))
    kx, ky = rng.normal(size=2) * 0.2
    z = 0.3 * np.sin(kx * xy[:, 0]) + 0.3 * np.cos(ky * xy[:, 1]) + rng.normal(0, 0.05, n)
    return LandmarkMap(np.c_[xy, z])


FALSE_ACCEPTS: list[str] = []


EPSILON_M = 0.05


def chance_size(ref, veh, mode, label=""):
    """(associations, largest consistent set) of an unrelated pair; records false accepts."""
    r = localize(
        ref, veh, LocalizationConfig(mode=mode, epsilon_m=EPSILON_M, epsilon_z_m=EPSILON_M)
    )
    if r.success:
        FALSE_ACCEPTS.append(label)
    return len(ref) * len(veh), r.clique_size


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", default="../shared/data/lunarloc-data")
    ap.add_argument("--out", default="chance.json")
    ap.add_argument("--mode", default="gravity")
    ap.add_argument("--synthetic", type=int, default=60, help="number of synthetic pairs")
    ap.add_argument("--synthetic-max", type=int, default=450, help="largest synthetic map")
    ap.add_argument("--skip-real", action="store_true", help="synthetic null model only")
    ap.add_argument(
        "--overhead", type=int, default=0, help="simulated sites whose LAC map is the reference"
    )
    ap.add_argument(
        "--per-site", type=int, default=10, help="unrelated vehicle maps per overhead site"
    )
    ap.add_argument(
        "--epsilon", type=float, default=0.05, help="consistency tolerance (m) of the search"
    )
    args = ap.parse_args()
    global EPSILON_M
    EPSILON_M = args.epsilon
    mode = Mode(args.mode)
    rows = []
    if Path(args.data).exists() and not args.skip_real:
        maps = {k: traverse_map(load_traverse(p)) for k, p in find_traverses(args.data).items()}
        for a, b in itertools.permutations(sorted(maps), 2):
            if a > b and (b, a) in [(x, y) for x, y, *_ in rows]:
                continue
            veh = maps[b]
            mirrored = LandmarkMap(veh.positions_xyz * np.array([-1.0, 1.0, 1.0]))
            m, k = chance_size(maps[a], mirrored, mode, f"mirrored {a}-{b}")
            rows.append((a, b, "real-mirrored", m, k))
            d, _ = cKDTree(veh.positions_xyz).query(maps[a].positions_xyz)
            ref = maps[a].subset(d > 1.0)
            if len(ref) >= 3:
                m2, k2 = chance_size(ref, veh, mode, f"disjoint {a}-{b}")
                rows.append((a, b, "real-disjoint", m2, k2))
                print(f"real {a}-{b}: mirrored m={m} k={k}; disjoint m={m2} k={k2}", flush=True)
    rng = np.random.default_rng(0)
    for t in range(args.synthetic):
        na, nb = (int(x) for x in rng.integers(20, args.synthetic_max, 2))
        m, k = chance_size(
            synthetic_field(rng, na), synthetic_field(rng, nb), mode, f"synthetic {na}x{nb}"
        )
        rows.append((na, nb, "synthetic", m, k))
        print(f"synthetic {na}x{nb}: m={m} chance clique={k}", flush=True)
    if args.overhead:
        from lunarloc.sim.simulate import simulate_site
        from lunarloc.io.overhead import grid_landmarks, site_geometric_map

        for seed in range(args.overhead):
            ref = grid_landmarks(site_geometric_map(simulate_site(1000 + seed)))
            for _ in range(args.per_site):
                nv = int(rng.integers(20, 160))
                r = localize(ref, synthetic_field(rng, nv), LocalizationConfig(mode=mode))
                if r.success:
                    FALSE_ACCEPTS.append(f"overhead site {seed} x {nv}")
                rows.append((len(ref), nv, "overhead", len(ref) * nv, r.clique_size))
                print(
                    f"overhead site {seed} ({len(ref)} rocks) x {nv}: m={len(ref) * nv} chance clique={r.clique_size} "
                    f"inliers after refinement={r.num_inliers} required={r.required_inliers} accepted={r.success}",
                    flush=True,
                )
    for kind in ("real-mirrored", "real-disjoint", "synthetic", "overhead"):
        sel = [r for r in rows if r[2] == kind]
        if sel:
            print(f"{kind}: {len(sel)} pairs, largest chance clique {max(r[4] for r in sel)}")
    fit = [r for r in rows if r[2] not in ("real-mirrored", "overhead")]
    if not fit:
        print(
            f"false accepts (success claimed on unrelated maps): {len(FALSE_ACCEPTS)} {FALSE_ACCEPTS}"
        )
        return
    ms = np.array([r[3] for r in fit], float)
    ks = np.array([r[4] for r in fit], float)
    # envelope a + b log10(m): least-squares slope, intercept raised to cover every point
    b = np.polyfit(np.log10(ms), ks, 1)[0]
    a = float(np.max(ks - b * np.log10(ms)))
    print(f"envelope: chance clique <= {a:.2f} + {b:.2f} * log10(m)  (max observed {ks.max():.0f})")
    print(
        f"false accepts (success claimed on unrelated maps) with the current rule: {len(FALSE_ACCEPTS)} {FALSE_ACCEPTS}"
    )
    Path(args.out).write_text(
        json.dumps({"rows": rows, "envelope": [a, b], "false_accepts": FALSE_ACCEPTS}, indent=1)
    )


if __name__ == "__main__":
    main()
