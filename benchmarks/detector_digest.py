"""Every detection and every mask record of the detector as JSON, and its SHA-256: to show that a
refactor of the detector changed nothing (run it on two checkouts and compare the digests).

    python benchmarks/detector_digest.py real [--out FILE]          # the four real LAC pairs
    python benchmarks/detector_digest.py ARCHIVE.lac [--out FILE]   # a (simulated) archive

``real``: each labelled pair of tests/data/lac_real_labels.json through ``Detector.detect_pair``
(as benchmarks/real_labels.py runs it), with the default config and with the small-rock stage off,
keeping tentatives and not. An archive: every frame through ``detect_archive`` (confirmation,
tentatives) with the default config, the small-rock stage off, and track fusion on (fuse 0.2 m).
Floats are written by repr, so equal digests mean bit-identical detections. Prints the digest and
the number of entries; the real pairs' images from $LUNARLOC_LAC_REAL or ../shared/data/lac-real.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def _value(v):
    if isinstance(v, (np.ndarray, tuple)):
        return [repr(float(x)) for x in np.ravel(v)]
    return repr(v) if isinstance(v, float) else v


def pair_entry(pr) -> dict:
    """A PairResult's detections (every field) and records (index, reason, depth, size, tentative)."""
    return dict(
        dets=[{f.name: _value(getattr(d, f.name)) for f in fields(d)} for d in pr.detections],
        recs=[
            (
                r.mask_index,
                None if r.reason is None else r.reason.value,
                repr(r.depth_m),
                repr(r.size_m),
                r.tentative,
            )
            for r in pr.records
        ],
        nmasks=len(pr.masks),
    )


def _configs(fused: bool):
    from lunarloc.perception.detector import DetectorConfig

    base = DetectorConfig()
    out = {
        "default": base,  # the small-rock stage on (its default)
        "off": replace(base, small_rocks=replace(base.small_rocks, enabled=False)),
    }
    if fused:
        out["fused"] = DetectorConfig(
            fuse_tol_m=0.2
        )  # the flat key: loads on both sides of the sections
    return out


def real_pairs() -> dict:
    import cv2

    from lunarloc.core.geometry import pose_to_matrix
    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.perception.detector import Detector

    labels = json.loads((HERE.parent / "tests" / "data" / "lac_real_labels.json").read_text())
    data = Path(
        os.environ.get("LUNARLOC_LAC_REAL", HERE.parent.parent / "shared" / "data" / "lac-real")
    )
    cam = labels["camera"]
    out = {}
    for name, cfg in _configs(fused=False).items():
        det = Detector(cfg, PinholeCamera(cam["width_px"], cam["height_px"], cam["hfov_deg"]))
        T_ro = ipex_rig(det.camera)["FrontLeft"].T_rover_optical
        for fr in labels["frames"]:
            L = cv2.imread(str(data / fr["left"]), cv2.IMREAD_GRAYSCALE)
            R = cv2.imread(str(data / fr["right"]), cv2.IMREAD_GRAYSCALE)
            if L is None or R is None:
                raise SystemExit(f"{fr['name']}: images not found under {data}")
            T, lander = None, None
            if fr.get("pose"):
                p = json.loads((data / fr["pose"]).read_text())
                T = pose_to_matrix(*[float(p[k]) for k in ("x", "y", "z", "roll", "pitch", "yaw")])
                lander = np.zeros(2)
            for keep in (False, True):
                pr = det.detect_pair(
                    L, R, T_ro, T, "FrontLeft", lander_xy=lander, keep_tentative=keep
                )
                out[f"{name}/{fr['name']}/kt{int(keep)}"] = pair_entry(pr)
    return out


def archive_frames(path: Path) -> dict:
    from lunarloc.io.lac.archive import LacArchive
    from lunarloc.perception.detector import detect_archive

    out = {}
    for name, cfg in _configs(fused=True).items():
        with LacArchive(path) as a:
            for fd in detect_archive(a, cfg):
                out[f"{name}/{fd.frame}"] = [pair_entry(p) for p in fd.pairs]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("source", help="'real' or a .lac archive")
    ap.add_argument("--out", type=Path, default=None, help="write the JSON here")
    a = ap.parse_args(argv)
    out = real_pairs() if a.source == "real" else archive_frames(Path(a.source))
    text = json.dumps(out, indent=0, sort_keys=True)
    print(hashlib.sha256(text.encode()).hexdigest(), len(out))
    if a.out is not None:
        a.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
