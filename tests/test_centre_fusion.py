"""Centre from several views: fuse_track_centres (DetectorConfig.fuse_*)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError
from lunarloc.core.geometry import invert_transform, pose_to_matrix, transform_points
from lunarloc.perception.camera import ipex_rig
from lunarloc.perception.detector import (
    CentreFusion,
    Detection,
    DetectorConfig,
    FrameDetections,
    MaskRecord,
    PairResult,
    fuse_track_centres,
)
from lunarloc.perception.masks import InstanceMasks

T_ROVER_OPTICAL = ipex_rig()["FrontLeft"].T_rover_optical


def _frame(k: int, x_rover: float, centres_map, with_mount: bool = True) -> FrameDetections:
    """Frame k, the rover at (x_rover, 0, 0) heading +x, one detection per map-frame centre."""
    T = pose_to_matrix(x_rover, 0.0, 0.0, 0.0, 0.0, 0.0)
    dets = []
    for p in centres_map:
        p_map = np.asarray(p, float)
        p_rover = transform_points(invert_transform(T), p_map[None])[0]
        p_opt = transform_points(invert_transform(T_ROVER_OPTICAL), p_rover[None])[0]
        dets.append(
            Detection(
                "FrontLeft",
                (640.0, 400.0),
                float(p_opt[2]),
                5.0,
                1.5,
                300,
                0.06,
                0.12,
                p_opt,
                p_rover,
                p_map,
            )
        )
    recs = [MaskRecord(i, None, 3.0, 0.06, None) for i in range(len(dets))]
    pair = PairResult(
        "FrontLeft",
        InstanceMasks((720, 1280)),
        recs,
        dets,
        None,
        T_rover_optical=T_ROVER_OPTICAL if with_mount else None,
    )
    return FrameDetections(k, T, [pair])


def _noisy_track(rng, n=12, rock=(6.0, 0.8, 0.05), sigma=0.04, extra=()):
    """A rock seen from a rover driving towards it; each sighting's centre off by sigma (m)."""
    rock = np.asarray(rock)
    return rock, [_frame(k, 0.3 * k, [rock + rng.normal(0.0, sigma, 3), *extra]) for k in range(n)]


def test_fusion_reduces_the_error_of_a_noisy_track():
    rng = np.random.default_rng(3)
    rock, frames = _noisy_track(rng)
    before = [float(np.linalg.norm(f.detections[0].p_map - rock)) for f in frames]
    for how in CentreFusion:
        _, again = _noisy_track(np.random.default_rng(3))
        out = list(fuse_track_centres(again, DetectorConfig(fuse_tol_m=0.2, fuse_estimator=how)))
        assert [f.frame for f in out] == list(range(12))
        after = [float(np.linalg.norm(f.detections[0].p_map - rock)) for f in out]
        assert np.median(after) < 0.6 * np.median(before), how


def test_off_is_todays_output_and_a_lone_detection_keeps_its_centre():
    rng = np.random.default_rng(5)
    _, frames = _noisy_track(rng)
    ids = [id(d) for f in frames for d in f.detections]
    out = list(fuse_track_centres(frames, DetectorConfig(fuse_tol_m=0.0)))
    assert [id(d) for f in out for d in f.detections] == ids  # the very same objects, untouched
    # a rock seen in one frame only, and another whose other sightings lie beyond the tolerance
    lone = [
        _frame(0, 0.0, [[3.0, 0.5, 0.0], [4.0, -1.0, 0.0]]),
        _frame(1, 0.3, [[4.0, -1.0 + 0.25, 0.0]]),
    ]
    first = [d.p_map.copy() for d in lone[0].detections]
    out = list(fuse_track_centres(lone, DetectorConfig(fuse_tol_m=0.2)))
    assert all(np.array_equal(d.p_map, p) for d, p in zip(out[0].detections, first))
    assert np.allclose(out[1].detections[0].p_map, [4.0, -0.75, 0.0])


def test_two_rocks_side_by_side_stay_apart_and_frames_are_consistent():
    # two rocks 0.15 m apart (within the tolerance): mutual nearest sightings keep them apart
    a, b = np.array([5.0, 0.0, 0.0]), np.array([5.0, 0.15, 0.0])
    frames = [
        _frame(k, 0.3 * k, [a + [0.01 * (-1) ** k, 0, 0], b + [0, 0.01 * (-1) ** k, 0]])
        for k in range(6)
    ]
    out = list(fuse_track_centres(frames, DetectorConfig(fuse_tol_m=0.2)))
    for f in out:
        pa, pb = (d.p_map for d in f.detections)
        assert np.linalg.norm(pa - a) < 0.02 and np.linalg.norm(pb - b) < 0.02
        for d in f.detections:  # p_rover and p_optical follow p_map
            assert np.allclose(transform_points(f.T_map_rover, d.p_rover[None])[0], d.p_map)
            assert np.allclose(transform_points(T_ROVER_OPTICAL, d.p_optical[None])[0], d.p_rover)


def test_causal_fusion_uses_only_earlier_frames_and_nearer_views_weigh_more():
    rock = np.array([6.0, 0.0, 0.0])
    offs = [np.array([0.0, 0.08 * (k + 1), 0.0]) for k in range(4)]  # each later view off more
    frames = [_frame(k, 1.0 * k, [rock + offs[k]]) for k in range(4)]
    causal = list(fuse_track_centres(frames, DetectorConfig(fuse_tol_m=0.2, fuse_causal=True)))
    assert np.allclose(causal[0].detections[0].p_map, rock + offs[0])  # nothing before it
    assert np.allclose(causal[1].detections[0].p_map, rock + (offs[0] + offs[1]) / 2)
    # range weighting: of two sightings the nearer one (rover 1 m on) dominates at power 2
    two = [_frame(k, 1.0 * k, [rock + offs[k]]) for k in range(2)]
    out = list(fuse_track_centres(two, DetectorConfig(fuse_tol_m=0.2, fuse_range_power=2.0)))
    y = out[0].detections[0].p_map[1]
    assert (offs[0][1] + offs[1][1]) / 2 < y < offs[1][1]


def test_without_a_camera_pose_p_optical_is_left_alone():
    rock = np.array([5.0, 0.3, 0.0])
    frames = [_frame(k, 0.3 * k, [rock + [0.02 * k, 0, 0]], with_mount=False) for k in range(3)]
    before = [f.detections[0].p_optical.copy() for f in frames]
    out = list(fuse_track_centres(frames, DetectorConfig(fuse_tol_m=0.2)))
    assert all(np.array_equal(f.detections[0].p_optical, p) for f, p in zip(out, before))
    assert not np.allclose(out[0].detections[0].p_map, rock)  # but its map centre moved
    # a frame without a pose passes unchanged
    nopose = FrameDetections(9, None, [replace(frames[0].pairs[0], detections=[])])
    assert list(fuse_track_centres([nopose], DetectorConfig(fuse_tol_m=0.2)))[0] is nopose


@pytest.mark.parametrize(
    "key, value",
    [
        ("fuse_tol_m", -0.1),
        ("fuse_range_power", -1.0),
        ("fuse_max_frames", 0),
        ("fuse_max_frames", 2.5),
        ("fuse_causal", "yes"),
        ("fuse_estimator", "mode"),
    ],
)
def test_fusion_settings_are_checked_and_round_trip(key, value, tmp_path):
    import json

    from lunarloc.config.run import RunConfig, load_config_file

    with pytest.raises(ConfigError):
        RunConfig.from_dict({"detector": {key: value}})
    good = {
        "fuse_tol_m": 0.25,
        "fuse_range_power": 1.5,
        "fuse_max_frames": 4,
        "fuse_causal": True,
        "fuse_estimator": "median",
    }[key]
    p = tmp_path / "config.json"
    p.write_text(json.dumps({"detector": {key: good}}))
    cfg, _ = load_config_file(p)
    assert getattr(cfg.detector, key) == good and RunConfig.from_dict(cfg.to_dict()) == cfg


def test_detect_archive_fuses_when_on_and_not_when_off(monkeypatch):
    import lunarloc.perception.detector as detector_mod

    rock = np.array([5.0, 0.4, 0.0])
    offs = [np.array([0.03 * (-1) ** k, 0.0, 0.0]) for k in range(4)]

    def frames(*_args, **_kwargs):
        return iter([_frame(k, 0.3 * k, [rock + offs[k]]) for k in range(4)])

    monkeypatch.setattr(detector_mod, "_detect_archive_frames", frames)
    for cfg, fused in (
        (DetectorConfig(fuse_tol_m=0.0), False),
        (DetectorConfig(fuse_tol_m=0.2), True),
    ):
        out = list(detector_mod.detect_archive(None, cfg, detector=detector_mod.Detector(cfg)))
        got = np.array([f.detections[0].p_map for f in out])
        assert np.allclose(got, rock + np.mean(offs, axis=0)) == fused
        assert np.allclose(got, rock + np.array(offs)) != fused


def test_landmark_centres_benchmark_scores_landmarks_against_the_true_rocks():
    from lunarloc.pipeline import landmark_centres as lc

    rng = np.random.default_rng(7)
    rocks = np.array(
        [[1, 4.0, 0.0, 0.1, 0.15], [2, 4.0, 1.5, 0.05, 0.06], [3, 6.0, -1.0, 0.1, 0.2]]
    )
    frames = np.arange(8)
    rover = np.column_stack([0.3 * frames, np.zeros(8), np.zeros(8)])
    D, DF, R = [], [], []
    for f in frames:
        for r in rocks:
            D.append(r[1:4] + rng.normal(0.0, 0.03, 3))
            DF.append(f)
            R.append(float(np.linalg.norm(r[1:4] - rover[f])))
    bias = np.array([0.02, 0.0, 0.0])  # one shared offset of every sighting of rock 3
    D = [d + bias if k % 3 == 2 else d for k, d in enumerate(D)]
    res = lc.evaluate([(frames, rover, D, DF, R, rocks, "x")], [3])
    det, lm = res["all"]["detections"], res["all"]["landmarks_ms3"]
    assert det["matched"] == 24 and lm["items"] == 3 and lm["matched"] == 3
    # r >= 0.1 m: rocks 1 and 3; detections only within 5 m (rock 3 from 4 of the 8 frames)
    assert lm["target"]["n"] == 2 and det["target"]["n"] == 8 + 4
    assert (
        lm["all"]["3d_median_m"] < det["all"]["3d_median_m"]
    )  # the cluster's median averages the noise
    assert set(res) == {"x", "all"}
