"""lunarloc.pipeline.perception_eval (behind benchmarks/bench_perception.py): where a missed
rock was lost (--misses), and the targets' intervals with the sites resampled."""

import numpy as np
import pytest

from lunarloc.core.errors import InputError
from lunarloc.perception.detector import MaskRecord, PairResult
from lunarloc.perception.masks import RejectReason, mask_stats, masks_from_labels
from lunarloc.perception.stereo import HeightMap
from lunarloc.pipeline import perception_eval as bench


def _pair(reasons, height=None):
    """Two masks on a 40 x 60 image: rows 10-19 x columns 10-29 and rows 25-34 x 40-54."""
    lab = np.zeros((40, 60), np.int32)
    lab[10:20, 10:30] = 1
    lab[25:35, 40:55] = 2
    masks = masks_from_labels(lab)
    recs = [
        MaskRecord(i, mask_stats(m, masks.image_shape), 3.0, 0.05, r)
        for i, (m, r) in enumerate(zip(masks, reasons))
    ]
    return PairResult("FrontLeft", masks, recs, [], None, height)


def test_a_miss_is_put_at_the_mask_overlapping_it_most_or_at_the_height_map():
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
    assert got["rejected_by"] == ""
    # a blob judged no rock says what judged it: the rules that fired, or the verifier
    pair = _pair([RejectReason.NOT_A_ROCK, None])
    pair.records[0].rejected_by = "verifier"
    got = bench.miss_stage(pair, rock)
    assert (got["stage"], got["rejected_by"]) == ("not_a_rock", "verifier")
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
    assert (
        got["stage"] == "no-blob" and got["valid_fraction"] == 1.0 and got["max_height_m"] == 0.02
    )


def test_misses_are_grouped_by_rock_most_missed_first():
    def row(archive, rock, frame, stage, rng):
        return dict(
            archive=archive,
            frame=frame,
            camera="FrontLeft",
            rock_id=rock,
            radius_m=0.2,
            range_m=rng,
            stage=stage,
        )

    rows = [
        row("a.lac", 7, 0, "elongated", 4.5),
        row("b.lac", 7, 0, "kept", 3.0),
        row("a.lac", 7, 40, "elongated", 3.9),
        row("a.lac", 7, 80, "tentative", 3.2),
        row("a.lac", 3, 0, "no-blob", 2.0),
    ]
    got = bench.misses_by_rock(rows)
    # the same id in two archives is two rocks; the most missed first
    assert [(g["archive"], g["rock_id"], g["missed"]) for g in got] == [
        ("a.lac", 7, 3),
        ("a.lac", 3, 1),
        ("b.lac", 7, 1),
    ]
    assert got[0]["stages"] == [("elongated", 2), ("tentative", 1)]
    assert (got[0]["range_min_m"], got[0]["range_max_m"]) == (3.2, 4.5)
    assert bench.misses_by_rock([]) == []


def _site(hit, total, tp, det, err):
    return {
        "target": np.array([hit, total]),
        "precision": np.array([tp, det]),
        "small": np.array([0, 0]),
        "err": list(err),
    }


def test_site_intervals_resample_sites_not_sightings():
    assert (
        bench.site_bootstrap({"site1": _site(9, 10, 9, 10, [0.03])}) == {}
    )  # one site: nothing to resample
    # identical sites: the interval shrinks to the figure itself
    same = bench.site_bootstrap({f"site{i}": _site(9, 10, 19, 20, [0.02, 0.04]) for i in range(5)})
    assert same["target_recall_r>=0.1_range<=5"] == [0.9, 0.9]
    assert same["precision_range<=5"] == [0.95, 0.95]
    assert "recall_0.05<=r<0.1_range<=3" not in same  # no small rock seen anywhere
    assert np.allclose(same["centroid_err_target_median_m"], 0.03)
    # one bad site among good ones: the interval spans the pooled figure and stays within
    # the sites' own range; many sightings at one site do not narrow it as independent
    # sightings would
    sites = {f"site{i}": _site(95, 100, 95, 100, [0.03] * 3) for i in range(4)}
    sites["site9"] = _site(50, 100, 80, 100, [0.10] * 3)
    lo, hi = bench.site_bootstrap(sites)["target_recall_r>=0.1_range<=5"]
    assert 0.5 <= lo < 430 / 500 < hi <= 0.95
    assert hi - lo > 0.1
    lo, hi = bench.site_bootstrap(sites)["centroid_err_target_median_m"]
    assert lo == 0.03 and hi >= 0.03


def test_counts_are_kept_per_site_and_summed_over_lightings():
    groups = []
    for hits in ((3, 1), (2, 2)):  # two lightings; in each, sites 7 and 8
        g = bench.Accumulator()
        for name, h in zip(("site7_sun_el5_traverse0.lac", "site8_sun_el5_traverse0.lac"), hits):
            g.begin_archive(name)
            g.rec[1, 0] += [h, 4]  # r 0.1-0.2 m within 2.5 m: h of 4 seen
            g.prec[0, 1] += [5, 6]
            g.err_target.extend([0.01 * h] * h)
            g.end_archive()
        groups.append(g)
    assert groups[0].by_site["site7"]["target"].tolist() == [3, 4]
    assert groups[0].by_site["site8"]["precision"].tolist() == [5, 6]
    total = bench.Accumulator()
    for g in groups:
        total.merge(g)
    assert total.by_site["site7"]["target"].tolist() == [5, 8]
    assert total.by_site["site8"]["err"] == [0.01, 0.02, 0.02]
    s = total.summary()
    assert s["sites"] == 2 and s["target_recall_counts"] == [8, 16]
    lo, hi = s["site_bootstrap_ci90"]["target_recall_r>=0.1_range<=5"]
    assert 3 / 8 <= lo <= 0.5 <= hi <= 5 / 8


def test_runs_pool_by_lighting_and_refuse_a_site_counted_twice(tmp_path):
    import json

    def run(path, lighting, sites):
        by_site = {
            k: {"target": [h, 10], "precision": [9, 10], "small": [1, 2], "err": [0.02, 0.04]}
            for k, h in sites.items()
        }
        path.write_text(json.dumps({"by_lighting": {lighting: {"by_site": by_site}}}))
        return path

    a = run(tmp_path / "a.json", "sun 5", {"site1": 9, "site2": 7})
    b = run(tmp_path / "b.json", "sun 5", {"site3": 8})
    c = run(tmp_path / "c.json", "lamps", {"site1": 6})
    pooled = bench.pool_runs([a, b, c])
    assert sorted(pooled) == ["lamps", "sun 5"] and sorted(pooled["sun 5"]) == [
        "site1",
        "site2",
        "site3",
    ]
    rows = bench.pooled_rows(pooled)
    assert rows["sun 5"]["target_recall_r>=0.1_range<=5"] == (0.8, [24, 30])
    assert rows["lamps"]["sites"] == 1 and rows["lamps"]["ci90"] == {}  # one site: no interval
    assert "sun 5 | 3 | 0.900" in "\n".join(bench.format_pooled(rows))
    with pytest.raises(InputError, match="site1 under sun 5 is in two runs"):
        bench.pool_runs([a, a])
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"by_lighting": {"sun 5": {"frames": 3}}}))
    with pytest.raises(InputError, match="no per-site counts"):
        bench.pool_runs([old])
    old.write_text("[1, 2]")  # not a run at all
    with pytest.raises(InputError, match="no per-site counts"):
        bench.pool_runs([old])
    old.write_text(json.dumps({"by_lighting": {"sun 5": {"by_site": {"site1": {"target": [1]}}}}}))
    with pytest.raises(InputError, match="counts of site1 under sun 5 are malformed"):
        bench.pool_runs([old])
    with pytest.raises(InputError, match="cannot read"):
        bench.pool_runs([tmp_path / "missing.json"])


def test_the_centre_breakdown_has_a_row_for_all_target_matches():
    # (true radius, range, 3D error, horizontal, along, lateral, vertical, est/true radius, oracle)
    rows = [
        (0.12, 1.0, 0.02, 0.01, 0.0, 0.0, 0.0, 1.0, 0.01),
        (0.12, 3.0, 0.04, 0.03, 0.0, 0.0, 0.0, 1.0, 0.03),
        (0.35, 3.0, 0.10, 0.08, 0.0, 0.0, 0.0, 0.8, 0.05),
    ]
    got = bench.centre_breakdown(rows)
    assert (
        got["all"]["n"] == 3
        and got["all"]["median_m"] == 0.04
        and got["all"]["true_radius_oracle_median_m"] == 0.03
    )
    assert got["radius 0.1-0.15"]["n"] == 2 and got["radius 0.3-0.5"]["median_m"] == 0.10
    assert got["range 2.5-5"]["n"] == 2 and "radius 0.15-0.2" not in got
