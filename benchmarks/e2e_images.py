"""End-to-end check from images (issue 4): maps built from the stereo images of two
simulated traverses of one site localize against each other with `lunarloc localize`.

Usage
-----
    python benchmarks/e2e_images.py --out DIR [--seed 21] [--traverses 2] [--duration 150]
        [--image-rate 1] [--vehicle-image-rate R] [--lighting sun|lamps|sun+lamps] [--sun-elevation DEG]
        [--width 1280 --height 720] [--rocks N] [--all-cameras]
        [--min-sightings 5 2] [--epsilon 0.05 0.08] [--poses gt/gt ...] [--online] [--json OUT.json]
        [--plan random|survey] [--reference-duration D] [--odometry SOURCE] [--run-config C.json --run-tag T]
        [--detect-config C.json] [--config C.json]

Steps (each runs the project's own command line; outputs already in DIR are reused):

1. ``lunarloc simulate --seed S --traverses N --out DIR --duration D --image-rate R
   --front-only --no-semantic`` (with ``--rocks N``, ``--plan survey``, ``--reference-duration``
   or ``--vehicle-image-rate`` the site is simulated through the Python API instead,
   e.g. ``SiteConfig(n_rocks=N)``: the command has no such options).
   ``--plan survey``: traverse 0 (the reference) surveys the site in an outward spiral about
   the lander (``TraversePlan.SURVEY``); every later traverse revisits that ground from
   another start (``TraversePlan.REVISIT``), as a later session of a mission would. The
   share of each vehicle path within 1.5 m and 3 m of the reference path is reported.
2. ``lunarloc detect DIR/traverse_i.lac -o DIR/det_i_<pose>.csv --pose <pose>`` for
   pose = ground-truth and odometry.
3. ``lunarloc map det_i_<pose>.csv -o map_i_<pose>_ms<M>.csv --min-sightings M``.
4. ``lunarloc localize map_0_<pose>.csv map_i_<pose>.csv --json --epsilon E`` for
   every traverse i > 0, every min-sightings M and epsilon E, and three pose pairs:

   * ``gt/gt``: both maps from ground-truth poses, so both are in the site (world)
     frame and the true ``T_ref_veh`` is the identity. Errors: ``|T p - p|`` at the
     origin, at the vehicle map's landmarks (median and max) and at the vehicle's
     last true position; rotation angle of ``T``.
   * ``odo/odo``: both maps from their odometry (each starts at the true first pose,
     so its frame is the world frame up to drift). The true relation is not rigid;
     the error reported is ``|T p_odo_last - p_gt_last|`` (the vehicle's last
     odometry position mapped into the reference map against its true position;
     it includes the reference map's own drift), next to the odometry-only error
     ``|p_odo_last - p_gt_last|``.
   * ``gt/odo``: a world-frame reference (ground-truth poses) and a drifting vehicle
     map (odometry): the same last-position error, with an exact reference.

Map quality: landmarks per map and how many lie within max(0.15 m, radius) of a
ground-truth rock centre (``rocks.csv``), with the median distance; an odometry
map's landmarks are placed by the same detections with ground-truth poses (the
detector output is the same, only the pose differs). Each result also counts the
inliers that pair landmarks of the same true rock ("good").
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from lunarloc.sim.rover import path_share_near

POSES = {"gt": "ground-truth", "odo": "odometry"}
PAIRS = [("gt", "gt"), ("odo", "odo"), ("gt", "odo")]


def _run(cmd: list[str], log: list[str]) -> str:
    shown = " ".join(shlex.quote(c) for c in cmd)
    print(f"$ {shown}", file=sys.stderr, flush=True)
    log.append(shown)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, check=False, capture_output=True, text=True)
    if r.returncode != 0:
        sys.stderr.write(r.stdout + r.stderr)
        raise SystemExit(f"command failed ({r.returncode}): {shown}")
    print(
        f"  ({time.perf_counter() - t0:.0f} s) {r.stdout.strip().splitlines()[-1] if r.stdout.strip() else ''}",
        file=sys.stderr,
        flush=True,
    )
    return r.stdout


def _lunarloc() -> list[str]:
    return [sys.executable, "-m", "lunarloc"]


def simulate(a, log: list[str]) -> list[Path]:
    paths = [a.out / f"traverse_{i}.lac" for i in range(a.traverses)]
    if all(p.exists() for p in paths):
        return paths
    if (
        a.rocks is None
        and a.vehicle_image_rate is None
        and a.plan == "random"
        and a.reference_duration is None
    ):
        cmd = (
            _lunarloc()
            + [
                "simulate",
                "--seed",
                str(a.seed),
                "--traverses",
                str(a.traverses),
                "--out",
                str(a.out),
                "--duration",
                f"{a.duration:g}",
                "--image-rate",
                f"{a.image_rate:g}",
                "--width",
                str(a.width),
                "--height",
                str(a.height),
                "--no-semantic",
                "--lighting",
                a.lighting,
                "--sun-elevation",
                f"{a.sun_elevation:g}",
            ]
            + ([] if a.all_cameras else ["--front-only"])
        )
        _run(cmd, log)
    else:
        from dataclasses import replace

        from lunarloc.sim.render import RenderConfig
        from lunarloc.sim.simulate import (
            ALL_CAMERAS,
            SimulationConfig,
            simulate_site,
            simulate_traverse,
        )
        from lunarloc.sim.site import SiteConfig

        site_cfg = SiteConfig() if a.rocks is None else replace(SiteConfig(), n_rocks=a.rocks)
        cfg = SimulationConfig(
            site=site_cfg,
            duration_s=a.duration,
            image_rate_hz=a.image_rate,
            width=a.width,
            height=a.height,
            semantic=False,
            cameras=ALL_CAMERAS if a.all_cameras else ("FrontLeft", "FrontRight"),
            render=RenderConfig(sun_elevation_deg=a.sun_elevation, lighting=a.lighting),
        )
        veh_rate = a.vehicle_image_rate or a.image_rate
        ref_cfg = replace(cfg, duration_s=a.reference_duration or a.duration)
        veh_cfg = replace(cfg, image_rate_hz=veh_rate)
        if a.plan == "survey":
            ref_cfg = replace(ref_cfg, rover=replace(cfg.rover, plan="survey"))
            veh_cfg = replace(veh_cfg, rover=replace(cfg.rover, plan="revisit"))
        log.append(
            f"python: simulate_traverse(simulate_site({a.seed}, cfg), traverse_i.lac, i, cfg) with SimulationConfig("
            f"site=SiteConfig(n_rocks={site_cfg.n_rocks}), duration_s={a.duration:g}, image_rate_hz={a.image_rate:g} "
            f"(vehicle traverses {veh_rate:g}), width={a.width}, height={a.height}, semantic=False, "
            f"render=RenderConfig(sun_elevation_deg={a.sun_elevation:g}, lighting={a.lighting!r}), cameras=...), "
            f"plan {a.plan} (reference {ref_cfg.rover.plan}, {ref_cfg.duration_s:g} s; vehicles {veh_cfg.rover.plan})"
        )
        print(f"$ {log[-1]}", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        site = simulate_site(a.seed, cfg)
        site.write_rocks_csv(a.out / "rocks.csv")
        for i, p in enumerate(paths):
            if not p.exists():
                simulate_traverse(site, p, i, ref_cfg if i == 0 else veh_cfg)
        print(f"  ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
    return paths


def _truth(archive: Path) -> dict:
    """Last ground-truth and odometry positions of a traverse (site frame, metres)."""
    from lunarloc.io.lac.archive import LacArchive

    with LacArchive(archive) as ar:
        gt = ar.positions()
        odo = ar.custom("odometry").to_array(("x", "y", "z"))
        frames = ar.frame_numbers
        odo_frames = ar.custom("odometry")["frame"]
    last = int(frames[-1])
    k = int(np.flatnonzero(odo_frames == last)[0])
    return {
        "gt_last": gt[-1],
        "odo_last": odo[k],
        "path_m": float(np.linalg.norm(np.diff(gt, axis=0), axis=1).sum()),
        "gt_xyz": gt,
    }


def _odometry_source(run_dir: Path) -> str | None:
    """The odometry a run used (its config.json's ``info``), None when not recorded."""
    try:
        return json.loads((run_dir / "config.json").read_text())["info"]["odometry_source"]
    except (OSError, KeyError, ValueError):
        return None


def _fix_record(run_dir: Path) -> dict:
    """Of a run's accepted fixes: the worst one's error and predicted error (m), and the
    first one's time (s from the run's first attempt's clock)."""
    atts = [a for a in json.loads((run_dir / "attempts.json").read_text()) if a["accepted"]]
    scored = [
        a for a in atts if a.get("fix_error_m") is not None and math.isfinite(a["fix_error_m"])
    ]
    worst = max(scored, key=lambda a: a["fix_error_m"]) if scored else None
    return {
        "worst_fix_predicted_m": None if worst is None else worst["predicted_error_m"],
        "first_fix_time_s": atts[0]["time_s"] if atts else None,
    }


def _landmark_rocks(
    map_path: Path, det_path: Path, gt_det_path: Path, rocks: np.ndarray, radius_m: float = 0.10
):
    """Ground-truth rock of each landmark of a map (-1: none within max(0.15 m, r)) and
    its distance, by the landmark's detections seen with ground-truth poses.

    `det_path` and `gt_det_path` hold the same detections (the same images run through
    the same detector) with the map's poses and with ground-truth poses: a landmark's
    world position is the median of the ground-truth-pose twins of the detections
    within `radius_m` (the clustering radius) of it. For a ground-truth-pose map both
    files are the same.
    """
    from lunarloc.io.maps import load_map, load_traverse

    P = load_map(map_path).positions_xyz
    D = load_traverse(det_path).detections_xyz
    G = load_traverse(gt_det_path).detections_xyz
    if len(D) != len(G):
        raise SystemExit(f"{det_path} and {gt_det_path} do not hold the same detections")
    ids = np.full(len(P), -1)
    dist = np.full(len(P), np.nan)
    for k, p in enumerate(P):
        near = np.linalg.norm(D - p, axis=1) <= radius_m
        w = np.median(G[near], axis=0) if near.any() else p
        d = np.linalg.norm(rocks[:, :3] - w, axis=1)
        j = int(d.argmin())
        dist[k] = d[j]
        if d[j] <= max(0.15, rocks[j, 3]):
            ids[k] = j
    return ids, dist


def _map_quality(ids: np.ndarray, dist: np.ndarray) -> dict:
    ok = ids >= 0
    return {
        "landmarks": len(ids),
        "on_rock": int(ok.sum()),
        "median_err_m": float(np.median(dist[ok])) if ok.any() else float("nan"),
    }


def _errors(
    T: np.ndarray | None, veh_map: Path, truth_veh: dict, ref_pose: str, veh_pose: str
) -> dict:
    from lunarloc.io.maps import load_map

    nan = float("nan")
    out = {
        "err_origin_m": nan,
        "err_landmarks_median_m": nan,
        "err_landmarks_max_m": nan,
        "rot_deg": nan,
        "err_last_m": nan,
        "odometry_only_err_last_m": nan,
        "t_norm_m": nan,
    }
    p_veh_last = truth_veh["gt_last"] if veh_pose == "gt" else truth_veh["odo_last"]
    if veh_pose == "odo":
        out["odometry_only_err_last_m"] = float(
            np.linalg.norm(truth_veh["odo_last"] - truth_veh["gt_last"])
        )
    if T is None:
        return out
    R, t = T[:3, :3], T[:3, 3]
    out["rot_deg"] = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    out["err_last_m"] = float(np.linalg.norm(R @ p_veh_last + t - truth_veh["gt_last"]))
    if ref_pose == veh_pose == "gt":  # both in the world frame: the truth is the identity
        P = load_map(veh_map).positions_xyz
        e = np.linalg.norm(P @ R.T + t - P, axis=1)
        out["err_origin_m"] = float(np.linalg.norm(t))
        out["err_landmarks_median_m"] = float(np.median(e))
        out["err_landmarks_max_m"] = float(np.max(e))
    # with odometry maps the truth is not rigid (drift): |t| only says how far T is from
    # the identity at the origin, it is not an error
    out["t_norm_m"] = float(np.linalg.norm(t))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--out", type=Path, required=True, help="working folder (archives, detections, maps)"
    )
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--traverses", type=int, default=2)
    ap.add_argument("--duration", type=float, default=150.0)
    ap.add_argument("--image-rate", type=float, default=1.0)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument(
        "--rocks", type=int, default=None, help="rocks on the site (default: the site's 386)"
    )
    ap.add_argument("--lighting", default="sun+lamps", help="sun | lamps | sun+lamps")
    ap.add_argument("--sun-elevation", type=float, default=12.0, help="degrees (<= 0: night)")
    ap.add_argument(
        "--vehicle-image-rate",
        type=float,
        default=None,
        help="camera rate of the vehicle traverses, Hz (default: --image-rate)",
    )
    ap.add_argument(
        "--all-cameras", action="store_true", help="record the rear pair too (default: front only)"
    )
    ap.add_argument("--min-sightings", type=int, nargs="+", default=[5, 2])
    ap.add_argument("--epsilon", type=float, nargs="+", default=[0.05, 0.08])
    ap.add_argument(
        "--poses",
        nargs="+",
        default=[f"{r}/{v}" for r, v in PAIRS],
        help="reference/vehicle pose pairs among gt/gt odo/odo gt/odo",
    )
    ap.add_argument(
        "--online",
        action="store_true",
        help="also run `lunarloc run` on every vehicle traverse against the reference map built with "
        "ground-truth poses (each --min-sightings), and report the online trajectory's RMSE",
    )
    ap.add_argument(
        "--plan",
        choices=["random", "survey"],
        default="random",
        help="random: every traverse drives random legs from the site's start; survey: the reference "
        "surveys around the lander and the vehicles revisit that ground from other starts",
    )
    ap.add_argument(
        "--reference-duration",
        type=float,
        default=None,
        help="reference traverse, s (default --duration)",
    )
    ap.add_argument(
        "--odometry",
        default=None,
        help="`lunarloc run --odometry` for --online (default: run's own, visual odometry)",
    )
    ap.add_argument(
        "--run-config",
        type=Path,
        default=None,
        help="`lunarloc run --config` for --online (e.g. a config.json with the loop's adaptive window)",
    )
    ap.add_argument(
        "--run-tag",
        default="",
        help="suffix of the --online run folders (runs whose folder exists are not run again)",
    )
    ap.add_argument(
        "--detect-config",
        type=Path,
        default=None,
        help="run config for `lunarloc detect` (e.g. a detector setting's before/after; use a fresh --out"
        " holding links to the archives, as detections and maps already there are reused)",
    )
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="one run configuration for both `lunarloc detect` and the --online `lunarloc run` (so"
        ' reference and vehicle see the same detector, e.g. \'{"detector": {"small_rocks":'
        ' {"enabled": true}}}\'); --detect-config / --run-config override it',
    )
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    if a.config is not None:
        a.detect_config = a.detect_config or a.config
        a.run_config = a.run_config or a.config
    a.out.mkdir(parents=True, exist_ok=True)
    pairs = [tuple(p.split("/")) for p in a.poses]
    log: list[str] = []
    t_start = time.perf_counter()
    archives = simulate(a, log)
    rocks_t = np.genfromtxt(a.out / "rocks.csv", delimiter=",", names=True)
    rocks = np.column_stack([rocks_t["x"], rocks_t["y"], rocks_t["z"], rocks_t["radius"]])
    needed = ["gt"] + sorted(
        {p for pr in pairs for p in pr} - {"gt"}
    )  # gt first: odo maps are judged by it
    rock_of: dict[Path, np.ndarray] = {}
    # detections and maps
    maps: dict[tuple[int, str, int], Path] = {}
    quality: dict[str, dict] = {}
    for i, arch in enumerate(archives):
        for pose in needed:
            det = a.out / f"det_{i}_{pose}.csv"
            if not det.exists():
                _run(
                    _lunarloc()
                    + ["detect", str(arch), "-o", str(det), "--pose", POSES[pose]]
                    + ([] if a.detect_config is None else ["--config", str(a.detect_config)]),
                    log,
                )
            for ms in a.min_sightings:
                m = a.out / f"map_{i}_{pose}_ms{ms}.csv"
                if not m.exists():
                    _run(
                        _lunarloc() + ["map", str(det), "-o", str(m), "--min-sightings", str(ms)],
                        log,
                    )
                maps[i, pose, ms] = m
                ids, dist = _landmark_rocks(m, det, a.out / f"det_{i}_gt.csv", rocks)
                rock_of[m] = ids
                quality[m.name] = _map_quality(ids, dist)
    truth = [_truth(p) for p in archives]
    rows = []
    for i in range(1, len(archives)):
        for rp, vp in pairs:
            for ms in a.min_sightings:
                ref, veh = maps[0, rp, ms], maps[i, vp, ms]
                for eps in a.epsilon:
                    out = _run(
                        _lunarloc()
                        + ["localize", str(ref), str(veh), "--json", "--epsilon", f"{eps:g}"],
                        log,
                    )
                    res = json.loads(out.strip().splitlines()[-1])
                    T = np.array(
                        [[math.nan if v is None else v for v in r] for r in res["T_ref_veh"]], float
                    )
                    T = T if np.all(np.isfinite(T)) else None
                    inl = np.asarray(res["inliers"], int).reshape(-1, 2)  # [vehicle, reference]
                    rv, rr = rock_of[veh][inl[:, 0]], rock_of[ref][inl[:, 1]]
                    correct = int(np.count_nonzero((rv >= 0) & (rv == rr)))
                    shared = len((set(rock_of[veh].tolist()) & set(rock_of[ref].tolist())) - {-1})
                    row = {
                        "ref": f"0:{rp}",
                        "veh": f"{i}:{vp}",
                        "min_sightings": ms,
                        "epsilon_m": eps,
                        "ref_landmarks": quality[ref.name]["landmarks"],
                        "veh_landmarks": quality[veh.name]["landmarks"],
                        "shared_rocks": shared,
                        "inliers": res["num_inliers"],
                        "correct_inliers": correct,
                        "required": res["required_inliers"],
                        "success": res["success"],
                        "reason": res["reason"],
                        "rmse_m": res["residual_rmse_m"],
                        **_errors(T, veh, truth[i], rp, vp),
                    }
                    rows.append(row)
    online = []
    if a.online:
        for i in range(1, len(archives)):
            for ms in a.min_sightings:
                odo_tag = "" if a.odometry is None else "_" + a.odometry.replace(":", "-")
                run_dir = a.out / f"run_{i}_ms{ms}{odo_tag}{'_' + a.run_tag if a.run_tag else ''}"
                if not (run_dir / "summary.json").exists():
                    _run(
                        _lunarloc()
                        + [
                            "run",
                            str(archives[i]),
                            "--reference",
                            str(maps[0, "gt", ms]),
                            "--out",
                            str(run_dir),
                            "--no-plot",
                        ]
                        + ([] if a.odometry is None else ["--odometry", a.odometry])
                        + ([] if a.run_config is None else ["--config", str(a.run_config)]),
                        log,
                    )
                rs = json.loads((run_dir / "summary.json").read_text())
                online.append(
                    {
                        "veh": i,
                        "min_sightings": ms,
                        "ref_landmarks": rs["reference_landmarks"],
                        "attempts": rs["attempts"],
                        "localized": rs["localized"],
                        "fixes": rs["fixes"],
                        "online_rmse_m": rs["ate_online"]["rmse_m"],
                        "corrected_rmse_m": rs["ate_corrected"]["rmse_m"],
                        "odometry_rmse_m": rs["ate_odometry"]["rmse_m"],
                        "path_m": rs["path_length_m"],
                        "worst_fix_m": rs.get("max_accepted_fix_error_m"),
                        **_fix_record(run_dir),
                        "odometry_source": _odometry_source(run_dir),
                    }
                )
    summary = {
        "online": online,
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()},
        "commands": log,
        "traverses": [
            {
                "archive": str(p),
                "path_m": t["path_m"],
                "odometry_err_last_m": float(np.linalg.norm(t["odo_last"] - t["gt_last"])),
                **(
                    {}
                    if i == 0
                    else {
                        f"share_near_reference_{d:g}m": path_share_near(
                            t["gt_xyz"], truth[0]["gt_xyz"], d
                        )
                        for d in (1.5, 3.0)
                    }
                ),
            }
            for i, (p, t) in enumerate(zip(archives, truth))
        ],
        "maps": quality,
        "results": rows,
        "wall_s": time.perf_counter() - t_start,
    }
    print_table(summary)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(summary, indent=1, default=float))
    return 0


LEGEND = (
    "errors in cm, rotation of T in degrees. shared: true rocks with a landmark in both maps; inl: inliers;"
    " good: inliers pairing landmarks of the same true rock; req: inliers required; rmse: residual at the inliers; e_orig, e_lm50, e_lmMx: |T p - p| at the origin and"
    " at the vehicle map's landmarks (median, max), gt/gt only (true T = identity); e_last: at the vehicle's last"
    " position against its true position; odo: the odometry-only error there; |t|: translation of T (with"
    " odometry maps not an error: drift)"
)


def print_table(s: dict) -> None:
    def cm(x):
        return "-" if x is None or not math.isfinite(x) else f"{100 * x:.1f}"

    for t in s["traverses"]:
        err = 100 * t["odometry_err_last_m"]
        near = "".join(
            f", {100 * v:.0f} % of it within {k.rsplit('_', 1)[1]} of the reference path"
            for k, v in t.items()
            if k.startswith("share_near_reference_")
        )
        print(
            f"{t['archive']}: path {t['path_m']:.1f} m, odometry error at the end {err:.1f} cm{near}"
        )
    print(
        "maps: landmarks; within max(0.15 m, r) of a true rock (odometry maps: judged by the same detections"
        " with ground-truth poses), median distance:"
    )
    for name, q in s["maps"].items():
        print(
            f"  {name}: {q['landmarks']}, {q['on_rock']} on a rock, median {cm(q['median_err_m'])} cm"
        )
    cols = [  # (header, width, cell)
        ("ref", 6, lambda r: r["ref"]),
        ("veh", 6, lambda r: r["veh"]),
        ("ms", 3, lambda r: r["min_sightings"]),
        ("eps", 5, lambda r: f"{r['epsilon_m']:.2f}"),
        ("L_ref", 5, lambda r: r["ref_landmarks"]),
        ("L_veh", 5, lambda r: r["veh_landmarks"]),
        ("shared", 6, lambda r: r["shared_rocks"]),
        ("inl", 4, lambda r: r["inliers"]),
        ("good", 4, lambda r: r["correct_inliers"]),
        ("req", 4, lambda r: r["required"]),
        ("ok", 3, lambda r: "yes" if r["success"] else "no"),
        ("rmse", 5, lambda r: cm(r["rmse_m"])),
        ("e_orig", 6, lambda r: cm(r["err_origin_m"])),
        ("e_lm50", 6, lambda r: cm(r["err_landmarks_median_m"])),
        ("e_lmMx", 6, lambda r: cm(r["err_landmarks_max_m"])),
        ("e_last", 6, lambda r: cm(r["err_last_m"])),
        ("odo", 6, lambda r: cm(r["odometry_only_err_last_m"])),
        ("|t|", 6, lambda r: cm(r["t_norm_m"])),
        ("rot", 5, lambda r: "-" if not math.isfinite(r["rot_deg"]) else f"{r['rot_deg']:.2f}"),
    ]
    print(LEGEND)
    print(" ".join(f"{h:>{w}}" for h, w, _ in cols) + "  reason")
    for r in s["results"]:
        print(" ".join(f"{f(r)!s:>{w}}" for _, w, f in cols) + f"  {r['reason']}")
    if s.get("online"):
        print(
            "online (`lunarloc run` of the vehicle traverse against the ground-truth-pose reference map): "
            "ATE RMSE of the online, corrected and odometry-only trajectories, cm"
        )
        print("veh ms L_ref attempts localized fixes online corrected odometry path_m worst_fix")
        for r in s["online"]:
            print(
                f"{r['veh']:>3} {r['min_sightings']:>2} {r['ref_landmarks']:>5} {r['attempts']:>8} {r['localized']:>9} "
                f"{r['fixes']:>5} {cm(r['online_rmse_m']):>6} {cm(r['corrected_rmse_m']):>9} "
                f"{cm(r['odometry_rmse_m']):>8} {r['path_m']:>6.1f} {cm(r.get('worst_fix_m')):>9}"
                f"  ({r.get('odometry_source')})"
            )
    print(f"wall time {s['wall_s']:.0f} s")


if __name__ == "__main__":
    sys.exit(main())
