"""Tentative mid-range detections, confirmed by a second view (DetectorConfig.tentative_*;
docs/perception-history.md, "Seventh pass: tentative mid-range detections")."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError
from lunarloc.perception.detector import (
    Detection,
    Detector,
    DetectorConfig,
    FrameDetections,
    MaskRecord,
    PairResult,
    confirm_across_frames,
)
from lunarloc.perception.masks import InstanceMasks, RejectReason
from lunarloc.perception.small_rocks import SmallRockConfig
from test_detector import CAM, ground_scene

# the mid-range strip of test_detector's flat-strip test with both strip rules off: rejected
# as elongated today; the tentative rule (2.5-6 m) keeps it for a second view to confirm
# (the small-rock stage off: it may see the lit top of this rock on its own, tests/test_small_rocks.py)
STRIPS_OFF = DetectorConfig(
    strip_max_eig_ratio=0.0,
    raised_strip_max_eig_ratio=0.0,
    tentative_max_range_m=0.0,
    small_rocks=SmallRockConfig(enabled=False),
)
TENTATIVE = replace(STRIPS_OFF, tentative_max_range_m=6.0, tentative_min_range_m=2.0)
# tentatives confirmed by their own repeats: 3 in the 3 neighbouring frames each way
REPEATS = replace(
    DetectorConfig(), tentative_max_range_m=6.0, tentative_confirm_frames=3, tentative_min_repeats=3
)


def _pair(cfg, c, keep_tentative):
    left, right, rig = ground_scene(tuple(c), 0.16)
    return Detector(cfg, CAM).detect_pair(
        left, right, rig["FrontLeft"].T_rover_optical, keep_tentative=keep_tentative
    )


def test_a_mid_range_blob_that_a_marginal_rule_rejects_becomes_a_tentative_detection():
    c = np.array([4.0, 0.0, -0.29])
    today = _pair(STRIPS_OFF, c, keep_tentative=True)
    assert today.detections == [] and [r.reason for r in today.records] == [RejectReason.ELONGATED]
    kept = _pair(TENTATIVE, c, keep_tentative=True)
    assert len(kept.detections) == 1
    d = kept.detections[0]
    assert d.tentative == "elongated" and not today.records[0].reason is None
    assert np.linalg.norm(d.p_rover[:2] - c[:2]) < 0.15
    # without keep_tentative (detect_frame's default: the online loop) it never comes out
    dropped = _pair(TENTATIVE, c, keep_tentative=False)
    assert dropped.detections == [] and [r.reason for r in dropped.records] == [
        RejectReason.TENTATIVE
    ]
    assert dropped.records[0].tentative == "elongated"  # the record keeps why it was tentative
    left, right, rig = ground_scene(tuple(c), 0.16)
    images = {"FrontLeft": left, "FrontRight": right}
    assert Detector(TENTATIVE, CAM).detect_frame(images, rig).detections == []
    assert [
        d.tentative
        for d in Detector(TENTATIVE, CAM).detect_frame(images, rig, keep_tentative=True).detections
    ] == ["elongated"]
    # nearer than tentative_min_range_m: rejected as today
    near = _pair(replace(TENTATIVE, tentative_min_range_m=4.5), c, keep_tentative=True)
    assert near.detections == [] and [r.reason for r in near.records] == [RejectReason.ELONGATED]
    # beyond tentative_max_eig_ratio: rejected as today
    long_ = _pair(
        replace(TENTATIVE, tentative_max_eig_ratio=d.eig_ratio - 1.0), c, keep_tentative=True
    )
    assert long_.detections == [] and [r.reason for r in long_.records] == [RejectReason.ELONGATED]


def test_the_off_switch_and_firm_detections_are_untouched():
    # a rock the default keeps: the same detection with tentatives on or off
    c = np.array([4.0, 0.0, -0.29])
    a = _pair(DetectorConfig(tentative_max_range_m=0.0), c, keep_tentative=True).detections
    b = _pair(DetectorConfig(), c, keep_tentative=True).detections
    assert len(a) == len(b) == 1 and b[0].tentative == ""
    assert np.array_equal(
        a[0].p_map if a[0].p_map is not None else a[0].p_rover,
        b[0].p_map if b[0].p_map is not None else b[0].p_rover,
    )


def _det(p, tentative=""):
    p = np.asarray(p, float)
    return Detection(
        "FrontLeft", (0.0, 0.0), 4.0, 5.0, 1.0, 100, 0.05, 0.1, p, p, p, tentative=tentative
    )


def _frame(k, x_rover, dets, pose=True):
    T = np.eye(4)
    T[0, 3] = x_rover
    recs = [MaskRecord(i, None, 4.0, 0.05, None) for i in range(len(dets))]
    return FrameDetections(
        k,
        T if pose else None,
        [PairResult("FrontLeft", InstanceMasks((720, 1280)), recs, dets, None)],
    )


ROCK = [4.0, 0.5, 0.0]


def _run(cfg, frames):
    out = list(confirm_across_frames(frames, cfg))
    assert [f.frame for f in out] == [f.frame for f in frames]
    return out


def test_a_tentative_that_another_view_confirms_is_kept_and_one_no_view_confirms_is_dropped():
    cfg = replace(
        DetectorConfig(), tentative_max_range_m=6.0, tentative_tol_m=0.1, confirm_tol_m=0.2
    )
    tol = cfg.tentative_tol_m
    seen = [0.5 * tol, 0.0, 0.0]
    # frame 0 tentative; frame 1 (0.5 m on) has a firm detection within tol: kept
    out = _run(
        cfg, [_frame(0, 0.0, [_det(ROCK, "too_small")]), _frame(1, 0.5, [_det(np.add(ROCK, seen))])]
    )
    assert len(out[0].detections) == 1 and out[0].detections[0].tentative == "too_small"
    # the other view's detection lies beyond tentative_tol_m (though within the crest rule's
    # confirm_tol_m): dropped, and its record says why
    off = [1.5 * tol, 0.0, 0.0]
    assert 1.5 * tol < cfg.confirm_tol_m
    out = _run(
        cfg, [_frame(0, 0.0, [_det(ROCK, "too_small")]), _frame(1, 0.5, [_det(np.add(ROCK, off))])]
    )
    assert out[0].detections == [] and out[0].pairs[0].records[0].reason is RejectReason.TENTATIVE
    # another view's tentative detection confirms nothing
    out = _run(cfg, [_frame(0, 0.0, [_det(ROCK, "crest")]), _frame(1, 0.5, [_det(ROCK, "crest")])])
    assert all(f.detections == [] for f in out)
    # no other view (a single frame, the rover standing still, no map pose): dropped
    assert _run(cfg, [_frame(0, 0.0, [_det(ROCK, "elongated")])])[0].detections == []
    still = _run(
        cfg, [_frame(k, 0.0, [_det(ROCK, "elongated"), _det([5.0, 0.0, 0.0])]) for k in range(3)]
    )
    assert all([d.tentative for d in f.detections] == [""] for f in still)
    nopose = _run(
        cfg, [_frame(k, 0.5 * k, [_det(ROCK, "elongated")], pose=False) for k in range(2)]
    )
    assert all(f.detections == [] for f in nopose)


def test_two_views_needed_when_asked():
    one = replace(DetectorConfig(), tentative_max_range_m=6.0)
    two = replace(one, tentative_min_views=2)

    def frames(firm_after):
        return [
            _frame(0, 0.0, [_det(ROCK)]),
            _frame(1, 0.5, [_det(ROCK, "quadric")]),
            _frame(2, 1.0, [_det(ROCK)] if firm_after else []),
        ]

    assert len(_run(one, frames(False))[1].detections) == 1  # the earlier view alone
    assert _run(two, frames(False))[1].detections == []
    assert len(_run(two, frames(True))[1].detections) == 1  # both views


def test_a_later_firm_view_confirms_when_asked_to_look_that_far():
    # the rock is tentative from frames 0-2 and firm only from frame 3 (nearer): with one
    # view each way frame 0 cannot be confirmed; with three it can, and frames of nothing
    # but tentatives still confirm nothing
    # (repeats of the tentative itself confirm it too by default; that rule is tested below)
    one = replace(
        DetectorConfig(),
        tentative_max_range_m=6.0,
        tentative_confirm_frames=1,
        tentative_min_repeats=0,
    )
    three = replace(one, tentative_confirm_frames=3)

    def frames(firm_last):
        fr = [_frame(k, 0.5 * k, [_det(ROCK, "too_small")]) for k in range(3)]
        return fr + [_frame(3, 1.5, [_det(ROCK, "" if firm_last else "too_small")])]

    assert [len(f.detections) for f in _run(one, frames(True))] == [0, 0, 1, 1]
    assert [len(f.detections) for f in _run(three, frames(True))] == [1, 1, 1, 1]
    assert all(f.detections == [] for f in _run(three, frames(False)))
    # beyond the third frame on that side: dropped
    late = frames(False) + [_frame(4, 2.0, [_det(ROCK)])]
    assert [len(f.detections) for f in _run(three, late)] == [0, 1, 1, 1, 1]
    # frames closer than confirm_min_baseline_m do not count as views
    crawl = [_frame(k, 0.01 * k, [_det(ROCK, "too_small")]) for k in range(3)] + [
        _frame(3, 0.5, [_det(ROCK)])
    ]
    assert [len(f.detections) for f in _run(one, crawl)] == [1, 1, 1, 1]


def test_a_large_tentative_is_confirmed_within_a_share_of_its_radius():
    # a large rock's centre moves with how much of it each view's mask holds: a tentative
    # of radius 0.4 m whose firm view lies 0.15 m away is kept at 0.5 x radius (0.2 m) and
    # dropped with the fixed 0.1 m alone; a small one (0.1 m) at 0.15 m is dropped either way
    cfg = replace(
        DetectorConfig(),
        tentative_max_range_m=6.0,
        tentative_tol_m=0.1,
        tentative_tol_per_radius=0.5,
    )
    fixed = replace(cfg, tentative_tol_per_radius=0.0)

    def frames(radius_m):
        tent = replace(_det(ROCK, "elongated"), radius_m=radius_m)
        return [_frame(0, 0.0, [tent]), _frame(1, 0.5, [_det(np.add(ROCK, [0.15, 0.0, 0.0]))])]

    assert len(_run(cfg, frames(0.4))[0].detections) == 1
    assert _run(fixed, frames(0.4))[0].detections == []
    assert _run(cfg, frames(0.1))[0].detections == []
    # the default
    assert DetectorConfig().tentative_tol_per_radius == 0.5


def test_a_tentative_seen_again_in_enough_neighbouring_frames_is_kept():
    # a rock seen only tentatively, never firmly, in four frames 0.5 m apart: each frame sees
    # it again in three of its neighbouring frames (three each way at most), so with
    # tentative_min_repeats 3 all four are kept; with 0 (off) or 4, none
    cfg = REPEATS

    def frames(n, step_m=0.0):
        return [
            _frame(k, 0.5 * k, [_det(np.add(ROCK, [step_m * k, 0.0, 0.0]), "too_small")])
            for k in range(n)
        ]

    assert [len(f.detections) for f in _run(cfg, frames(4))] == [1, 1, 1, 1]
    assert all(f.detections == [] for f in _run(replace(cfg, tentative_min_repeats=0), frames(4)))
    assert all(f.detections == [] for f in _run(replace(cfg, tentative_min_repeats=4), frames(4)))
    # three frames give each at most two repeats; blobs that wander by more than the
    # tolerance from frame to frame (stereo noise) do not repeat
    assert all(f.detections == [] for f in _run(cfg, frames(3)))
    assert all(f.detections == [] for f in _run(cfg, frames(6, step_m=1.5 * cfg.tentative_tol_m)))
    assert DetectorConfig().tentative_min_repeats == 3


def test_a_tentative_the_verifier_is_sure_of_needs_one_repeat():
    # a rock partly hidden at mid-range is tentative frame after frame, never firm beside it,
    # and often seen in fewer than tentative_min_repeats (3) neighbouring frames: with
    # rules.verifier_confirm_score set, a tentative the blob verifier scored at least that is
    # kept when seen again (as any detection) in one neighbouring frame; one scored under it,
    # or not scored (NaN), still needs three; a single sighting is dropped whatever its score
    base = REPEATS
    base = replace(base, rules=replace(base.rules, verifier_min_score=0.7))
    cfg = replace(base, rules=replace(base.rules, verifier_confirm_score=0.95))
    off = replace(base, rules=replace(base.rules, verifier_confirm_score=0.0))

    def frames(score, n=2, pose=True, step_m=0.0):
        return [
            _frame(
                k,
                0.5 * k,
                [replace(_det(np.add(ROCK, [step_m * k, 0, 0]), "crest"), verifier_score=score)],
                pose,
            )
            for k in range(n)
        ]

    assert [len(f.detections) for f in _run(cfg, frames(0.97))] == [1, 1]
    assert [d.tentative for d in _run(cfg, frames(0.95))[0].detections] == ["crest"]
    for c, s in ((cfg, 0.9), (cfg, float("nan")), (off, 0.99)):
        assert all(f.detections == [] for f in _run(c, frames(s)))
    assert _run(cfg, frames(0.99, n=1))[0].detections == []
    # the repeat must lie within the tentative tolerance
    tol = cfg.tentative_tol_m
    assert all(f.detections == [] for f in _run(cfg, frames(0.99, step_m=1.5 * tol)))
    # the verifier off (verifier_min_score 0): the setting does nothing
    no_verifier = replace(cfg, rules=replace(cfg.rules, verifier_min_score=0.0))
    assert all(f.detections == [] for f in _run(no_verifier, frames(0.99)))
    # with no map pose every tentative is dropped, as before
    assert all(f.detections == [] for f in _run(cfg, frames(0.99, pose=False)))
    # its range is checked
    for bad in (-0.1, 1.1):
        with pytest.raises(ConfigError, match="verifier_confirm_score"):
            replace(cfg.rules, verifier_confirm_score=bad)


def test_confirmation_off_passes_everything_through():
    off = replace(DetectorConfig(), confirm_tol_m=0.0, tentative_max_range_m=0.0)
    fr = [
        _frame(
            0, 0.0, [_det(ROCK, "crest"), replace(_det([6.0, 0.0, 0.0]), needs_confirmation=True)]
        )
    ]
    assert len(_run(off, fr)[0].detections) == 2


@pytest.mark.parametrize(
    "key, value",
    [
        ("tentative_max_range_m", -1.0),
        ("tentative_min_range_m", -0.5),
        ("tentative_max_eig_ratio", -1.0),
        ("tentative_tol_m", 0.0),
        ("tentative_min_views", 3),
        ("tentative_min_views", 1.5),
        ("tentative_confirm_frames", 0),
        ("tentative_confirm_frames", 11),
        ("tentative_confirm_frames", 2.5),
        ("tentative_tol_per_radius", -0.1),
        ("tentative_min_repeats", -1),
        ("tentative_min_repeats", 21),
        ("tentative_min_repeats", 2.5),
    ],
)
def test_tentative_settings_are_checked_and_round_trip(key, value):
    import json

    from lunarloc.config.run import RunConfig

    with pytest.raises(ConfigError, match=key):
        RunConfig.from_dict({"detector": {key: value}})
    good = {
        "tentative_max_range_m": 5.5,
        "tentative_min_range_m": 3.0,
        "tentative_max_eig_ratio": 45.0,
        "tentative_tol_m": 0.12,
        "tentative_min_views": 2,
        "tentative_confirm_frames": 4,
        "tentative_tol_per_radius": 0.8,
        "tentative_min_repeats": 4,
    }[key]
    cfg = RunConfig.from_dict({"detector": {key: good}})
    assert getattr(cfg.detector, key) == good and getattr(cfg.detector, key) != getattr(
        DetectorConfig(), key
    )
    assert (
        RunConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    )  # through a config file's JSON


def test_the_range_band_must_be_a_band():
    with pytest.raises(ConfigError, match="tentative_min_range_m"):
        DetectorConfig(tentative_max_range_m=2.0, tentative_min_range_m=2.5)
