"""Scoring the rock detector on simulated traverses, where the true rocks are known: the
logic behind ``benchmarks/bench_perception.py`` (which prints and writes what this computes)
and ``benchmarks/landmark_centres.py`` (which matches detections as this does).

* :func:`match` pairs detections with true rocks one-to-one (within max(0.15 m, r));
* :class:`Accumulator` counts recall by true radius and range band, precision by estimated
  radius and depth band, the centre errors, the false positives by cause
  (:func:`fp_cause`) and, on request, where each missed target was lost
  (:func:`miss_stage`); per site too, for the intervals of :func:`site_bootstrap`;
* :func:`run_archive` runs the detector over one archive into an accumulator;
* :func:`pool_runs` / :func:`pooled_rows` pool the per-site counts of earlier runs;
* :func:`centre_error_parts` / :func:`centre_breakdown` split the centre error;
* :func:`misses_by_rock` groups the missed sightings by rock.

The metrics are described in ``benchmarks/bench_perception.py`` and docs/perception.md.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

import numpy as np

from lunarloc.core.errors import InputError
from lunarloc.core.geometry import transform_points
from lunarloc.perception.camera import STEREO_PAIRS
from lunarloc.perception.detector import (
    CentreEstimator,
    CentreMethod,
    Detector,
    DetectorConfig,
    detect_archive,
)

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


FP_CAUSES = (
    "terrain",
    "lander",
    "rock-duplicate",
    "rock-part",
    "small-rock-offcentre",
    "rock-offcentre",
)


def fp_cause(
    d,
    semantic: np.ndarray,
    id_to_idx: dict,
    centres: np.ndarray,
    radii: np.ndarray,
    matched_rock: dict,
) -> str:
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
        return (
            "lander" if np.count_nonzero(semantic_lander_mask(win)) * 2 >= win.size else "terrain"
        )
    j = id_to_idx.get(int(np.bincount(rid[rid >= 0]).argmax()))
    if j is None:
        return "terrain"
    if j in matched_rock:
        return "rock-duplicate"
    if radii[j] > 2.0 * max(d.radius_m, 0.02) and radii[j] >= 0.2:
        return "rock-part"
    return "small-rock-offcentre" if radii[j] < 0.1 else "rock-offcentre"


MISS_FIELDS = (
    "archive",
    "frame",
    "camera",
    "rock_id",
    "radius_m",
    "range_m",
    "stage",
    "tentative_rules",
    "rejected_by",
    "overlap",
    "mask_eig_ratio",
    "mask_depth_m",
    "valid_fraction",
    "max_height_m",
)


def miss_stage(pair, rock_px: np.ndarray) -> dict:
    """Where a missed rock was lost in one pair (`rock_px`: its pixels in the left image).
    The mask overlapping most of the rock is followed through the filters: its reject
    reason (``elongated``, ``tentative`` with the rules that made it one in
    ``tentative_rules``, ``unconfirmed``, ``not_a_rock`` with the rules that fired or
    ``verifier`` in ``rejected_by``, ...) or ``kept``
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
    out = dict(
        stage="no-blob",
        tentative_rules="",
        rejected_by="",
        overlap=overlap / n,
        mask_eig_ratio=float("nan"),
        mask_depth_m=float("nan"),
        valid_fraction=float("nan"),
        max_height_m=float("nan"),
    )
    if best is not None:
        rec = next((r for r in pair.records if r.mask_index == best), None)
        out["stage"] = "kept" if rec is None or rec.reason is None else rec.reason.value
        if rec is not None:
            out["mask_eig_ratio"], out["mask_depth_m"] = (
                float(rec.stats.eig_ratio),
                float(rec.depth_m),
            )
            out["tentative_rules"] = rec.tentative  # why a dropped tentative was tentative
            out["rejected_by"] = rec.rejected_by  # the rules or the verifier (not_a_rock)
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
    """The counts behind every figure of the perception benchmark, over the frames added;
    `min_gt_px` is the fewest pixels of a rock that make it visible in a left image."""

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
        # [on a rock, all]: the small-rock stage's own detections within 5 m (in the precision's
        # bands)
        self.stage_prec = np.zeros(2, int)
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
        self._mark = (
            self.rec.copy(),
            self.prec.copy(),
            self.small_near.copy(),
            len(self.err_target),
        )

    def end_archive(self) -> None:
        rec, prec, small, n_err = self._mark
        site = self.by_site.setdefault(
            site_key(self.archive),
            {
                "target": np.zeros(2, int),
                "precision": np.zeros(2, int),
                "small": np.zeros(2, int),
                "err": [],
            },
        )
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
        self.stage_prec += other.stage_prec
        for k, v in other.fp_causes.items():
            self.fp_causes[k] += v
        for k in ("err3d", "err_xy", "err3d_surface", "err_target", "target_rows"):
            getattr(self, k).extend(getattr(other, k))
        for k, v in other.times.items():
            self.times.setdefault(k, []).extend(v)
        self.n_frames += other.n_frames
        self.n_det += other.n_det
        for key, c in other.by_site.items():
            site = self.by_site.setdefault(
                key,
                {
                    "target": np.zeros(2, int),
                    "precision": np.zeros(2, int),
                    "small": np.zeros(2, int),
                    "err": [],
                },
            )
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
                if (
                    j not in matched_rock
                    and self.misses is not None
                    and radii[j] >= 0.1
                    and rng <= 5.0
                ):
                    self.misses.append(
                        dict(
                            archive=self.archive,
                            frame=fd.frame,
                            camera=pair.camera,
                            rock_id=r,
                            radius_m=float(radii[j]),
                            range_m=rng,
                            **miss_stage(pair, rid == r),
                        )
                    )
                if j in matched_rock:
                    self.rec[sb, rb, 0] += 1
                    i, dist = matched_rock[j]
                    self.err3d.append(dist)
                    self.err_xy.append(float(np.linalg.norm(det_xyz[i, :2] - centres[j, :2])))
                    if radii[j] >= 0.1 and rng <= 5.0:
                        self.err_target.append(dist)
                        self.target_rows.append(
                            centre_error_parts(
                                det_xyz[i],
                                centres[j],
                                radii[j],
                                rng,
                                cam_pos,
                                dets[i].radius_m,
                                detector.config,
                            )
                        )
        for i, d in enumerate(dets):
            if i not in matched_det and d.depth_m < 5.0 and semantics.get(d.camera) is not None:
                self.fp_causes[
                    fp_cause(d, semantics[d.camera], id_to_idx, centres, radii, matched_rock)
                ] += 1
            sb, rb = _band(d.radius_m, SIZE_BANDS), _band(d.depth_m, RANGE_BANDS)
            if sb < 0 or rb < 0:
                continue
            self.prec[sb, rb, 1] += 1
            if i in matched_det:
                self.prec[sb, rb, 0] += 1
            if d.small_rock and rb < 2:
                self.stage_prec += [int(i in matched_det), 1]
            # surface (uncorrected) centroid error, for comparison
            if i in matched_det and detector.config.centre.correction:
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
            "frames_per_s": float(
                1.0 / max(sum(float(np.mean(v)) for k, v in self.times.items() if k != "cpu"), 1e-9)
            ),
            # process CPU time per frame (all threads), when the detector reports it
            "cpu_ms_per_frame": float(1000.0 * np.mean(self.times["cpu"]))
            if "cpu" in self.times
            else float("nan"),
            "precision_range<=5": float(prec_5[0] / max(prec_5[1], 1)),
            "precision_counts_range<=5": prec_5.tolist(),
            "small_rock_stage_precision_range<=5": float(
                self.stage_prec[0] / max(self.stage_prec[1], 1)
            ),
            "small_rock_stage_precision_counts_range<=5": self.stage_prec.tolist(),
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
            "by_site": {
                k: {n: (v.tolist() if isinstance(v, np.ndarray) else list(v)) for n, v in c.items()}
                for k, c in self.by_site.items()
            },
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
    would be counted twice): InputError, as is a file without per-site counts."""
    pooled: dict[str, dict[str, dict]] = {}
    for path in paths:
        try:
            run = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise InputError(f"cannot read {path}: {e}") from None
        groups = run.get("by_lighting") if isinstance(run, dict) else None
        if (
            not isinstance(groups, dict)
            or not groups
            or any(
                not isinstance(g, dict) or not isinstance(g.get("by_site"), dict)
                for g in groups.values()
            )
        ):
            raise InputError(
                f"{path} has no per-site counts (written by an older bench_perception.py?)"
            )
        for lighting, g in groups.items():
            sites = pooled.setdefault(lighting, {})
            for key, c in g["by_site"].items():
                if key in sites:
                    raise InputError(
                        f"{key} under {lighting} is in two runs ({path} and an earlier one)"
                    )
                try:
                    sites[key] = {
                        n: np.asarray(c[n], int).reshape(2)
                        for n in ("target", "precision", "small")
                    }
                    sites[key]["err"] = [float(e) for e in c["err"]]
                except (KeyError, TypeError, ValueError):
                    raise InputError(
                        f"{path}: the counts of {key} under {lighting} are malformed"
                    ) from None
    return pooled


def pooled_rows(pooled: dict[str, dict[str, dict]]) -> dict:
    """Per lighting (sorted): the pooled figures (ratio, [hits, total]) and the median centre
    error, with their 90 % site-bootstrap intervals (``ci90``)."""

    def ratio(sites, k):
        c = sum((s[k] for s in sites.values()), np.zeros(2, int))
        return float(c[0] / c[1]) if c[1] else float("nan"), c.tolist()

    out = {}
    for lighting, sites in sorted(pooled.items()):
        errs = [e for s in sites.values() for e in s["err"]]
        out[lighting] = {
            "sites": len(sites),
            "ci90": site_bootstrap(sites),
            "precision_range<=5": ratio(sites, "precision"),
            "target_recall_r>=0.1_range<=5": ratio(sites, "target"),
            "recall_0.05<=r<0.1_range<=3": ratio(sites, "small"),
            "centroid_err_target_median_m": float(np.median(errs)) if errs else float("nan"),
        }
    return out


def format_pooled(rows: dict) -> list[str]:
    """The table of :func:`pooled_rows`: a header, then one line per lighting."""
    lines = [
        "lighting | sites | P(<=5m) [90 %] | R(r>=.1,<=5m) [90 %] | R(.05-.1,<=3m) [90 %] | err50 "
        "cm [90 %]"
    ]
    for lighting, row in rows.items():
        ci = row["ci90"]

        def cell(k, scale=1.0, fmt="{:.3f}"):
            v = row[k][0] if isinstance(row[k], tuple) else row[k]
            iv = ci.get(k)
            return fmt.format(scale * v) + (
                "" if iv is None else " [" + ", ".join(fmt.format(scale * x) for x in iv) + "]"
            )

        lines.append(
            " | ".join(
                [
                    lighting,
                    str(row["sites"]),
                    cell("precision_range<=5"),
                    cell("target_recall_r>=0.1_range<=5"),
                    cell("recall_0.05<=r<0.1_range<=3"),
                    cell("centroid_err_target_median_m", 100.0, "{:.1f}"),
                ]
            )
        )
    return lines


def site_bootstrap(
    by_site: dict[str, dict], n_boot: int = 2000, level: float = 0.9, seed: int = 0
) -> dict:
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
    counts = {
        k: np.array([by_site[s][k] for s in keys], float) for k in ("target", "precision", "small")
    }
    errs = [np.asarray(by_site[s]["err"], float) for s in keys]
    draws = rng.integers(0, len(keys), size=(n_boot, len(keys)))
    out = {}
    q = (100 * (1 - level) / 2, 100 * (1 + level) / 2)
    for name, k in (
        ("precision_range<=5", "precision"),
        ("target_recall_r>=0.1_range<=5", "target"),
        ("recall_0.05<=r<0.1_range<=3", "small"),
    ):
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


def centre_error_parts(
    est: np.ndarray,
    true: np.ndarray,
    r_true: float,
    rng: float,
    cam: np.ndarray,
    r_est: float,
    cfg: DetectorConfig,
) -> tuple:
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
    if cfg.centre.method is CentreMethod.STEREO_POINTS:
        f = est[:2] - cam[:2]
        f = f / max(float(np.linalg.norm(f)), 1e-9)
        dR = r_true - r_est
        k_along, k_z = cfg.centre.range_factor, cfg.centre.height_factor
        # BLEND: its radius terms (the near anchor unclamped)
        if cfg.centre.estimator is CentreEstimator.BLEND:
            w = cfg.centre.near_weight
            k_along, k_z = (
                (1 - w) * cfg.centre.range_factor + w * cfg.centre.near_range_factor,
                cfg.centre.ring_radius_factor,
            )
        moved = est + dR * np.array([k_along * f[0], k_along * f[1], -k_z])
        oracle = float(np.linalg.norm(moved - true))
    return (
        float(r_true),
        float(rng),
        float(np.linalg.norm(e)),
        float(np.linalg.norm(e[:2])),
        along,
        lat,
        float(e[2]),
        float(r_est / r_true),
        oracle,
    )


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
            "n": int(len(m)),
            "median_m": float(np.median(m[:, 2])),
            "p90_m": float(np.percentile(m[:, 2], 90)),
            "xy_median_m": float(np.median(m[:, 3])),
            "along_median_m": float(np.median(m[:, 4])),
            "lateral_abs_median_m": float(np.median(np.abs(m[:, 5]))),
            "vertical_median_m": float(np.median(m[:, 6])),
            "radius_ratio_median": float(np.median(m[:, 7])),
            "true_radius_oracle_median_m": float(np.median(m[:, 8]))
            if np.isfinite(m[:, 8]).all()
            else None,
        }
    return out


def lander_xy(ar) -> np.ndarray:
    """The lander's centre in the map frame: ``LacArchive.lander_pose_map()`` where the
    archive reader has it (initial.toml ``lander`` is rover-relative in the LAC), else
    initial.toml ``lander`` as this branch's simulator writes it (map frame)."""
    f = getattr(ar, "lander_pose_map", None)
    pose = f() if callable(f) else ar.initial["lander"]
    return np.asarray([float(v) for v in pose[:2]])


def run_archive(
    path: Path,
    cfg: DetectorConfig,
    every: int,
    acc: Accumulator,
    detector: Detector | None = None,
    progress: Callable[[str], None] | None = None,
) -> Detector:
    """Accumulate one archive's metrics. The camera (image size, field of view) is read
    from the archive and `cfg`'s pixel-sized parameters (tuned at 1280 px) are scaled
    to its width; `detector` is reused when it was built for the same camera. `progress`
    is told the archive's image size and field of view. Returns the detector used."""
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.detector import mounts_from_archive_row
    from lunarloc.config.run import scaled_detector_config
    from lunarloc.perception.camera import camera_from_archive

    with LacArchive(path) as ar:
        t = ar.custom("rocks")
        rocks = np.column_stack([t["id"], t["x"], t["y"], t["z"], t["radius"]])
        frames = [
            int(f)
            for f in ar.frame_numbers
            if ar.camera_row(STEREO_PAIRS[0][0], int(f)) is not None
        ][::every]
        cam = camera_from_archive(ar)
        det = detector if detector is not None and detector.camera == cam else None
        if det is None:
            det = Detector(scaled_detector_config(cam.width, base=cfg), cam)
        if progress is not None:
            progress(f"{path}: {cam.width}x{cam.height} px, hfov {cam.hfov_deg:g} deg")
        lander_xy_map = lander_xy(ar)  # known to a LAC agent: detections on the lander are dropped
        acc.begin_archive(path.name)
        for fd in detect_archive(
            ar,
            det.config,
            "ground-truth",
            detector=det,
            frames=frames,
            lander_xy=lander_xy_map,
            keep_depth=acc.misses is not None,
        ):
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


def pair_speed(path: Path, repeats: int = 5, cfg: DetectorConfig | None = None) -> dict:
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
    return {
        "pair_wall_ms": 1000 * wall,
        "pair_cpu_ms": 1000 * cpu,
        "pairs_per_s_wall": 1 / wall,
        "pairs_per_s_cpu": 1 / cpu,
    }


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
        out.append(
            dict(
                archive=archive,
                rock_id=rock_id,
                radius_m=float(g[0]["radius_m"]),
                missed=len(g),
                range_min_m=min(rng),
                range_max_m=max(rng),
                stages=Counter(r["stage"] for r in g).most_common(),
            )
        )
    return sorted(out, key=lambda d: (-d["missed"], d["archive"], str(d["rock_id"])))
