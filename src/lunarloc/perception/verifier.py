"""A learned check of the height-map detector's blobs: is this candidate a rock?

The height-map detector's false positives on LAC-look terrain are crests and hummocks at
2.5-5 m that pass every hand-made rule (docs/perception-status.md, "Where it fails"). The
verifier scores each blob that the rules keep from a feature vector (:func:`blob_features`):

* the geometric measures the rules already computed (its depth, radius, heights above the
  local ground, the ring, the quadric ground and the ground in front, the share of nearer
  surface around it, its lateral extension, its disparity roughness, its size and
  elongation), each NaN as 0 with a flag;
* the appearance of the left image around it: grey-level statistics of the mask and of the
  ring of ground around it (lit face, shaded side, shadow: contrast against the ring's
  spread), the image gradient over the mask, its outline and the ring, the spread of the
  gradient's orientations, and a small normalised grey patch around it (4 x 4).

A small model (logistic regression; the format admits ReLU hidden layers), trained with
scikit-learn by ``benchmarks/train_verifier.py`` on blobs of rendered LAC-look sites labelled
by the simulator's truth, maps the standardised features to P(rock). The model ships as plain
arrays (``verifier_model.npz`` beside this module: feature means and scales, the layers'
weights; no pickle) and runs with numpy (:class:`BlobVerifier`). The detector rejects a blob
scoring under a threshold that depends on the blob (:func:`verifier_threshold`:
``DetectorConfig.rules.verifier_min_score`` for a firm blob of estimated radius under
``rules.verifier_max_radius_m``, ``verifier_tentative_min_score`` for a tentative one,
``verifier_large_min_score`` for a larger one; ``verifier_min_score`` 0.7 by default, 0 turns
the verifier off).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from lunarloc.core.errors import InputError, import_cv2
from lunarloc.perception.images import gradient_magnitude
from lunarloc.perception.masks import InstanceMask

__all__ = [
    "APPEARANCE_FEATURES",
    "FEATURE_NAMES",
    "GEOMETRIC_FIELDS",
    "MODEL_PATH",
    "PACKAGED_MODELS",
    "Z_CLIP",
    "BlobVerifier",
    "appearance_features",
    "blob_features",
    "default_verifier",
    "verifier_named",
    "verifier_threshold",
]

#: The packaged model.
MODEL_PATH = Path(__file__).with_name("verifier_model.npz")

#: Detection attributes that may be NaN (read as 0, with a flag feature each).
_NAN_FLAGGED = (
    "height_front_m",
    "height_ring_m",
    "height_quadric_m",
    "nearer_ring_fraction",
    "extension_ratio",
    "disparity_roughness",
)
#: Detection attributes read as geometric features, in the model's order.
GEOMETRIC_FIELDS: tuple[str, ...] = (
    "depth_m",
    "radius_m",
    "size_m",
    "eig_ratio",
    "height_m",
) + _NAN_FLAGGED
#: Standardised features are clipped to +-Z_CLIP before the model sees them (in training too):
#: a measure far outside the training sites' range (a real frame's) cannot swing the score.
Z_CLIP = 4.0
_PATCH = 4  # the grey patch's side (cells)
_N_ORIENT = 8  # gradient orientation bins

_APPEARANCE = (
    "tentative",
    "top_per_radius",
    "quadric_per_radius",
    "top_above_ring_m",
    "mask_contrast",  # (mask mean - ring mean) / ring spread
    "mask_spread",  # mask's p95 - p5 over the ring's spread
    "mask_bright",  # mask's p95 - ring's p50, over the ring's spread
    "mask_dark",  # ring's p50 - mask's p5, over the ring's spread
    "ring_dark_fraction",  # share of the ring darker than its median by 3 spreads (a shadow)
    "ring_spread_grey",  # the ring's spread (grey levels)
    "mask_grad_p50",
    "mask_grad_p95",
    "outline_grad",  # mean gradient along the mask's outline
    "ring_grad_p50",
    "outline_over_ring_grad",
    "orient_peak",  # the strongest orientation bin's share of the gradient
    "orient_entropy",  # entropy of the orientation histogram (nats)
)
#: The feature vector's names, in order.
FEATURE_NAMES: tuple[str, ...] = (
    GEOMETRIC_FIELDS
    + tuple(f"{f}_nan" for f in _NAN_FLAGGED)
    + _APPEARANCE
    + tuple(f"patch_{i}" for i in range(_PATCH * _PATCH))
)
#: The names of :func:`appearance_features`, the image-only tail of FEATURE_NAMES.
APPEARANCE_FEATURES: tuple[str, ...] = FEATURE_NAMES[FEATURE_NAMES.index("mask_contrast") :]


def _q(a: np.ndarray, q: float) -> float:
    """Quantile `q` of the sorted 1-D array `a` (linear between ranks, as np.quantile)."""
    v = (a.size - 1) * q
    lo = int(v)
    hi = min(lo + 1, a.size - 1)
    return float(a[lo] + (a[hi] - a[lo]) * (v - lo))


def _finite(x: float) -> float:
    return float(x) if math.isfinite(x) else 0.0


def blob_features(det, image: np.ndarray, mask: InstanceMask) -> np.ndarray:
    """The feature vector (float64, len(FEATURE_NAMES)) of one blob: `det` carries the
    geometric measures (any object with the attributes GEOMETRIC_FIELDS and ``tentative``,
    e.g. a Detection), `image` is the left grey image (H, W; uint8) and `mask` the blob's
    mask in it."""
    img, crop = _checked(image, mask)
    g = [float(getattr(det, f)) for f in GEOMETRIC_FIELDS]
    geo = dict(zip(GEOMETRIC_FIELDS, g))
    out = [_finite(v) for v in g]
    out += [0.0 if math.isfinite(geo[f]) else 1.0 for f in _NAN_FLAGGED]
    R = max(_finite(geo["radius_m"]), 1e-3)
    top = _finite(geo["height_m"])
    out += [
        1.0 if getattr(det, "tentative", "") else 0.0,
        top / R,
        _finite(geo["height_quadric_m"]) / R,
        top - _finite(geo["height_ring_m"]),
    ]
    x = np.asarray(out + _appearance(img, crop, mask), float)
    return np.where(np.isfinite(x), x, 0.0)


def appearance_features(image: np.ndarray, mask: InstanceMask) -> np.ndarray:
    """The image-only part of :func:`blob_features` (APPEARANCE_FEATURES: grey statistics of
    the mask and its ring, gradients, orientation spread, the grey patch) of the left grey
    image (H, W; uint8) around `mask`."""
    img, crop = _checked(image, mask)
    x = np.asarray(_appearance(img, crop, mask), float)
    return np.where(np.isfinite(x), x, 0.0)


def _checked(image: np.ndarray, mask: InstanceMask) -> tuple[np.ndarray, np.ndarray]:
    """The grey image and the mask's boolean crop, or InputError."""
    img = np.asarray(image)
    if img.ndim != 2:
        raise InputError(f"blob_features: expected a grey image (H, W), got {img.shape}")
    crop = np.asarray(mask.crop, bool)
    if not crop.any():
        raise InputError("blob_features: empty mask")
    return img, crop


def _appearance(img: np.ndarray, crop: np.ndarray, mask: InstanceMask) -> list[float]:
    """The appearance features (APPEARANCE_FEATURES) of the mask `crop` at (mask.u0, mask.v0)
    in the grey image `img`."""
    cv2 = import_cv2()
    # a window around the mask: the mask, a ring of ground about half its size wide
    H, W = img.shape
    h, w = crop.shape
    rim = max(3, round(0.5 * math.sqrt(crop.sum())))
    pad = rim + 2
    v0, v1 = max(mask.v0 - pad, 0), min(mask.v0 + h + pad, H)
    u0, u1 = max(mask.u0 - pad, 0), min(mask.u0 + w + pad, W)
    win = np.asarray(img[v0:v1, u0:u1], np.float32)
    sel = np.zeros(win.shape, np.uint8)
    sel[mask.v0 - v0 : mask.v0 - v0 + h, mask.u0 - u0 : mask.u0 - u0 + w] = crop
    grown = cv2.dilate(sel, np.ones((2 * rim + 1, 2 * rim + 1), np.uint8)) > 0
    inner = sel > 0
    ring = grown & ~inner
    outline = inner & ~(cv2.erode(sel, np.ones((3, 3), np.uint8)) > 0)
    m_px = np.sort(win[inner])
    r_px = np.sort(win[ring]) if ring.any() else m_px
    r50 = _q(r_px, 0.5)
    r_sp = (_q(r_px, 0.84) - _q(r_px, 0.16)) / 2 + 1.0
    m5, m95 = _q(m_px, 0.05), _q(m_px, 0.95)
    sm = cv2.GaussianBlur(win, (0, 0), 1.0)
    gx = cv2.Sobel(sm, cv2.CV_32F, 1, 0, ksize=3) * np.float32(0.125)
    gy = cv2.Sobel(sm, cv2.CV_32F, 0, 1, ksize=3) * np.float32(0.125)
    mag = gradient_magnitude(cv2, gx, gy)
    mg = np.sort(mag[inner])
    rg50 = _q(np.sort(mag[ring]), 0.5) if ring.any() else _q(mg, 0.5)
    og = float(mag[outline].mean()) if outline.any() else float(mg.mean())
    # orientation spread over mask and ring (modulo 180 degrees: a shading edge either way)
    ang = (np.arctan2(gy[grown], gx[grown]) % np.pi) / np.pi * _N_ORIENT
    hist = np.bincount(
        np.minimum(ang.astype(int), _N_ORIENT - 1), weights=mag[grown], minlength=_N_ORIENT
    )
    hist = hist / (hist.sum() + 1e-9)
    nz = hist[hist > 0]
    out = [
        (float(m_px.mean()) - float(r_px.mean())) / r_sp,
        (m95 - m5) / r_sp,
        (m95 - r50) / r_sp,
        (r50 - m5) / r_sp,
        float(np.searchsorted(r_px, r50 - 3 * r_sp)) / r_px.size,
        r_sp,
        _q(mg, 0.5),
        _q(mg, 0.95),
        og,
        rg50,
        og / (rg50 + 1.0),
        float(hist.max()),
        float(-(nz * np.log(nz)).sum()),
    ]
    # the grey patch: the window resampled, normalised by the ring's median and spread
    patch = cv2.resize(win, (_PATCH, _PATCH), interpolation=cv2.INTER_AREA)
    return out + list(((patch - r50) / r_sp).ravel().astype(float))


@dataclass(frozen=True)
class BlobVerifier:
    """A multilayer perceptron over standardised features (clipped to +-Z_CLIP): hidden layers
    with ReLU, one logistic output (no hidden layer: logistic regression). ``weights[k]`` is
    (n_in, n_out) and ``biases[k]`` (n_out,)."""

    feature_names: tuple[str, ...]
    mean: np.ndarray
    scale: np.ndarray
    weights: tuple[np.ndarray, ...]
    biases: tuple[np.ndarray, ...]

    def __post_init__(self) -> None:
        n = len(self.feature_names)
        if self.mean.shape != (n,) or self.scale.shape != (n,):
            raise InputError("verifier model: mean/scale do not match its feature names")
        if not self.weights or len(self.weights) != len(self.biases):
            raise InputError("verifier model: needs as many bias vectors as weight matrices")
        k = n
        for Wk, bk in zip(self.weights, self.biases):
            if Wk.ndim != 2 or Wk.shape[0] != k or bk.shape != (Wk.shape[1],):
                raise InputError("verifier model: layer shapes do not chain")
            k = Wk.shape[1]
        if k != 1:
            raise InputError("verifier model: the last layer must have one output")
        if not (np.all(np.isfinite(self.scale)) and np.all(self.scale > 0)):
            raise InputError("verifier model: feature scales must be finite and positive")

    def score(self, X: np.ndarray) -> np.ndarray:
        """P(rock) of each row of X (N, n_features), or of one vector (n_features,)."""
        X = np.asarray(X, float)
        one = X.ndim == 1
        X = np.atleast_2d(X)
        if X.ndim != 2 or X.shape[1] != len(self.feature_names):
            raise InputError(
                f"verifier: features of shape {X.shape} given, the model takes "
                f"{len(self.feature_names)} per row"
            )
        a = np.clip((X - self.mean) / self.scale, -Z_CLIP, Z_CLIP)
        for k, (Wk, bk) in enumerate(zip(self.weights, self.biases)):
            a = a @ Wk + bk
            if k < len(self.weights) - 1:
                a = np.maximum(a, 0.0)
        p = 1.0 / (1.0 + np.exp(-np.clip(a[:, 0], -50, 50)))
        return p[0] if one else p

    def save(self, path: Path) -> None:
        """Write the model as plain arrays (.npz, no pickle)."""
        arrays = {
            "feature_names": np.array(self.feature_names, dtype=str),
            "mean": self.mean,
            "scale": self.scale,
        }
        for k, (Wk, bk) in enumerate(zip(self.weights, self.biases)):
            arrays[f"W{k}"] = np.asarray(Wk, np.float32)
            arrays[f"b{k}"] = np.asarray(bk, np.float32)
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(
        cls,
        path: Path,
        feature_names: tuple[str, ...] = FEATURE_NAMES,
        what: str = "verifier model",
        trainer: str = "benchmarks/train_verifier.py",
    ) -> BlobVerifier:
        """Read a model written by :meth:`save` (checks its features are `feature_names`, this
        module's by default; `what` and `trainer` name the model and its script in errors)."""
        try:
            with np.load(Path(path), allow_pickle=False) as z:
                names = tuple(str(s) for s in z["feature_names"])
                n_layers = sum(1 for k in z.files if k.startswith("W"))
                Ws = tuple(np.asarray(z[f"W{k}"], float) for k in range(n_layers))
                bs = tuple(np.asarray(z[f"b{k}"], float) for k in range(n_layers))
                mean, scale = np.asarray(z["mean"], float), np.asarray(z["scale"], float)
        except (OSError, KeyError, ValueError) as e:
            raise InputError(f"{what} {path}: {e}") from e
        if names != tuple(feature_names):
            raise InputError(
                f"{what} {path}: its features are not this version's "
                f"({len(names)} against {len(feature_names)}); retrain it ({trainer})"
            )
        return cls(names, mean, scale, Ws, bs)


@lru_cache(maxsize=1)
def default_verifier() -> BlobVerifier:
    """The packaged model (read once)."""
    return BlobVerifier.load(MODEL_PATH)


#: The packaged models by name (``DetectorConfig.rules.verifier_model``).
PACKAGED_MODELS = {
    "default": MODEL_PATH,
    "low_ground": MODEL_PATH.with_name("verifier_model_low_ground.npz"),
}


@lru_cache(maxsize=4)
def _packaged(name: str) -> BlobVerifier:
    return BlobVerifier.load(PACKAGED_MODELS[name])


def verifier_named(name: str) -> BlobVerifier:
    """The packaged model `name` (read once): ``"default"`` is :func:`default_verifier`."""
    if name == "default":
        return default_verifier()
    if name not in PACKAGED_MODELS:
        raise InputError(
            f"no packaged verifier model {name!r} (models: {', '.join(PACKAGED_MODELS)})"
        )
    return _packaged(name)


def verifier_threshold(
    rules, tentative: bool, radius_m: float, depth_m: float = float("nan")
) -> float:
    """The score under which the detector rejects a blob (0: not judged), from a RuleConfig's
    verifier fields: ``verifier_min_score`` for a firm blob of estimated radius under
    ``verifier_max_radius_m`` (0 turns the verifier off altogether), or
    ``verifier_far_min_score`` for such a blob at a depth of ``verifier_far_m`` or more
    (0: off), ``verifier_tentative_min_score`` for a tentative one and
    ``verifier_large_min_score`` for one of that radius or more."""
    if rules.verifier_min_score <= 0:
        return 0.0
    if tentative:
        return float(rules.verifier_tentative_min_score)
    if not radius_m < rules.verifier_max_radius_m:
        return float(rules.verifier_large_min_score)
    if 0 < rules.verifier_far_m <= depth_m:
        return float(rules.verifier_far_min_score)
    return float(rules.verifier_min_score)
