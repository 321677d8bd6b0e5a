"""Helper used to hand-label the real LAC pairs (tests/data/lac_real_labels.json).

    python benchmarks/label_real_pairs.py disparity LEFT RIGHT OUT.npy
    python benchmarks/label_real_pairs.py tile LEFT x0 y0 x1 y1 SCALE OUT.png     # crop, upscale, pixel grid
    python benchmarks/label_real_pairs.py measure OUT.npy x0,y0,x1,y1 ...          # range and width of boxes

The range of a box is the median SGBM range in the inner half of the box (full resolution, 256
disparities, block 5, 3-way, both images padded on the left by the search range); its width is the
box width x range / fx. Camera: 1280x720, 70 degree HFOV, 0.162 m baseline (the LAC's front pair).
"""

from __future__ import annotations

import sys

import numpy as np

FX_PX = 640.0 / np.tan(np.radians(35.0))
BASELINE_M = 0.162


def disparity(left: np.ndarray, right: np.ndarray, n_disp: int = 256) -> np.ndarray:
    import cv2

    lp = cv2.copyMakeBorder(left, 0, 0, n_disp, 0, cv2.BORDER_CONSTANT, value=0)
    rp = cv2.copyMakeBorder(right, 0, 0, n_disp, 0, cv2.BORDER_CONSTANT, value=0)
    sg = cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=n_disp,
        blockSize=5,
        P1=8 * 25,
        P2=32 * 25,
        uniquenessRatio=5,
        speckleWindowSize=100,
        speckleRange=2,
        disp12MaxDiff=1,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    d = sg.compute(lp, rp).astype(np.float32)[:, n_disp:] / 16.0
    d[d <= 0] = np.nan
    return d


def measure(d: np.ndarray, box) -> tuple[float, float]:
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    sub = d[y0 + h // 4 : y1 - h // 4 + 1, x0 + w // 4 : x1 - w // 4 + 1]
    v = sub[np.isfinite(sub)]
    if v.size < 3:
        sub = d[max(0, y0 - 3) : y1 + 3, max(0, x0 - 3) : x1 + 3]
        v = sub[np.isfinite(sub)]
    if v.size < 3:
        return float("nan"), float("nan")
    z = FX_PX * BASELINE_M / float(np.median(v))
    return z, (x1 - x0) * z / FX_PX


def tile(img: np.ndarray, box, scale: int) -> np.ndarray:
    import cv2

    x0, y0, x1, y1 = box
    big = cv2.cvtColor(
        cv2.resize(img[y0:y1, x0:x1], None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC),
        cv2.COLOR_GRAY2BGR,
    )
    for x in range((x0 // 10 + 1) * 10, x1, 10):
        cv2.line(
            big,
            ((x - x0) * scale, 0),
            ((x - x0) * scale, 12 if x % 100 == 0 else 5),
            (0, 200, 0),
            1,
        )
        if x % 40 == 0:
            cv2.putText(
                big,
                str(x),
                ((x - x0) * scale + 2, 12),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.35,
                (0, 255, 255),
                1,
            )
    for y in range((y0 // 10 + 1) * 10, y1, 10):
        cv2.line(
            big,
            (0, (y - y0) * scale),
            (12 if y % 100 == 0 else 5, (y - y0) * scale),
            (0, 200, 0),
            1,
        )
        if y % 40 == 0:
            cv2.putText(
                big,
                str(y),
                (2, (y - y0) * scale - 2),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.35,
                (0, 255, 255),
                1,
            )
    return big


def main(argv: list[str]) -> int:
    import cv2

    if not argv:
        print(__doc__)
        return 2
    cmd = argv[0]
    if cmd == "disparity":
        L = cv2.imread(argv[1], cv2.IMREAD_GRAYSCALE)
        R = cv2.imread(argv[2], cv2.IMREAD_GRAYSCALE)
        np.save(argv[3], disparity(L, R))
    elif cmd == "tile":
        img = cv2.imread(argv[1], cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(argv[7], tile(img, [int(a) for a in argv[2:6]], int(argv[6])))
    elif cmd == "measure":
        d = np.load(argv[1])
        for s in argv[2:]:
            z, w = measure(d, [int(a) for a in s.split(",")])
            print(f"{s}: range {z:.2f} m, width {w:.3f} m")
    else:
        print(__doc__)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
