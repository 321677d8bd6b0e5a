"""CPU time of the rock detector on the four real LAC front pairs (1280x720), with the
small-rock stage off and on.

    python benchmarks/real_pair_speed.py [--data DIR] [--repeat 3]

DIR defaults to $LUNARLOC_LAC_REAL or ../shared/data/lac-real. Each pair runs once to warm
up (OpenCV allocations), then `--repeat` times through ``Detector.detect_pair`` (no rover
pose; levelling from stereo as by default); reported: process CPU time per pair (all
threads, so it does not depend much on the machine's load) and wall time per pair.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

HERE = Path(__file__).resolve().parent
PAIRS = [("FrontLeft_99.png", "FrontRight_99.png")] + [
    (f"ipex/FrontLeft_1_{f}.png", f"ipex/FrontRight_1_{f}.png") for f in (179, 185, 191)
]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--data",
        type=Path,
        default=Path(
            os.environ.get("LUNARLOC_LAC_REAL", HERE.parent.parent / "shared/data/lac-real")
        ),
    )
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    import cv2

    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.perception.detector import Detector, DetectorConfig

    pairs = [
        (
            cv2.imread(str(a.data / left), cv2.IMREAD_GRAYSCALE),
            cv2.imread(str(a.data / right), cv2.IMREAD_GRAYSCALE),
        )
        for left, right in PAIRS
    ]
    if any(p is None for pair in pairs for p in pair):
        print(f"the real LAC pairs are not under {a.data}", file=sys.stderr)
        return 2
    cam = PinholeCamera(1280, 720)
    T = ipex_rig(cam)["FrontLeft"].T_rover_optical
    for on in (False, True):
        cfg = DetectorConfig()
        det = Detector(replace(cfg, small_rocks=replace(cfg.small_rocks, enabled=on)), cam)
        for left, right in pairs:
            det.detect_pair(left, right, T)
        c0, w0, n = time.process_time(), time.perf_counter(), 0
        for _ in range(a.repeat):
            for left, right in pairs:
                det.detect_pair(left, right, T)
                n += 1
        cpu, wall = (time.process_time() - c0) / n, (time.perf_counter() - w0) / n
        print(
            f"small rocks {'on ' if on else 'off'}: {1000 * cpu:.0f} ms CPU per pair ({1 / cpu:.1f} pairs/s CPU), "
            f"{1000 * wall:.0f} ms wall; load average {os.getloadavg()[0]:.1f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
