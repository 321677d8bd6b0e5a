"""Where the detector loses rocks of 0.025-0.05 m within 3 m (the small-rock band of issue 29):
every sighting of such a rock in the archives' left images (at least 50 pixels), hit or missed,
and for a missed one the stage that lost it.

    python benchmarks/tiny_misses.py ARCHIVE.lac ... [--config RUN.json] [--every 2]

The detector runs as ``sim_heldout.py`` runs it (``perception_eval.run_archive``: ground-truth
poses, cross-frame confirmation, the lander dropped). A missed sighting's stage is
``perception_eval.miss_stage``'s (the mask overlapping the rock most: a height-map blob's or a
small-rock candidate's reject reason, e.g. ``tentative``, ``unconfirmed``, ``flat``,
``not_a_rock``, or ``kept`` when the detection overlapping it lies beyond the match tolerance);
with no mask on it, the small-rock stage's candidates of that pair tell why (recomputed beside
the detector's own, which they do not change):

* ``cand-excluded``: a candidate on the rock, centred on a height-map blob;
* ``cand-precheck``: a candidate on the rock whose height-map neighbourhood stands nowhere
  ``min_lowres_height_m`` high (no window);
* ``cand-nowindow``: a candidate that got no window (too few valid points);
* ``beyond-budget``: no candidate within the limits, one with 400 + 200 candidates;
* ``low-contrast``: only with contrast 1.5 and 400 + 200 candidates (only when the
  configuration's contrast is higher);
* ``no-cand``: not even then.

Prints the run's precision and band counts, the stages' counts and the same per archive.
Needs the archives' semantic images (simulated sites).
"""

from __future__ import annotations

import argparse
import dataclasses
from collections import Counter
from pathlib import Path

import numpy as np

import lunarloc.perception.detector as D
import lunarloc.perception.small_rocks as SR
from lunarloc.pipeline import perception_eval as pe

_STORE: dict = {}
_CUR: dict = {}


def _key(T) -> tuple | None:
    return None if T is None else tuple(np.round(np.asarray(T)[:3, 3], 5))


def _instrument() -> None:
    """Keep, per pair (keyed by its map pose), the stage's exclusion, heights and candidates."""
    detect_pair, detect_small_rocks = D.Detector.detect_pair, D.detect_small_rocks

    def pair(self, left, right, T_rover_optical, T_map_rover=None, *args, **kw):
        _CUR["key"] = _key(T_map_rover)
        return detect_pair(self, left, right, T_rover_optical, T_map_rover, *args, **kw)

    def stage(left, right, disp, scale, camera, baseline_m, cfg, up, exclude, *args, **kw):
        out = detect_small_rocks(
            left, right, disp, scale, camera, baseline_m, cfg, up, exclude, *args, **kw
        )
        info = {"exclude": exclude.copy(), "hl": kw.get("height_lowres"), "scale": scale}
        many = dataclasses.replace(cfg, max_candidates=400, max_dark_candidates=200)
        low = dataclasses.replace(many, contrast_z=1.5, dark_contrast_z=1.5)
        for name, c in (("def", cfg), ("big", many), ("low", low)):
            info[name] = SR._candidates(left, disp, scale, camera.fx, baseline_m, c)
        _STORE[_CUR.get("key")] = info
        return out

    D.Detector.detect_pair = pair
    D.detect_small_rocks = stage


def _why_no_mask(info: dict, rock: np.ndarray, min_height_m: float) -> str:
    H, W = rock.shape

    def on_rock(cands):
        out = []
        for u0, v0, crop, *_ in cands:
            h, w = crop.shape
            if (rock[v0 : v0 + h, u0 : u0 + w] & crop).any():
                out.append((u0, v0, crop))
        return out

    hits = on_rock(info["def"])
    if hits:
        ex = [
            info["exclude"][min(v0 + c.shape[0] // 2, H - 1), min(u0 + c.shape[1] // 2, W - 1)]
            for u0, v0, c in hits
        ]
        if all(ex):
            return "cand-excluded"
        u0, v0, c = hits[ex.index(False)]
        hl, k = info["hl"], info["scale"]
        if hl is not None:
            bh, bw = c.shape
            hh = hl[
                max(v0 // k - 1, 0) : (v0 + bh) // k + 2, max(u0 // k - 1, 0) : (u0 + bw) // k + 2
            ]
            if not np.any(hh >= min_height_m):
                return "cand-precheck"
        return "cand-nowindow"
    if on_rock(info["big"]):
        return "beyond-budget"
    if on_rock(info["low"]):
        return "low-contrast"
    return "no-cand"


class _Acc(pe.Accumulator):
    def __init__(self, min_height_m: float) -> None:
        super().__init__()
        self.rows: list[dict] = []
        self.misses = []  # asks run_archive for the height maps (keep_depth)
        self.min_height_m = min_height_m

    def add_frame(self, fd, semantics, rocks, detector, mounts) -> None:
        super().add_frame(fd, semantics, rocks, detector, mounts)
        ids, centres, radii = rocks[:, 0].astype(int), rocks[:, 1:4], rocks[:, 4]
        index = {int(i): k for k, i in enumerate(ids)}
        det_xyz = np.array([d.p_map for d in fd.detections]).reshape(-1, 3)
        matched = {j for _, j, _ in pe.match(det_xyz, centres, radii)}
        info = _STORE.get(_key(fd.T_map_rover))
        for pair in fd.pairs:
            sem = semantics.get(pair.camera)
            if sem is None:
                continue
            rid = pe._rock_ids(sem)
            cam = (fd.T_map_rover @ mounts[pair.camera].T_rover_optical)[:3, 3]
            vis, cnt = np.unique(rid[rid >= 0], return_counts=True)
            for r, c in zip(vis.tolist(), cnt.tolist()):
                if c < self.min_gt_px or r not in index:
                    continue
                j = index[r]
                rng = float(np.linalg.norm(centres[j] - cam))
                if not (0.025 <= radii[j] < 0.05 and rng <= 3.0):
                    continue
                stage = "hit"
                if j not in matched:
                    stage = pe.miss_stage(pair, rid == r)["stage"]
                    if stage == "no-blob" and info is not None:
                        stage = _why_no_mask(info, rid == r, self.min_height_m)
                self.rows.append({"archive": self.archive, "stage": stage})


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("archives", nargs="+", type=Path)
    ap.add_argument(
        "--config", type=Path, default=None, help="a run configuration: its detector section"
    )
    ap.add_argument("--every", type=int, default=2, help="use every N-th camera frame")
    a = ap.parse_args(argv)
    cfg = D.DetectorConfig()
    if a.config is not None:
        from lunarloc.config.run import load_config_file

        cfg = load_config_file(a.config)[0].detector
    _instrument()
    acc = _Acc(cfg.small_rocks.min_lowres_height_m)
    det = None
    for p in a.archives:
        det = pe.run_archive(p, cfg, a.every, acc, det)
    s = acc.summary()
    keys = (
        "precision_counts_range<=5",
        "target_recall_counts",
        "recall_0.05<=r<0.1_range<=3_counts",
        "recall_0.025<=r<0.05_range<=3_counts",
        "small_rock_stage_precision_counts_range<=5",
    )
    print({k: s[k] for k in keys})
    print(f"sightings {len(acc.rows)}:", Counter(r["stage"] for r in acc.rows).most_common())
    for name in sorted({r["archive"] for r in acc.rows}):
        rows = [r for r in acc.rows if r["archive"] == name]
        print(f"{name} {len(rows)}:", Counter(r["stage"] for r in rows).most_common())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
