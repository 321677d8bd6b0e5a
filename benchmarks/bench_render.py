"""Benchmark: ray-cast rendering time of 1280x720 stereo pairs, and the size of a traverse archive.

    python benchmarks/bench_render.py                 # render timing only (sun+lamps)
    python benchmarks/bench_render.py --lighting sun  # one lighting (sun, lamps, sun+lamps)
    python benchmarks/bench_render.py --archive 120   # also write a 120 s traverse and report its size

The CPU may be shared with other jobs; report the figures with that caveat. The CPU
time (process time, all threads) is less sensitive to other jobs than the wall time.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from lunarloc.sim.render import Lighting, RenderConfig, SiteRenderer
from lunarloc.sim.rover import plan_traverse
from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse, traverse_seed
from lunarloc.perception.camera import PinholeCamera, ipex_rig


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pairs", type=int, default=10, help="number of stereo pairs to time")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument(
        "--archive", type=float, default=0.0, help="also write a traverse of this many seconds"
    )
    ap.add_argument("--image-rate", type=float, default=2.0)
    ap.add_argument(
        "--lighting",
        type=Lighting.parse,
        default=Lighting.SUN_LAMPS,
        help="sun, lamps or sun+lamps",
    )
    ap.add_argument("--sun-elevation", type=float, default=RenderConfig.sun_elevation_deg)
    args = ap.parse_args()

    t0 = time.perf_counter()
    site = simulate_site(args.seed)
    t1 = time.perf_counter()
    render_cfg = RenderConfig(lighting=args.lighting, sun_elevation_deg=args.sun_elevation)
    renderer = SiteRenderer(site, render_cfg)
    t2 = time.perf_counter()
    print(
        f"site generation {t1 - t0:.2f} s, scene + BVH build {t2 - t1:.2f} s ({len(renderer.faces)} triangles)"
    )
    rig = ipex_rig(PinholeCamera(args.width, args.height))
    pair = [rig["FrontLeft"], rig["FrontRight"]]
    traj = plan_traverse(site, 120.0, seed=traverse_seed(args.seed, 0))
    renderer.render_rover(traj.poses[0], pair)  # warm-up (numba compile / cache load)
    times, cpu = [], []
    for k in np.linspace(0, len(traj) - 1, args.pairs).astype(int):
        t, c = time.perf_counter(), time.process_time()
        renderer.render_rover(traj.poses[k], pair)
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    times = np.array(times)
    print(
        f"lighting {args.lighting}, sun {args.sun_elevation:g} deg; "
        f"stereo pair {args.width}x{args.height}: median {np.median(times):.3f} s, mean {times.mean():.3f} s, "
        f"min {times.min():.3f} s, max {times.max():.3f} s over {len(times)} pairs "
        f"({1.0 / np.median(times):.2f} pairs/s); CPU time (all threads) median {np.median(cpu):.3f} s"
    )
    if args.archive > 0:
        cfg = SimulationConfig(
            duration_s=args.archive,
            image_rate_hz=args.image_rate,
            width=args.width,
            height=args.height,
            render=render_cfg,
        )
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            path, traj = simulate_traverse(
                site, Path(tmp) / "traverse.lac", 0, cfg, renderer=renderer
            )
            dt = time.perf_counter() - t
            size = path.stat().st_size
        print(
            f"traverse {args.archive:g} s, 4 cameras at {args.image_rate:g} Hz, {args.width}x{args.height} "
            f"grayscale + semantic: {size / 1e6:.1f} MB, written in {dt:.1f} s ({traj.path_length():.1f} m)"
        )


if __name__ == "__main__":
    main()
