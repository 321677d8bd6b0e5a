"""The per-tick component (lunarloc.OnlineLocalizer) as an agent calls it: accuracy, time per
update() and memory, over short traverses and over a long replay.

Usage
-----
    python benchmarks/bench_online_component.py --out bench-output/online-component
        [--seeds 0 13 15] [--duration 40] [--width 320] [--rocks 800]
        [--long-hours 2.0] [--long-seed 0] [--max-keyframes 1500]

1. **Traverses** (one per seed): simulate a site and a traverse (front stereo pair at 10 Hz,
   20 Hz ticks), replay it through :class:`lunarloc.PlaybackAgent` exactly as the LAC calls
   an agent, odometry inside the component (stereo VO + IMU), no custom record read.
   Reports the position RMSE against ground truth (all ticks, and ticks after the first
   accepted fix), the internal odometry's RMSE, and update() time (median, p99, max).
2. **Long replay** (``--long-hours`` of mission time): the traverse of ``--long-seed`` is
   played in a loop with mission time running on. The rover "teleports" from the last
   frame to the first at each lap, which no onboard odometry could follow, so here the
   caller passes odometry (``update(..., odometry=T_odo_rover)``): the ground-truth motion
   with a 2 % scale error and a 0.5 deg/min heading drift, the lap jump included. Reports,
   per lap: update() time (median, p99, max), process RSS, the component's history sizes
   (keyframes held, observations, attempts kept) and the position RMSE of the lap.

Images of the looped traverse are decoded once and kept (so RSS growth after the first lap
is the component's). Timings are wall-clock on whatever machine runs this; say whether it
was under load.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import time
from pathlib import Path

import numpy as np

from lunarloc import CameraRig, OnlineLocalizer, PlaybackAgent, load_reference
from lunarloc.core.geometry import invert_transform, pose_to_matrix


def simulate(d: Path, seed: int, duration: float, width: int, rocks: int) -> tuple[Path, Path]:
    from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse
    from lunarloc.sim.site import SiteConfig

    d.mkdir(parents=True, exist_ok=True)
    lac, ref = d / "traverse.lac", d / "rocks.csv"
    if not lac.is_file():
        cfg = SimulationConfig(
            site=SiteConfig(n_rocks=rocks),
            duration_s=duration,
            image_rate_hz=10.0,
            width=width,
            height=width * 9 // 16,
            cameras=("FrontLeft", "FrontRight"),
            semantic=False,
        )
        site = simulate_site(seed, cfg.site)
        site.write_rocks_csv(ref)
        simulate_traverse(site, lac, 1, cfg)
    return lac, ref


def rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * resource.getpagesize() / 2**20


def stats_ms(t: list[float]) -> dict:
    a = 1000 * np.asarray(t)
    return {
        "median_ms": round(float(np.median(a)), 3),
        "p99_ms": round(float(np.percentile(a, 99)), 3),
        "max_ms": round(float(a.max()), 3),
        "max_at_call": int(a.argmax()),
        "n": int(len(a)),
    }


def make_localizer(env, ref_path: Path, max_keyframes: int) -> OnlineLocalizer:
    from dataclasses import replace

    from lunarloc.online.component import OnlineConfig

    cams = ("FrontLeft", "FrontRight")
    rig = CameraRig.from_sensors(env.sensors(), {c: env.get_camera_position(c) for c in cams})
    loc = OnlineLocalizer(
        load_reference(ref_path),
        env.get_initial_position(),
        replace(OnlineConfig(), max_keyframes=max_keyframes),
        rig=rig,
    )
    loc.warm_up()
    return loc


def run_traverse(lac: Path, ref: Path, max_keyframes: int) -> dict:
    times, err, err_odo, localized = [], [], [], []
    with PlaybackAgent(lac) as env:
        loc = make_localizer(env, ref, max_keyframes)
        while True:
            data = env.input_data()
            t0 = time.perf_counter()
            e = loc.update(
                env.get_mission_time(),
                data,
                env.get_imu_data(),
                env.get_linear_speed(),
                env.get_angular_speed(),
            )
            times.append(time.perf_counter() - t0)
            g = env.get_transform_matrix()
            err.append(float(np.linalg.norm(e.T_map_rover[:3, 3] - g[:3, 3])))
            err_odo.append(float(np.linalg.norm(loc._T_map_odo[:3, 3] - g[:3, 3])))
            localized.append(e.localized)
            if env.at_end():
                break
            env.step_frame()
    err, err_odo = np.asarray(err), np.asarray(err_odo)
    first = localized.index(True) if any(localized) else None
    rmse = lambda x: round(float(np.sqrt(np.mean(x**2))), 4)  # noqa: E731
    return {
        "ticks": len(err),
        "fixes": int(e.fixes),
        "first_fix_tick": first,
        "attempts": len(loc.recent_attempts),
        "rmse_m": rmse(err),
        "rmse_after_first_fix_m": rmse(err[first:]) if first is not None else None,
        "final_error_m": round(float(err[-1]), 4),
        "odometry_rmse_m": rmse(err_odo),
        "odometry_final_error_m": round(float(err_odo[-1]), 4),
        "update": stats_ms(times),
    }


def drifted(
    T_prev_gt, T_gt, T_prev_odo, scale=1.02, yaw_rate_rad_s=math.radians(0.5 / 60), dt=0.05
):
    """Next odometry pose: the ground-truth motion with a scale error and a heading drift.
    The drift turns about the vertical (the odometry frame's z), as a gyro-bias heading drift
    does, so roll and pitch stay right (gravity keeps them; a drift about the body's z axis
    would leak into them: 2.3 deg of pitch after 2 h on this traverse)."""
    rel = invert_transform(T_prev_gt) @ T_gt
    rel[:3, 3] *= scale
    T = T_prev_odo @ rel
    T[:3, :3] = pose_to_matrix(0, 0, 0, 0, 0, yaw_rate_rad_s * dt)[:3, :3] @ T[:3, :3]
    return T


def run_long(
    lac: Path, ref: Path, hours: float, max_keyframes: int, rows: list, progress=print
) -> list[dict]:
    with PlaybackAgent(lac) as env:
        loc = make_localizer(env, ref, max_keyframes)
        frames, cache = [], []
        while True:  # decode the lap once
            frames.append(env.frame)
            cache.append(
                (
                    env.input_data(),
                    env.get_imu_data(),
                    env.get_linear_speed(),
                    env.get_angular_speed(),
                    env.get_transform_matrix(),
                    env.get_mission_time(),
                )
            )
            if env.at_end():
                break
            env.step_frame()
    dt = 0.05
    lap_s = cache[-1][5] - cache[0][5] + dt
    laps = max(1, math.ceil(hours * 3600 / lap_s))
    T_prev_gt, T_odo = None, None
    t_mission = 0.0
    for lap in range(laps):
        times, err = [], []
        for data, imu, v, w, T_gt, _ in cache:
            T_odo = T_gt.copy() if T_prev_gt is None else drifted(T_prev_gt, T_gt, T_odo)
            T_prev_gt = T_gt
            t0 = time.perf_counter()
            e = loc.update(t_mission, data, imu, v, w, odometry=T_odo)
            times.append(time.perf_counter() - t0)
            err.append(float(np.linalg.norm(e.T_map_rover[:3, 3] - T_gt[:3, 3])))
            t_mission += dt
        err = np.asarray(err)
        g = loc.loop.graph
        row = {
            "lap": lap,
            "mission_time_h": round(t_mission / 3600, 4),
            "update": stats_ms(times),
            "rss_mb": round(rss_mb(), 1),
            "keyframes_held": len(loc.loop.keyframes),
            "observations_held": g.num_observations,
            "fixes_held": len(g.fixes),
            "reanchors": loc.reanchors,
            "fixes_total": e.fixes,
            "lap_rmse_m": round(float(np.sqrt(np.mean(err**2))), 4),
            "lap_max_error_m": round(float(err.max()), 4),
        }
        rows.append(row)
        progress(json.dumps(row))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=Path("bench-output/online-component"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 13, 15])
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--rocks", type=int, default=800)
    ap.add_argument("--long-hours", type=float, default=2.0)
    ap.add_argument("--long-seed", type=int, default=0)
    ap.add_argument("--max-keyframes", type=int, default=1500)
    ap.add_argument("--skip-traverses", action="store_true")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    out = {"args": {k: str(v) for k, v in vars(a).items()}, "traverses": [], "long": []}
    if not a.skip_traverses:
        for seed in a.seeds:
            lac, ref = simulate(a.out / f"seed_{seed}", seed, a.duration, a.width, a.rocks)
            r = {"seed": seed, **run_traverse(lac, ref, a.max_keyframes)}
            out["traverses"].append(r)
            print(json.dumps(r), flush=True)
            (a.out / "bench_online_component.json").write_text(json.dumps(out, indent=1))
    if a.long_hours > 0:
        lac, ref = simulate(
            a.out / f"seed_{a.long_seed}", a.long_seed, a.duration, a.width, a.rocks
        )

        def progress(line):
            print(line, flush=True)
            (a.out / "bench_online_component.json").write_text(json.dumps(out, indent=1))

        run_long(lac, ref, a.long_hours, a.max_keyframes, out["long"], progress)
    (a.out / "bench_online_component.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
