"""The detector's faster internals give exactly what the plain forms they replace give."""

from __future__ import annotations

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")


def test_components_in_a_row_band_equal_opencv_on_the_whole_image():
    from lunarloc.perception.segment import _components

    rng = np.random.default_rng(0)
    for t in range(400):
        h, w = int(rng.integers(2, 90)), int(rng.integers(2, 90))
        if t % 3:
            img = (rng.random((h, w)) < rng.random() * 0.7).astype(np.uint8)
        else:
            blur = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.5)
            img = (blur > 0.5).astype(np.uint8)
        a = int(rng.integers(0, h))
        b = int(rng.integers(a, h + 1))
        img[:a] = 0
        img[b:] = 0
        if t % 7 == 0:
            img[a:b] = 1  # full rows of foreground
        n, lab, st, _ = cv2.connectedComponentsWithStats(img, connectivity=8)
        n2, lab2, st2 = _components(img)
        assert n2 == n
        assert lab2.dtype == lab.dtype and np.array_equal(lab2, lab)
        assert np.array_equal(st2, st)


def test_lowres_index_is_the_sorted_unique_cells_of_the_mask_pixels():
    from lunarloc.perception.masks import InstanceMask
    from lunarloc.perception.stereo import HeightMap

    rng = np.random.default_rng(1)
    for k in (1, 2, 3):
        h, w = 40, 60
        hm = HeightMap(*(np.zeros((h, w), np.float32),) * 2, None, np.zeros((h, w)), k, 0, None)
        for _ in range(50):
            ch, cw = int(rng.integers(1, 30)), int(rng.integers(1, 30))
            crop = rng.random((ch, cw)) < 0.4
            u0, v0 = int(rng.integers(0, w * k - 5)), int(rng.integers(0, h * k - 5))
            rows, cols = hm.lowres_index(InstanceMask(u0, v0, crop))
            vv, uu = np.nonzero(crop)
            lv, lu = (vv + v0) // k, (uu + u0) // k
            ok = (lv < h) & (lu < w)
            key = np.unique(lv[ok].astype(np.int64) * w + lu[ok])
            assert rows.dtype == np.int64 and cols.dtype == np.int64
            assert np.array_equal(rows, key // w) and np.array_equal(cols, key % w)


def test_quantiles64_is_numpy_quantile_of_a_list_bit_for_bit():
    from lunarloc.perception.detector import _quantiles64

    rng = np.random.default_rng(2)
    for t in range(3000):
        n = int(rng.integers(1, 300)) if t % 2 else int(rng.integers(1, 6))
        z = (rng.random(n) * rng.choice([1, 5, 30]) + rng.random() * 3).astype(np.float32)
        if t % 3 == 0:
            z = np.round(z, 1).astype(np.float32)  # ties
        if t % 5 == 0:
            z = z.astype(np.float64)
        qs = (0.05, 0.95) if t % 4 else (float(rng.random()), float(rng.random()))
        want = np.quantile(z, list(qs))
        got = _quantiles64(z.copy(), qs)
        assert [np.float64(v).tobytes() for v in got] == [v.tobytes() for v in want]


def test_heights_filled_later_equal_heights_computed_at_once():
    from lunarloc.perception.camera import PinholeCamera, ipex_rig
    from lunarloc.perception.stereo import GroundConfig, fill_ground_heights, ground_height_map

    cam = PinholeCamera()
    T = ipex_rig(cam)["FrontLeft"].T_rover_optical
    rng = np.random.default_rng(3)
    h, w = cam.height // 2, cam.width // 2
    disp = (rng.random((h, w)) * 60 + 1).astype(np.float32)
    disp[: h // 3] = np.nan  # sky
    disp[rng.random((h, w)) < 0.3] = np.nan
    full = ground_height_map(disp, 2, cam, 0.162, T, GroundConfig(), 95.0)
    lazy = ground_height_map(disp, 2, cam, 0.162, T, GroundConfig(), 95.0, heights=False)
    assert np.isnan(lazy.height).all()
    assert lazy.depth.tobytes() == full.depth.tobytes()
    assert lazy.points_rover.tobytes() == full.points_rover.tobytes()
    assert fill_ground_heights(lazy) is lazy
    assert lazy.height.tobytes() == full.height.tobytes()
    assert lazy.valid_u0 == full.valid_u0
    assert fill_ground_heights(lazy).height.tobytes() == full.height.tobytes()  # once only
