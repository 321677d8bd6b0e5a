"""benchmarks/repeatability.py's by-depth breakdown: each r >= 0.1 m sighting's deviation from
its rock's session mean lands in its detection-depth band; small rocks and rocks seen too
few times are left out."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import repeatability

from lunarloc.sim.repeatability import SightingLog


def test_deviation_by_depth_splits_near_and_far_sightings():
    log, depths = SightingLog(), {}
    # rock 1 (r 0.15): two near sightings 1 cm either side of its mean, two far ones 5 cm
    for xy, z in (((0.01, 0.0), 2.0), ((-0.01, 0.0), 2.5), ((0.0, 0.05), 4.5), ((0.0, -0.05), 4.2)):
        log.add("s", 1, xy)
        depths.setdefault(("s", 1), []).append(z)
    # rock 2 is small and rock 3 seen twice: neither counts
    for rock, r_xy in ((2, (0.3, 0.0)), (3, (0.0, 0.3))):
        for k in range(4 if rock == 2 else 2):
            log.add("s", rock, r_xy)
            depths.setdefault(("s", rock), []).append(3.5)
    radii = {("s", 1): 0.15, ("s", 2): 0.05, ("s", 3): 0.2}
    out = repeatability.deviation_by_depth(log, depths, radii, min_sightings=3)
    assert out["0-3"]["n"] == 2 and out["0-3"]["median_m"] == pytest.approx(0.01)
    assert out[">=4"]["n"] == 2 and out[">=4"]["median_m"] == pytest.approx(0.05)
    assert out["3-4"]["n"] == 0 and np.isnan(out["3-4"]["median_m"])
