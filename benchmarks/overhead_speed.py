"""Speed of localizing a vehicle map against a large overhead map, as the tolerances grow.

A 600-rock reference (a team's LAC rock map holds about that many) with per-landmark
sigma of a 0.15 m grid (cell / sqrt(12)), and a 150-landmark vehicle map that sees 100
of its rocks (3 cm noise) plus 50 spurious ones. The consistency search runs at the
configured tolerance (``--epsilon``) raised to what the maps' sigma needs
(``LocalizationConfig.search_sigmas``; ``--search-sigmas 0`` keeps the given epsilon), and
so do refinement and acceptance; each line prints the tolerances the search ran at. Reports wall and CPU time per call (CPU time is what a
quiet machine's wall time would be for the single-threaded parts; the search uses up to
``threads`` threads), after a warm-up call (compile time excluded).

An unrelated vehicle map (no overlap: a rover asking in the wrong map, or any attempt
that must be refused) is the slow case of an exhaustive search, as no large consistent
set bounds the yaw bins: ``--unrelated N`` times N such maps (150-rock fields on the
whole 27 m site and on a 14 m patch, which has a true vehicle map's density), and prints
what the screen before the exhaustive search (``localize._screen``) scored each: inliers
beyond chance at the best of the candidate poses voted by the reference's rock triangles,
against what passing needs. ``--no-screen`` times the exhaustive search alone.

Usage: python benchmarks/overhead_speed.py [--epsilon 0.05 0.10 0.15] [--repeat 3] [--search-sigmas S] [--threads N]
       [--unrelated N] [--no-screen]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from conftest import make_pair, rock_field  # noqa: E402

from lunarloc.localization.config import LocalizationConfig  # noqa: E402
from lunarloc.localization.localize import localize  # noqa: E402
from lunarloc.io.maps import LandmarkMap  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--epsilon", type=float, nargs="+", default=[0.05, 0.10, 0.15])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument(
        "--search-sigmas",
        type=float,
        default=None,
        help="LocalizationConfig.search_sigmas (default: the config's; 0 = the given epsilon exactly)",
    )
    ap.add_argument(
        "--threads", type=int, default=None, help="search threads (default: the config's)"
    )
    ap.add_argument(
        "--unrelated",
        type=int,
        default=1,
        help="unrelated vehicle maps per tolerance (alternately whole site / 14 m patch)",
    )
    ap.add_argument(
        "--no-screen", action="store_true", help="no screen before the exhaustive search"
    )
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    ref, veh, T, _ = make_pair(rng, n_ref=600, n_common=100, n_outliers=50, noise=0.03)
    q = 0.15 / math.sqrt(12)
    ref = LandmarkMap(
        ref.positions_xyz, sigma_xy_m=np.full(len(ref), q), sigma_z_m=np.full(len(ref), q)
    )
    unrelated = [
        LandmarkMap(rock_field(rng, 150, size=27.0 if k % 2 == 0 else 14.0))
        for k in range(args.unrelated)
    ]
    localize(LandmarkMap(ref.positions_xyz[:40]), LandmarkMap(veh.positions_xyz[:20]))  # compile
    for eps in args.epsilon:
        kw = {} if args.search_sigmas is None else {"search_sigmas": args.search_sigmas}
        if args.threads is not None:
            kw["threads"] = args.threads
        if args.no_screen:
            kw["screen_min_incidences"] = 0
        cfg = LocalizationConfig(epsilon_m=eps, epsilon_z_m=eps, **kw)
        for name, v in [("true pair", veh)] + [
            (f"unrelated{k}", u) for k, u in enumerate(unrelated)
        ]:
            walls, cpus = [], []
            for _ in range(args.repeat):
                t0, c0 = time.perf_counter(), time.process_time()
                r = localize(ref, v, cfg)
                walls.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            err = ""
            if name == "true pair" and r.success:
                E = r.T_ref_veh @ np.linalg.inv(T)
                err = f", error {np.linalg.norm(E[:3, 3]) * 100:.1f} cm at the origin"
            run = cfg.for_maps(
                ref, v
            )  # the tolerances the search ran at (raised to the maps' sigma)
            screen = next((c for c in r.checks if c.name == "screen"), None)
            if "screen" not in r.timings:
                how = "no screen"
            else:
                how = (
                    f"screen {'passed' if screen.passed else 'refused'}: {screen.value:.1f} inliers beyond chance, "
                    f"passing needs {screen.limit:.1f}"
                )
            print(
                f"epsilon {eps * 100:4.0f} cm (search {run.epsilon_m * 100:.1f} / {run.epsilon_z_m * 100:.1f} cm) {name:10s}: wall {np.median(walls):6.2f} s, CPU {np.median(cpus):6.2f} s; "
                f"success {r.success} ({r.num_inliers} inliers, clique {r.clique_size}, need {r.required_inliers}{err}; {how})",
                flush=True,
            )


if __name__ == "__main__":
    main()
