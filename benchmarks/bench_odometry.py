"""Benchmark: odometry drift on simulated ~100 m traverses (visual and IMU dead reckoning).

Two steps, so the expensive rendering is done once and can run in the background:

    # 1. simulate the traverses (front stereo pair only, no semantic images); cached
    python benchmarks/bench_odometry.py generate --out bench-output/odometry \
        --sizes 640x360 1280x720 --sites 0 1 2 --distance 100 --image-rate 2
    # 2. run the odometry sources over them and print the drift table
    python benchmarks/bench_odometry.py evaluate --out bench-output/odometry --source visual imu

Figures per traverse: path length, final position error as % of the path length,
final heading error in degrees per metre travelled, and for `visual` the odometry
rate in frames/s (image decoding and rendering excluded: images are read first).
The CPU is shared with other jobs: report the rates as measured under load.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def _size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def _archive_name(site: int, width: int, height: int, rate: float, distance: float) -> str:
    return f"site{site}_{width}x{height}_{rate:g}hz_{distance:g}m.lac"


def _duration_for(site, distance_m: float, seed: int, rover_cfg) -> float:
    """Shortest traverse duration (s, a multiple of 10) whose path is at least `distance_m` long."""
    from lunarloc.data.rover import plan_traverse

    duration = 10.0 * np.ceil(distance_m / rover_cfg.speed_mps * 1.15 / 10.0)
    while plan_traverse(site, duration, seed=seed, config=rover_cfg).path_length() < distance_m:
        duration += 10.0
    return duration


def generate(args) -> None:
    from lunarloc.data.render import SiteRenderer
    from lunarloc.data.simulate import SimulationConfig, simulate_site, simulate_traverse, traverse_seed

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for size in args.sizes:
        w, h = _size(size)
        for site_seed in args.sites:
            path = out / _archive_name(site_seed, w, h, args.image_rate, args.distance)
            if path.exists():
                print(f"{path}: exists, skipped", flush=True)
                continue
            base = SimulationConfig()
            site = simulate_site(site_seed, base.site)
            duration = _duration_for(site, args.distance, traverse_seed(site_seed, 0), base.rover)
            cfg = SimulationConfig(
                duration_s=duration, image_rate_hz=args.image_rate, width=w, height=h,
                cameras=("FrontLeft", "FrontRight"), semantic=False,
            )  # fmt: skip
            renderer = SiteRenderer(site, cfg.render)
            t0 = time.perf_counter()
            tmp = path.with_suffix(".partial")
            _, traj = simulate_traverse(site, tmp, 0, cfg, renderer=renderer)
            tmp.rename(path)
            print(
                f"{path}: {duration:g} s, {traj.path_length():.1f} m, rendered in {time.perf_counter() - t0:.0f} s",
                flush=True,
            )


def _final_errors(T_est: np.ndarray, T_true: np.ndarray) -> dict:
    """Drift of an odometry trajectory against the truth, both starting at the same pose."""
    from lunarloc.geometry import invert_transform, rotation_angle, yaw_of

    # express both in the frame of their first pose
    est = np.einsum("ij,njk->nik", invert_transform(T_est[0]), T_est)
    tru = np.einsum("ij,njk->nik", invert_transform(T_true[0]), T_true)
    length = float(np.linalg.norm(np.diff(tru[:, :3, 3], axis=0), axis=1).sum())
    final_m = float(np.linalg.norm(est[-1, :3, 3] - tru[-1, :3, 3]))
    dyaw = np.degrees(yaw_of(est[-1, :3, :3]) - yaw_of(tru[-1, :3, :3]))
    dyaw = float((dyaw + 180.0) % 360.0 - 180.0)
    rot_deg = float(np.degrees(rotation_angle(est[-1, :3, :3].T @ tru[-1, :3, :3])))
    rmse = float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - tru[:, :3, 3]) ** 2, axis=1))))
    return {
        "length_m": length,
        "final_error_m": final_m,
        "final_error_pct": 100.0 * final_m / max(length, 1e-9),
        "heading_error_deg": dyaw,
        "rotation_error_deg": rot_deg,
        "deg_per_m": abs(rot_deg) / max(length, 1e-9),
        "rmse_m": rmse,
    }


def _truth(archive, frames: np.ndarray) -> np.ndarray:
    from lunarloc.geometry import pose_to_matrix

    poses = archive.poses()
    index = {int(f): i for i, f in enumerate(archive.frame_numbers)}
    return np.stack([pose_to_matrix(*poses[index[int(f)]]) for f in frames])


def _run_visual(archive, config) -> tuple[np.ndarray, np.ndarray, dict]:
    from lunarloc.odometry.visual import StereoVisualOdometry, front_pair_setup

    camera, T_rover_left, T_rover_right, left_name, right_name = front_pair_setup(archive)
    frames = np.intersect1d(archive.camera_frames(left_name)["frame"], archive.camera_frames(right_name)["frame"])
    images = [(archive.grayscale(left_name, int(f)), archive.grayscale(right_name, int(f))) for f in frames]
    vo = StereoVisualOdometry(camera, T_rover_left, T_rover_right, config)
    T = np.empty((len(frames), 4, 4))
    n_ok = 0
    t0 = time.perf_counter()
    for i, (left, right) in enumerate(images):
        T[i] = vo.update(left, right)
        n_ok += bool(vo.last_ok)
    elapsed = time.perf_counter() - t0
    return frames, T, {"frames": len(frames), "fps": len(frames) / elapsed, "visual_fraction": n_ok / len(frames)}


def _run_imu(archive) -> tuple[np.ndarray, np.ndarray, dict] | None:
    try:
        from lunarloc.odometry import imu
    except ImportError:
        return None
    fn = getattr(imu, "imu_odometry_frames", None) or getattr(imu, "imu_odometry", None)
    if fn is None:
        return None
    t0 = time.perf_counter()
    frames, T = fn(archive)
    return np.asarray(frames), np.asarray(T), {"seconds": time.perf_counter() - t0}


def evaluate(args) -> None:
    from lunarloc.data.lac import LacArchive
    from lunarloc.odometry.visual import VisualOdometryConfig

    out = Path(args.out)
    paths = sorted(out.glob("*.lac"))
    if args.match:
        paths = [p for p in paths if any(m in p.name for m in args.match)]
    config = VisualOdometryConfig.from_dict(json.loads(Path(args.config).read_text())) if args.config else None
    rows = []
    for path in paths:
        with LacArchive(path) as archive:
            for source in args.source:
                if source == "visual":
                    res = _run_visual(archive, config)
                elif source == "imu":
                    res = _run_imu(archive)
                    if res is None:
                        print(f"{path.name}: imu: lunarloc.odometry.imu not available, skipped", flush=True)
                        continue
                else:
                    raise SystemExit(f"unknown source {source!r}")
                frames, T, extra = res
                row = {"archive": path.name, "source": source, **_final_errors(T, _truth(archive, frames)), **extra}
                rows.append(row)
                print(
                    f"{path.name:28s} {source:6s} {row['length_m']:6.1f} m  final {row['final_error_m']:6.2f} m "
                    f"({row['final_error_pct']:5.2f} %)  heading {row['heading_error_deg']:+6.2f} deg "
                    f"({row['deg_per_m']:.4f} deg/m)  rmse {row['rmse_m']:.2f} m"
                    + (f"  {row['fps']:.1f} frames/s, visual {100 * row['visual_fraction']:.0f} %" if "fps" in row else ""),
                    flush=True,
                )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="simulate the traverses (cached)")
    g.add_argument("--out", default="bench-output/odometry")
    g.add_argument("--sizes", nargs="+", default=["640x360", "1280x720"])
    g.add_argument("--sites", nargs="+", type=int, default=[0, 1, 2], help="site seeds (traverse 0 of each)")
    g.add_argument("--distance", type=float, default=100.0, help="path length, metres")
    g.add_argument("--image-rate", type=float, default=2.0, help="camera rate, Hz (divides 20)")
    e = sub.add_parser("evaluate", help="run odometry sources over the generated traverses")
    e.add_argument("--out", default="bench-output/odometry")
    e.add_argument("--source", nargs="+", default=["visual", "imu"], choices=["visual", "imu"])
    e.add_argument("--match", nargs="*", help="only archives whose name contains one of these")
    e.add_argument("--config", help="VisualOdometryConfig as JSON")
    e.add_argument("--json", help="write the rows here")
    args = ap.parse_args()
    generate(args) if args.cmd == "generate" else evaluate(args)


if __name__ == "__main__":
    main()
