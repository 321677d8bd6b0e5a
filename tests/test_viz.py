"""Figures of a loop run (synthetic traverse, no images; plus an example frame)."""

import numpy as np
import pytest

from _loop_data import synthetic_traverse
from lunarloc.core.errors import FileFormatError
from lunarloc.pipeline.evaluation import DriftModel
from lunarloc.io.maps import LandmarkMap
from lunarloc.config.run import RunConfig
from lunarloc.pipeline.runner import run
from lunarloc.io.runs import write_run
from lunarloc.pipeline.sources import TraverseCsvSource
from lunarloc.viz import plot_run


def test_plot_run_writes_figures(tmp_path):
    rocks, trav = synthetic_traverse(length_m=10.0)
    res = run(
        TraverseCsvSource(trav, DriftModel(0.1, 0.03)),
        LandmarkMap(rocks),
        RunConfig.for_detections(),
    )
    res.rocks = np.column_stack([np.arange(len(rocks)), rocks, np.full(len(rocks), 0.1)])
    res.example = {
        "image": (np.random.default_rng(0).uniform(0, 255, (90, 160))).astype(np.uint8),
        "uv": np.array([[40.0, 50.0]]),
        "radius_px": np.array([5.0]),
        "depth_m": np.array([3.2]),
        "frame": 10,
        "camera": "FrontLeft",
    }
    write_run(res, tmp_path)
    paths = plot_run(tmp_path, tmp_path / "fig")
    assert sorted(p.name for p in paths) == ["error.png", "frame.png", "map.png"]
    for p in paths:
        assert p.stat().st_size > 10_000
        assert p.read_bytes()[:4] == b"\x89PNG"


def test_plot_run_rejects_other_folders(tmp_path):
    with pytest.raises(FileFormatError, match="not a lunarloc run folder"):
        plot_run(tmp_path)
