"""Train the small-rock stage's learned judge (lunarloc.perception.small_rocks) on rendered
LAC-look sites.

Usage
-----
    # 1. render the training sites (LAC look, as sim_heldout.py renders them), sunlit and
    #    lamp-lit (one site: about 30 s CPU)
    python benchmarks/sim_heldout.py --seeds 430 431 ... 443 --render-only --out-dir TRAIN
    python benchmarks/sim_heldout.py --seeds 530 531 ... 539 --lighting lamps --render-only \
        --out-dir TRAIN
    # 2. the stage's candidates of every archive, with features and labels (cached in --cache)
    python benchmarks/train_small_rocks.py extract TRAIN/*.lac --cache CACHE
    #    (--opt-in: the candidates of the opt-in settings too, OPT_IN; see "Opt-in candidates")
    # 3. fit and write the model (the packaged one: src/lunarloc/perception/small_rock_judge.npz)
    python benchmarks/train_small_rocks.py fit CACHE/site4*.npz CACHE/site5*.npz [--hidden 16] \
        [--out MODEL.npz]
    # offline check on other sites' candidates: rocks kept and terrain kept as the score rises,
    # against the hand verdict (the stage's defaults without the judge)
    python benchmarks/train_small_rocks.py check CACHE/site30*.npz [--model MODEL.npz]

Data recipe
-----------
Training sites: those of ``train_verifier.py``'s data recipe (430-443 and lamp-lit 530-539).

Candidates: the detector with its learned models off (``train_verifier.models_off``), the judge's floors and candidate limits of
:data:`EXTRACT` (lower than any deployed setting, so that a deployed configuration's
candidates are a subset), on every frame with the ground-truth rover pose and the lander
dropped (as ``sim_heldout.py`` runs it), the judge replaced by one that passes everything
(so every candidate above the floors is measured). Each candidate that passes the floors
gives one row: :func:`~lunarloc.perception.small_rocks.judge_features`.

Labels, from the simulator's semantic image of the left camera: the rock ids under the
candidate's rock mask (the blob and its raised neighbours); a rock (1) when one rock covers at
least :data:`ROCK_SHARE` of the mask, terrain (0) when rocks cover less than
:data:`TERRAIN_SHARE` of it; the rest (a mask straddling a rock's edge) is left out of
training. The rock's radius and its range from the camera are kept for the offline check.

Model: features standardised and clipped to +-Z_CLIP (as the height-map verifier),
scikit-learn's MLPClassifier with one hidden layer (``--hidden``; 0 = logistic regression),
written as plain arrays (BlobVerifier.save, no pickle) and checked against scikit-learn's own
probabilities. The packaged one: ``fit CACHE/site4*.npz CACHE/site5*.npz`` with the defaults
(16 hidden units, ``--alpha`` 1e-3, random state 0, early stopping; scikit-learn 1.9.1): 5283
candidates (2941 rocks) of the 24 sites (3060 and 1899 of the sunlit ones); the refit
reproduces the file array for array. Its threshold (``judge_min_score`` 0.92) was chosen for
the sunlit-only judge on development sites 300-302 and the real pairs
(docs/perception-status.md, "Small rocks") and kept.

Opt-in candidates (``extract --opt-in``; not the packaged judge): the candidates of
:data:`OPT_IN` too (O.json of docs/perception-status.md: contrast 1.5, inside the height map's
rejected and tentative blobs, limits counting the checked candidates), so that O.json's
candidates are a subset of the training ones; the same sites, labels and fit: 9597 candidates
(4699 rocks) of the 24 sites, the refit reproducing its file array for array from the cache.
Better than the packaged judge on the simulated development sites in both lightings, it loses a
real rock and keeps one of O.json's two false detections on the real pairs, so it is not
packaged (docs/perception-status.md, "The judge retrained on the opt-in candidates").

Why the lamp-lit sites: the judge fitted on the sunlit 430-443 alone dropped true rocks at
night. Offline at 0.92 (an ad-hoc check, each half of 530-539 scored by a judge fitted on
430-443 and the other half): the sunlit-only judge kept 325 rock candidates of 530-539 (145
of 0.025-0.05 m within 3 m), the sunlit + lamp-lit ones 631 (176), terrain 3 and 2; on the
sunlit development candidates 300-302 rocks 197-204 against 189, terrain 3-5 against 4.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lunarloc.perception.small_rocks import JUDGE_FEATURES, JUDGE_PATH, load_judge
from lunarloc.perception.verifier import BlobVerifier

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_verifier import fit_model, models_off

#: The stage's settings while extracting (floors and limits under the deployed ones).
EXTRACT = dict(  # noqa: C408
    judge_min_score=0.5,
    judge_min_top_m=0.005,
    judge_min_snr=1.5,
    judge_dark_min_points=20,
    max_candidates=60,
    max_dark_candidates=30,
    min_lowres_height_m=0.005,
)
#: ... and with ``extract --opt-in``, the candidates of the opt-in settings too (O.json, docs/
#: perception-status.md: peaks down to contrast 1.5, inside the height map's rejected and
#: tentative blobs, the limits counting only the candidates that get a window).
OPT_IN = dict(  # noqa: C408
    contrast_z=1.5, inside_rejected=True, inside_tentative=True, count_checked=True
)
ROCK_SHARE = 0.3
TERRAIN_SHARE = 0.05


def _pass_all() -> BlobVerifier:
    n = len(JUDGE_FEATURES)
    return BlobVerifier(
        JUDGE_FEATURES, np.zeros(n), np.ones(n), (np.zeros((n, 1)),), (np.array([50.0]),)
    )


def extract(path: Path, cache: Path, opt_in: bool = False) -> Path:
    """Features and labels of every candidate above the floors of one archive (with `opt_in`,
    the candidates of :data:`OPT_IN` too)."""
    import lunarloc.perception.detector as detector_mod
    from lunarloc.config.run import scaled_detector_config
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.camera import STEREO_PAIRS, camera_from_archive
    from lunarloc.perception.detector import Detector, _detect_archive_frames
    from lunarloc.perception.small_rocks import detect_small_rocks
    from lunarloc.pipeline.perception_eval import lander_xy
    from lunarloc.sim.render import semantic_to_rock_id

    out = cache / f"{path.stem}.npz"
    if out.exists():
        return out
    t0 = time.process_time()
    seen: list = []
    judge = _pass_all()

    def wrapped(*a, **k):
        k["judge"] = judge
        r = detect_small_rocks(*a, **k)
        seen.extend(r)
        return r

    rows: dict[str, list] = {
        k: [] for k in ("X", "y", "radius_m", "range_m", "share", "frame", "rank")
    }
    orig = detector_mod.detect_small_rocks
    detector_mod.detect_small_rocks = wrapped
    try:
        with LacArchive(path) as ar:
            t = ar.custom("rocks")
            rid_to = {int(i): k for k, i in enumerate(t["id"])}
            centres = np.column_stack([t["x"], t["y"], t["z"]])
            radii = np.asarray(t["radius"], float)
            cam = camera_from_archive(ar)
            base = models_off()  # the candidates of the detector the judge was trained on
            extra = OPT_IN if opt_in else {}
            base = replace(base, small_rocks=replace(base.small_rocks, **EXTRACT, **extra))
            det = Detector(scaled_detector_config(cam.width, base=base), cam)
            left = STEREO_PAIRS[0][0]
            frames = [int(f) for f in ar.frame_numbers if ar.camera_row(left, int(f)) is not None]
            from lunarloc.perception.detector import mounts_from_archive_row

            for fd in _detect_archive_frames(
                ar, det, "ground-truth", frames, False, None, lander_xy(ar)
            ):
                rocks, seen[:] = list(seen), []
                rid = semantic_to_rock_id(ar.semantic(left, fd.frame))
                crow = {c: ar.camera_row(c, fd.frame) for c in ar.cameras}
                mounts = mounts_from_archive_row({k: v for k, v in crow.items() if v}, det.camera)
                cam_pos = (fd.T_map_rover @ mounts[left].T_rover_optical)[:3, 3]
                for r in rocks:
                    if r.features is None:
                        continue
                    h, w = r.crop.shape
                    ids = rid[r.v0 : r.v0 + h, r.u0 : r.u0 + w][r.crop]
                    on = ids[ids >= 0]
                    share_any = on.size / max(ids.size, 1)
                    rad, rng, share = np.nan, np.nan, 0.0
                    if on.size:
                        v, c = np.unique(on, return_counts=True)
                        top = int(v[np.argmax(c)])
                        share = c.max() / ids.size
                        if top in rid_to:
                            j = rid_to[top]
                            rad = radii[j]
                            rng = float(np.linalg.norm(centres[j] - cam_pos))
                    lab = 1 if share >= ROCK_SHARE else (0 if share_any < TERRAIN_SHARE else -1)
                    rows["X"].append(r.features)
                    rows["y"].append(lab)
                    rows["radius_m"].append(rad)
                    rows["range_m"].append(rng)
                    rows["share"].append(share)
                    rows["frame"].append(fd.frame)
                    rows["rank"].append(r.rank)
    finally:
        detector_mod.detect_small_rocks = orig
    cache.mkdir(parents=True, exist_ok=True)
    arr = {k: np.asarray(v) for k, v in rows.items()}
    arr["X"] = arr["X"].reshape(-1, len(JUDGE_FEATURES)).astype(float)
    np.savez_compressed(out, feature_names=np.array(JUDGE_FEATURES, dtype=str), **arr)
    y = arr["y"]
    print(
        f"{path.name}: {len(y)} candidates ({int((y == 1).sum())} rocks, "
        f"{int((y == 0).sum())} terrain), {time.process_time() - t0:.0f} s CPU",
        file=sys.stderr,
    )
    return out


def load(paths: list[Path]) -> dict[str, np.ndarray]:
    parts = [dict(np.load(p, allow_pickle=False)) for p in paths]
    for p, d in zip(paths, parts):
        if tuple(str(s) for s in d["feature_names"]) != JUDGE_FEATURES:
            raise SystemExit(f"{p}: features of another version; extract again")
    out = {k: np.concatenate([d[k] for d in parts]) for k in parts[0] if k != "feature_names"}
    out["site"] = np.concatenate([np.full(len(d["y"]), i) for i, d in enumerate(parts)])
    return out


def fit(paths: list[Path], out: Path, hidden: int = 16, alpha: float = 1e-3, seed: int = 0):
    d = load(paths)
    keep = d["y"] >= 0
    X, y = d["X"][keep], d["y"][keep]
    model = fit_model(X, y, JUDGE_FEATURES, hidden, alpha, seed, max_iter=1000)
    model.save(out)
    print(
        f"fitted on {len(y)} candidates of {len(paths)} sites ({int(y.sum())} rocks); "
        f"wrote {out} ({out.stat().st_size} bytes)"
    )
    return model


def hand_verdict(d: dict[str, np.ndarray]) -> np.ndarray:
    """Which rows the stage's defaults without the judge keep (its floors and limits, as far
    as the features tell them; ``min_median_snr`` is off by default)."""
    from lunarloc.perception.small_rocks import SmallRockConfig

    c = SmallRockConfig()
    f = {n: d["X"][:, i] for i, n in enumerate(JUDGE_FEATURES)}
    dark = f["dark"] > 0.5
    ok = (
        (f["top_m"] >= c.min_top_m)
        & (f["top_snr"] >= c.min_snr)
        & ((f["top_m"] >= c.confident_top_m) | (f["top_snr"] >= c.low_top_snr))
        & (f["lowres_height_m"] >= c.min_lowres_height_m)
        & (d["rank"] < np.where(dark, c.max_dark_candidates, c.max_candidates))
    )
    return ok & (
        ~dark | ((f["top_snr"] >= c.dark_min_snr) & (f["blob_points"] >= c.dark_min_points))
    )


def check(paths: list[Path], model: BlobVerifier) -> None:
    """Offline figures on other sites' candidates (not the benchmark's: every frame's candidate
    counted, the same rock in several frames each time): rocks of 0.025-0.05 m within 3 m kept,
    all rocks kept, terrain kept, as the threshold rises; the hand verdict first."""
    d = load(paths)
    s = model.score(d["X"])
    tiny = (d["y"] == 1) & (d["radius_m"] >= 0.025) & (d["radius_m"] < 0.05) & (d["range_m"] <= 3)

    def row(name, k):
        tp, fp = int((k & (d["y"] == 1)).sum()), int((k & (d["y"] == 0)).sum())
        amb = int((k & (d["y"] == -1)).sum())
        print(
            f"{name} | {int((k & tiny).sum())} | {tp} | {fp} | {amb} | {tp / max(tp + fp, 1):.3f}"
        )

    print("keep | tiny rocks (<=3 m) | rocks | terrain | edge | rocks/(rocks+terrain)")
    row("hand verdict", hand_verdict(d))
    for th in (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.92, 0.95):
        row(f"score >= {th:.2f}", s >= th)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("mode", choices=("extract", "fit", "check"))
    ap.add_argument("paths", type=Path, nargs="+")
    ap.add_argument("--cache", type=Path, default=Path("bench-output/small-rock-cache"))
    ap.add_argument("--out", type=Path, default=JUDGE_PATH)
    ap.add_argument("--model", type=Path, default=JUDGE_PATH)
    ap.add_argument(
        "--opt-in", action="store_true", help="extract: the opt-in settings' candidates too"
    )
    ap.add_argument("--hidden", type=int, default=16, help="hidden units (0: logistic)")
    ap.add_argument("--alpha", type=float, default=1e-3, help="L2 penalty (1 / C for logistic)")
    a = ap.parse_args(argv)
    if a.mode == "extract":
        for p in a.paths:
            extract(p, a.cache, a.opt_in)
    elif a.mode == "fit":
        fit(a.paths, a.out, a.hidden, a.alpha)
    else:
        check(a.paths, load_judge(a.model))
    return 0


if __name__ == "__main__":
    sys.exit(main())
