"""CPU time of the rock detector on the four real LAC front pairs (1280x720), with the
small-rock stage off and on.

    python benchmarks/real_pair_speed.py [--data DIR] [--repeat 3]

    python benchmarks/real_pair_speed.py --stages [--repeat 4]

    python benchmarks/real_pair_speed.py [--stages] --config RUN.json   # a run configuration's detector

DIR defaults to $LUNARLOC_LAC_REAL or ../shared/data/lac-real. Each pair runs once to warm
up (OpenCV allocations), then `--repeat` times through ``Detector.detect_pair`` (no rover
pose; levelling from stereo as by default); reported: process CPU time per pair (all
threads, so it does not depend much on the machine's load) and wall time per pair.

``--stages``: the small-rock stage on only, with the detector's stages timed (process CPU
per pair, including the timing wrappers' own small cost; nested stages are indented and
count in their parent too) and the page faults (fresh memory pages the kernel had to map,
a cost that shows as system time) per pair. The small-rock stage is split into its
candidates (difference-of-Gaussians blobs and, with count_checked, their pre-checks), its
full-resolution windows (their SGBM match and their local ground fit), the verdicts and the
learned judge's features.
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
    ap.add_argument("--stages", action="store_true", help="time the detector's stages")
    ap.add_argument(
        "--config", type=Path, default=None, help="a run configuration (JSON): its detector section"
    )
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
    cfg = DetectorConfig()
    if a.config is not None:
        from lunarloc.config.run import load_config_file

        cfg = load_config_file(a.config)[0].detector
    if a.stages:
        return _stages(pairs, cam, T, a.repeat, cfg)
    for on in (False, True):
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


# (label, module, attribute path): what --stages times, in the order of a pair's work
_STAGES = [
    ("height map", "lunarloc.perception.detector", "Detector.height_map"),
    ("  disparity (SGBM, 1/2 res)", "lunarloc.perception.stereo", "StereoMatcher.disparity_lowres"),
    ("  ground heights", "lunarloc.perception.detector", "ground_height_map"),
    ("  view's ground plane", "lunarloc.perception.detector", "ground_plane"),
    ("height blobs", "lunarloc.perception.detector", "Detector._segment_blobs"),
    ("  split at depth steps", "lunarloc.perception.detector", "split_at_depth_steps"),
    ("judge the blobs", "lunarloc.perception.detector", "Detector._judge_masks"),
    ("  measure kept blobs", "lunarloc.perception.detector", "Detector._measure_blob"),
    ("small-rock stage", "lunarloc.perception.detector", "Detector._add_small_rocks"),
    ("  candidates (DoG blobs)", "lunarloc.perception.small_rocks", "_candidates"),
    ("  windows (full-res match)", "lunarloc.perception.small_rocks", "_local_heights"),
    ("    SGBM of the windows", "lunarloc.perception.small_rocks", "_Matcher.window"),
    ("    local ground fit", "lunarloc.perception.small_rocks", "_ground_heights"),
    ("  verdicts", "lunarloc.perception.small_rocks", "_judge"),
    ("  judge's features", "lunarloc.perception.small_rocks", "judge_features"),
    ("whole pair", "lunarloc.perception.detector", "Detector.detect_pair"),
]


def _stages(pairs, cam, T, repeat: int, cfg) -> int:
    import functools
    import importlib
    import resource

    from lunarloc.perception.detector import Detector

    acc: dict[str, list[float]] = {}

    def wrap(label, fn):
        @functools.wraps(fn)
        def timed(*args, **kw):
            r0, c0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.process_time()
            try:
                return fn(*args, **kw)
            finally:
                s = acc.setdefault(label, [0.0, 0.0, 0])
                s[0] += time.process_time() - c0
                s[1] += resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0
                s[2] += 1

        return timed

    for label, module, path in _STAGES:
        owner = importlib.import_module(module)
        *parents, name = path.split(".")
        for p in parents:
            owner = getattr(owner, p)
        setattr(owner, name, wrap(label, getattr(owner, name)))
    det = Detector(cfg, cam)
    for left, right in pairs:
        det.detect_pair(left, right, T)
    acc.clear()
    for _ in range(repeat):
        for left, right in pairs:
            det.detect_pair(left, right, T)
    n = repeat * len(pairs)
    print(
        f"small rocks {'on' if cfg.small_rocks.enabled else 'off'}, {n} pairs, load average {os.getloadavg()[0]:.1f}"
    )
    for label, _, _ in _STAGES:
        cpu, faults, calls = acc.get(label, (0.0, 0.0, 0))
        print(
            f"{label:30s} {1000 * cpu / n:6.1f} ms CPU per pair, {faults / n:6.0f} page faults, "
            f"{calls / n:4.1f} calls per pair"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
