"""The LAC map from what the rover sees: scores on simulated LAC-look sites with
three pose sources, the mapping cost per stereo pair, and memory over a long replay.

Usage
-----
    # 1. sites: 386 rocks, a survey traverse circling the lander, front stereo pair, 2 Hz
    python benchmarks/bench_lac_map.py simulate --out DIR --seeds 281 282 283 284 285 \
        [--lamps-only 284] [--duration 160] [--width 640]
    # 2. scores: run the online loop with a mapper, then place the same frames with the
    #    ground-truth, odometry and corrected poses and score each against the 16-ray truth
    python benchmarks/bench_lac_map.py score --out DIR --seeds 281 282 283 284 285 [--json OUT.json]
        [--figure-seed 281] [--dump] [--config RUN.json] [--mapper-config JSON]
    # 2b. re-score recorded runs (score --dump) with other mapper settings, nothing re-run:
    python benchmarks/bench_lac_map.py rescore --out DIR --seeds 281 282 \
        --mapper-config '{"rock_recentre_min_m": null}' '{}' [--json OUT.json]
    # 2b'. the per-cell rock model (LacMapperConfig.rock_cells="model") trained on recorded
    #      development runs (score --dump), leave-one-site-out scores first with --cv:
    python benchmarks/bench_lac_map.py train-rock-cells --out DEV --seeds 286 287 --cv \
        [--model-out src/lunarloc/mapping/lac_rock_cells.npz]
    # 2c. where the corrected poses lose points against ground truth (recorded runs, score --dump):
    #     one pose component at a time taken from the corrected poses
    python benchmarks/bench_lac_map.py decompose --out DIR --seeds 292 294
    # 2d. the detections' error along the viewing ray against the true rock centres, by stage,
    #     radius band, range and lighting (the detector with ground-truth poses; any archives
    #     rendered with custom/rocks.csv: these sites' traverse.lac, sim_heldout's)
    python benchmarks/bench_lac_map.py range-bias --archives DIR/seed_286/traverse.lac ... [--every 8]
    # 2e. SGBM's disparity error against the ray-cast truth per OpenCV mode (the height map's
    #     half-resolution match and the crop match's full-resolution parameters)
    python benchmarks/bench_lac_map.py disparity-bias --out DIR --seeds 286 288 [--frames 3]
    # 3. cost: detection vs mapping per stereo pair, CPU time (an archive at each resolution)
    python benchmarks/bench_lac_map.py cost --archive A.lac [--frames 40] [--small-rocks|--no-small-rocks]
    # 4. memory: the mapper fed for a long replay (the archive's frames cycled with their
    #    ground-truth poses, shifted around the site; the detector is not re-run)
    python benchmarks/bench_lac_map.py memory --archive A.lac --hours 2 --rate-hz 2
    # 5. the agent (examples/lac_agent.py) through the stand-in leaderboard, lac_map off and on:
    #    run_step CPU per tick, the map writing's share, cells written before finalize, scores
    python benchmarks/bench_lac_map.py agent --out DIR [--seed 302] [--duration 60] [--width 640]

Each site's truth is ``site_geometric_map(simulate_site(seed))`` (the LAC's 16-ray rule). "Seen"
cells are those the ground-truth-placed frames observed (the same set for all three pose
sources). Prints one line per site and source; writes the rows as JSON with ``--json``.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def _small_rocks(cfg, enabled: bool | None):
    """`cfg` with the detector's small-rock stage on or off (None: as `cfg` has it)."""
    if enabled is None:
        return cfg
    stage = replace(cfg.detector.small_rocks, enabled=enabled)
    return replace(cfg, detector=replace(cfg.detector, small_rocks=stage))


def simulate(a) -> None:
    from lunarloc.sim.render import RenderConfig, SiteRenderer
    from lunarloc.sim.rover import RoverConfig
    from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse

    for seed in a.seeds:
        light = "lamps" if seed in a.lamps_only else "sun+lamps"
        cfg = SimulationConfig(
            duration_s=a.duration,
            image_rate_hz=a.image_rate,
            width=a.width,
            height=a.width * 9 // 16,
            cameras=("FrontLeft", "FrontRight"),
            semantic=False,
            rover=RoverConfig(plan="survey"),
            render=RenderConfig(lighting=light),
        )
        d = a.out / f"seed_{seed}"
        d.mkdir(parents=True, exist_ok=True)
        site = simulate_site(seed, cfg.site)
        site.write_rocks_csv(d / "rocks.csv")
        (d / "lighting.txt").write_text(light + "\n")
        t0 = time.perf_counter()
        if not (d / "traverse.lac").is_file():
            simulate_traverse(
                site, d / "traverse.lac", 0, cfg, renderer=SiteRenderer(site, cfg.render)
            )
        print(f"seed {seed} ({light}): {time.perf_counter() - t0:.0f} s", flush=True)


def _scores(mapper, frames, T, truth, seen):
    from lunarloc.io.overhead import score_geometric_map
    from lunarloc.pipeline.runner import place_mapper

    place_mapper(mapper, frames, T)
    est = mapper.grid()
    all_ = score_geometric_map(est.array, truth)
    s_seen = score_geometric_map(est.array, truth, cells=est.observed if seen is None else seen)
    return est, all_, s_seen


#: what ``score --dump`` records of each detection (beyond what the mapper keeps)
DETECTION_FIELDS = (
    "x_rover",
    "y_rover",
    "z_rover",
    "radius_m",
    "depth_m",
    "area_px",
    "sigma_px",
    "height_m",
    "small_rock",
    "verifier_score",
    "tentative",
    "needs_confirmation",
    "ground_noise_m",
    "image_gradient",
)


class _record_detections:
    """While alive, every frame the runner adds to a mapper also has its detections'
    :data:`DETECTION_FIELDS` recorded in ``rows`` ({frame id: (M, F) float array})."""

    def __init__(self) -> None:
        from lunarloc.pipeline import runner

        self.rows: dict = {}
        self._runner = runner
        self._orig = orig = runner.add_to_mapper

        def add(mapper, frame_id, T_map_rover, fd, detector, images):
            rows = [
                [
                    *np.asarray(d.p_rover, float)[:3],
                    d.radius_m,
                    d.depth_m,
                    d.area_px,
                    d.sigma_px,
                    d.height_m,
                    float(d.small_rock),
                    d.verifier_score,
                    float(bool(d.tentative)),
                    float(d.needs_confirmation),
                    d.ground_noise_m,
                    d.image_gradient,
                ]
                for d in fd.detections
            ]
            arr = np.array(rows, float).reshape(-1, len(DETECTION_FIELDS))
            old = self.rows.get(frame_id)
            self.rows[frame_id] = arr if old is None else np.concatenate([old, arr])
            return orig(mapper, frame_id, T_map_rover, fd, detector, images)

        runner.add_to_mapper = add

    def stop(self) -> None:
        self._runner.add_to_mapper = self._orig


def score(a) -> None:
    from lunarloc.config.run import RunConfig
    from lunarloc.io.overhead import site_geometric_map
    from lunarloc.mapping.lac_map import LacMapper, LacMapperConfig
    from lunarloc.pipeline.reference import load_reference
    from lunarloc.pipeline.runner import run
    from lunarloc.pipeline.sources import ArchiveSource
    from lunarloc.sim.simulate import simulate_site

    mcfg = LacMapperConfig(**json.loads(a.mapper_config)) if a.mapper_config else LacMapperConfig()
    rows = []
    for seed in a.seeds:
        d = a.out / f"seed_{seed}"
        light = (d / "lighting.txt").read_text().strip() if (d / "lighting.txt").is_file() else "?"
        truth = site_geometric_map(simulate_site(seed))
        cfg = RunConfig()
        if a.config:  # a run configuration (e.g. the detector's verifier on)
            from lunarloc.config.run import load_config_file

            cfg = load_config_file(a.config)[0]
        cfg = _small_rocks(cfg, a.small_rocks)
        mapper = LacMapper(mcfg)
        detections = _record_detections() if a.dump else None
        t0 = time.perf_counter()
        res = run(
            ArchiveSource(d / "traverse.lac", cfg.odometry, cfg.detector.pairs),
            load_reference(d / "rocks.csv"),
            cfg,
            mapper=mapper,
        )
        wall = time.perf_counter() - t0
        if detections is not None:
            detections.stop()
        if a.dump:  # the mapper and the three pose sets, to re-score other mapper settings without re-running
            import pickle

            with open(d / "mapper_dump.pkl", "wb") as fh:
                pickle.dump(
                    {
                        "mapper": mapper,
                        "frames": res.frames,
                        "gt": res.T_map_rover_true,
                        "odometry": res.T_odo_rover,
                        "corrected": res.T_map_rover,
                        # per frame id: every detection's DETECTION_FIELDS (the mapper keeps
                        # only centre and radius), to study the rock map's errors
                        "detections": detections.rows,
                        "detection_fields": DETECTION_FIELDS,
                    },
                    fh,
                )
        summ = res.summary()
        n_img = max(res.num_image_frames, 1)
        extra = {
            "path_m": summ["path_length_m"],
            "image_frames": res.num_image_frames,
            "detection_ms_per_frame": round(1000 * res.timings_s.get("detection", 0) / n_img, 1),
            "lac_map_ms_per_frame": round(1000 * res.timings_s.get("lac_map", 0) / n_img, 2),
            "loop_wall_s": round(wall, 1),
            "mapper_mb": round(mapper.memory_bytes() / 1e6, 2),
        }
        poses = {
            "gt": res.T_map_rover_true,
            "odometry": res.T_odo_rover,
            "corrected": res.T_map_rover,
        }
        site_rows, out, seen = _site_rows(seed, light, mapper, res.frames, poses, truth, extra)
        rows += site_rows
        if a.figure_seed == seed:
            from lunarloc.viz import plot_lac_maps

            for name in ("gt", "corrected"):
                est = out[name][0]
                p = plot_lac_maps(
                    est.array,
                    truth,
                    a.out / f"lac_map_seed{seed}_{name}.png",
                    observed=seen,
                    title=f"site {seed} ({light}), {name} poses",
                )
                print(f"wrote {p}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    _summary(rows)


def _site_rows(seed, light, mapper, frames, poses, truth, extra=None):
    """Place `mapper`'s frames with each pose set of `poses` ({"gt", "odometry", "corrected"}:
    (F, 4, 4) per entry of `frames`) and score each against `truth`, over the whole map and
    over the cells the ground-truth-placed frames saw. Prints a line per pose set; returns the
    rows, {name: (estimate, whole-map score, seen score)} and the seen cells."""
    from lunarloc.core.metrics import ate

    est_gt, all_gt, seen_gt = _scores(mapper, frames, poses["gt"], truth, None)
    seen = est_gt.observed
    out = {"gt": (est_gt, all_gt, seen_gt)}
    for name in ("odometry", "corrected"):
        out[name] = _scores(mapper, frames, poses[name], truth, seen)
    T_true = np.asarray(poses["gt"])
    rows = []
    for name, (est, s_all, s_seen) in out.items():
        T_src = np.asarray(poses[name])
        dz = T_src[:, 2, 3] - T_true[:, 2, 3]  # the frames' height error (m)
        tp = round(s_seen["rock_recall"] * s_seen["rock_cells_true"])
        row = {
            "seed": seed,
            "lighting": light,
            "poses": name,
            "seen_cells": int(seen.sum()),
            "rock_cells_true_seen": s_seen["rock_cells_true"],
            "seen_geometric": round(s_seen["geometric"], 4),
            "seen_rock_precision": round(s_seen["rock_precision"], 4),
            "seen_rock_recall": round(s_seen["rock_recall"], 4),
            "seen_rock_f1": round(s_seen["rock_f1"], 4),
            # counts, for the pooled figures over all sites
            "seen_rock_tp": tp,
            "seen_rock_fp": s_seen["rock_cells_produced"] - tp,
            "seen_rock_fn": int(s_seen["rock_cells_true"]) - tp,
            "all_geometric": round(s_all["geometric"], 4),
            "all_rock_precision": round(s_all["rock_precision"], 4),
            "all_rock_recall": round(s_all["rock_recall"], 4),
            "all_rock_f1": round(s_all["rock_f1"], 4),
            "all_points_total": round(s_all["points"]["total"], 1),
            "seen_points_geo_rock": round(
                s_seen["points"]["geometric_map"] + s_seen["points"]["rocks_map"], 1
            ),
            "all_points_geo_rock": round(
                s_all["points"]["geometric_map"] + s_all["points"]["rocks_map"], 1
            ),
            "interp_within_1m_geometric": _interp_share(est, truth, 1.0),
            "rocks_mapped": int(len(est.rocks)),
            "ate_rmse_m": 0.0 if name == "gt" else ate(T_src[:, :3, 3], T_true[:, :3, 3])["rmse_m"],
            # the poses' height above the truth over the frames (median, p90 of |dz|)
            "dz_median_m": round(float(np.median(dz)), 4),
            "dz_abs_p90_m": round(float(np.percentile(np.abs(dz), 90)), 4),
            **(extra or {}),
        }
        rows.append(row)
        print(
            f"seed {seed} {light:9s} {name:9s}: seen {row['seen_cells']} cells: height {row['seen_geometric']:.3f}, "
            f"rock P {row['seen_rock_precision']:.2f} R {row['seen_rock_recall']:.2f} F1 {row['seen_rock_f1']:.3f} "
            f"({row['seen_points_geo_rock']:.0f} pts) | whole map: height {row['all_geometric']:.3f}, "
            f"F1 {row['all_rock_f1']:.3f} ({row['all_points_geo_rock']:.0f} pts) | ATE {row['ate_rmse_m']:.3f} m, "
            f"height {100 * row['dz_median_m']:+.2f} cm (median; |dz| p90 {100 * row['dz_abs_p90_m']:.1f} cm)",
            flush=True,
        )
    return rows, out, seen


def _load_dump(d: Path) -> dict:
    """A site's ``score --dump`` (our own benchmark's pickle), its mapper brought up to date:
    frozen detections from before the viewing directions (0) or the ranges (NaN)."""
    import pickle

    with open(d / "mapper_dump.pkl", "rb") as fh:
        dump = pickle.load(fh)
    m = dump["mapper"]
    fz = m._frozen_rocks
    if fz.shape[1] < 7:
        pad = [np.zeros((len(fz), 6 - fz.shape[1]))] if fz.shape[1] < 6 else []
        m._frozen_rocks = np.column_stack([fz, *pad, np.full(len(fz), np.nan)])
    return dump


def rescore(a) -> None:
    """Re-score recorded runs (``score --dump``'s ``mapper_dump.pkl`` per site) with mapper
    settings: the same frames, detections and three pose sets, placed again and scored; no
    detection or loop is re-run. Each ``--mapper-config`` (JSON of LacMapperConfig fields,
    ``{}`` the defaults) gives its own rows and summary."""

    from lunarloc.io.overhead import site_geometric_map
    from lunarloc.mapping.lac_map import LacMapperConfig
    from lunarloc.sim.simulate import simulate_site

    configs = a.mapper_config or ["{}"]
    rows = {c: [] for c in configs}
    for seed in a.seeds:
        d = a.out / f"seed_{seed}"
        light = (d / "lighting.txt").read_text().strip() if (d / "lighting.txt").is_file() else "?"
        dump = _load_dump(d)
        mapper = dump["mapper"]
        truth = site_geometric_map(simulate_site(seed))
        poses = {k: np.asarray(dump[k]) for k in ("gt", "odometry", "corrected")}
        for c in configs:
            mapper.config = LacMapperConfig(**json.loads(c))
            print(f"mapper config {c}")
            rows[c] += _site_rows(seed, light, mapper, dump["frames"], poses, truth)[0]
    for c in configs:
        print(f"== mapper config {c}")
        _summary(rows[c])
    if a.json:
        Path(a.json).write_text(
            json.dumps(rows if len(configs) > 1 else rows[configs[0]], indent=1)
        )


def _rock_cell_rows(mapper, frames, poses, truth):
    """Per pose set of `poses`: the per-cell rock model's candidate cells, features and labels
    (the truth's rock flag), the footprint rule's flags and the seen cells (ground truth)."""
    from lunarloc.pipeline.runner import place_mapper

    out, seen = {}, None
    for name, T in poses.items():
        place_mapper(mapper, frames, T)
        est = mapper.grid()
        if seen is None:
            seen = est.observed.reshape(-1)
        cells, X = mapper.rock_cell_features(est.array[:, :, 2], est.height_sigma_m, est.weight)
        out[name] = {
            "cells": cells,
            "X": X,
            "y": truth[:, :, 3].reshape(-1)[cells] > 0.5,
            "truth": truth[:, :, 3].reshape(-1) > 0.5,
            "footprint": est.array[:, :, 3].reshape(-1) > 0.5,
        }
    for v in out.values():
        v["seen"] = seen
    return out


def _export_trees(clf, path, features) -> None:
    """A fitted binary HistGradientBoostingClassifier as plain arrays (lac_map's
    rock_cell_probability evaluates them; no pickle)."""
    trees = [pred[0].nodes for pred in clf._predictors]
    m = max(len(t) for t in trees)
    arr = {
        k: np.zeros((len(trees), m), dt)
        for k, dt in (
            ("feature", np.int64),
            ("threshold", float),
            ("left", np.int64),
            ("right", np.int64),
            ("is_leaf", bool),
            ("value", float),
        )
    }
    for i, t in enumerate(trees):
        k = len(t)
        leaf = t["is_leaf"].astype(bool)
        arr["feature"][i, :k] = np.where(leaf, 0, t["feature_idx"])
        arr["threshold"][i, :k] = t["num_threshold"]
        arr["left"][i, :k] = t["left"]
        arr["right"][i, :k] = t["right"]
        arr["is_leaf"][i, :k] = leaf
        arr["is_leaf"][i, k:] = True
        arr["value"][i, :k] = t["value"]
    np.savez(
        path,
        baseline=float(np.ravel(clf._baseline_prediction)[0]),
        max_depth=max(int(t["depth"].max()) for t in trees),
        features=np.array(features),
        **arr,
    )


def train_rock_cells(a) -> None:
    """Train the per-cell rock model on recorded development runs (``score --dump``), both
    pose sets (ground truth and corrected) of every site; with ``--cv`` first score it
    leave-one-site-out (pooled rock F1 over the seen cells per threshold, against the
    footprint rule). Writes the model with ``--model-out``."""

    from sklearn.ensemble import HistGradientBoostingClassifier

    from lunarloc.io.overhead import site_geometric_map
    from lunarloc.mapping.lac_map import ROCK_CELL_FEATURES, LacMapperConfig
    from lunarloc.sim.simulate import simulate_site

    def fit(X, y):
        return HistGradientBoostingClassifier(
            max_depth=3, max_iter=150, learning_rate=0.05, random_state=0
        ).fit(X, y)

    data = {}
    for seed in a.seeds:
        dump = _load_dump(a.out / f"seed_{seed}")
        mapper = dump["mapper"]
        mapper.config = LacMapperConfig()
        truth = site_geometric_map(simulate_site(seed))
        poses = {k: np.asarray(dump[k]) for k in ("gt", "corrected")}
        data[seed] = _rock_cell_rows(mapper, dump["frames"], poses, truth)
        print(f"seed {seed}: {len(data[seed]['gt']['cells'])} candidate cells", flush=True)
    if a.cv:
        ths = np.round(np.arange(0.25, 0.61, 0.05), 2)
        for pose in ("gt", "corrected"):
            base, tot = np.zeros(3), {t: np.zeros(3) for t in ths}
            for seed in a.seeds:
                tr = [data[s][p] for s in a.seeds if s != seed for p in ("gt", "corrected")]
                clf = fit(
                    np.concatenate([v["X"] for v in tr]), np.concatenate([v["y"] for v in tr])
                )
                v = data[seed][pose]
                seen, y = v["seen"], v["truth"]
                P = np.zeros(len(seen))
                P[v["cells"]] = clf.predict_proba(v["X"])[:, 1]
                f = v["footprint"]
                base += [(seen & y & f).sum(), (seen & ~y & f).sum(), (seen & y & ~f).sum()]
                for t in ths:
                    f = P >= t
                    tot[t] += [(seen & y & f).sum(), (seen & ~y & f).sum(), (seen & y & ~f).sum()]

            def f1(v):
                return 2 * v[0] / max(2 * v[0] + v[1] + v[2], 1)

            print(
                f"{pose}: footprint rule pooled F1 {f1(base):.4f} ({base.astype(int)} right / "
                f"false / missed); model, leave one site out: "
                + ", ".join(f"{t:.2f}: {f1(tot[t]):.4f}" for t in ths),
                flush=True,
            )
    if a.model_out:
        allv = [data[s][p] for s in a.seeds for p in ("gt", "corrected")]
        clf = fit(np.concatenate([v["X"] for v in allv]), np.concatenate([v["y"] for v in allv]))
        _export_trees(clf, a.model_out, ROCK_CELL_FEATURES)
        print(f"wrote {a.model_out}")


def decompose(a) -> None:
    """Where the corrected poses lose (or gain) map points against the ground truth, from
    recorded runs (``score --dump``): the seen geo + rock points with the ground-truth poses
    taking one component of the corrected poses at a time (x and y, z, roll and pitch, yaw;
    then all), and the corrected poses' mean error in the rover frame (along / across track,
    moving frames) with their xy error's median and p90."""

    from lunarloc.core.geometry import matrix_to_pose, pose_to_matrix
    from lunarloc.io.overhead import score_geometric_map, site_geometric_map
    from lunarloc.pipeline.runner import place_mapper
    from lunarloc.sim.simulate import simulate_site

    parts = (("xy", [0, 1]), ("z", [2]), ("roll+pitch", [3, 4]), ("yaw", [5]), ("all", range(6)))
    for seed in a.seeds:
        dump = _load_dump(a.out / f"seed_{seed}")
        m, frames = dump["mapper"], np.asarray(dump["frames"])
        G, C = np.asarray(dump["gt"]), np.asarray(dump["corrected"])
        site = simulate_site(seed)
        truth = site_geometric_map(site)
        place_mapper(m, frames, G)
        seen = m.grid().observed

        def points(T):
            place_mapper(m, frames, T)
            sc = score_geometric_map(m.grid().array, truth, cells=seen)
            return sc["points"]["geometric_map"] + sc["points"]["rocks_map"], sc

        p_gt = points(G)[0]
        qg = np.array([matrix_to_pose(T) for T in G])
        qc = np.array([matrix_to_pose(T) for T in C])
        out = []
        for name, cols in parts:
            q = qg.copy()
            q[:, list(cols)] = qc[:, list(cols)]
            p, sc = points(np.array([pose_to_matrix(*x) for x in q]))
            out.append(
                f"{name} {p - p_gt:+.1f} (height {sc['geometric']:.4f}, F1 {sc['rock_f1']:.3f})"
            )
        index = {int(f): k for k, f in enumerate(frames.tolist())}
        k = np.array([index[int(f)] for f in m.frame_ids if int(f) in index])
        e = np.einsum("nji,nj->ni", G[k, :3, :3], C[k, :3, 3] - G[k, :3, 3])  # rover frame
        moving = np.r_[False, np.linalg.norm(np.diff(G[k, :2, 3], axis=0), axis=1) > 0.02]
        exy = np.linalg.norm(C[k, :2, 3] - G[k, :2, 3], axis=1)
        print(
            f"seed {seed}: ground-truth poses {p_gt:.1f} seen geo + rock points; with the "
            f"corrected poses' {'; '.join(out)} | corrected error (rover frame, mean over "
            f"moving frames): along {100 * e[moving, 0].mean():+.2f} cm, across "
            f"{100 * e[moving, 1].mean():+.2f} cm; xy median {100 * np.median(exy):.1f} cm, "
            f"p90 {100 * np.percentile(exy, 90):.1f} cm",
            flush=True,
        )
        # the detections of rocks under 10 cm radius placed with each pose set, matched to the
        # nearest true rock (within max(10 cm, half its radius)): the median error along the
        # viewing ray (rover to rock), by range from the rover
        from scipy.spatial import cKDTree

        R = site.rocks.table()[:, 1:]
        tree = cKDTree(R[:, :2])
        for name, T in (("ground-truth", G), ("corrected", C)):
            radial, rng = [], []
            for fid, fr in m._frames.items():
                if len(fr.rocks) == 0 or int(fid) not in index:
                    continue
                Tk = T[index[int(fid)]]
                p = fr.rocks[:, :3].astype(np.float64)
                P = p @ Tk[:3, :3].T + Tk[:3, 3]
                d, j = tree.query(P[:, :2])
                ok = (d < np.maximum(0.1, 0.5 * R[j, 3])) & (R[j, 3] < 0.1)
                u = (P[ok, :2] - Tk[:2, 3]) / np.linalg.norm(P[ok, :2] - Tk[:2, 3], axis=1)[:, None]
                radial.append(np.sum((P[ok, :2] - R[j[ok], :2]) * u, axis=1))
                rng.append(np.linalg.norm(p[ok, :2], axis=1))
            radial, rng = np.concatenate(radial), np.concatenate(rng)
            bands = ((0, 2), (2, 3), (3, 9))
            txt = ", ".join(
                f"{a}-{b} m {100 * np.median(radial[(rng >= a) & (rng < b)]):+.2f} cm"
                for a, b in bands
                if np.any((rng >= a) & (rng < b))
            )
            print(
                f"seed {seed}: rocks under 10 cm placed with the {name} poses, {len(radial)} "
                f"detections: error along the viewing ray (median) {100 * np.median(radial):+.2f} "
                f"cm; by range {txt}",
                flush=True,
            )
        # every detection placed with the ground-truth poses and matched to its rock (within
        # max(10 cm, its radius)): the shift along the rover's heading that would make a frame's
        # detections meet their rocks (the mean of rock - detection), averaged over the moving
        # image frames (what the landmark ties pull the corrected poses by), and the medians by
        # radius; the odometry's distance over the true one (steps of 10 image frames)
        moving_ids = {int(f) for f, mv in zip(m.frame_ids, moving) if mv and int(f) in index}
        shift, by_radius = [], []
        for fid, fr in m._frames.items():
            if len(fr.rocks) == 0 or int(fid) not in moving_ids:
                continue
            Tk = G[index[int(fid)]]
            P = fr.rocks[:, :3].astype(np.float64) @ Tk[:3, :3].T + Tk[:3, 3]
            d, j = tree.query(P[:, :2])
            ok = d < np.maximum(0.1, R[j, 3])
            if ok.any():
                along = (R[j[ok], :2] - P[ok, :2]) @ Tk[:2, 0]  # the heading: the rover's x
                shift.append(along.mean())
                by_radius.append(np.column_stack([R[j[ok], 3], along]))
        br = np.concatenate(by_radius) if by_radius else np.zeros((0, 2))
        txt = ", ".join(
            f"r {a:g}-{b:g} m {100 * np.median(br[(br[:, 0] >= a) & (br[:, 0] < b), 1]):+.2f} cm"
            for a, b in ((0, 0.1), (0.1, 0.2), (0.2, 9))
            if np.any((br[:, 0] >= a) & (br[:, 0] < b))
        )
        O = np.asarray(dump["odometry"])
        step = max(len(frames) // max(len(m.frame_ids), 1), 1) * 10
        dg = np.linalg.norm(np.diff(G[::step, :2, 3], axis=0), axis=1)
        do = np.linalg.norm(np.diff(O[::step, :2, 3], axis=0), axis=1)
        print(
            f"seed {seed}: detections placed with the ground-truth poses, {len(br)} in "
            f"{len(shift)} moving frames: shift along the heading to meet their rocks (rock - "
            f"detection) {100 * np.mean(shift) if shift else np.nan:+.2f} cm (mean over frames); "
            f"median by radius {txt} | odometry distance / true {do.sum() / max(dg.sum(), 1e-9):.4f}",
            flush=True,
        )


def range_bias(a) -> None:
    """The detections' error along the viewing ray against the true rock centres: the detector
    (the run configuration's, scaled to each archive's width) on every `--every`-th frame of each
    archive with its ground-truth rover pose; each detection matched to the nearest true rock
    (horizontally, within max(10 cm, its radius)); its error is the horizontal offset of its
    centre from the rock's along the camera-to-rock direction (positive: too far) and across it.
    Medians by stage (the small-rock stage or the height-map path), true radius band, range
    from the camera and lighting (the archive's lighting.txt, or "lamps" in its name)."""
    from lunarloc.config.run import RunConfig, load_config_file, scaled_detector_config
    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.camera import camera_from_archive
    from lunarloc.perception.detector import Detector, mounts_from_archive_row
    from lunarloc.pipeline.perception_eval import lander_xy

    cfg = load_config_file(a.config)[0] if a.config else RunConfig()
    rows = []
    for path in a.archives:
        lt = path.parent / "lighting.txt"
        light = (
            lt.read_text().strip()
            if lt.is_file()
            else ("lamps" if "lamps" in path.name else "sun+lamps")
        )
        with LacArchive(path) as ar:
            t = ar.custom("rocks")
            rocks = np.column_stack([t["x"], t["y"], t["z"], t["radius"]])
            cam = camera_from_archive(ar)
            det = Detector(scaled_detector_config(cam.width, base=cfg.detector), cam)
            lxy = lander_xy(ar)
            k = 0
            for rec in ar.iter_frames(semantic=False):
                if not any(c in rec.grayscale for c, _ in det.config.pairs):
                    continue
                k += 1
                if (k - 1) % a.every:
                    continue
                s = rec.state
                T = pose_to_matrix(s["x"], s["y"], s["z"], s["roll"], s["pitch"], s["yaw"])
                mounts = mounts_from_archive_row(rec.cameras, cam)
                fd = det.detect_frame(rec.grayscale, mounts, T, rec.frame, lander_xy=lxy)
                for pair in fd.pairs:
                    cam_xy = (T @ pair.T_rover_optical)[:2, 3]
                    for d in pair.detections:
                        dxy = np.linalg.norm(rocks[:, :2] - d.p_map[:2], axis=1)
                        j = int(np.argmin(dxy))
                        if dxy[j] > max(0.1, rocks[j, 3]):
                            continue
                        u = rocks[j, :2] - cam_xy
                        rng = float(np.linalg.norm(u))
                        u /= rng
                        e = d.p_map[:2] - rocks[j, :2]
                        rows.append(
                            (int(d.small_rock), rocks[j, 3], rng, float(e @ u),
                             float(e @ np.array([-u[1], u[0]])), light)
                        )  # fmt: skip
        print(f"{path}: {k} frames, {len(rows)} matched detections so far", flush=True)
    small = np.array([r[0] for r in rows], bool)
    rad, rng, along, across = (np.array([r[i] for r in rows], float) for i in (1, 2, 3, 4))
    light = np.array([r[5] for r in rows])

    def line(name, m):
        if np.count_nonzero(m) >= 5:
            q = 100 * np.percentile(along[m], [25, 50, 75])
            print(
                f"{name}: n {np.count_nonzero(m)}, along the ray median {q[1]:+.2f} cm "
                f"(quartiles {q[0]:+.2f} / {q[2]:+.2f}), across {100 * np.median(across[m]):+.2f} cm"
            )

    for stage, sm in (("small-rock stage", small), ("height-map path", ~small)):
        for lo, hi in ((0.0, 0.05), (0.05, 0.1), (0.1, 0.2), (0.2, 9.0), (0.0, 0.1)):
            for r0, r1 in ((0, 2), (2, 3), (3, 4), (4, 9), (0, 9)):
                m = sm & (rad >= lo) & (rad < hi) & (rng >= r0) & (rng < r1)
                line(f"{stage}, r {lo:g}-{hi:g} m, range {r0}-{r1} m", m)
        for lt in np.unique(light):
            line(f"{stage}, r < 0.1 m, {lt}", sm & (rad < 0.1) & (light == lt))


def disparity_bias(a) -> None:
    """SGBM's disparity error against the ray-cast truth, per OpenCV mode (stereo.SGBM_MODES),
    on `--frames` evenly spaced frames of each site's archive (DIR/seed_N/traverse.lac): the
    height map's half-resolution match (the detector's height_stereo, every setting but the
    mode as configured) and a full-resolution match with the parameters of the crop match
    (stereo.mask_disparity_fullres: block 5, P1 8 x 25, P2 32 x 25, no speckle filter) over
    the whole frame. Pixels are classed by the ray cast: ground, rock (the rock's mask eroded
    by 2 pixels at full resolution; wholly rock at half resolution); errors in full-resolution
    pixels (positive: too near), medians by the true depth; CPU time of the half-resolution
    match per frame."""
    import cv2

    from lunarloc.config.run import RunConfig, scaled_detector_config
    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.camera import camera_from_archive
    from lunarloc.perception.detector import Detector, mounts_from_archive_row
    from lunarloc.perception.stereo import first_ground_row, sgbm_mode_flag, to_gray_u8
    from lunarloc.sim.render import SEM_ROCK_OFFSET, SiteRenderer
    from lunarloc.sim.simulate import simulate_site

    bands = ((0, 2), (2, 3), (3, 4), (4, 6))
    acc: dict = {}
    cpu = dict.fromkeys(a.modes, 0.0)
    n_frames = 0
    for seed in a.seeds:
        rend = SiteRenderer(simulate_site(seed))
        with LacArchive(a.out / f"seed_{seed}" / "traverse.lac") as ar:
            cam = camera_from_archive(ar)
            det = Detector(scaled_detector_config(cam.width, base=RunConfig().detector), cam)
            hs = det.height_stereo
            k = hs.config.downscale
            fb = cam.fx * hs.baseline_m
            rays = cam.rays_optical().reshape(-1, 3)
            frs = [
                int(f) for f in ar.frame_numbers if ar.camera_row("FrontLeft", int(f)) is not None
            ]
            step = max(len(frs) // (a.frames + 1), 1)
            pick = set(frs[step::step][: a.frames])
            for rec in ar.iter_frames(semantic=False):
                if rec.frame not in pick:
                    continue
                n_frames += 1
                s = rec.state
                T = pose_to_matrix(s["x"], s["y"], s["z"], s["roll"], s["pitch"], s["yaw"])
                mounts = mounts_from_archive_row(rec.cameras, cam)
                T_left = T @ mounts["FrontLeft"].T_rover_optical
                t, lab = rend.cast_rays(
                    np.repeat(T_left[:3, 3][None], len(rays), 0), rays @ T_left[:3, :3].T
                )
                Z = (t * rays[:, 2]).reshape(cam.height, cam.width)
                lab = lab.reshape(cam.height, cam.width)
                with np.errstate(divide="ignore", invalid="ignore"):
                    d_true = fb / Z
                rock = lab >= SEM_ROCK_OFFSET
                rock_in = cv2.erode(rock.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
                L, R = (
                    to_gray_u8(rec.grayscale["FrontLeft"]),
                    to_gray_u8(rec.grayscale["FrontRight"]),
                )
                v0 = first_ground_row(L)
                hh, ww = cam.height // k, cam.width // k
                d_true_lr = d_true[: hh * k, : ww * k].reshape(hh, k, ww, k).mean(axis=(1, 3))
                lab_lr = lab[: hh * k, : ww * k].reshape(hh, k, ww, k)
                Z_lr = Z[: hh * k, : ww * k].reshape(hh, k, ww, k).mean(axis=(1, 3))
                for mode in a.modes:
                    flag = sgbm_mode_flag(mode)
                    create = cv2.StereoSGBM_create
                    hs._matchers.clear()
                    cv2.StereoSGBM_create = lambda *p, _f=flag, _c=create, **kw: _c(
                        *p, **{**kw, "mode": _f}
                    )
                    try:
                        t0 = time.process_time()
                        d_lr = hs.disparity_lowres(L, R, v_start=v0, sky_level=6) * k
                        cpu[mode] += time.process_time() - t0
                    finally:
                        cv2.StereoSGBM_create = create
                    hs._matchers.clear()
                    sg = cv2.StereoSGBM_create(
                        minDisparity=0, numDisparities=128 if cam.width > 1000 else 64, blockSize=5,
                        P1=8 * 25, P2=32 * 25, disp12MaxDiff=1, uniquenessRatio=10,
                        speckleWindowSize=0, mode=flag,
                    )  # fmt: skip
                    d_full = sg.compute(L, R).astype(np.float32) / 16.0
                    d_full[d_full <= 0] = np.nan
                    for res, err, depth, classes in (
                        ("full", d_full - d_true, Z, (("ground", lab == 1), ("rock", rock_in))),
                        ("half", d_lr - d_true_lr, Z_lr, (
                            ("ground", (lab_lr == 1).all(axis=(1, 3))),
                            ("rock", (lab_lr >= SEM_ROCK_OFFSET).all(axis=(1, 3))),
                        )),
                    ):  # fmt: skip
                        for cls, m in classes:
                            for b0, b1 in bands:
                                sel = m & np.isfinite(err) & (depth >= b0) & (depth < b1)
                                acc.setdefault((res, cls, b0, b1, mode), []).append(err[sel])
        print(f"seed {seed}: {len(pick)} frames", flush=True)
    for (res, cls, b0, b1, mode), v in sorted(acc.items()):
        v = np.concatenate(v)
        if v.size >= 20:
            print(
                f"{res} resolution, {cls}, depth {b0}-{b1} m, {mode}: n {v.size}, disparity error "
                f"median {np.median(v):+.3f} px, |error| > 1 px {np.mean(np.abs(v) > 1):.3f}"
            )
    for mode in a.modes:
        print(
            f"{mode}: half-resolution match {1000 * cpu[mode] / max(n_frames, 1):.1f} ms CPU a frame"
        )


def _interp_share(est, truth, within_m: float):
    sel = est.interpolated & (est.fill_distance_m <= within_m)
    if not sel.any():
        return None
    return round(float(np.mean(np.abs(est.array[:, :, 2][sel] - truth[:, :, 2][sel]) < 0.05)), 4)


def _summary(rows) -> None:
    """Per pose source: the mean over sites, the pooled figures (all sites' seen cells as one
    map) and, against the ground-truth poses, each site's gap in seen geo + rock points."""
    gt_pts = {x["seed"]: x["seen_points_geo_rock"] for x in rows if x["poses"] == "gt"}
    for name in ("gt", "odometry", "corrected"):
        r = [x for x in rows if x["poses"] == name]
        if not r:
            continue
        g = np.array([x["seen_geometric"] for x in r])
        f = np.array([x["seen_rock_f1"] for x in r])
        ga = np.array([x["all_geometric"] for x in r])
        fa = np.array([x["all_rock_f1"] for x in r])
        print(
            f"{name:9s}: seen height {g.mean():.3f} (min {g.min():.3f}), seen rock F1 {f.mean():.3f} (min {f.min():.3f}); "
            f"whole map height {ga.mean():.3f}, F1 {fa.mean():.3f} over {len(r)} sites"
        )
        tp, fp, fn = (sum(x[f"seen_rock_{k}"] for x in r) for k in ("tp", "fp", "fn"))
        cells = sum(x["seen_cells"] for x in r)
        seen_h = sum(x["seen_geometric"] * x["seen_cells"] for x in r) / max(cells, 1)
        gaps = [
            round(x["seen_points_geo_rock"] - gt_pts[x["seed"]], 1)
            for x in r
            if x["seed"] in gt_pts
        ]
        print(
            f"{'':9s}  pooled: seen height {seen_h:.3f}, rock P {tp / max(tp + fp, 1):.3f} "
            f"R {tp / max(tp + fn, 1):.3f} F1 {2 * tp / max(2 * tp + fp + fn, 1):.3f} "
            f"({tp} / {fp} / {fn} cells right / false / missed); "
            f"LAC points (whole map) mean {np.mean([x['all_points_total'] for x in r]):.0f}; "
            f"seen geo + rock points against ground-truth poses per site {gaps}"
        )


def cost(a) -> None:
    """Per stereo pair: detection (with the height map kept) vs the mapper's add_frame."""
    from lunarloc.config.run import RunConfig
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.mapping.lac_map import LacMapper
    from lunarloc.perception.camera import camera_from_archive, ipex_rig
    from lunarloc.perception.detector import Detector
    from lunarloc.pipeline.runner import add_to_mapper

    cfg = _small_rocks(RunConfig(), a.small_rocks)
    with LacArchive(a.archive) as ar:
        cam = camera_from_archive(ar)
        det = Detector(cfg.detector_for(cam.width), cam)
        mounts = ipex_rig(cam)
        frames = [int(f) for f in ar.frame_numbers if ar.camera_row("FrontLeft", int(f))][
            : a.frames
        ]
        images = [{c: ar.grayscale(c, f) for c in ("FrontLeft", "FrontRight")} for f in frames]
    m = LacMapper()
    t_det0, t_det, t_map = [], [], []
    clock = (
        time.process_time
    )  # CPU seconds of this process: robust to other jobs on a shared machine
    for k, im in enumerate(images):
        t0 = clock()
        det.detect_frame(im, mounts, None, k)
        t1 = clock()
        fd = det.detect_frame(im, mounts, None, k, keep_depth=True)
        t2 = clock()
        add_to_mapper(m, k, np.eye(4), fd, det, im)
        t3 = clock()
        if k >= 2:  # after warm-up
            t_det0.append(t1 - t0)
            t_det.append(t2 - t1)
            t_map.append(t3 - t2)
    m.grid()  # first call: imports
    t0 = clock()
    m.grid()
    t_grid = clock() - t0
    med = lambda v: 1000 * float(np.median(v))  # noqa: E731
    print(
        f"{a.archive} {cam.width}x{cam.height}, {len(t_map)} pairs, small-rock stage {'on' if cfg.detector.small_rocks.enabled else 'off'}, "
        f"CPU time (median): detection {med(t_det0):.1f} ms "
        f"(with the height map kept {med(t_det):.1f} ms), mapper add_frame {med(t_map):.2f} ms "
        f"({100 * med(t_map) / med(t_det0):.1f} % of detection); grid() of {len(m)} frames {1000 * t_grid:.0f} ms"
    )


def memory(a) -> None:
    """Feed the mapper for `hours` at `rate_hz` with the archive's frames cycled (ground-truth
    poses; each cycle shifted so the rover keeps covering the site)."""
    from lunarloc.config.run import RunConfig
    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.mapping.lac_map import LacMapper, LacMapperConfig
    from lunarloc.perception.camera import camera_from_archive, ipex_rig
    from lunarloc.perception.detector import Detector

    cfg = RunConfig()
    with LacArchive(a.archive) as ar:
        cam = camera_from_archive(ar)
        det = Detector(cfg.detector_for(cam.width), cam)
        mounts = ipex_rig(cam)
        fr = ar.frames
        frames = [int(f) for f in ar.frame_numbers if ar.camera_row("FrontLeft", int(f))][
            : a.frames
        ]
        cached = []
        for f in frames:
            im = {c: ar.grayscale(c, f) for c in ("FrontLeft", "FrontRight")}
            fd = det.detect_frame(im, mounts, None, f, keep_depth=True)
            pts = np.concatenate(
                [p.height.points_rover.reshape(-1, 3) for p in fd.pairs if p.height is not None]
            )
            rocks = np.array([[*d.p_rover, d.radius_m] for d in fd.detections]).reshape(-1, 4)
            i = int(np.flatnonzero(np.asarray(fr["frame"]) == f)[0])
            T = pose_to_matrix(
                fr["x"][i], fr["y"][i], fr["z"][i], fr["roll"][i], fr["pitch"][i], fr["yaw"][i]
            )
            cached.append((T, pts, rocks))
    m = LacMapper(LacMapperConfig(**json.loads(a.mapper_config)) if a.mapper_config else None)
    n_total = int(a.hours * 3600 * a.rate_hz)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    marks = {int(n_total * q) for q in (0.1, 0.25, 0.5, 0.75, 1.0)}
    for k in range(n_total):
        T, pts, rocks = cached[k % len(cached)]
        cyc = k // len(cached)
        S = pose_to_matrix(((cyc * 1.3) % 6) - 3, ((cyc * 0.7) % 6) - 3, 0, 0, 0, 0.3 * cyc)
        m.add_frame(k, S @ T, pts, rocks)
        if k + 1 in marks:
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            print(
                f"{k + 1} frames ({(k + 1) / a.rate_hz / 3600:.2f} h): mapper holds {m.memory_bytes() / 1e6:.1f} MB "
                f"({len(m)} re-placeable frames, {m.frozen_frames} frozen), process max RSS {rss:.0f} MB "
                f"(+{rss - rss0:.0f} MB), {time.perf_counter() - t0:.0f} s",
                flush=True,
            )
    t1 = time.perf_counter()
    m.grid()
    print(f"grid() after {n_total} frames: {1000 * (time.perf_counter() - t1):.0f} ms")


def agent(a) -> None:
    """examples/lac_agent.py through the stand-in leaderboard (tests/standins), closed loop,
    with and without ``lac_map``: run_step CPU per tick, the map writing's share, the cells
    written before finalize, and the final map's LAC scores."""
    root = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "tests" / "standins"))
    import lunarsim

    agent_file = root / "examples" / "lac_agent.py"
    for lac_map in (False, True):
        world, conf = lunarsim.prepare_site(
            a.out / f"agent_{a.seed}_{'map' if lac_map else 'nomap'}",
            a.seed,
            width=a.width,
            height=a.width * 9 // 16,
            rocks=a.rocks,
            output="",
            lac_map=lac_map,
            lac_map_cells_per_tick=a.cells_per_tick,
        )
        filled = []

        def observe(ag, filled=filled):
            gm = ag.get_geometric_map()
            if gm is not None and len(filled) % 20 == 0:
                filled.append(int(np.isfinite(gm.get_map_array()[:, :, 2]).sum()))
            else:
                filled.append(filled[-1] if filled else 0)

        run = lunarsim.run_agent(
            agent_file, conf, world, a.duration, evaluation=True, score=True, observe=observe
        )
        cpu = 1000 * np.array(run.run_step_cpu_s)
        ag = run.agent
        w = 1000 * np.array(ag.map_write_cpu_s) if lac_map else np.zeros(1)
        sc = run.scores or {}
        print(
            f"seed {a.seed} {a.width}px lac_map={lac_map}: {run.ticks} ticks, run_step CPU median {np.median(cpu):.1f} ms, "
            f"p95 {np.percentile(cpu, 95):.1f}, max {cpu.max():.0f}; map writing per tick: median {np.median(w):.2f} ms, "
            f"p99 {np.percentile(w, 99):.2f}, max {w.max():.1f} ms; cells in the map before finalize {filled[-1]}; "
            f"finalize's whole-map write {1000 * (ag.map_finish_cpu_s or 0):.0f} ms CPU; scores {sc}",
            flush=True,
        )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("simulate")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--seeds", type=int, nargs="+", required=True)
    s.add_argument("--lamps-only", type=int, nargs="*", default=[284])
    s.add_argument("--duration", type=float, default=160.0)
    s.add_argument("--image-rate", type=float, default=2.0)
    s.add_argument("--width", type=int, default=640)
    s = sub.add_parser("score")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--seeds", type=int, nargs="+", required=True)
    s.add_argument("--json", default=None)
    s.add_argument("--figure-seed", type=int, default=None)
    s.add_argument("--mapper-config", default=None, help="JSON of LacMapperConfig fields")
    s.add_argument(
        "--config", default=None, help="a run configuration file (JSON; RunConfig sections)"
    )
    s.add_argument(
        "--dump", action="store_true", help="pickle the mapper and poses into each site's folder"
    )
    s.add_argument(
        "--small-rocks",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the detector's small-rock stage on / off (unset: the configuration's value, on by "
        "default: the map's rocks under 5 cm)",
    )
    s = sub.add_parser("rescore")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--seeds", type=int, nargs="+", required=True)
    s.add_argument("--json", default=None)
    s.add_argument(
        "--mapper-config",
        nargs="*",
        default=None,
        help="JSON of LacMapperConfig fields, one set per argument ({} the defaults)",
    )
    s = sub.add_parser("train-rock-cells")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--seeds", type=int, nargs="+", required=True)
    s.add_argument("--cv", action="store_true", help="leave-one-site-out scores first")
    s.add_argument("--model-out", type=Path, default=None)
    s = sub.add_parser("decompose")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--seeds", type=int, nargs="+", required=True)
    s = sub.add_parser("range-bias")
    s.add_argument("--archives", type=Path, nargs="+", required=True)
    s.add_argument("--every", type=int, default=1, help="every n-th frame with images")
    s.add_argument(
        "--config", default=None, help="a run configuration file (JSON; RunConfig sections)"
    )
    s = sub.add_parser("disparity-bias")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--seeds", type=int, nargs="+", required=True)
    s.add_argument("--frames", type=int, default=3, help="frames per site")
    s.add_argument("--modes", nargs="+", default=["3way", "hh4", "hh", "sgbm"])
    s = sub.add_parser("cost")
    s.add_argument("--archive", type=Path, required=True)
    s.add_argument("--frames", type=int, default=30)
    s.add_argument(
        "--small-rocks",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the detector's small-rock stage on / off (unset: the default configuration's, on)",
    )
    s = sub.add_parser("memory")
    s.add_argument("--archive", type=Path, required=True)
    s.add_argument("--frames", type=int, default=60)
    s.add_argument("--hours", type=float, default=2.0)
    s.add_argument("--rate-hz", type=float, default=2.0)
    s.add_argument("--mapper-config", default=None)
    s = sub.add_parser("agent")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--seed", type=int, default=302)
    s.add_argument("--rocks", type=int, default=386)
    s.add_argument("--duration", type=float, default=60.0)
    s.add_argument("--width", type=int, default=640)
    s.add_argument("--cells-per-tick", type=int, default=400)
    a = ap.parse_args()
    {
        "simulate": simulate,
        "score": score,
        "rescore": rescore,
        "decompose": decompose,
        "train-rock-cells": train_rock_cells,
        "range-bias": range_bias,
        "disparity-bias": disparity_bias,
        "cost": cost,
        "memory": memory,
        "agent": agent,
    }[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
