"""Indexed (lost-in-space) search in a large reference map: right pose, refusals, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lunarloc.association.index import IndexConfig, ReferenceIndex, triangles
from lunarloc.sim.fields import uniform_rock_field, vehicle_window
from lunarloc.core.errors import ConfigError, DegenerateGeometryError, InputError
from lunarloc.core.geometry import rotation_angle, transform_points
from lunarloc.localization.config import LocalizationConfig, Mode
from lunarloc.localization.large import Search, build_index, localize_large
from lunarloc.io.maps import LandmarkMap


@pytest.fixture(scope="module")
def field5k():
    rng = np.random.default_rng(7)
    ref = uniform_rock_field(rng, 5000)
    return ref, build_index(ref)


def _pose_error(T_est, T_true, P):
    """Largest position error over the (vehicle-frame) points P, and rotation error (deg)."""
    d = np.linalg.norm(transform_points(T_est, P) - transform_points(T_true, P), axis=1)
    return float(d.max()), math.degrees(rotation_angle(T_est[:3, :3] @ T_true[:3, :3].T))


def test_triangles_match_brute_force():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 6, (40, 2))
    got = {tuple(t) for t in triangles(xy, 2.0, 0.4, chunk_pairs=7)}
    want = set()
    for i in range(40):
        for j in range(i + 1, 40):
            for k in range(j + 1, 40):
                d = [np.linalg.norm(xy[a] - xy[b]) for a, b in ((i, j), (i, k), (j, k))]
                if all(0.4 <= x <= 2.0 for x in d):
                    want.add((i, j, k))
    assert got == want and len(want) > 10


@pytest.mark.parametrize("seed", [1, 2])
def test_indexed_search_finds_the_pose_in_5000_rocks(field5k, seed):
    ref, index = field5k
    win = vehicle_window(np.random.default_rng(seed), ref, 150)
    res = localize_large(ref, win.vehicle, index=index, search="indexed")
    assert res.success, res.reason
    assert res.search == "indexed" and res.winner >= 0
    assert set(res.timings) == {"index", "vote", "exact"}  # stages, each counted once in time_s
    dt, drot = _pose_error(res.T_ref_veh, win.T_ref_veh, win.vehicle.positions_xyz)
    assert dt < 0.1 and drot < 0.5
    # inliers pair vehicle landmarks with the reference rocks they were cut from
    assert np.mean(win.ref_index[res.inliers[:, 0]] == res.inliers[:, 1]) > 0.95
    # the exact search ran on crops, not on the whole map
    assert all(c.get("crop_rocks", 0) < 1000 for c in res.candidates)
    assert res.considered < len(ref) * len(win.vehicle) / 3


def test_unrelated_vehicle_map_is_refused(field5k):
    ref, index = field5k
    other = uniform_rock_field(np.random.default_rng(99), 5000)
    for seed in range(2):
        win = vehicle_window(np.random.default_rng(seed), other, 150)
        res = localize_large(ref, win.vehicle, index=index, search="indexed")
        assert not res.success, res.reason


def test_mirror_image_is_refused(field5k):
    ref, index = field5k
    win = vehicle_window(np.random.default_rng(3), ref, 150)
    mirrored = LandmarkMap(win.vehicle.positions_xyz * np.array([-1.0, 1.0, 1.0]))
    assert not localize_large(ref, mirrored, index=index, search="indexed").success


def test_vehicle_map_without_triangles_is_refused(field5k):
    ref, index = field5k
    sparse = LandmarkMap(np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0.1]]))
    res = localize_large(ref, sparse, index=index, search="indexed")
    assert not res.success and "no candidate region" in res.reason
    assert not np.any(np.isfinite(res.T_ref_veh))


def test_repeated_pattern_is_ambiguous():
    """Two identical copies of a site far apart: both candidate regions localize; refuse."""
    rng = np.random.default_rng(5)
    site = uniform_rock_field(rng, 1500).positions_xyz
    ref = LandmarkMap(np.vstack([site, site + np.array([200.0, 0.0, 0.0])]))
    win = vehicle_window(np.random.default_rng(1), LandmarkMap(site), 150)
    res = localize_large(ref, win.vehicle, search="indexed")
    assert not res.success
    assert "ambiguous" in res.reason


def test_auto_uses_full_search_for_small_maps():
    rng = np.random.default_rng(4)
    ref = uniform_rock_field(rng, 400)
    win = vehicle_window(rng, ref, 100)
    res = localize_large(ref, win.vehicle)
    assert res.search == "full" and res.success
    assert _pose_error(res.T_ref_veh, win.T_ref_veh, win.vehicle.positions_xyz)[0] < 0.1


def test_bad_inputs_give_clear_errors(field5k):
    ref, index = field5k
    win = vehicle_window(np.random.default_rng(1), ref, 150)
    with pytest.raises(InputError, match="vehicle map is empty"):
        localize_large(ref, LandmarkMap(np.zeros((0, 3))), index=index)
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        localize_large(
            ref, LandmarkMap(np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)]), index=index
        )
    with pytest.raises(ConfigError, match="search must be one of"):
        localize_large(ref, win.vehicle, search="fast")
    with pytest.raises(ConfigError, match="gravity-aware"):
        localize_large(
            ref, win.vehicle, LocalizationConfig(mode=Mode.SIX_DOF), search=Search.INDEXED
        )
    with pytest.raises(ConfigError, match="another reference map"):
        localize_large(ref.subset(np.arange(100)), win.vehicle, index=index, search="indexed")
    with pytest.raises(ConfigError, match="neighbours"):
        IndexConfig(neighbours=1)
    with pytest.raises(InputError, match="finite"):
        ReferenceIndex(np.full((5, 3), np.nan), 0.05)
    with pytest.raises(InputError, match="does not fit"):
        vehicle_window(
            np.random.default_rng(0), uniform_rock_field(np.random.default_rng(0), 100), 150
        )


def test_cli_localize_uses_the_index_for_a_large_reference(tmp_path, capsys):
    import json

    from lunarloc.cli import main
    from lunarloc.io.maps import save_map

    rng = np.random.default_rng(11)
    ref = uniform_rock_field(rng, 2500)
    win = vehicle_window(rng, ref, 120)
    ref_p = save_map(ref, tmp_path / "ref.csv")
    veh_p = save_map(win.vehicle, tmp_path / "veh.csv")
    assert main(["localize", str(ref_p), str(veh_p), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["search"] == "indexed" and d["success"] is True
    assert _pose_error(np.array(d["T_ref_veh"]), win.T_ref_veh, win.vehicle.positions_xyz)[0] < 0.1
    assert main(["localize", str(ref_p), str(veh_p), "--search", "fast"]) == 2
