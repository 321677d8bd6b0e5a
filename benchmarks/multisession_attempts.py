"""Why an online run gets (or does not get) fixes: the loop's attempts of a multi-session
vehicle traverse, one by one, against what the simulator knows (issue 11, item 3).

Usage
-----
    python benchmarks/multisession_attempts.py SITE_DIR [SITE_DIR ...] [--min-sightings 5]
        [--odometry visual|record:odometry] [--loop '{"window_target_landmarks": 0}']
        [--attempts] [--json OUT.json] [--config RUN.json]

SITE_DIR is a folder `benchmarks/e2e_images.py --plan survey --online` wrote: the vehicle
archive `traverse_1.lac`, the site's `rocks.csv`, the reference detections `det_0_gt.csv` and
the reference map `map_0_gt_ms<M>.csv`. The vehicle's per-frame rock detections (rover frame)
and its odometry (visual, and the archive's `odometry` record) are computed once and cached in
`SITE_DIR/vehicle_frames.npz`; each run then replays them through
:class:`lunarloc.online.loop.LoopState` with the run configuration's image defaults (`RunConfig()`)
and `--loop` overrides - the same loop `lunarloc run` drives, in a few seconds. `--config`
starts from a run configuration file instead of `RunConfig()`: its detector detects (cached
apart, in `vehicle_frames_<digest>.npz`, when its detector section is not the default's), its
loop and localization sections replay.

Per attempt (`--attempts`): the window's path length and landmarks, how many of them lie on a
true rock (a landmark's detections placed with ground-truth poses, within max(0.15 m, r) of a
rock of `rocks.csv`), how many of those rocks the reference map holds (and the reference's
sightings of the ones it misses: 0 = never detected there, 1-4 = cut by its min-sightings),
the inliers found and how many are true, the inliers the chance test required and the
associations it was judged at, and the outcome. Per run: fixes/attempts, online / corrected /
odometry RMSE, and every accepted fix's error against its predicted error.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

CACHE = "vehicle_frames.npz"


def _cache_path(site: Path, cfg) -> Path:
    """The detections' cache of `cfg`'s detector and odometry: `CACHE` for the defaults'."""
    import hashlib

    from lunarloc.config.run import RunConfig
    from lunarloc.core.configs import config_to_dict

    def sections(c):
        return {"detector": config_to_dict(c.detector), "odometry": config_to_dict(c.odometry)}

    mine = sections(cfg)
    if mine == sections(RunConfig()):
        return site / CACHE
    digest = hashlib.sha256(json.dumps(mine, sort_keys=True).encode()).hexdigest()[:8]
    return site / f"vehicle_frames_{digest}.npz"


def cache_vehicle(site: Path, cfg=None) -> Path:
    """Detect rocks in every image frame of SITE/traverse_1.lac once (rover frame, before the
    lander exclusion, which depends on the odometry) and keep both odometries."""
    from lunarloc.config.run import OdometryConfig, RunConfig
    from lunarloc.perception.detector import Detector
    from lunarloc.pipeline.sources import ArchiveSource

    cfg = cfg or RunConfig()
    out = _cache_path(site, cfg)
    if out.exists():
        return out
    arch = site / "traverse_1.lac"
    rows: dict[str, list] = {
        k: [] for k in ("frames", "times", "T_visual", "T_true", "keyframe", "ndet")
    }
    dets = []
    with ArchiveSource(arch, cfg.odometry, cfg.detector.pairs) as src:
        det = Detector(cfg.detector_for(src.camera.width), src.camera)
        lander = np.zeros(0) if src.lander_xy is None else np.asarray(src.lander_xy, float)
        for fr in src:
            n = -1
            if fr.images is not None:
                fd = det.detect_frame(fr.images, fr.mounts, None, fr.frame)
                d = np.array([x.p_rover for x in fd.detections], float).reshape(-1, 3)
                dets.append(d)
                n = len(d)
            for k, v in (
                ("frames", fr.frame),
                ("times", fr.time_s),
                ("T_visual", fr.T_odo_rover),
                ("T_true", fr.T_map_rover_true),
                ("keyframe", fr.keyframe),
                ("ndet", n),
            ):
                rows[k].append(v)
    with ArchiveSource(arch, OdometryConfig(source="record:odometry"), cfg.detector.pairs) as src:
        T_record = np.array([fr.T_odo_rover for fr in src])
    np.savez(
        out,
        **{k: np.array(v) for k, v in rows.items()},
        T_record=T_record,
        lander_xy=lander,
        det=np.concatenate(dets) if dets else np.zeros((0, 3)),
    )
    return out


def rock_ids(P: np.ndarray, rocks: np.ndarray) -> np.ndarray:
    """The rock (row of `rocks`: x, y, z, radius) within max(0.15 m, r) of each point, -1: none."""
    if len(P) == 0:
        return np.zeros(0, int)
    d = np.linalg.norm(rocks[None, :, :3] - P[:, None, :], axis=2)
    j = d.argmin(axis=1)
    return np.where(d[np.arange(len(P)), j] <= np.maximum(0.15, rocks[j, 3]), j, -1)


def _rocks(site: Path) -> np.ndarray:
    t = np.genfromtxt(site / "rocks.csv", delimiter=",", names=True)
    return np.column_stack([t["x"], t["y"], t["z"], t["radius"]])


def _reference_sightings(site: Path, rocks: np.ndarray) -> np.ndarray:
    """Per rock: the reference frames (ground-truth poses) that detected it."""
    from lunarloc.io.maps import load_traverse

    tr = load_traverse(site / "det_0_gt.csv")
    ids = rock_ids(tr.detections_xyz, rocks)
    count = np.zeros(len(rocks), int)
    for r in np.unique(ids[ids >= 0]):
        count[r] = len(np.unique(tr.detection_frame[ids == r]))
    return count


def _diagnosing_loop(truth: dict):
    """A LoopState that records, per attempt, what the window held against the truth."""
    from scipy.spatial import cKDTree

    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.online import loop as loop_module

    class DiagnosingLoop(loop_module.LoopState):
        rows: list

        def _attempt(self, k, frame, t):
            poses = self.graph.poses()
            win, P, _F, _I, _veh, _length = self.local_map(k, poses)
            seen: dict = {}
            localize = loop_module.localize

            def recording(ref, veh, cfg, **kw):
                res = localize(ref, veh, cfg, **kw)
                seen.update(ref=ref, veh=veh, res=res)
                return res

            loop_module.localize = recording
            try:
                att = super()._attempt(k, frame, t)
            finally:
                loop_module.localize = localize
            kfs = self.graph.keyframes
            path = np.array([kf.path_m for kf in kfs])
            row = {
                "frame": frame,
                "time_s": t,
                "window_m": round(float(path[k] - path[win[0]]), 2),
                "landmarks": att.landmarks,
                "reference": att.reference_landmarks,
                "inliers": att.inliers,
                "accepted": att.accepted,
                "fix_error_m": att.fix_error_m,
                "predicted_error_m": att.predicted_error_m,
                "reason": att.reason,
            }
            if "veh" in seen:
                ref, veh, res = seen["ref"], seen["veh"], seen["res"]
                G = [
                    transform(
                        truth["T_true"][truth["index"][kfs[j].frame]], kfs[j].detections_rover
                    )
                    for j in win
                    if len(kfs[j].detections_rover)
                ]
                G = np.concatenate(G) if G else np.zeros((0, 3))
                V = veh.positions_xyz
                _, near = cKDTree(V).query(P, distance_upper_bound=self.config.aggregation.radius_m)
                vid = np.array(
                    [
                        rock_ids(np.median(G[near == i], axis=0)[None], truth["rocks"])[0]
                        if np.any(near == i)
                        else -1
                        for i in range(len(V))
                    ]
                )
                rid = rock_ids(ref.positions_xyz, truth["rocks"])
                # each vehicle landmark where ground-truth poses place it, against the reference
                Vt = np.array(
                    [
                        np.median(G[near == i], axis=0) if np.any(near == i) else np.full(3, np.nan)
                        for i in range(len(V))
                    ]
                ).reshape(-1, 3)
                dref = (
                    np.linalg.norm(Vt[:, None, :] - truth["reference_xyz"][None], axis=2).min(
                        axis=1
                    )
                    if len(truth["reference_xyz"])
                    else np.full(len(V), np.inf)
                )
                T_true = truth["T_true"][truth["index"][frame]]
                would = float("nan")
                if np.all(np.isfinite(res.T_ref_veh)):
                    x, y, z, yaw = poses[k]
                    roll, pitch = kfs[k].roll_pitch_rad
                    T_fix = res.T_ref_veh @ pose_to_matrix(x, y, z, roll, pitch, yaw)
                    would = float(np.linalg.norm(T_fix[:3, 3] - T_true[:3, 3]))
                window_rocks = set(vid[vid >= 0].tolist())
                missing = window_rocks - truth["reference_rocks"]
                inl = res.inliers
                row.update(
                    {
                        "on_rock": len(window_rocks),
                        "in_reference": len(window_rocks & truth["reference_rocks"]),
                        "in_crop": len(window_rocks & set(rid[rid >= 0].tolist())),
                        "missing_reference_sightings": sorted(
                            int(truth["sightings"][r]) for r in missing
                        ),
                        "true_inliers": int(
                            np.sum((vid[inl[:, 0]] >= 0) & (vid[inl[:, 0]] == rid[inl[:, 1]]))
                        )
                        if len(inl)
                        else 0,
                        "required": res.required_inliers,
                        "associations": res.num_associations,
                        "overlap_0.1m": int(np.sum(dref <= 0.1)),
                        "failed_checks": [c.name for c in res.checks if not c.passed],
                        "would_be_error_m": would,
                        **_oracle_crop(self, ref, veh, Vt, truth["reference_xyz"]),
                        "odometry_error_m": float(
                            np.linalg.norm(
                                truth["T_odo"][truth["index"][frame]][:3, 3] - T_true[:3, 3]
                            )
                        ),
                    }
                )
            self.rows.append(row)
            return att

    return DiagnosingLoop


def _oracle_crop(
    state, ref, veh, Vt: np.ndarray, reference_xyz: np.ndarray, radii=(0.5, 1.0, 2.0)
) -> dict:
    """What the chance test would require if the reference were cropped to the landmarks within
    r (horizontal) of the window landmarks' TRUE positions (an oracle crop: the best any prior
    could do), for each r: {"required_at_crop_<r>m": [reference landmarks kept, inliers required]}."""
    from lunarloc.localization.chance import chance_clique_size

    cfg = state.window_localization().for_maps(ref, veh)
    out = {}
    ok = np.all(np.isfinite(Vt), axis=1)
    for r in radii:
        d = (
            np.linalg.norm(Vt[ok][:, None, :2] - reference_xyz[None, :, :2], axis=2).min(axis=0)
            if np.any(ok)
            else np.full(len(reference_xyz), np.inf)
        )
        n = int(np.sum(d <= r))
        m = len(veh) * n
        need = max(
            cfg.min_inliers,
            int(
                np.ceil(
                    chance_clique_size(m, cfg.mode, cfg.epsilon_m, cfg.epsilon_z_m)
                    + cfg.chance_margin
                )
            ),
        )
        out[f"required_at_crop_{r:g}m"] = [n, need]
    return out


def transform(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    return P @ T[:3, :3].T + T[:3, 3]


def replay(
    site: Path,
    min_sightings: int,
    odometry: str,
    loop_overrides: dict,
    diagnose: bool,
    localization_overrides: dict | None = None,
    cfg=None,
):
    from lunarloc.config.run import RunConfig, config_from_dict
    from lunarloc.online.loop import LoopState
    from lunarloc.perception.detector import on_lander
    from lunarloc.pipeline.reference import load_reference

    cfg = cfg or RunConfig()
    z = np.load(cache_vehicle(site, cfg))
    loop_cfg = config_from_dict(type(cfg.loop), {**cfg.loop.to_dict(), **loop_overrides}, "loop")
    ref = load_reference(site / f"map_0_gt_ms{min_sightings}.csv")
    if diagnose:
        rocks = _rocks(site)
        rid = rock_ids(ref.positions_xyz, rocks)
        cls = _diagnosing_loop(
            {
                "T_true": z["T_true"],
                "index": {int(f): i for i, f in enumerate(z["frames"])},
                "rocks": rocks,
                "reference_rocks": set(rid[rid >= 0].tolist()),
                "reference_xyz": ref.positions_xyz,
                "T_odo": z["T_visual"] if odometry == "visual" else z["T_record"],
                "sightings": _reference_sightings(site, rocks),
            }
        )
    else:
        cls = LoopState
    loc = dataclasses.replace(cfg.localization, **(localization_overrides or {}))
    state = cls(ref, loop_cfg, loc, odometry=odometry)  # the windows state this odometry's bounds
    state.rows = []
    T = z["T_visual"] if odometry == "visual" else z["T_record"]
    offset = 0
    t0 = time.process_time()
    for i in range(len(z["frames"])):
        d = None
        if z["ndet"][i] >= 0:
            d = z["det"][offset : offset + z["ndet"][i]]
            offset += z["ndet"][i]
            if len(z["lander_xy"]):
                d = d[~on_lander(d, T[i], z["lander_xy"])]
        state.step(
            int(z["frames"][i]),
            float(z["times"][i]),
            T[i],
            d,
            z["T_true"][i],
            keyframe=bool(z["keyframe"][i]),
        )
    res = state.finish(int(np.sum(z["keyframe"])))
    s = res.summary()
    fixes = [
        [round(a.fix_error_m, 4), round(a.predicted_error_m, 4), round(a.window_m, 1), a.time_s]
        for a in res.attempts
        if a.accepted
    ]
    return {
        "site": site.name,
        "min_sightings": min_sightings,
        "odometry": odometry,
        "loop": loop_overrides,
        "attempts": s["attempts"],
        "fixes": s["fixes"],
        "online_rmse_m": s["ate_online"]["rmse_m"],
        "corrected_rmse_m": s["ate_corrected"]["rmse_m"],
        "odometry_rmse_m": s["ate_odometry"]["rmse_m"],
        "accepted_fixes": fixes,
        "first_fix_s": fixes[0][3] if fixes else None,
        "cpu_s": round(time.process_time() - t0, 2),
        "per_attempt": state.rows,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("sites", type=Path, nargs="+")
    ap.add_argument(
        "--min-sightings",
        type=int,
        nargs="+",
        default=[5],
        help="reference map(s) map_0_gt_ms<M>.csv",
    )
    ap.add_argument(
        "--odometry", nargs="+", default=["visual"], choices=["visual", "record:odometry"]
    )
    ap.add_argument(
        "--loop",
        default="{}",
        help="LoopConfig overrides as JSON (on the configuration's loop section)",
    )
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="a run configuration file (default: RunConfig(), the image defaults)",
    )
    ap.add_argument(
        "--attempts", action="store_true", help="print and keep the per-attempt diagnosis"
    )
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    overrides = json.loads(a.loop)
    cfg = None
    if a.config is not None:
        from lunarloc.config.run import load_config_file

        cfg = load_config_file(a.config)[0]
    out = []
    for site in a.sites:
        for ms in a.min_sightings:
            for odo in a.odometry:
                r = replay(site, ms, odo, overrides, a.attempts, cfg=cfg)
                out.append(r)
                worst = max(r["accepted_fixes"], default=None)
                print(
                    f"{site.name} ms{ms} {odo:16s} fixes {r['fixes']}/{r['attempts']} online {100 * r['online_rmse_m']:.1f} cm"
                    f" corrected {100 * r['corrected_rmse_m']:.1f} odometry {100 * r['odometry_rmse_m']:.1f}"
                    f" first fix {r['first_fix_s']} s worst fix "
                    + (
                        "-"
                        if worst is None
                        else f"{100 * worst[0]:.1f} cm (predicted {100 * worst[1]:.1f})"
                    )
                )
                for row in r["per_attempt"]:
                    print(
                        "   ",
                        json.dumps(
                            {
                                k: (round(v, 3) if isinstance(v, float) else v)
                                for k, v in row.items()
                            }
                        ),
                    )
    if a.json:
        a.json.write_text(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
