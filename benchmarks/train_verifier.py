"""Train the learned blob verifier (lunarloc.perception.verifier) on rendered LAC-look sites.

Usage
-----
    # 1. render the training sites (LAC look, as sim_heldout.py renders them), sunlit and
    #    lamp-lit (one site: about 30 s CPU)
    python benchmarks/sim_heldout.py --seeds 430 431 ... 443 --render-only --out-dir TRAIN
    python benchmarks/sim_heldout.py --seeds 530 531 ... 539 --lighting lamps --render-only \
        --out-dir TRAIN
    # 2. the blobs of every archive, with features and labels (cached beside --cache)
    python benchmarks/train_verifier.py extract TRAIN/*.lac --cache CACHE
    # 3. fit and write the model (the packaged one: src/lunarloc/perception/verifier_model.npz)
    python benchmarks/train_verifier.py fit CACHE/site4*.npz CACHE/site5*.npz --firm-only \
        [--out MODEL.npz]
    # offline check on other sites' blobs: precision / recall as the score threshold rises
    python benchmarks/train_verifier.py check CACHE/site30*.npz [--model MODEL.npz]

Data recipe
-----------
Training sites: seeds 430-443 (``sun+lamps``) and 530-539 (``--lighting lamps``: the rover's
lamps alone, a night site), ``SiteConfig.lac_style()`` and ``RenderConfig.lac_style()``,
sun elevation ``(6, 12, 20)[seed % 3]`` degrees and azimuth ``(97 * seed) % 360`` degrees
(ignored by the renderer at night), 60 s of the random plan at 0.5 Hz, front stereo pair at
1280x720 (``sim_heldout.py``'s ``render``). None of them is a development (300-304) or
scoring site (400-403, 410-413, 420-423, 460-463, 468-471, 480-487, 540-547).

Blobs: the default detector with the small-rock stage and the verifier off, on every frame
with the ground-truth rover pose and the lander dropped, tentative detections kept (the
verifier judges blobs before cross-frame confirmation), as ``detect_archive`` runs it. Each kept
height-map blob gives one row: :func:`~lunarloc.perception.verifier.blob_features` of
the detection, its mask and the left image.

Labels, from the simulator's truth (``custom/rocks.csv``), matched per frame as
``bench_perception.py`` matches (one to one, greedy by distance, a detection within
max(0.15 m, rock radius) of a rock's centre): a matched detection is a rock (1); an
unmatched one farther than that tolerance + 0.1 m from every rock is terrain (0); the rest
(parts of rocks, duplicates beside one) are left out of training.

Model (the packaged one): the firm blobs only (the detector judges only those; a tentative
one is judged by a neighbouring frame), features standardised and clipped to +-Z_CLIP,
scikit-learn's LogisticRegression (C = 1 / 0.3), rocks of radius >= 0.1 m weighted 2 (the
recall the targets name): 2203 blobs (1694 rocks) of the 24 sites (1277 and 1001 of the
sunlit ones). ``--hidden N`` fits an MLPClassifier with one hidden layer instead (tried on
300-304: no better; on the lamp-lit sites, below, no better either). Written as plain arrays
(BlobVerifier.save), checked against scikit-learn's own probabilities.

Why the lamp-lit sites: the model fitted on the sunlit 430-443 alone dropped true rocks at
night. Offline (firm blobs at 0.7, tentative at 0.5, within 5 m; an ad-hoc check, each half of
530-539 scored by a model fitted on 430-443 and the other half): the sunlit-only model kept
742 of 1110 rock blobs of 530-539 (205/254 of r >= 0.1 m), the sunlit + lamp-lit ones 878
(228/254); terrain kept 79 against 145 of 1661. On the sunlit development blobs 300-304 the
same models kept 116-144 terrain blobs of 700 against 94 (rocks 573-583 of 651 against 574):
one logistic model for both lightings is less strict in sunlight; an 8- or 16-unit hidden
layer did not separate the two better.

The blobs were extracted with the detector's models off (:func:`models_off`: the height-saddle
split off too). More data did not make a better model: 23 sites (430-452), extracted with the
split on (``extract --config`` with ``{"detector": {"classical": {"height_split_step_m":
0.01}}}``; 6069 blobs, 2094 firm), fitted firm-only or on firm and tentative blobs, logistic
or a 8-/16-unit MLP, was no better on development sites 300-304 at the detector's
thresholds (0.7 firm, 0.5 tentative and large): precision 0.926-0.939 against 0.932, and
103-105 sightings of r >= 0.1 m within 5 m against 107 of 142; so the sunlit model stayed
then (the 14 sunlit sites of the packaged model are 430-443).

The low-ground model (``verifier_model_low_ground.npz``, ``rules.verifier_model``
"low_ground", opt-in with ``ground.quantile`` 0.4): the same 24 sites and recipe, blobs
extracted on the lower ground, rocks of r >= 0.1 m weighted 4 (``--big-weight 4``; 2631 firm
blobs, 1939 rocks)::

    echo '{"detector": {"ground": {"quantile": 0.4}, "classical": {"height_split_step_m": 0},
           "rules": {"verifier_min_score": 0}, "small_rocks": {"judge_min_score": 0}}}' > Q40off.json
    python benchmarks/train_verifier.py extract TRAIN/*.lac --cache CACHE40 --config Q40off.json
    python benchmarks/train_verifier.py fit CACHE40/site4*.npz CACHE40/site5*.npz --firm-only \
        --big-weight 4 --out src/lunarloc/perception/verifier_model_low_ground.npz
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lunarloc.perception.verifier import (
    FEATURE_NAMES,
    MODEL_PATH,
    Z_CLIP,
    BlobVerifier,
    blob_features,
)


def models_off(base=None):
    """`base` (default: DetectorConfig()) with the learned models off: the blob verifier, its
    height-saddle split and the small-rock judge, the detector whose blobs and candidates the
    packaged models were trained on (their defaults are on)."""
    from lunarloc.perception.detector import DetectorConfig

    base = base or DetectorConfig()
    return replace(
        base,
        classical=replace(base.classical, height_split_step_m=0.0),
        rules=replace(base.rules, verifier_min_score=0.0),
        small_rocks=replace(base.small_rocks, judge_min_score=0.0),
    )


def extract(path: Path, cache: Path, base=None) -> Path:
    """Features and labels of every kept height-map blob of one archive -> cache/<stem>.npz.
    `base`: the DetectorConfig to run (default: :func:`models_off` of the defaults, the split
    off); the small-rock stage and the verifier are turned off in it."""
    from lunarloc.config.run import scaled_detector_config
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.camera import camera_from_archive
    from lunarloc.perception.detector import Detector, _detect_archive_frames
    from lunarloc.pipeline.perception_eval import lander_xy, match

    out = cache / f"{path.stem}.npz"
    if out.exists():
        return out
    t0 = time.process_time()
    X, y, depth, rock_r, frame, tent = [], [], [], [], [], []
    with LacArchive(path) as ar:
        t = ar.custom("rocks")
        centres = np.column_stack([t["x"], t["y"], t["z"]])
        radii = np.asarray(t["radius"], float)
        cam = camera_from_archive(ar)
        base = base or models_off()  # the height map's blobs: small-rock stage, verifier off
        base = replace(
            base,
            small_rocks=replace(base.small_rocks, enabled=False),
            rules=replace(base.rules, verifier_min_score=0.0),
        )
        det = Detector(scaled_detector_config(cam.width, base=base), cam)
        for fd in _detect_archive_frames(ar, det, "ground-truth", None, False, None, lander_xy(ar)):
            rows = []
            for pair in fd.pairs:
                kept = [r for r in pair.records if r.reason is None]
                assert len(kept) == len(pair.detections)
                L = fd_left(ar, pair.camera, fd.frame)
                for r, d in zip(kept, pair.detections):
                    if d.small_rock:
                        continue
                    rows.append((d, blob_features(d, L, pair.masks[r.mask_index])))
            if not rows:
                continue
            P = np.array([d.p_map for d, _ in rows])
            m = {i: j for i, j, _ in match(P, centres, radii)}
            dist = np.linalg.norm(P[:, None] - centres[None], axis=2) - np.maximum(0.15, radii)
            for k, (d, x) in enumerate(rows):
                X.append(x)
                if k in m:
                    y.append(1)
                    rock_r.append(radii[m[k]])
                else:
                    y.append(0 if dist[k].min() > 0.1 else -1)
                    rock_r.append(np.nan)
                depth.append(d.depth_m)
                frame.append(fd.frame)
                tent.append(bool(d.tentative))
    cache.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out,
        X=np.array(X, float).reshape(-1, len(FEATURE_NAMES)),
        y=np.array(y, int),
        depth_m=np.array(depth),
        rock_radius_m=np.array(rock_r),
        frame=np.array(frame),
        tentative=np.array(tent),
        feature_names=np.array(FEATURE_NAMES, dtype=str),
    )
    print(
        f"{path.name}: {len(y)} blobs ({sum(v == 1 for v in y)} rocks, "
        f"{sum(v == 0 for v in y)} terrain), {time.process_time() - t0:.0f} s CPU",
        file=sys.stderr,
    )
    return out


def fd_left(ar, camera: str, frame: int) -> np.ndarray:
    from lunarloc.perception.stereo import to_gray_u8

    return to_gray_u8(ar.grayscale(camera, frame))


def load(paths: list[Path]) -> dict[str, np.ndarray]:
    parts = [dict(np.load(p, allow_pickle=False)) for p in paths]
    for p, d in zip(paths, parts):
        if tuple(str(s) for s in d["feature_names"]) != FEATURE_NAMES:
            raise SystemExit(f"{p}: features of another version; extract again")
    out = {k: np.concatenate([d[k] for d in parts]) for k in parts[0] if k != "feature_names"}
    out["site"] = np.concatenate([np.full(len(d["y"]), i) for i, d in enumerate(parts)])
    return out


def fit_model(
    X: np.ndarray,
    y: np.ndarray,
    feature_names: tuple[str, ...],
    hidden: int,
    alpha: float,
    seed: int,
    max_iter: int,
    weight: np.ndarray | None = None,
) -> BlobVerifier:
    """A BlobVerifier fitted to rows `X` and labels `y`: features standardised and clipped to
    +-Z_CLIP, then scikit-learn's MLPClassifier with one hidden layer of `hidden` units (L2
    `alpha`) or, with `hidden` 0, its LogisticRegression (C = 1 / alpha); `weight` (integer
    row weights; the MLP takes none, so its rows are repeated). Checked against
    scikit-learn's own probabilities."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.neural_network import MLPClassifier

    mean = X.mean(axis=0)
    scale = X.std(axis=0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    Z = np.clip((X - mean) / scale, -Z_CLIP, Z_CLIP)
    if hidden > 0:
        clf = MLPClassifier(
            hidden_layer_sizes=(hidden,),
            alpha=alpha,
            max_iter=max_iter,
            early_stopping=True,
            random_state=seed,
        )
        if weight is None:
            clf.fit(Z, y)
        else:
            rep = np.repeat(np.arange(len(y)), weight.astype(int))
            clf.fit(Z[rep], y[rep])
        Ws = tuple(np.asarray(c, float) for c in clf.coefs_)
        bs = tuple(np.asarray(b, float) for b in clf.intercepts_)
    else:  # logistic regression (C = 1 / alpha): one layer, no hidden units
        clf = LogisticRegression(C=1.0 / alpha, max_iter=5000)
        clf.fit(Z, y, sample_weight=weight)
        Ws, bs = (np.asarray(clf.coef_, float).T,), (np.asarray(clf.intercept_, float),)
    model = BlobVerifier(tuple(feature_names), mean, scale, Ws, bs)
    p_sk = clf.predict_proba(Z)[:, 1]
    assert np.allclose(p_sk, model.score(X), atol=1e-4), "numpy inference differs from sklearn"
    return model


def fit(
    paths: list[Path],
    out: Path,
    hidden: int = 0,
    alpha: float = 0.3,
    firm_only: bool = False,
    seed: int = 0,
    big_weight: float = 2.0,
):
    d = load(paths)
    keep = d["y"] >= 0
    if firm_only:
        keep &= ~d["tentative"]
    X, y = d["X"][keep], d["y"][keep]
    w = np.where((y == 1) & (d["rock_radius_m"][keep] >= 0.1), big_weight, 1.0)
    model = fit_model(X, y, FEATURE_NAMES, hidden, alpha, seed, max_iter=500, weight=w)
    model.save(out)
    print(
        f"fitted on {len(y)} blobs of {len(paths)} sites ({int(y.sum())} rocks); "
        f"wrote {out} ({out.stat().st_size} bytes)"
    )
    return model


def check(paths: list[Path], model: BlobVerifier) -> None:
    """Offline figures on other sites' blobs (before cross-frame confirmation, so not the
    benchmark's): kept rocks and terrain within 5 m as the threshold rises."""
    d = load(paths)
    s = model.score(d["X"])
    near = d["depth_m"] < 5.0
    big = near & (d["y"] == 1) & (d["rock_radius_m"] >= 0.1)
    print("threshold | rocks kept (<5 m) | r>=0.1 kept | terrain kept | P(<5m, firm+tentative)")
    for th in (0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5):
        k = s >= th
        tp = int((k & near & (d["y"] == 1)).sum())
        fp = int((k & near & (d["y"] == 0)).sum())
        amb = int((k & near & (d["y"] == -1)).sum())
        print(
            f"{th:4.2f} | {tp} | {int((k & big).sum())}/{int(big.sum())} | {fp} | "
            f"{tp / max(tp + fp + amb, 1):.3f}"
        )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("mode", choices=("extract", "fit", "check"))
    ap.add_argument("paths", type=Path, nargs="+")
    ap.add_argument("--cache", type=Path, default=Path("bench-output/verifier-cache"))
    ap.add_argument("--out", type=Path, default=MODEL_PATH)
    ap.add_argument("--model", type=Path, default=MODEL_PATH)
    ap.add_argument("--hidden", type=int, default=0, help="hidden units (0: logistic regression)")
    ap.add_argument("--alpha", type=float, default=0.3, help="L2 penalty (1 / C for logistic)")
    ap.add_argument("--firm-only", action="store_true", help="fit on firm blobs only")
    ap.add_argument(
        "--big-weight", type=float, default=2.0, help="fit: weight of rocks of r >= 0.1 m"
    )
    ap.add_argument("--config", type=Path, default=None, help="extract: a run config's detector")
    a = ap.parse_args(argv)
    if a.mode == "extract":
        base = None
        if a.config is not None:
            from lunarloc.config.run import load_config_file

            base = load_config_file(a.config)[0].detector
        for p in a.paths:
            extract(p, a.cache, base)
    elif a.mode == "fit":
        fit(a.paths, a.out, a.hidden, a.alpha, a.firm_only, big_weight=a.big_weight)
    else:
        check(a.paths, BlobVerifier.load(a.model))
    return 0


if __name__ == "__main__":
    sys.exit(main())
