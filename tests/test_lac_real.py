"""The one real LAC frame (`../shared/data/lac-real/`, or $LUNARLOC_LAC_REAL): no detection
on the lander, the near rocks found. One frame: a smoke test of the transfer to the
LAC's imagery, not a benchmark (the constants were not tuned to it)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from lunarloc.core.geometry import pose_to_matrix
from lunarloc.perception.camera import PinholeCamera, ipex_rig
from lunarloc.perception.detector import Detector, DetectorConfig

LAC_REAL = Path(
    os.environ.get(
        "LUNARLOC_LAC_REAL",
        Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lac-real",
    )
)
FILES = ("FrontLeft_99.png", "FrontRight_99.png", "pose_99.json")

pytestmark = pytest.mark.skipif(
    not all((LAC_REAL / f).is_file() for f in FILES),
    reason=f"real LAC frame not found in {LAC_REAL}",
)

# image boxes (u0, v0, u1, v1) of what the frame shows (README of the data): the
# lander, and the rocks near the rover
LANDER_BOX = (770, 40, 1160, 395)
NEAR_ROCKS = {
    "boulder ahead left": (205, 400, 335, 510),
    "bottom centre": (455, 498, 498, 535),
    "bottom right": (1128, 594, 1192, 640),
}


@pytest.fixture(scope="module")
def frame():
    import cv2

    left = cv2.imread(str(LAC_REAL / FILES[0]), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(LAC_REAL / FILES[1]), cv2.IMREAD_GRAYSCALE)
    p = json.loads((LAC_REAL / FILES[2]).read_text())
    T_map_rover = pose_to_matrix(*[float(p[k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")])
    det = Detector(DetectorConfig(), PinholeCamera(1280, 720, 70.0))
    T_rover_optical = ipex_rig(det.camera)["FrontLeft"].T_rover_optical
    # the lander stands at the site centre (the map origin)
    with_lander = det.detect_pair(
        left, right, T_rover_optical, T_map_rover, "FrontLeft", lander_xy=np.zeros(2)
    )
    without = det.detect_pair(left, right, T_rover_optical, T_map_rover, "FrontLeft")
    return with_lander, without


def _inside(uv, box) -> bool:
    return box[0] <= uv[0] <= box[2] and box[1] <= uv[1] <= box[3]


def test_no_detection_on_the_lander(frame):
    with_lander, without = frame
    assert not any(_inside(d.uv, LANDER_BOX) for d in with_lander.detections)
    # without its pose, the lander's tall parts (deck, tanks, panels) are still no rock
    tall = [d for d in without.detections if _inside(d.uv, LANDER_BOX) and d.uv[1] < 300]
    assert not tall, [d.uv for d in tall]


def test_near_rocks_are_found_at_plausible_range(frame):
    with_lander, _ = frame
    for name, box in NEAR_ROCKS.items():
        hits = [d for d in with_lander.detections if _inside(d.uv, box)]
        assert hits, f"{name} not found"
        assert all(0.8 < d.depth_m < 2.0 and d.radius_m < 0.3 for d in hits), name
