"""benchmarks/bench_lac_leaderboard.py's attempts.json rows: every field nees_online.py and a
reader of the fix covariance need, the heading's distortion allowance included, for the
successful attempts only, and JSON-writable. Nothing is rendered."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

pytest.importorskip(
    "embreex", reason="the benchmark imports the stand-in simulator (lunarloc[sim])"
)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_lac_leaderboard as bench

from lunarloc.online.loop import Attempt


def _attempt(frame: int, success: bool, **kw) -> Attempt:
    return Attempt(
        frame=frame,
        time_s=0.05 * frame,
        keyframe=frame // 5,
        landmarks=12,
        reference_landmarks=40,
        success=success,
        accepted=success,
        **kw,
    )


def test_attempt_records_keep_the_fix_and_both_distortion_allowances():
    fix = {
        "inliers": 11,
        "predicted_error_m": 0.03,
        "fix_xyz": [1.0, 2.0, 0.1],
        "fix_covariance_xyz": [[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 4e-4]],
        "fix_yaw_rad": 0.5,
        "fix_sigma_yaw_rad": 0.004,
        "fix_distortion_m": 0.012,
        "fix_distortion_yaw_rad": 0.0021,
    }
    rows = bench.attempt_records([_attempt(40, True, **fix), _attempt(60, False, inliers=4)])
    assert len(rows) == 1  # the refused localization is not a fix
    (row,) = json.loads(json.dumps(rows))
    assert set(row) == set(bench.ATTEMPT_FIELDS)
    assert row["frame"] == 40 and row["accepted"] is True
    for k, v in fix.items():
        assert row[k] == v, k
    # every kept field is an Attempt attribute (a renamed one would fail here, not mid-run)
    assert all(hasattr(_attempt(1, True), k) for k in bench.ATTEMPT_FIELDS)
    # an attempt that never set the allowance keeps it as NaN, not absent
    (bare,) = bench.attempt_records([_attempt(3, True)])
    assert math.isnan(bare["fix_distortion_yaw_rad"])
