"""The LAC map: the 16-ray truth, the mapper (heights, rocks, re-placing, bounded memory,
filling), the LAC's scoring rules, writing into a GeometricMap, and the CLI."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from lunarloc.core.errors import ConfigError, InputError
from lunarloc.core.geometry import invert_transform, pose_to_matrix
from lunarloc.io.overhead import (
    LAC_CELL_M,
    UNFILLED,
    empty_lac_grid,
    score_geometric_map,
    site_geometric_map,
    validate_lac_grid,
)
from lunarloc.mapping.lac_map import LacMapper, LacMapperConfig, _rock_cells, write_geometric_map


class _Rocks:
    def __init__(self, R):
        self.centers, self.axes, self.yaws = R[:, :3], R[:, 3:6], R[:, 6]

    def __len__(self):
        return len(self.centers)


def fake_site(size_m=6.0, rocks=(), slope=0.0):
    """A fake site: the plane z = slope * x and ellipsoid rocks (x, y, z, a, b, c, yaw)."""
    return SimpleNamespace(
        config=SimpleNamespace(size_m=size_m),
        terrain_height=lambda x, y: slope * np.asarray(x, float) + 0.0 * np.asarray(y, float),
        rocks=_Rocks(np.array(rocks, float).reshape(-1, 7)),
    )


# --------------------------------------------------------------------------- the truth


def test_truth_uses_sixteen_rays_any_hit_and_mean_height():
    g0 = empty_lac_grid(6.0)
    # a 2.5 cm rock on a ray point a quarter cell off the centre of cell [10, 10]: the centre
    # ray misses it, one of the 16 rays hits it
    cx, cy = g0[10, 10, 0] + 0.375 * LAC_CELL_M, g0[10, 10, 1] + 0.375 * LAC_CELL_M
    site = fake_site(rocks=[(cx, cy, 0.1 * cx, 0.025, 0.025, 0.08, 0.0)], slope=0.1)
    lac, centre = site_geometric_map(site), site_geometric_map(site, rule="centre")
    assert lac[10, 10, 3] == 1 and centre[10, 10, 3] == 0
    assert lac[:, :, 3].sum() == 1
    # the ray hitting the rock raises the mean by its height over 16
    plane = 0.1 * lac[10, 10, 0]
    assert lac[10, 10, 2] == pytest.approx(plane + 0.08 / 16, abs=1e-3)
    # on a plane the 16-ray mean is the centre height
    assert lac[3, 3, 2] == pytest.approx(0.1 * lac[3, 3, 0], abs=1e-9)
    with pytest.raises(InputError, match="rule"):
        site_geometric_map(site, rule="corner")


# --------------------------------------------------------------------------- scoring


def test_score_counts_unfilled_cells_as_failures_and_gives_the_points():
    truth = empty_lac_grid()
    truth[:, :, 2] = 0.2
    truth[120:124, 50:54, 3] = 1
    p = truth.copy()
    p[:90, :, 2] = UNFILLED  # half the map unfilled
    p[:90, :, 3] = UNFILLED
    s = score_geometric_map(p, truth, mission_time_s=86400.0 / 4)
    assert s["geometric"] == pytest.approx(0.5)
    assert s["cells_filled"] == 90 * 180
    assert s["productivity"] == 1.0  # half the cells in a quarter of the mission: capped
    assert s["rock_f1"] == 1.0 and s["points"]["rocks_map"] == pytest.approx(300)
    assert s["points"]["total"] == pytest.approx(150 + 300 + 250 + 150)
    s24 = score_geometric_map(p, truth)  # default: 24 h
    assert s24["productivity"] == pytest.approx(0.5)
    assert score_geometric_map(p, truth, fiducials_used=True)["points"]["localization"] == 0
    # restricted to the filled half: all within tolerance
    seen = np.zeros((180, 180), bool)
    seen[90:] = True
    assert score_geometric_map(p, truth, cells=seen)["geometric"] == 1.0
    with pytest.raises(InputError, match="mask"):
        score_geometric_map(p, truth, cells=seen[:10])
    with pytest.raises(InputError):
        validate_lac_grid(p)  # -inf only where allowed
    with pytest.raises(InputError, match="mission time"):
        score_geometric_map(p, truth, mission_time_s=0.0)


# --------------------------------------------------------------------------- the mapper


def surface(x, y):
    return 0.15 * np.sin(0.7 * x) + 0.1 * np.cos(0.5 * y) + 0.02 * x


def frame_points(T_map_rover, rng, n=6000, max_range=4.0, noise=0.005, outliers=0.03):
    """Rover-frame points of the surface in front of the rover (a 70 degree wedge)."""
    r = np.sqrt(rng.uniform(0.5**2, max_range**2, n))
    a = rng.uniform(-0.6, 0.6, n)
    xr, yr = r * np.cos(a), r * np.sin(a)
    P_map = (T_map_rover @ np.c_[xr, yr, np.zeros(n), np.ones(n)].T).T[:, :3]
    P_map[:, 2] = surface(P_map[:, 0], P_map[:, 1]) + rng.normal(0, noise, n)
    bad = rng.random(n) < outliers
    P_map[bad, 2] += rng.choice([-1, 1], bad.sum()) * rng.uniform(0.3, 1.0, bad.sum())
    return (invert_transform(T_map_rover) @ np.c_[P_map, np.ones(n)].T).T[:, :3]


def circle_poses(k=40, radius=4.0):
    out = []
    for th in np.linspace(0, 2 * np.pi, k, endpoint=False):
        x, y = radius * np.cos(th), radius * np.sin(th)
        out.append(pose_to_matrix(x, y, surface(x, y) + 0.3, 0.0, 0.0, th + np.pi / 2))
    return out


def true_cells(grid):
    return surface(grid[:, :, 0], grid[:, :, 1])


def test_heights_are_robust_to_outliers_and_unseen_cells_are_interpolated(rng):
    cfg = LacMapperConfig(size_m=15.0)
    m = LacMapper(cfg)
    for k, T in enumerate(circle_poses()):
        m.add_frame(k, T, frame_points(T, rng))
    est = m.grid()
    assert est.array.shape == (100, 100, 4)
    err = np.abs(est.array[:, :, 2] - true_cells(est.array))
    assert est.observed.sum() > 2000
    assert np.mean(err[est.observed] < 0.05) > 0.95  # 3 % gross outliers do not move the medians
    assert np.all(np.isfinite(est.array[:, :, 2]))  # fill=all: every cell filled
    assert np.array_equal(est.interpolated, ~est.observed)
    near = est.interpolated & (est.fill_distance_m <= 0.5)
    assert near.any() and np.mean(err[near] < 0.05) > 0.6
    assert np.all(np.isfinite(est.height_sigma_m[est.observed])) and np.all(np.isnan(est.height_sigma_m[~est.observed]))
    none = LacMapper(LacMapperConfig(size_m=15.0, fill="none"))
    none.add_frame(0, circle_poses()[0], frame_points(circle_poses()[0], rng))
    g = none.grid()
    assert np.all(g.array[~g.observed, 2] == UNFILLED) and not g.interpolated.any()


def test_repose_moves_what_a_frame_placed(rng):
    poses = circle_poses(20)
    shifted = [pose_to_matrix(0.6, -0.4, 0.0, 0.0, 0.0, 0.2) @ T for T in poses]
    m = LacMapper(LacMapperConfig(size_m=15.0, fill="none"))
    good = LacMapper(LacMapperConfig(size_m=15.0, fill="none"))
    for k, (T, S) in enumerate(zip(poses, shifted)):
        pts = frame_points(T, rng, outliers=0.0)
        rocks = np.array([[2.0, 0.1, 0.1, 0.2]])
        m.add_frame(k, S, pts, rocks)  # placed with a wrong pose, as odometry would
        good.add_frame(k, T, pts, rocks)
    bad = m.grid()
    assert np.mean(np.abs(bad.array[bad.observed, 2] - true_cells(bad.array)[bad.observed]) < 0.05) < 0.7
    assert all(m.repose(k, T) for k, T in enumerate(poses))
    assert not m.repose("never added", poses[0])
    a, b = m.grid(), good.grid()
    assert np.array_equal(a.array, b.array, equal_nan=True) and np.array_equal(a.rocks, b.rocks)


def test_bounded_memory_freezes_the_oldest_frames(rng):
    poses = circle_poses(30)
    small = LacMapper(LacMapperConfig(size_m=15.0, max_frames=5))
    full = LacMapper(LacMapperConfig(size_m=15.0))
    for k, T in enumerate(poses):
        pts = frame_points(T, rng, outliers=0.0)
        small.add_frame(k, T, pts)
        full.add_frame(k, T, pts)
    assert len(small) == 5 and small.frozen_frames == 25 and small.frame_ids == list(range(25, 30))
    assert small.memory_bytes() < full.memory_bytes() / 3
    assert not small.repose(0, poses[0]) and small.repose(29, poses[29])
    a, b = small.grid(), full.grid()
    assert np.array_equal(a.observed, b.observed)
    err = np.abs(a.array[:, :, 2] - true_cells(a.array))
    assert np.mean(err[a.observed] < 0.05) > 0.95


def test_rocks_need_two_sightings_and_mark_the_cells_any_ray_reaches(rng):
    m = LacMapper(LacMapperConfig(size_m=9.0, fill="none"))
    T0 = pose_to_matrix(-2.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    T1 = pose_to_matrix(-1.5, 0.5, 0.0, 0.0, 0.0, 0.0)
    rock_map = np.array([1.0, 0.2, 0.05])
    for k, T in enumerate((T0, T1)):
        p = (invert_transform(T) @ np.r_[rock_map, 1.0])[:3] + rng.normal(0, 0.01, 3)
        dets = [[*p, 0.2]]
        if k == 0:  # a false detection seen once
            dets.append([*(invert_transform(T) @ np.r_[-1.0, -2.0, 0.0, 1.0])[:3], 0.1])
        m.add_frame(k, T, frame_points(T, rng, n=500, max_range=2.0) if k else None, np.array(dets))
    est = m.grid()
    assert len(est.rocks) == 1 and np.allclose(est.rocks[0, :2], rock_map[:2], atol=0.03)
    flags = est.array[:, :, 3] == 1
    want = _rock_cells(est.rocks, est.array, LAC_CELL_M)
    assert np.array_equal(flags, want) and flags.sum() > 0
    # the any-ray rule: a cell is flagged iff one of its 16 ray points lies in the footprint
    xs = est.array[:, 0, 0]
    off = np.array([-3, -1, 1, 3]) / 8 * LAC_CELL_M
    i, j = np.nonzero(flags | np.roll(flags, 1, 0))  # flagged cells and their neighbours
    for a, b in zip(i, j):
        rx, ry = np.meshgrid(xs[a] + off, xs[b] + off, indexing="ij")
        hit = np.any(np.hypot(rx - est.rocks[0, 0], ry - est.rocks[0, 1]) <= est.rocks[0, 2])
        assert hit == flags[a, b]
    # a flagged cell without points still gets a height, so it counts as filled
    assert np.all(np.isfinite(est.array[flags, 2]))


def test_exclusion_disc_and_bad_inputs(rng):
    m = LacMapper(LacMapperConfig(size_m=15.0, fill="none"))
    m.exclude_disc((0.0, 0.0), 3.0)
    for k, T in enumerate(circle_poses(12, radius=1.0)):
        m.add_frame(k, T, frame_points(T, rng))
    est = m.grid()
    r = np.hypot(est.array[:, :, 0], est.array[:, :, 1])
    assert est.observed.any() and not est.observed[r < 2.9].any()
    with pytest.raises(InputError, match="4x4"):
        m.add_frame(99, np.full((4, 4), np.nan))
    with pytest.raises(InputError, match="points_rover"):
        m.add_frame(99, np.eye(4), np.zeros((5, 2)))
    with pytest.raises(InputError, match="rocks_rover"):
        m.add_frame(99, np.eye(4), None, np.zeros((2, 5)))
    with pytest.raises(InputError):
        m.exclude_disc((np.nan, 0.0), 1.0)
    with pytest.raises(ConfigError):
        LacMapperConfig(size_m=10.0, cell_m=0.15)  # not a whole number of cells
    with pytest.raises(ConfigError):
        LacMapperConfig(fill="everything")
    assert LacMapper().grid().array.shape == (180, 180, 4)  # nothing added: an unfilled map


class FakeGeometricMap:
    """The leaderboard's GeometricMap as far as write_geometric_map uses it."""

    def __init__(self, n=180):
        self._map = empty_lac_grid(n * LAC_CELL_M)
        self._map[:, :, 2:] = -np.inf
        self.calls = 0

    def get_cell_number(self):
        return self._map.shape[0]

    def get_map_array(self):
        return self._map

    def set_cell_height(self, i, j, h):
        self.calls += 1
        self._map[i, j, 2] = h
        return True

    def set_cell_rock(self, i, j, flag):
        self.calls += 1
        self._map[i, j, 3] = flag
        return True


def test_write_geometric_map_into_a_fake_leaderboard_map(rng):
    m = LacMapper(LacMapperConfig(fill="none"))
    for k, T in enumerate(circle_poses(10)):
        m.add_frame(k, T, frame_points(T, rng), np.array([[2.0, 0.0, 0.1, 0.15]]))
    est = m.grid()
    gm = FakeGeometricMap()
    n = write_geometric_map(est, gm)
    assert n == int(est.filled.sum()) > 0
    arr = gm.get_map_array()
    assert np.array_equal(arr[:, :, 2], est.array[:, :, 2])
    assert np.array_equal(arr[:, :, 3] == 1, est.array[:, :, 3] == 1)
    assert np.all(arr[~est.filled, 3] == -np.inf)  # unfilled cells left alone
    with pytest.raises(InputError, match="cells a side"):
        write_geometric_map(est, FakeGeometricMap(60))
    moved = FakeGeometricMap()
    moved._map[:, :, 0] += 1.0
    with pytest.raises(InputError, match="centres"):
        write_geometric_map(est, moved)
    with pytest.raises(InputError, match="set_cell_rock"):
        write_geometric_map(est, SimpleNamespace(set_cell_height=lambda i, j, h: True))


def test_cli_score_seen_only_and_figure(tmp_path, rng, capsys):
    from lunarloc.cli import main
    from lunarloc.mapping.lac_map import save_lac_map

    m = LacMapper()
    for k, T in enumerate(circle_poses(10)):
        m.add_frame(k, T, frame_points(T, rng, outliers=0.0))
    est = m.grid()
    truth = est.array.copy()
    truth[:, :, 2] = true_cells(truth)
    truth[:, :, 3] = 0
    np.save(tmp_path / "truth.npy", truth)
    save_lac_map(est, tmp_path / "map.npy")
    assert main(["score", str(tmp_path / "map.npy"), str(tmp_path / "truth.npy"), "--json", "--seen-only"]) == 0
    seen = json.loads(capsys.readouterr().out)
    assert seen["cells"] == int(est.observed.sum()) and seen["geometric"] > 0.95
    assert main(["score", str(tmp_path / "map.npy"), str(tmp_path / "truth.npy"), "--mission-time", "600",
                 "--figure", str(tmp_path / "cmp.png")]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "LAC points" in out and (tmp_path / "cmp.png").stat().st_size > 10_000
    (tmp_path / "other.npy").write_bytes((tmp_path / "truth.npy").read_bytes())
    assert main(["score", str(tmp_path / "other.npy"), str(tmp_path / "truth.npy"), "--seen-only"]) == 2
    assert "cells.npz" in capsys.readouterr().err
