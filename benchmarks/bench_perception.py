"""Benchmark of the perception front end on simulated traverses (ground truth known).

Usage
-----
    python benchmarks/bench_perception.py ARCHIVE.lac [ARCHIVE.lac ...] [--every N]
        [--segmenter classical|fastsam --weights PATH] [--no-centre-correction]
        [--centre-method METHOD] [--config RUN_CONFIG.json] [--breakdown] [--json OUT.json]
    python benchmarks/bench_perception.py --simulate SEED [SEED ...] [--lighting sun|lamps|sun+lamps]
        [--sun-elevation DEG] [--duration S] [--width W --height H] ...   # renders first (front pair)
    python benchmarks/bench_perception.py --lac-real DIR [--figure PNG]  # the real LAC frame
    python benchmarks/bench_perception.py --speed ARCHIVE.lac             # time one front pair
    python benchmarks/bench_perception.py ARCHIVE.lac ... --misses MISSES.csv  # where each miss is lost, rocks missed most
    python benchmarks/bench_perception.py --pool RUN1.json RUN2.json ...  # pool earlier runs' sites, with intervals
    python benchmarks/bench_perception.py --real-labels [DIR] [--misses M.csv]  # the labelled real LAC pairs

Archives must come from `lunarloc simulate` (they hold ``custom/rocks.csv`` and the
semantic images). The image size and field of view are read from each archive
(``initial.toml``); the detector's pixel-sized parameters, tuned at 1280x720, are
scaled to the archive's width (``lunarloc.config.run.scaled_detector_config``).
Detections use the ground-truth rover pose, so the errors measured are those of
perception alone.

Metrics
-------
* A ground-truth rock is *visible* in a left image when it covers at least
  ``--min-gt-px`` pixels there and none of them is within 2 px of the border (the
  method rejects masks cut by the border by design). Its range is the distance from
  the camera to its centre.
* A detection matches a rock when its 3D centroid is within max(0.15 m, rock radius)
  of the rock's centre; matching is one-to-one per frame, greedy by distance; a
  detection may match any rock (visible or not, e.g. one occluded at the border).
* Recall by size band (true radius) and range band, over visible rocks; precision by
  estimated-radius band and range band (detection depth), over detections.
* Centroid error of matched detections: 3D and horizontal (median, p90), for the
  visible-surface centroid and the centre-corrected one.
* 90 % intervals of the targets' figures (precision within 5 m, the two recalls, the
  median centre error), per lighting, by a bootstrap over sites (`site_bootstrap`): a
  rock is seen in several frames and terrain fools the detector frame after frame, so
  the sites, not the sightings, are the independent draws. With four sites an interval
  is often 0.1 wide; pool more sites to judge a target.
* Time per frame per stage (segment, filter, stereo), both left images of a frame.
  With the classical segmenter "stereo" is the half-resolution SGBM + ground height
  map that segmentation itself uses, so images/s counts all three stages.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lunarloc.core.geometry import transform_points
from lunarloc.perception.camera import STEREO_PAIRS
from lunarloc.perception.detector import CentreEstimator, CentreMethod, Detector, DetectorConfig, detect_archive

SIZE_BANDS = [(0.0, 0.1), (0.1, 0.2), (0.2, 0.4), (0.4, 10.0)]
RANGE_BANDS = [(0.0, 2.5), (2.5, 5.0), (5.0, 8.0)]


def _band(x: float, bands) -> int:
    for i, (lo, hi) in enumerate(bands):
        if lo <= x < hi:
            return i
    return -1


def _rock_ids(sem: np.ndarray) -> np.ndarray:
    from lunarloc.sim.render import semantic_to_rock_id

    return semantic_to_rock_id(sem)


def match(det_xyz: np.ndarray, rock_xyz: np.ndarray, rock_r: np.ndarray, min_tol: float = 0.15):
    """Greedy one-to-one matching. Returns list of (det index, rock index, distance)."""
    if len(det_xyz) == 0 or len(rock_xyz) == 0:
        return []
    d = np.linalg.norm(det_xyz[:, None, :] - rock_xyz[None, :, :], axis=2)
    tol = np.maximum(min_tol, rock_r)[None, :]
    pairs = np.argwhere(d <= tol)
    order = np.argsort(d[pairs[:, 0], pairs[:, 1]])
    used_d, used_r, out = set(), set(), []
    for k in order:
        i, j = pairs[k]
        if i in used_d or j in used_r:
            continue
        used_d.add(i)
        used_r.add(j)
        out.append((int(i), int(j), float(d[i, j])))
    return out


FP_CAUSES = ("terrain", "lander", "rock-duplicate", "rock-part", "small-rock-offcentre", "rock-offcentre")


def fp_cause(d, semantic: np.ndarray, id_to_idx: dict, centres: np.ndarray, radii: np.ndarray, matched_rock: dict) -> str:
    """Why an unmatched detection is false, from the semantic label that dominates a
    7x7 window at its image centroid: terrain (no rock there: a ridge, a crater rim, a
    stereo error), lander, or a rock that is already matched by another detection
    (duplicate), much larger than the detection (a part of it: a knob, a split mask),
    or whose centre is beyond the match tolerance (off-centre; 'small' when its radius
    is under 0.1 m, below the target band)."""
    from lunarloc.sim.render import semantic_lander_mask

    u, v = int(round(d.uv[0])), int(round(d.uv[1]))
    win = np.asarray(semantic)[max(v - 3, 0) : v + 4, max(u - 3, 0) : u + 4]
    rid = _rock_ids(win)
    if np.count_nonzero(rid >= 0) * 2 < rid.size:
        return "lander" if np.count_nonzero(semantic_lander_mask(win)) * 2 >= win.size else "terrain"
    j = id_to_idx.get(int(np.bincount(rid[rid >= 0]).argmax()))
    if j is None:
        return "terrain"
    if j in matched_rock:
        return "rock-duplicate"
    if radii[j] > 2.0 * max(d.radius_m, 0.02) and radii[j] >= 0.2:
        return "rock-part"
    return "small-rock-offcentre" if radii[j] < 0.1 else "rock-offcentre"


MISS_FIELDS = ("archive", "frame", "camera", "rock_id", "radius_m", "range_m", "stage", "tentative_rules", "overlap",
               "mask_eig_ratio", "mask_depth_m", "valid_fraction", "max_height_m")


def miss_stage(pair, rock_px: np.ndarray) -> dict:
    """Where a missed rock was lost in one pair (`rock_px`: its pixels in the left image).
    The mask overlapping most of the rock is followed through the filters: its reject
    reason (``elongated``, ``tentative`` with the rules that made it one in
    ``tentative_rules``, ``unconfirmed``, ``not_a_rock``, ...) or ``kept``
    (kept, but its centre lies beyond the match tolerance: it joined another body or saw
    only part of the rock). With no overlapping mask the stage is ``no-blob``, with the
    share of the rock's low-resolution pixels that have a height and the highest of those
    heights above the fitted ground (``pair.height`` needed: ``detect_archive(...,
    keep_depth=True)``)."""
    best, overlap = None, 0
    for k, m in enumerate(pair.masks):
        h, w = m.crop.shape
        o = int(np.count_nonzero(rock_px[m.v0 : m.v0 + h, m.u0 : m.u0 + w] & m.crop))
        if o > overlap:
            best, overlap = k, o
    n = max(int(np.count_nonzero(rock_px)), 1)
    out = dict(stage="no-blob", tentative_rules="", overlap=overlap / n, mask_eig_ratio=float("nan"), mask_depth_m=float("nan"),
               valid_fraction=float("nan"), max_height_m=float("nan"))
    if best is not None:
        rec = next((r for r in pair.records if r.mask_index == best), None)
        out["stage"] = "kept" if rec is None or rec.reason is None else rec.reason.value
        if rec is not None:
            out["mask_eig_ratio"], out["mask_depth_m"] = float(rec.stats.eig_ratio), float(rec.depth_m)
            out["tentative_rules"] = rec.tentative  # why a dropped tentative was tentative
        return out
    hm = pair.height
    if hm is not None:
        vv, uu = np.nonzero(rock_px)
        lv, lu = vv // hm.scale, uu // hm.scale
        ok = (lv < hm.height.shape[0]) & (lu < hm.height.shape[1])
        hh = hm.height[lv[ok], lu[ok]]
        good = np.isfinite(hh)
        out["valid_fraction"] = float(good.mean()) if hh.size else 0.0
        out["max_height_m"] = float(hh[good].max()) if good.any() else float("nan")
    return out


class Accumulator:
    def __init__(self) -> None:
        self.rec = np.zeros((len(SIZE_BANDS), len(RANGE_BANDS), 2), int)  # [hit, total]
        self.prec = np.zeros((len(SIZE_BANDS), len(RANGE_BANDS), 2), int)  # [tp, total]
        self.err3d: list[float] = []
        self.err_xy: list[float] = []
        self.err3d_surface: list[float] = []
        self.err_target: list[float] = []  # r >= 0.1, range <= 5
        # per target match (r >= 0.1, range <= 5): the error's parts, for --breakdown
        self.target_rows: list[tuple] = []
        self.small_near = np.zeros(2, int)  # [hit, visible]: 0.05 <= r < 0.1 within 3 m
        self.tiny_near = np.zeros(2, int)  # [hit, visible]: 0.025 <= r < 0.05 within 3 m
        self.times: dict[str, list[float]] = {}
        # false positives within 5 m by what lies under the detection's image centroid
        self.fp_causes: dict[str, int] = {k: 0 for k in FP_CAUSES}
        self.n_frames = 0
        self.n_det = 0
        # rows of MISS_FIELDS for each missed target sighting (r >= 0.1 m within 5 m) when a
        # list is given (--misses); needs the frames' height maps (keep_depth)
        self.misses: list[dict] | None = None
        self.archive = ""
        # per site (`site_key`): the counts behind the targets, for the bootstrap intervals
        self.by_site: dict[str, dict] = {}
        self._mark: tuple | None = None

    def begin_archive(self, name: str) -> None:
        """Start counting an archive; `end_archive` adds its share to its site's counts."""
        self.archive = name
        self._mark = (self.rec.copy(), self.prec.copy(), self.small_near.copy(), len(self.err_target))

    def end_archive(self) -> None:
        rec, prec, small, n_err = self._mark
        site = self.by_site.setdefault(site_key(self.archive), {
            "target": np.zeros(2, int), "precision": np.zeros(2, int), "small": np.zeros(2, int), "err": []})
        site["target"] += (self.rec - rec)[1:, :2].sum(axis=(0, 1))
        site["precision"] += (self.prec - prec)[:, :2].sum(axis=(0, 1))
        site["small"] += self.small_near - small
        site["err"].extend(self.err_target[n_err:])
        self._mark = None

    def merge(self, other: "Accumulator") -> None:
        """Add another accumulator's counts (the total over lightings)."""
        self.rec += other.rec
        self.prec += other.prec
        self.small_near += other.small_near
        self.tiny_near += other.tiny_near
        for k, v in other.fp_causes.items():
            self.fp_causes[k] += v
        for k in ("err3d", "err_xy", "err3d_surface", "err_target", "target_rows"):
            getattr(self, k).extend(getattr(other, k))
        for k, v in other.times.items():
            self.times.setdefault(k, []).extend(v)
        self.n_frames += other.n_frames
        self.n_det += other.n_det
        for key, c in other.by_site.items():
            site = self.by_site.setdefault(key, {
                "target": np.zeros(2, int), "precision": np.zeros(2, int), "small": np.zeros(2, int), "err": []})
            for k in ("target", "precision", "small"):
                site[k] += c[k]
            site["err"].extend(c["err"])

    def add_frame(self, fd, semantics: dict, rocks: np.ndarray, detector: Detector, mounts) -> None:
        self.n_frames += 1
        for k, v in fd.timings.items():
            self.times.setdefault(k, []).append(v)
        T_map_rover = fd.T_map_rover
        ids, centres, radii = rocks[:, 0].astype(int), rocks[:, 1:4], rocks[:, 4]
        id_to_idx = {int(i): k for k, i in enumerate(ids)}
        dets = fd.detections
        self.n_det += len(dets)
        det_xyz = np.array([d.p_map for d in dets]).reshape(-1, 3)
        m = match(det_xyz, centres, radii)
        matched_rock = {j: (i, dist) for i, j, dist in m}
        matched_det = {i: j for i, j, _ in m}
        # recall over visible rocks of every left camera
        for pair in fd.pairs:
            sem = semantics.get(pair.camera)
            if sem is None:
                continue
            rid = _rock_ids(sem)
            H, W = rid.shape
            inner = np.zeros_like(rid, bool)
            inner[2 : H - 2, 2 : W - 2] = True
            vis_ids, counts = np.unique(rid[rid >= 0], return_counts=True)
            edge_ids = set(np.unique(rid[(rid >= 0) & ~inner]).tolist())
            cam_pos = (T_map_rover @ mounts[pair.camera].T_rover_optical)[:3, 3]
            for r, c in zip(vis_ids.tolist(), counts.tolist()):
                if c < self.min_gt_px or r in edge_ids or r not in id_to_idx:
                    continue
                j = id_to_idx[r]
                rng = float(np.linalg.norm(centres[j] - cam_pos))
                sb, rb = _band(radii[j], SIZE_BANDS), _band(rng, RANGE_BANDS)
                if sb < 0 or rb < 0:
                    continue
                self.rec[sb, rb, 1] += 1
                small_near = 0.05 <= radii[j] < 0.1 and rng <= 3.0
                self.small_near += [int(small_near and j in matched_rock), int(small_near)]
                tiny_near = 0.025 <= radii[j] < 0.05 and rng <= 3.0
                self.tiny_near += [int(tiny_near and j in matched_rock), int(tiny_near)]
                if j not in matched_rock and self.misses is not None and radii[j] >= 0.1 and rng <= 5.0:
                    self.misses.append(dict(archive=self.archive, frame=fd.frame, camera=pair.camera, rock_id=r,
                                            radius_m=float(radii[j]), range_m=rng, **miss_stage(pair, rid == r)))
                if j in matched_rock:
                    self.rec[sb, rb, 0] += 1
                    i, dist = matched_rock[j]
                    self.err3d.append(dist)
                    self.err_xy.append(float(np.linalg.norm(det_xyz[i, :2] - centres[j, :2])))
                    if radii[j] >= 0.1 and rng <= 5.0:
                        self.err_target.append(dist)
                        self.target_rows.append(
                            centre_error_parts(det_xyz[i], centres[j], radii[j], rng, cam_pos, dets[i].radius_m,
                                               detector.config)
                        )
        for i, d in enumerate(dets):
            if i not in matched_det and d.depth_m < 5.0 and semantics.get(d.camera) is not None:
                self.fp_causes[fp_cause(d, semantics[d.camera], id_to_idx, centres, radii, matched_rock)] += 1
            sb, rb = _band(d.radius_m, SIZE_BANDS), _band(d.depth_m, RANGE_BANDS)
            if sb < 0 or rb < 0:
                continue
            self.prec[sb, rb, 1] += 1
            if i in matched_det:
                self.prec[sb, rb, 0] += 1
            # surface (uncorrected) centroid error, for comparison
            if i in matched_det and detector.config.centre_correction:
                p = d.p_optical - d.p_optical / np.linalg.norm(d.p_optical) * d.radius_m
                pm = transform_points(T_map_rover @ mounts[d.camera].T_rover_optical, p[None])[0]
                self.err3d_surface.append(float(np.linalg.norm(pm - centres[matched_det[i]])))

    min_gt_px = 50

    def summary(self) -> dict:
        def pct(a, q):
            return float(np.percentile(a, q)) if len(a) else float("nan")

        rec_t = self.rec[1:, :2].sum(axis=(0, 1))
        prec_t = self.prec[1:, :2].sum(axis=(0, 1))
        # precision over all detections within 5 m (any estimated size)
        prec_5 = self.prec[:, :2].sum(axis=(0, 1))
        return {
            "frames": self.n_frames,
            "detections": self.n_det,
            "target_recall_r>=0.1_range<=5": float(rec_t[0] / max(rec_t[1], 1)),
            "target_recall_counts": rec_t.tolist(),
            "target_precision_est_r>=0.1_range<=5": float(prec_t[0] / max(prec_t[1], 1)),
            "recall_0.05<=r<0.1_range<=3": float(self.small_near[0] / max(self.small_near[1], 1)),
            "recall_0.05<=r<0.1_range<=3_counts": self.small_near.tolist(),
            "recall_0.025<=r<0.05_range<=3": float(self.tiny_near[0] / max(self.tiny_near[1], 1)),
            "recall_0.025<=r<0.05_range<=3_counts": self.tiny_near.tolist(),
            "frames_per_s": float(1.0 / max(sum(float(np.mean(v)) for k, v in self.times.items() if k != "cpu"), 1e-9)),
            # process CPU time per frame (all threads), when the detector reports it
            "cpu_ms_per_frame": float(1000.0 * np.mean(self.times["cpu"])) if "cpu" in self.times else float("nan"),
            "precision_range<=5": float(prec_5[0] / max(prec_5[1], 1)),
            "precision_counts_range<=5": prec_5.tolist(),
            "centroid_err_target_median_m": pct(self.err_target, 50),
            "centroid_err_target_p90_m": pct(self.err_target, 90),
            "centroid_err3d_median_m": pct(self.err3d, 50),
            "centroid_err3d_p90_m": pct(self.err3d, 90),
            # horizontal error of the same matches (what localization mostly uses)
            "centroid_err_target_xy_median_m": pct([r[3] for r in self.target_rows], 50),
            "centroid_err_target_xy_p90_m": pct([r[3] for r in self.target_rows], 90),
            "centroid_err_xy_median_m": pct(self.err_xy, 50),
            "centroid_err_xy_p90_m": pct(self.err_xy, 90),
            "surface_centroid_err3d_median_m": pct(self.err3d_surface, 50),
            "surface_centroid_err3d_p90_m": pct(self.err3d_surface, 90),
            "recall_by_size_range": self.rec.tolist(),
            "precision_by_estsize_range": self.prec.tolist(),
            "false_positives_within_5m_by_cause": dict(self.fp_causes),
            "centre_breakdown": centre_breakdown(self.target_rows),
            "sites": len(self.by_site),
            "site_bootstrap_ci90": site_bootstrap(self.by_site),
            # the counts behind the targets per site, so that runs can be pooled (--pool)
            "by_site": {k: {n: (v.tolist() if isinstance(v, np.ndarray) else list(v)) for n, v in c.items()}
                        for k, c in self.by_site.items()},
            "time_per_frame_s": {k: float(np.mean(v)) for k, v in self.times.items()},
            # left images per second through segmentation + filtering, counting the
            # low-resolution stereo height map ("stereo") that the classical segmenter
            # needs; two left images per frame
            "images_per_s_segment_filter_stereo": float(
                2.0 / max(sum(float(np.mean(v)) for k, v in self.times.items() if k != "cpu"), 1e-9)
            ),
        }


def site_key(archive: str) -> str:
    """The site an archive shows: `site<seed>` from `--simulate`'s names, else the name."""
    import re

    m = re.search(r"site(\d+)", archive)
    return f"site{m.group(1)}" if m else archive


def pool_runs(paths: list[Path]) -> dict[str, dict[str, dict]]:
    """The per-site counts of several `--json` outputs, merged per lighting:
    {lighting: {site: counts}}. A site scored twice under one lighting is an error (it
    would be counted twice)."""
    pooled: dict[str, dict[str, dict]] = {}
    for path in paths:
        try:
            run = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise SystemExit(f"--pool: cannot read {path}: {e}")
        groups = run.get("by_lighting") if isinstance(run, dict) else None
        if not isinstance(groups, dict) or not groups or any(
                not isinstance(g, dict) or not isinstance(g.get("by_site"), dict) for g in groups.values()):
            raise SystemExit(f"--pool: {path} has no per-site counts (written by an older bench_perception.py?)")
        for lighting, g in groups.items():
            sites = pooled.setdefault(lighting, {})
            for key, c in g["by_site"].items():
                if key in sites:
                    raise SystemExit(f"--pool: {key} under {lighting} is in two runs ({path} and an earlier one)")
                try:
                    sites[key] = {n: np.asarray(c[n], int).reshape(2) for n in ("target", "precision", "small")}
                    sites[key]["err"] = [float(e) for e in c["err"]]
                except (KeyError, TypeError, ValueError):
                    raise SystemExit(f"--pool: {path}: the counts of {key} under {lighting} are malformed") from None
    return pooled


def print_pooled(pooled: dict[str, dict[str, dict]]) -> dict:
    """One row per lighting: the pooled figures with their 90 % site-bootstrap intervals."""
    def ratio(sites, k):
        c = sum((s[k] for s in sites.values()), np.zeros(2, int))
        return float(c[0] / c[1]) if c[1] else float("nan"), c.tolist()

    out = {}
    print("lighting | sites | P(<=5m) [90 %] | R(r>=.1,<=5m) [90 %] | R(.05-.1,<=3m) [90 %] | err50 cm [90 %]")
    for lighting, sites in sorted(pooled.items()):
        ci = site_bootstrap(sites)
        errs = [e for s in sites.values() for e in s["err"]]
        row = {"sites": len(sites), "ci90": ci,
               "precision_range<=5": ratio(sites, "precision"),
               "target_recall_r>=0.1_range<=5": ratio(sites, "target"),
               "recall_0.05<=r<0.1_range<=3": ratio(sites, "small"),
               "centroid_err_target_median_m": float(np.median(errs)) if errs else float("nan")}
        out[lighting] = row

        def cell(k, scale=1.0, fmt="{:.3f}"):
            v = row[k][0] if isinstance(row[k], tuple) else row[k]
            iv = ci.get(k)
            return fmt.format(scale * v) + ("" if iv is None else " [" + ", ".join(fmt.format(scale * x) for x in iv) + "]")
        print(" | ".join([lighting, str(len(sites)), cell("precision_range<=5"), cell("target_recall_r>=0.1_range<=5"),
                          cell("recall_0.05<=r<0.1_range<=3"), cell("centroid_err_target_median_m", 100.0, "{:.1f}")]))
    return out


def site_bootstrap(by_site: dict[str, dict], n_boot: int = 2000, level: float = 0.9, seed: int = 0) -> dict:
    """Intervals for the targets' figures with the sites as the unit of resampling.

    A rock is seen in several frames and a false detection on terrain persists from
    frame to frame, so sightings are not independent; sites are. The sites are drawn
    with replacement `n_boot` times and each figure (a ratio of pooled counts, or the
    median of the pooled centre errors) recomputed: the central `level` interval of
    those draws. Empty (fewer than two sites) when there is nothing to resample."""
    keys = sorted(by_site)
    if len(keys) < 2:
        return {}
    rng = np.random.default_rng(seed)
    counts = {k: np.array([by_site[s][k] for s in keys], float) for k in ("target", "precision", "small")}
    errs = [np.asarray(by_site[s]["err"], float) for s in keys]
    draws = rng.integers(0, len(keys), size=(n_boot, len(keys)))
    out = {}
    q = (100 * (1 - level) / 2, 100 * (1 + level) / 2)
    for name, k in (("precision_range<=5", "precision"), ("target_recall_r>=0.1_range<=5", "target"),
                    ("recall_0.05<=r<0.1_range<=3", "small")):
        c = counts[k][draws].sum(axis=1)  # (n_boot, 2)
        ok = c[:, 1] > 0
        if ok.any():
            out[name] = [float(v) for v in np.percentile(c[ok, 0] / c[ok, 1], q)]
    med = [np.median(e) for e in (np.concatenate([errs[i] for i in d]) for d in draws) if len(e)]
    if med:
        out["centroid_err_target_median_m"] = [float(v) for v in np.percentile(med, q)]
    return out


CENTRE_SIZE_BANDS = [(0.1, 0.15), (0.15, 0.2), (0.2, 0.3), (0.3, 0.5), (0.5, 10.0)]
CENTRE_RANGE_BANDS = [(0.0, 2.5), (2.5, 5.0)]


def centre_error_parts(est: np.ndarray, true: np.ndarray, r_true: float, rng: float, cam: np.ndarray, r_est: float,
                       cfg: DetectorConfig) -> tuple:
    """One matched detection's centre error, split: (true radius, range, 3D error, horizontal
    error, along the horizontal viewing ray (+ = too far), across it, vertical (+ = too high),
    estimated / true radius, 3D error with the true radius). The last is an oracle for the
    stereo-points centre (centre_range_factor x R beyond the visible surface along the ray,
    centre_height_factor x R below its top): the same centre moved as if R were the true
    radius (the ray taken from the camera to the estimate; for the BLEND estimator its own
    radius factors); NaN for other methods."""
    e = np.asarray(est, float) - true
    v = true[:2] - cam[:2]
    v = v / max(float(np.linalg.norm(v)), 1e-9)
    along, lat = float(e[:2] @ v), float(-e[0] * v[1] + e[1] * v[0])
    oracle = float("nan")
    if cfg.centre_method is CentreMethod.STEREO_POINTS:
        f = est[:2] - cam[:2]
        f = f / max(float(np.linalg.norm(f)), 1e-9)
        dR = r_true - r_est
        k_along, k_z = cfg.centre_range_factor, cfg.centre_height_factor
        if cfg.centre_estimator is CentreEstimator.BLEND:  # its radius terms (the near anchor unclamped)
            w = cfg.centre_near_weight
            k_along, k_z = (1 - w) * cfg.centre_range_factor + w * cfg.centre_near_range_factor, cfg.centre_ring_radius_factor
        moved = est + dR * np.array([k_along * f[0], k_along * f[1], -k_z])
        oracle = float(np.linalg.norm(moved - true))
    return (float(r_true), float(rng), float(np.linalg.norm(e)), float(np.linalg.norm(e[:2])), along, lat, float(e[2]),
            float(r_est / r_true), oracle)


def centre_breakdown(rows: list[tuple]) -> dict:
    """Centre error of target matches, all of them ("all") and by true radius band and by
    range band: count, median / p90 3D error, median horizontal error, median signed
    along-ray and vertical parts, median |lateral| part, median estimated / true radius,
    and the median error with the true radius (oracle; see centre_error_parts)."""
    a = np.asarray(rows, float).reshape(-1, 9)
    out = {}
    subsets = [("all", np.ones(len(a), bool))]
    for name, col, bands in (("radius", 0, CENTRE_SIZE_BANDS), ("range", 1, CENTRE_RANGE_BANDS)):
        for lo, hi in bands:
            key = f"{name} {lo:g}-{hi:g}" if hi < 10 else f"{name} >={lo:g}"
            subsets.append((key, (a[:, col] >= lo) & (a[:, col] < hi)))
    for key, sel in subsets:
        m = a[sel]
        if not len(m):
            continue
        out[key] = {
            "n": int(len(m)), "median_m": float(np.median(m[:, 2])), "p90_m": float(np.percentile(m[:, 2], 90)),
            "xy_median_m": float(np.median(m[:, 3])), "along_median_m": float(np.median(m[:, 4])),
            "lateral_abs_median_m": float(np.median(np.abs(m[:, 5]))), "vertical_median_m": float(np.median(m[:, 6])),
            "radius_ratio_median": float(np.median(m[:, 7])),
            "true_radius_oracle_median_m": float(np.median(m[:, 8])) if np.isfinite(m[:, 8]).all() else None,
        }  # fmt: skip
    return out


def print_breakdown(groups: dict[str, dict]) -> None:
    """The centre error's parts per lighting, over all target matches and by true radius and
    range band (cm)."""
    print("centre error of target matches (cm): n, median, p90, horizontal median, along-ray (+ far), |lateral|, "
          "vertical (+ high), est/true radius, median with the true radius")
    for name, s in groups.items():
        print(f"{name}: median {100 * s['centroid_err_target_median_m']:.1f}, horizontal "
              f"{100 * s['centroid_err_target_xy_median_m']:.1f}")
        for band, b in s["centre_breakdown"].items():
            o = b["true_radius_oracle_median_m"]
            print(f"  {band:>14} {b['n']:4d} {100 * b['median_m']:5.1f} {100 * b['p90_m']:5.1f} "
                  f"{100 * b['xy_median_m']:5.1f} {100 * b['along_median_m']:+5.1f} {100 * b['lateral_abs_median_m']:4.1f} "
                  f"{100 * b['vertical_median_m']:+5.1f} {b['radius_ratio_median']:5.2f} "
                  + ("-" if o is None else f"{100 * o:5.1f}"))


def print_summary(s: dict) -> None:
    def band(b):
        return f"{b[0]:g}-{b[1]:g}" if b[1] < 10 else f">={b[0]:g}"

    print(f"frames {s['frames']}, detections {s['detections']}")
    print("recall (hit/visible) by true radius [m] x range [m]")
    print("radius \\ range " + "".join(f"{band(r):>16}" for r in RANGE_BANDS))
    for i, sb in enumerate(SIZE_BANDS):
        row = s["recall_by_size_range"][i]
        print(f"{band(sb):>14} " + "".join(f"{(h / t if t else float('nan')):>8.2f} ({h:>3}/{t:>3})" for h, t in row))
    print("precision (tp/detections) by estimated radius [m] x depth [m]")
    for i, sb in enumerate(SIZE_BANDS):
        row = s["precision_by_estsize_range"][i]
        print(f"{band(sb):>14} " + "".join(f"{(h / t if t else float('nan')):>8.2f} ({h:>3}/{t:>3})" for h, t in row))
    for k, v in s.items():
        if k not in ("recall_by_size_range", "precision_by_estsize_range", "centre_breakdown"):
            if k != "by_lighting":
                print(f"{k}: {v}")


def _lander_xy(ar) -> np.ndarray:
    """The lander's centre in the map frame: ``LacArchive.lander_pose_map()`` where the
    archive reader has it (initial.toml ``lander`` is rover-relative in the LAC), else
    initial.toml ``lander`` as this branch's simulator writes it (map frame)."""
    f = getattr(ar, "lander_pose_map", None)
    pose = f() if callable(f) else ar.initial["lander"]
    return np.asarray([float(v) for v in pose[:2]])


def run_archive(path: Path, cfg: DetectorConfig, every: int, acc: Accumulator, detector: Detector | None = None):
    """Accumulate one archive's metrics. The camera (image size, field of view) is read
    from the archive and `cfg`'s pixel-sized parameters (tuned at 1280 px) are scaled
    to its width; `detector` is reused when it was built for the same camera."""
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.detector import mounts_from_archive_row
    from lunarloc.config.run import scaled_detector_config
    from lunarloc.perception.camera import camera_from_archive

    with LacArchive(path) as ar:
        t = ar.custom("rocks")
        rocks = np.column_stack([t["id"], t["x"], t["y"], t["z"], t["radius"]])
        frames = [int(f) for f in ar.frame_numbers if ar.camera_row(STEREO_PAIRS[0][0], int(f)) is not None][::every]
        cam = camera_from_archive(ar)
        det = detector if detector is not None and detector.camera == cam else None
        if det is None:
            det = Detector(scaled_detector_config(cam.width, base=cfg), cam)
        print(f"{path}: {cam.width}x{cam.height} px, hfov {cam.hfov_deg:g} deg", file=sys.stderr)
        lander_xy = _lander_xy(ar)  # known to a LAC agent: detections on the lander are dropped
        acc.begin_archive(path.name)
        for fd in detect_archive(ar, det.config, "ground-truth", detector=det, frames=frames, lander_xy=lander_xy,
                                 keep_depth=acc.misses is not None):
            sem = {left: ar.semantic(left, fd.frame) for left, _ in det.config.pairs}
            rows = {c: ar.camera_row(c, fd.frame) for c in ar.cameras}
            mounts = mounts_from_archive_row({k: v for k, v in rows.items() if v}, det.camera)
            acc.add_frame(fd, sem, rocks, det, mounts)
        acc.end_archive()
    return det


def lighting_label(path: Path) -> str:
    """The lighting an archive was rendered with, from its description ("lighting
    sun+lamps", else "sun elevation E deg" -> "sun E")."""
    import re

    from lunarloc.io.lac.archive import LacArchive

    with LacArchive(path) as ar:
        desc = str(ar.metadata.get("description", ""))
    m = re.search(r"lighting[ =:]+([\w+]+)", desc)
    el = re.search(r"sun elevation (-?[\d.]+) deg", desc)
    if m and m.group(1) != "sun":
        return m.group(1) + (f" (sun {el.group(1)})" if el and "sun" in m.group(1) else "")
    return f"sun {el.group(1)}" if el else "unknown"


def print_groups(groups: dict[str, dict]) -> None:
    """One row per lighting: the issue's targets side by side."""
    hdr = ("lighting", "frames", "P(<=5m)", "R(r>=.1,<=5m)", "R(.05-.1,<=3m)", "R(.025-.05,<=3m)", "err50 cm",
           "err90 cm", "frames/s", "CPU ms/frame")
    print(" | ".join(hdr))
    for name, s in groups.items():
        print(" | ".join([
            name, str(s["frames"]), f"{s['precision_range<=5']:.2f}", f"{s['target_recall_r>=0.1_range<=5']:.2f}",
            f"{s['recall_0.05<=r<0.1_range<=3']:.2f}",
            f"{s.get('recall_0.025<=r<0.05_range<=3', float('nan')):.2f} ({s.get('recall_0.025<=r<0.05_range<=3_counts', ['-', '-'])[1]})",
            f"{100 * s['centroid_err_target_median_m']:.1f}", f"{100 * s['centroid_err_target_p90_m']:.1f}", f"{s['frames_per_s']:.1f}", f"{s['cpu_ms_per_frame']:.0f}",
        ]))  # fmt: skip
    ci = {name: s["site_bootstrap_ci90"] for name, s in groups.items() if s.get("site_bootstrap_ci90")}
    if ci:
        print("90 % intervals, the sites resampled (bootstrap): P(<=5m) | R(r>=.1,<=5m) | R(.05-.1,<=3m) | err50 cm")
        for name, c in ci.items():
            def iv(k, scale=1.0, fmt="{:.3f}"):
                return "-" if k not in c else "[" + ", ".join(fmt.format(scale * v) for v in c[k]) + "]"
            print(f"{name} ({groups[name]['sites']} sites): " + " | ".join([
                iv("precision_range<=5"), iv("target_recall_r>=0.1_range<=5"), iv("recall_0.05<=r<0.1_range<=3"),
                iv("centroid_err_target_median_m", 100.0, "{:.1f}")]))
    print("false positives within 5 m by cause: " + ", ".join(FP_CAUSES))
    for name, s in groups.items():
        c = s.get("false_positives_within_5m_by_cause", {})
        print(f"{name}: " + " ".join(str(c.get(k, 0)) for k in FP_CAUSES))


def lac_real_frame(folder: Path, figure: Path | None = None, cfg: DetectorConfig | None = None) -> list:
    """Detect rocks on the real LAC frame (FrontLeft/FrontRight_99.png, pose_99.json; the
    lander stands at the site centre, the map origin); print the detections and draw
    them (kept masks green, rejected ones coloured by filter) into `figure`. `cfg`: the
    detector configuration (default DetectorConfig())."""
    import cv2

    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.perception.detector import debug_overlay

    left = cv2.imread(str(folder / "FrontLeft_99.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(folder / "FrontRight_99.png"), cv2.IMREAD_GRAYSCALE)
    if left is None or right is None:
        raise SystemExit(f"no FrontLeft_99.png / FrontRight_99.png in {folder}")
    p = json.loads((folder / "pose_99.json").read_text())
    T = pose_to_matrix(*[float(p[k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")])
    det = Detector(cfg or DetectorConfig(), PinholeCamera(left.shape[1], left.shape[0], 70.0))
    T_ro = ipex_rig(det.camera)["FrontLeft"].T_rover_optical
    det.detect_pair(left, right, T_ro, T, "FrontLeft")  # warm-up (OpenCV allocations)
    t0 = time.perf_counter()
    pr = det.detect_pair(left, right, T_ro, T, "FrontLeft", keep_depth=True, lander_xy=np.zeros(2))
    dt = time.perf_counter() - t0
    print(f"real LAC frame 99: {len(pr.detections)} detections in {1000 * dt:.0f} ms (wall)")
    for d in pr.detections:
        print(f"  u,v {d.uv[0]:6.0f} {d.uv[1]:5.0f}  depth {d.depth_m:5.2f} m  radius {d.radius_m:5.3f} m  "
              f"map {d.p_map[0]:6.2f} {d.p_map[1]:6.2f} {d.p_map[2]:6.2f}")  # fmt: skip
    counts: dict[str, int] = {}
    for r in pr.records:
        if r.reason is not None:
            counts[r.reason.value] = counts.get(r.reason.value, 0) + 1
    print("  rejected masks by filter:", counts)
    if figure is not None:
        figure.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(figure), debug_overlay(left, pr)[:, : left.shape[1]])
        print(f"  figure -> {figure}")
    return pr.detections


def speed(path: Path, repeats: int = 5, cfg: DetectorConfig | None = None) -> dict:
    """Wall and process-CPU time of the detector on one 1280x720 front pair of an
    archive (after a warm-up run): per stereo pair and per two-pair frame."""
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.camera import ipex_rig

    with LacArchive(path) as ar:
        f = next(int(f) for f in ar.frame_numbers if ar.camera_row("FrontLeft", int(f)) is not None)
        L, R = ar.grayscale("FrontLeft", f), ar.grayscale("FrontRight", f)
    det = Detector(cfg or DetectorConfig())
    T = ipex_rig(det.camera)["FrontLeft"].T_rover_optical
    det.detect_pair(L, R, T)
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(repeats):
        det.detect_pair(L, R, T)
    wall = (time.perf_counter() - w0) / repeats
    cpu = (time.process_time() - c0) / repeats
    return {"pair_wall_ms": 1000 * wall, "pair_cpu_ms": 1000 * cpu, "pairs_per_s_wall": 1 / wall,
            "pairs_per_s_cpu": 1 / cpu}  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("archives", nargs="*", type=Path)
    ap.add_argument("--simulate", type=int, nargs="*", default=[], help="site seeds to render first")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds per simulated traverse")
    ap.add_argument("--image-rate", type=float, default=0.5, help="simulated camera rate, Hz")
    ap.add_argument("--width", type=int, default=1280, help="simulated image width, px")
    ap.add_argument("--height", type=int, default=720, help="simulated image height, px")
    ap.add_argument("--lighting", default="sun+lamps", help="simulated lighting: sun | lamps | sun+lamps")
    ap.add_argument("--sun-elevation", type=float, default=12.0, help="simulated sun elevation, degrees (<= 0: night)")
    ap.add_argument("--out-dir", type=Path, default=Path("bench-output/perception"))
    ap.add_argument("--every", type=int, default=1, help="use every N-th camera frame")
    ap.add_argument("--segmenter", default=None, help="classical | fastsam (default: the config's, classical)")
    ap.add_argument("--weights", default=None)
    ap.add_argument("--no-centre-correction", action="store_true")
    ap.add_argument("--centre-method", default=None, help=" | ".join(m.value for m in CentreMethod) + " (default: the config's)")
    ap.add_argument("--breakdown", action="store_true",
                    help="print the centre error by true radius and range band, split along / across the ray / vertical")
    ap.add_argument("--min-gt-px", type=int, default=50)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--lac-real", type=Path, default=None, help="run the real LAC frame in this folder and stop")
    ap.add_argument("--figure", type=Path, default=None, help="with --lac-real: draw the detections here")
    ap.add_argument("--speed", action="store_true", help="time the detector on one front pair of each archive")
    ap.add_argument("--config", type=Path, default=None,
                    help="a run configuration (config.json, `lunarloc config`): its detector section is benchmarked")
    ap.add_argument("--pool", type=Path, nargs="+", default=None, metavar="JSON",
                    help="pool the per-site counts of earlier --json outputs (other sites, or other lightings) and "
                    "print each lighting's figures with 90 %% intervals, the sites resampled; detects nothing")
    ap.add_argument("--misses", type=Path, default=None,
                    help="write each missed sighting of a rock r >= 0.1 m within 5 m, with the stage where it was "
                    "lost (the mask overlapping it most: its reject reason, or kept but off-centre; or no blob), to "
                    "this CSV, and print the counts by stage and the rocks missed most")
    ap.add_argument("--real-labels", type=Path, nargs="?", const=Path(""), default=None, metavar="DIR",
                    help="score the hand-labelled real LAC pairs (tests/data/lac_real_labels.json; images in DIR, default "
                    "$LUNARLOC_LAC_REAL or ../shared/data/lac-real) with benchmarks/real_labels.py, with --config, "
                    "--misses and --json passed on, and stop")
    ap.add_argument("--small-rocks", action="store_true",
                    help="turn the small-rock stage on (DetectorConfig.small_rocks.enabled; off by default)")
    a = ap.parse_args(argv)
    if a.small_rocks and a.real_labels is None:
        ap.error("--small-rocks goes with --real-labels; for archives give --config with "
                 '{"detector": {"small_rocks": {"enabled": true}}}')
    if a.real_labels is not None:
        import real_labels

        args = (["--data", str(a.real_labels)] if str(a.real_labels) not in ("", ".") else [])
        for flag, v in (("--config", a.config), ("--misses", a.misses), ("--json", a.json)):
            args += [flag, str(v)] if v is not None else []
        args += ["--small-rocks"] if a.small_rocks else []
        return real_labels.main(args)
    base = DetectorConfig()
    if a.config is not None:
        from lunarloc.config.run import load_config_file

        base = load_config_file(a.config)[0].detector
    if a.centre_method:
        base = replace(base, centre_method=CentreMethod(a.centre_method))
    if a.pool is not None:
        pooled = print_pooled(pool_runs(a.pool))
        if a.json:
            a.json.parent.mkdir(parents=True, exist_ok=True)
            a.json.write_text(json.dumps(pooled, indent=2))
        return 0
    if a.lac_real is not None:
        lac_real_frame(a.lac_real, a.figure, base)
        return 0
    if a.speed:
        for p in a.archives:
            print(p, json.dumps({k: round(v, 1) for k, v in speed(p, cfg=base).items()}))
        return 0
    archives = list(a.archives)
    for seed in a.simulate:
        from lunarloc.sim.simulate import SimulationConfig, simulate_site, simulate_traverse

        from lunarloc.sim.render import RenderConfig

        sc = SimulationConfig(duration_s=a.duration, image_rate_hz=a.image_rate, width=a.width, height=a.height,
                              cameras=("FrontLeft", "FrontRight"),
                              render=RenderConfig(sun_elevation_deg=a.sun_elevation, lighting=a.lighting))  # fmt: skip
        size = "" if (a.width, a.height) == (1280, 720) else f"_{a.width}x{a.height}"
        light = f"_{a.lighting.replace('+', '_')}_el{a.sun_elevation:g}"
        p = a.out_dir / f"site{seed}{light}_traverse0{size}.lac"
        if not p.exists():
            a.out_dir.mkdir(parents=True, exist_ok=True)
            t0 = time.time()
            simulate_traverse(simulate_site(seed, sc), p, 0, sc)
            print(f"rendered {p} in {time.time() - t0:.0f} s", file=sys.stderr)
        archives.append(p)
    if not archives:
        ap.error("give archives or --simulate SEED")
    cfg = replace(base, segmenter=a.segmenter or base.segmenter, weights=a.weights or base.weights,
                  centre_correction=base.centre_correction and not a.no_centre_correction)
    acc = Accumulator()
    acc.min_gt_px = a.min_gt_px
    det = None
    configs = {}  # the detector config used at each image size (pixel parameters scaled)
    groups: dict[str, Accumulator] = {}
    misses: list[dict] = []
    for p in archives:
        g = groups.setdefault(lighting_label(p), Accumulator())
        g.min_gt_px = a.min_gt_px
        if a.misses is not None:
            g.misses = misses
        det = run_archive(p, cfg, a.every, g, det)
        configs[f"{det.camera.width}x{det.camera.height}"] = det.config.to_dict()
    for g in groups.values():  # the total over all archives
        acc.merge(g)
    s = acc.summary()
    s["by_lighting"] = {k: g.summary() for k, g in groups.items()}
    s["archives"] = [str(p) for p in archives]
    s["config"] = configs[next(iter(configs))] if len(configs) == 1 else configs
    print_summary(s)
    print_groups({**s["by_lighting"], "all": s})
    if a.breakdown:
        print_breakdown({**s["by_lighting"], "all": s})
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(s, indent=2, default=str))
    if a.misses is not None:
        write_misses(a.misses, misses)
    return 0


def write_misses(path: Path, rows: list[dict]) -> None:
    """The missed target sightings as CSV (MISS_FIELDS), and their counts by stage."""
    import csv
    from collections import Counter

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=MISS_FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()})
    counts = Counter(r["stage"] for r in rows)
    print(f"missed target sightings: {len(rows)} -> {path}; by stage: "
          + ", ".join(f"{k} {v}" for k, v in counts.most_common()))
    rules = Counter(r.get("tentative_rules") or "?" for r in rows if r["stage"] == "tentative")
    if rules:
        print("tentatives never confirmed, by the rules that made them tentative: "
              + ", ".join(f"{k} {v}" for k, v in rules.most_common()))
    groups = misses_by_rock(rows)
    if groups:
        print("rocks missed most (archive, rock id, radius, range, sightings missed, stages):")
        for g in groups[:10]:
            print(f"  {g['archive']}  rock {g['rock_id']}  r {g['radius_m']:.2f} m  {g['range_min_m']:.1f}-"
                  f"{g['range_max_m']:.1f} m  {g['missed']} x  " + ", ".join(f"{k} {v}" for k, v in g["stages"]))


def misses_by_rock(rows: list[dict]) -> list[dict]:
    """The missed sightings grouped by rock (archive, rock_id), most missed first: a few rocks
    missed frame after frame are most misses, and one look at each explains them."""
    from collections import Counter

    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["archive"], r["rock_id"]), []).append(r)
    out = []
    for (archive, rock_id), g in groups.items():
        rng = [float(r["range_m"]) for r in g]
        out.append(dict(archive=archive, rock_id=rock_id, radius_m=float(g[0]["radius_m"]), missed=len(g),
                        range_min_m=min(rng), range_max_m=max(rng),
                        stages=Counter(r["stage"] for r in g).most_common()))
    return sorted(out, key=lambda d: (-d["missed"], d["archive"], str(d["rock_id"])))


if __name__ == "__main__":
    sys.exit(main())
