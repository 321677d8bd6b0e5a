"""Checks on the paper's real traverses; skipped when ../shared/data/lunarloc-data is absent."""

import numpy as np

from lunarloc.pipeline.evaluation import PAPER_PAIRS, bench_pairs, drifted_detections, DriftModel
from lunarloc.io.maps import load_traverse


def test_all_traverses_load(real_data):
    for k in range(1, 18):
        t = load_traverse(real_data / "csv" / f"traverse_{k}.csv")
        assert len(t.detections_xyz) > 0 and np.all(np.isfinite(t.detections_xyz))


def test_paper_pairs_localize_under_2cm(real_data):
    s = bench_pairs(real_data, PAPER_PAIRS, seed=7)
    for r in s.results:
        assert r.success, (r.reference, r.vehicle, r.reason)
        assert r.err_origin_m < 0.02, (r.reference, r.vehicle, r.err_origin_m)
        assert r.correct


def test_drift_simulation_moves_detections(real_data):
    t = load_traverse(real_data / "csv" / "traverse_5.csv")
    det, rover, T_last = drifted_detections(
        t, DriftModel(heading_drift_deg_per_m=0.5, scale_error=0.02)
    )
    assert det.shape == t.detections_xyz.shape
    end_err = np.linalg.norm(rover[-1] - t.rover_xyz[-1])
    assert end_err > 0.01 * t.path_length
    assert np.allclose(rover[0], t.rover_xyz[0])
