"""The learned blob verifier: numpy inference of a tiny model built here, its file format, its
features, its configuration field and its effect on the detector's judgement of a rendered
blob."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest
from test_detector import CAM, ground_scene

from lunarloc.core.configs import config_from_dict
from lunarloc.core.errors import ConfigError, InputError
from lunarloc.perception import detector as detector_mod
from lunarloc.perception.detector import Detector, DetectorConfig
from lunarloc.perception.masks import InstanceMask, RejectReason
from lunarloc.perception.small_rocks import SmallRockConfig
from lunarloc.perception.verifier import (
    FEATURE_NAMES,
    MODEL_PATH,
    PACKAGED_MODELS,
    BlobVerifier,
    blob_features,
    default_verifier,
    verifier_named,
    verifier_threshold,
)

N = len(FEATURE_NAMES)


def tiny_model(w_top: float, bias: float, hidden: bool = False) -> BlobVerifier:
    """A model reading one feature (the blob's top above the local ground, standardised by
    mean 0.05 m and scale 0.02 m): logistic(w_top * z + bias), or the same through one ReLU
    unit (hidden=True; positive w_top then)."""
    k = FEATURE_NAMES.index("height_m")
    mean, scale = np.zeros(N), np.ones(N)
    mean[k], scale[k] = 0.05, 0.02
    W = np.zeros((N, 1))
    W[k, 0] = w_top
    if hidden:
        return BlobVerifier(
            FEATURE_NAMES, mean, scale, (W, np.array([[1.0]])), (np.zeros(1), np.array([bias]))
        )
    return BlobVerifier(FEATURE_NAMES, mean, scale, (W,), (np.array([bias]),))


@dataclass
class _Measures:
    depth_m: float = 3.0
    radius_m: float = 0.1
    size_m: float = 0.2
    eig_ratio: float = 1.5
    height_m: float = 0.09
    height_front_m: float = float("nan")
    height_ring_m: float = 0.01
    height_quadric_m: float = 0.08
    nearer_ring_fraction: float = 0.0
    extension_ratio: float = float("nan")
    disparity_roughness: float = 0.05
    tentative: str = ""


def test_tiny_model_scores_as_written_by_hand():
    m = tiny_model(2.0, -1.0)
    X = np.zeros((3, N))
    k = FEATURE_NAMES.index("height_m")
    X[:, k] = [0.05, 0.09, 0.01]  # z = 0, 2, -2
    want = 1.0 / (1.0 + np.exp(-(2.0 * np.array([0.0, 2.0, -2.0]) - 1.0)))
    assert np.allclose(m.score(X), want)
    assert m.score(X[1]) == pytest.approx(want[1])  # one vector: one score
    # a hidden ReLU layer cuts the negative side off: logistic(bias) below the mean
    h = tiny_model(2.0, -1.0, hidden=True)
    assert np.allclose(h.score(X), [1 / (1 + math.e), want[1], 1 / (1 + math.e)])


def test_model_round_trips_as_plain_arrays_and_refuses_other_features(tmp_path):
    m = tiny_model(2.0, -1.0, hidden=True)
    p = tmp_path / "m.npz"
    m.save(p)
    with np.load(p, allow_pickle=False) as z:  # no object arrays in the file
        assert all(z[k].dtype != object for k in z.files)
    back = BlobVerifier.load(p)
    X = np.random.default_rng(0).normal(0, 1, (5, N))
    assert np.allclose(back.score(X), m.score(X), atol=1e-6)
    # a model of another feature set, a broken file, wrong shapes: clear errors
    other = BlobVerifier(FEATURE_NAMES[:-1] + ("other",), m.mean, m.scale, m.weights, m.biases)
    other.save(tmp_path / "o.npz")
    with pytest.raises(InputError, match="retrain"):
        BlobVerifier.load(tmp_path / "o.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError):
        BlobVerifier.load(tmp_path / "bad.npz")
    with pytest.raises(InputError, match="features"):
        m.score(np.zeros((2, N + 1)))
    with pytest.raises(InputError, match="chain"):
        BlobVerifier(FEATURE_NAMES, m.mean, m.scale, (np.zeros((N, 2)),), (np.zeros(1),))
    with pytest.raises(InputError, match="scales"):
        BlobVerifier(FEATURE_NAMES, m.mean, 0 * m.scale, m.weights, m.biases)


def test_features_are_finite_flag_missing_measures_and_refuse_bad_input():
    rng = np.random.default_rng(1)
    img = (128 + rng.normal(0, 10, (120, 160))).clip(0, 255).astype(np.uint8)
    yy, xx = np.mgrid[:20, :20]
    crop = (yy - 10) ** 2 + (xx - 10) ** 2 < 64
    img[50:70, 70:90][crop] = 200  # a lit blob
    mask = InstanceMask(70, 50, crop)
    x = blob_features(_Measures(), img, mask)
    assert x.shape == (N,) and np.all(np.isfinite(x))
    f = dict(zip(FEATURE_NAMES, x))
    assert f["height_front_m_nan"] == 1 and f["extension_ratio_nan"] == 1
    assert f["height_ring_m_nan"] == 0 and f["height_front_m"] == 0
    assert f["mask_contrast"] > 3  # far brighter than the ring's spread
    dark = img.copy()
    dark[50:70, 70:90][crop] = 128
    assert blob_features(_Measures(), dark, mask)[FEATURE_NAMES.index("mask_contrast")] < 1
    # at the image's corner the window is cut, the features still finite
    assert np.all(np.isfinite(blob_features(_Measures(), img, InstanceMask(0, 0, crop))))
    with pytest.raises(InputError, match="empty"):
        blob_features(_Measures(), img, InstanceMask(0, 0, np.zeros((3, 3), bool)))
    with pytest.raises(InputError, match="grey"):
        blob_features(_Measures(), np.zeros((4, 4, 3), np.uint8), mask)


def test_config_field_range_and_json():
    assert DetectorConfig().rules.verifier_min_score == 0.0 or (
        0.0 < DetectorConfig().rules.verifier_min_score < 1.0
    )
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(ConfigError, match="verifier_min_score"):
            replace(DetectorConfig().rules, verifier_min_score=bad)
    for bad in (0.0, -1.0):
        with pytest.raises(ConfigError, match="verifier_max_radius_m"):
            replace(DetectorConfig().rules, verifier_max_radius_m=bad)
    c = config_from_dict(
        DetectorConfig, {"rules": {"verifier_min_score": 0.4, "verifier_max_radius_m": 0.5}}
    )
    assert c.rules.verifier_min_score == 0.4 and c.rules.verifier_max_radius_m == 0.5


def _scene_detector(score: float, max_radius_m: float = 0.3, large: float = 0.0):
    cfg = DetectorConfig(small_rocks=SmallRockConfig(enabled=False))
    rules = replace(
        cfg.rules,
        verifier_min_score=score,
        verifier_max_radius_m=max_radius_m,
        verifier_large_min_score=large,
    )
    return Detector(replace(cfg, rules=rules), CAM)


def test_the_verifier_judges_a_rendered_blob(monkeypatch):
    # a 0.12 m rock 3 m ahead on flat rendered ground: the rules keep it; a model that says
    # "rock" keeps it with its score, one that says "terrain" rejects it as not a rock
    left, right, rig = ground_scene((3.0, 0.0, -0.15), 0.12)
    T = rig["FrontLeft"].T_rover_optical
    off = _scene_detector(0.0).detect_pair(left, right, T)
    assert len(off.detections) == 1 and math.isnan(off.detections[0].verifier_score)
    monkeypatch.setattr(detector_mod, "default_verifier", lambda: tiny_model(5.0, 5.0))
    kept = _scene_detector(0.5).detect_pair(left, right, T)
    assert len(kept.detections) == 1 and kept.detections[0].verifier_score > 0.5
    assert np.allclose(kept.detections[0].p_rover, off.detections[0].p_rover)
    monkeypatch.setattr(detector_mod, "default_verifier", lambda: tiny_model(0.0, -5.0))
    gone = _scene_detector(0.5).detect_pair(left, right, T)
    assert gone.detections == []
    assert RejectReason.NOT_A_ROCK in [r.reason for r in gone.records]
    # a blob as large as verifier_max_radius_m is not judged unless verifier_large_min_score
    big = _scene_detector(0.5, max_radius_m=0.05, large=0.0).detect_pair(left, right, T)
    assert len(big.detections) == 1 and math.isnan(big.detections[0].verifier_score)
    assert (
        _scene_detector(0.5, max_radius_m=0.05, large=0.5).detect_pair(left, right, T).detections
        == []
    )


def test_the_packaged_model_loads_is_small_and_keeps_a_plain_rock():
    assert MODEL_PATH.stat().st_size < 1_000_000
    m = default_verifier()
    assert m.feature_names == FEATURE_NAMES
    left, right, rig = ground_scene((3.0, 0.0, -0.15), 0.12)
    T = rig["FrontLeft"].T_rover_optical
    pr = _scene_detector(0.01).detect_pair(left, right, T)
    assert len(pr.detections) == 1 and 0.01 <= pr.detections[0].verifier_score <= 1.0


def test_the_low_ground_model_is_packaged_and_chosen_by_the_config(monkeypatch):
    # rules.verifier_model names a packaged model; "low_ground" (fitted on blobs of a lower
    # ground) loads, is small, has this version's features and is the one the detector asks for
    assert PACKAGED_MODELS["default"] == MODEL_PATH
    assert PACKAGED_MODELS["low_ground"].stat().st_size < 1_000_000
    low = verifier_named("low_ground")
    assert low.feature_names == FEATURE_NAMES and verifier_named("default") is default_verifier()
    assert not np.allclose(low.mean, default_verifier().mean)
    with pytest.raises(InputError, match="no packaged verifier model"):
        verifier_named("nope")
    c = config_from_dict(DetectorConfig, {"rules": {"verifier_model": "low_ground"}})
    assert c.rules.verifier_model == "low_ground"
    assert DetectorConfig().rules.verifier_model in PACKAGED_MODELS
    with pytest.raises(ConfigError, match="verifier_model"):
        replace(DetectorConfig().rules, verifier_model="nope")
    # the detector scores with the named model: one that says "terrain" under that name
    # rejects the rendered rock that the default model's stand-in keeps
    left, right, rig = ground_scene((3.0, 0.0, -0.15), 0.12)
    T = rig["FrontLeft"].T_rover_optical
    monkeypatch.setattr(detector_mod, "default_verifier", lambda: tiny_model(5.0, 5.0))
    monkeypatch.setattr(
        detector_mod,
        "verifier_named",
        lambda name: tiny_model(0.0, -5.0) if name == "low_ground" else None,
    )
    det = _scene_detector(0.5)
    assert len(det.detect_pair(left, right, T).detections) == 1
    cfg = replace(det.config, rules=replace(det.config.rules, verifier_model="low_ground"))
    assert Detector(cfg, CAM).detect_pair(left, right, T).detections == []


def test_a_tentative_blob_is_left_to_cross_frame_confirmation(monkeypatch):
    # test_tentative's mid-range strip (kept as a tentative detection): a model that says
    # "terrain" does not judge it; confirmation by a neighbouring frame does
    from test_tentative import TENTATIVE

    left, right, rig = ground_scene((4.0, 0.0, -0.29), 0.16)
    T = rig["FrontLeft"].T_rover_optical
    monkeypatch.setattr(detector_mod, "default_verifier", lambda: tiny_model(0.0, -5.0))
    rules = replace(TENTATIVE.rules, verifier_min_score=0.5, verifier_tentative_min_score=0.0)
    pr = Detector(replace(TENTATIVE, rules=rules), CAM).detect_pair(
        left, right, T, keep_tentative=True
    )
    assert len(pr.detections) == 1 and pr.detections[0].tentative
    assert math.isnan(pr.detections[0].verifier_score)
    # with verifier_tentative_min_score set, the same model rejects it before confirmation
    rules = replace(rules, verifier_tentative_min_score=0.5)
    gone = Detector(replace(TENTATIVE, rules=rules), CAM).detect_pair(
        left, right, T, keep_tentative=True
    )
    assert gone.detections == []
    assert RejectReason.NOT_A_ROCK in [r.reason for r in gone.records]
    # a model that says "rock" keeps it, tentative, with its score
    monkeypatch.setattr(detector_mod, "default_verifier", lambda: tiny_model(5.0, 5.0))
    kept = Detector(replace(TENTATIVE, rules=rules), CAM).detect_pair(
        left, right, T, keep_tentative=True
    )
    assert len(kept.detections) == 1 and kept.detections[0].tentative
    assert kept.detections[0].verifier_score > 0.5


def test_verifier_threshold_by_blob_kind():
    r = replace(
        DetectorConfig().rules,
        verifier_min_score=0.7,
        verifier_tentative_min_score=0.4,
        verifier_large_min_score=0.5,
        verifier_max_radius_m=0.3,
    )
    assert verifier_threshold(r, False, 0.1) == 0.7
    assert verifier_threshold(r, True, 0.1) == 0.4
    assert verifier_threshold(r, False, 0.3) == 0.5
    assert verifier_threshold(r, False, float("nan")) == 0.5  # an unknown radius: judged as large
    # verifier_min_score 0 turns every kind off
    assert verifier_threshold(replace(r, verifier_min_score=0.0), True, 0.1) == 0.0
    # a firm small blob at verifier_far_m or deeper: verifier_far_min_score (0 m: off)
    far = replace(r, verifier_far_m=3.5, verifier_far_min_score=0.6)
    assert verifier_threshold(far, False, 0.1, 3.5) == 0.6
    assert verifier_threshold(far, False, 0.1, 3.4) == 0.7
    assert verifier_threshold(far, False, 0.1) == 0.7  # depth unknown (NaN)
    assert verifier_threshold(far, True, 0.1, 4.0) == 0.4  # tentatives and large blobs as before
    assert verifier_threshold(far, False, 0.3, 4.0) == 0.5
    assert verifier_threshold(replace(far, verifier_far_m=0.0), False, 0.1, 4.0) == 0.7
    for f in ("verifier_tentative_min_score", "verifier_large_min_score", "verifier_far_min_score"):
        for bad in (-0.1, 1.0):
            with pytest.raises(ConfigError, match=f):
                replace(r, **{f: bad})


def test_appearance_features_are_the_same_bits_wherever_the_heap_puts_the_arrays():
    """The gradient magnitude behind the orientation and gradient features comes out bit-identical
    whatever the memory alignment of the arrays involved (OpenCV's IPP path rounds the first
    pixels differently into an output that is not 32-byte aligned; before, the orientation
    features' last digits, and so verifier_score's, moved from run to run)."""
    from lunarloc.perception.verifier import appearance_features

    rng = np.random.default_rng(7)
    img = np.clip(rng.normal(120, 40, (90, 120)), 0, 255).astype(np.uint8)
    # a blob at the image's corner: the window's first pixels (where the two roundings differ)
    # are on the mask
    mask = InstanceMask(0, 0, np.ones((30, 36), bool))
    seen = set()
    keep = []
    for k in range(40):
        # move the heap: arrays of the windows' size, and 16 bytes apart, kept between calls
        keep.append(np.empty(4000 + 16 * k + 8 * (k % 3), np.uint8))
        seen.add(appearance_features(img, mask).tobytes())
    assert len(seen) == 1
