"""benchmarks/bench_perception.py --misses: where a missed rock was lost."""

import importlib.util
from pathlib import Path

import numpy as np

from lunarloc.perception.detector import MaskRecord, PairResult
from lunarloc.perception.masks import RejectReason, mask_stats, masks_from_labels
from lunarloc.perception.stereo import HeightMap

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_perception.py"


def _bench():
    spec = importlib.util.spec_from_file_location("bench_perception", BENCH)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _pair(reasons, height=None):
    """Two masks on a 40 x 60 image: rows 10-19 x columns 10-29 and rows 25-34 x 40-54."""
    lab = np.zeros((40, 60), np.int32)
    lab[10:20, 10:30] = 1
    lab[25:35, 40:55] = 2
    masks = masks_from_labels(lab)
    recs = [MaskRecord(i, mask_stats(m, masks.image_shape), 3.0, 0.05, r) for i, (m, r) in enumerate(zip(masks, reasons))]
    return PairResult("FrontLeft", masks, recs, [], None, height)


def test_a_miss_is_put_at_the_mask_overlapping_it_most_or_at_the_height_map():
    bench = _bench()
    rock = np.zeros((40, 60), bool)
    rock[12:22, 20:34] = True  # mostly under the first mask
    got = bench.miss_stage(_pair([RejectReason.ELONGATED, None]), rock)
    assert got["stage"] == "elongated" and 0.3 < got["overlap"] < 0.7
    assert got["mask_depth_m"] == 3.0 and got["mask_eig_ratio"] > 1.0
    # a dropped tentative says which marginal rules made it one
    pair = _pair([RejectReason.TENTATIVE, None])
    pair.records[0].tentative = "contrast+quadric"
    got = bench.miss_stage(pair, rock)
    assert (got["stage"], got["tentative_rules"]) == ("tentative", "contrast+quadric")
    # kept, but not matched: the detection's centre lies too far from the rock's
    assert bench.miss_stage(_pair([None, None]), rock)["stage"] == "kept"
    # no mask over it: the height map says why no blob formed (half its pixels without
    # a height, the rest 2 cm above the ground)
    H = np.full((20, 30), 0.02)
    H[6:11, :10] = np.nan  # low-resolution rows 6-10, columns 0-9: full-resolution 12-21, 0-19
    hm = HeightMap(np.ones((20, 30)), np.ones((20, 30)), np.zeros((20, 30, 3)), H, 2, 0, np.eye(4))
    far = np.zeros((40, 60), bool)
    far[12:22, 0:8] = True  # left of both masks, over the rows without heights
    got = bench.miss_stage(_pair([None, None], hm), far)
    assert got["stage"] == "no-blob" and got["overlap"] == 0.0
    assert got["valid_fraction"] == 0.0 and np.isnan(got["max_height_m"])
    near = np.zeros((40, 60), bool)
    near[12:22, 30:38] = True  # columns 15-18 low-res: heights of 2 cm; no mask there
    got = bench.miss_stage(_pair([None, None], hm), near)
    assert got["stage"] == "no-blob" and got["valid_fraction"] == 1.0 and got["max_height_m"] == 0.02


def test_misses_are_grouped_by_rock_most_missed_first():
    bench = _bench()

    def row(archive, rock, frame, stage, rng):
        return dict(archive=archive, frame=frame, camera="FrontLeft", rock_id=rock, radius_m=0.2, range_m=rng,
                    stage=stage)

    rows = [row("a.lac", 7, 0, "elongated", 4.5), row("b.lac", 7, 0, "kept", 3.0), row("a.lac", 7, 40, "elongated", 3.9),
            row("a.lac", 7, 80, "tentative", 3.2), row("a.lac", 3, 0, "no-blob", 2.0)]
    got = bench.misses_by_rock(rows)
    # the same id in two archives is two rocks; the most missed first
    assert [(g["archive"], g["rock_id"], g["missed"]) for g in got] == [("a.lac", 7, 3), ("a.lac", 3, 1), ("b.lac", 7, 1)]
    assert got[0]["stages"] == [("elongated", 2), ("tentative", 1)]
    assert (got[0]["range_min_m"], got[0]["range_max_m"]) == (3.2, 4.5)
    assert bench.misses_by_rock([]) == []
