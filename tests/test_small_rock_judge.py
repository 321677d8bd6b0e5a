"""The small-rock stage's learned judge (perception/small_rocks.py): its numpy inference and
plain-array IO, its settings' ranges, and what it decides on a rendered frame (a small rock on
a textured plane, ray-cast into a synthetic stereo pair as test_small_rocks.py renders it)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_small_rocks import BASELINE_M, CAM, _render, _uv

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.perception.camera import ipex_rig
from lunarloc.perception.detector import Detector, DetectorConfig
from lunarloc.perception.small_rocks import (
    JUDGE_FEATURES,
    SmallRockConfig,
    default_judge,
    detect_small_rocks,
    ground_plane,
    load_judge,
)
from lunarloc.perception.verifier import Z_CLIP, BlobVerifier

N = len(JUDGE_FEATURES)


def _constant_judge(logit: float) -> BlobVerifier:
    """A judge that gives every candidate the score sigmoid(logit)."""
    return BlobVerifier(
        JUDGE_FEATURES, np.zeros(N), np.ones(N), (np.zeros((N, 1)),), (np.array([logit]),)
    )


def test_the_judges_inference_is_a_standardised_clipped_mlp_and_survives_its_npz(tmp_path):
    rng = np.random.default_rng(0)
    mean, scale = rng.normal(size=N), rng.uniform(0.5, 2.0, N)
    W0, b0 = rng.normal(size=(N, 3)), rng.normal(size=3)
    W1, b1 = rng.normal(size=(3, 1)), rng.normal(size=1)
    model = BlobVerifier(JUDGE_FEATURES, mean, scale, (W0, W1), (b0, b1))
    path = tmp_path / "judge.npz"
    model.save(path)
    back = load_judge(path)
    X = rng.normal(scale=3.0, size=(5, N))
    Z = np.clip((X - mean) / scale, -Z_CLIP, Z_CLIP)
    want = 1.0 / (1.0 + np.exp(-(np.maximum(Z @ W0 + b0, 0.0) @ W1 + b1)[:, 0]))
    # the file holds float32 weights
    assert np.allclose(back.score(X), want, atol=1e-4)
    assert np.allclose(model.score(X), want, atol=1e-12)
    assert abs(float(back.score(X[0])) - want[0]) < 1e-4
    # a model over other features is refused with a clear error, as is a missing file
    other = BlobVerifier(JUDGE_FEATURES[:-1], mean[:-1], scale[:-1], (W0[:-1], W1), (b0, b1))
    other.save(tmp_path / "other.npz")
    with pytest.raises(InputError, match="retrain"):
        load_judge(tmp_path / "other.npz")
    with pytest.raises(InputError):
        load_judge(tmp_path / "missing.npz")


def test_the_packaged_judge_loads_and_scores_in_range():
    judge = default_judge()
    assert judge.feature_names == JUDGE_FEATURES
    p = judge.score(np.zeros((2, N)))
    assert p.shape == (2,) and np.all((p >= 0) & (p <= 1))


@pytest.mark.parametrize(
    "bad",
    [
        {"judge_min_score": 1.5},
        {"judge_min_score": -0.1},
        {"judge_min_top_m": 0.0},
        {"judge_min_snr": -1.0},
        {"judge_dark_min_points": 0},
    ],
)
def test_the_judges_settings_are_range_checked(bad):
    with pytest.raises(ConfigError):
        SmallRockConfig(**bad)


def _stage(L, R, cfg, judge=None, keep_rejected=False):
    det = Detector(DetectorConfig(), CAM)
    T_ro = ipex_rig(CAM)["FrontLeft"].T_rover_optical
    hm = det.height_map(L, R, T_ro)
    n_up = ground_plane(hm.points_rover, hm.depth)
    up = hm.T_rover_optical[:3, :3].T @ n_up if n_up is not None else None
    return detect_small_rocks(
        L,
        R,
        hm.disparity,
        hm.scale,
        CAM,
        BASELINE_M,
        cfg,
        up,
        keep_rejected=keep_rejected,
        judge=judge,
    )


def test_the_judge_decides_the_candidates_that_pass_its_floors():
    x, z, rad, top = 0.3, 2.5, 0.025, 0.025
    L, R = _render(0.0, (x, z, rad, top))
    u, v = _uv(x, z, 0.0)

    def at_rock(rocks):
        return [
            r
            for r in rocks
            if abs(r.u0 + r.crop.shape[1] / 2 - u) < 25 and abs(r.v0 + r.crop.shape[0] / 2 - v) < 25
        ]

    on = replace(SmallRockConfig(), judge_min_score=0.5)
    # a judge that passes everything: the rock is found, with its features and score
    found = _stage(L, R, on, _constant_judge(20.0))
    hit = at_rock(found)
    assert len(hit) == 1 and hit[0].reason is None
    f = hit[0].features
    assert f is not None and f.shape == (N,) and np.all(np.isfinite(f))
    assert hit[0].score > 0.99 and hit[0].rank >= 0
    names = dict(zip(JUDGE_FEATURES, f))
    assert abs(names["depth_m"] - z) < 0.25 and names["top_m"] > 0.4 * top
    assert names["top_snr"] == pytest.approx(names["top_m"] / names["noise_m"], rel=1e-6)
    # one that rejects everything: nothing is a rock, and the rejected come back as "judged"
    assert _stage(L, R, on, _constant_judge(-20.0)) == []
    rejected = at_rock(_stage(L, R, on, _constant_judge(-20.0), keep_rejected=True))
    assert [r.reason for r in rejected] == ["judged"]
    # the judge is not consulted when off: the hand verdict decides (features not measured)
    off = _stage(L, R, replace(on, judge_min_score=0.0), _constant_judge(-20.0))
    assert len(at_rock(off)) == 1 and at_rock(off)[0].features is None


def test_the_judge_is_on_by_default_and_asks_the_packaged_judge():
    # on by default at 0.92, with the height-map verifier (docs/perception-status.md)
    assert SmallRockConfig().judge_min_score == 0.92
    cfg = SmallRockConfig()
    x, z, rad, top = -0.2, 2.0, 0.02, 0.02
    L, R = _render(10.0, (x, z, rad, top), seed=2)
    u, v = _uv(x, z, 10.0)
    rocks = _stage(L, R, cfg)
    hit = [
        r
        for r in rocks
        if abs(r.u0 + r.crop.shape[1] / 2 - u) < 25 and abs(r.v0 + r.crop.shape[0] / 2 - v) < 25
    ]
    assert len(hit) == 1 and hit[0].score >= cfg.judge_min_score
    assert hit[0].score == pytest.approx(float(default_judge().score(hit[0].features)))


def test_judge_path_points_the_stage_at_another_judge(tmp_path):
    # a judge file other than the packaged one (SmallRockConfig.judge_path), e.g. a refit
    x, z, rad, top = 0.3, 2.5, 0.025, 0.025
    L, R = _render(0.0, (x, z, rad, top))
    u, v = _uv(x, z, 0.0)
    _constant_judge(20.0).save(tmp_path / "yes.npz")
    _constant_judge(-20.0).save(tmp_path / "no.npz")
    on = replace(SmallRockConfig(), judge_min_score=0.5)
    yes = _stage(L, R, replace(on, judge_path=str(tmp_path / "yes.npz")))
    hit = [
        r
        for r in yes
        if abs(r.u0 + r.crop.shape[1] / 2 - u) < 25 and abs(r.v0 + r.crop.shape[0] / 2 - v) < 25
    ]
    assert len(hit) == 1 and hit[0].score > 0.99
    assert _stage(L, R, replace(on, judge_path=str(tmp_path / "no.npz"))) == []
    # a judge passed in still wins over the file; a missing file is a clear error
    assert _stage(L, R, replace(on, judge_path=str(tmp_path / "no.npz")), _constant_judge(20.0))
    with pytest.raises(InputError):
        _stage(L, R, replace(on, judge_path=str(tmp_path / "missing.npz")))
    # the key reads from a run configuration's detector section
    from lunarloc.core.configs import config_from_dict

    cfg = config_from_dict(DetectorConfig, {"small_rocks": {"judge_path": "j.npz"}})
    assert cfg.small_rocks.judge_path == "j.npz"
    assert DetectorConfig().small_rocks.judge_path is None
