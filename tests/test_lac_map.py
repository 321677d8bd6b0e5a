"""The LAC map: the 16-ray truth, the mapper (heights, rocks, re-placing, bounded memory,
filling), the LAC's scoring rules, writing into a GeometricMap, and the CLI."""

from __future__ import annotations

import json
import math
from dataclasses import replace
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
    assert np.all(np.isfinite(est.height_sigma_m[est.observed])) and np.all(
        np.isnan(est.height_sigma_m[~est.observed])
    )
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
    assert (
        np.mean(np.abs(bad.array[bad.observed, 2] - true_cells(bad.array)[bad.observed]) < 0.05)
        < 0.7
    )
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
    fixed = LacMapper(LacMapperConfig(size_m=15.0)).memory_bytes()  # the per-cell arrays, no frame
    assert small.memory_bytes() - fixed < (full.memory_bytes() - fixed) / 3
    assert not small.repose(0, poses[0]) and small.repose(29, poses[29])
    a, b = small.grid(), full.grid()
    assert np.array_equal(a.observed, b.observed)
    err = np.abs(a.array[:, :, 2] - true_cells(a.array))
    assert np.mean(err[a.observed] < 0.05) > 0.95


def test_rocks_need_two_sightings_and_mark_the_cells_any_ray_reaches(rng):
    m = LacMapper(
        LacMapperConfig(
            size_m=9.0,
            fill="none",
            rock_min_sightings=2,
            rock_recentre_min_m=None,
            rock_cells="footprint",
        )
    )  # the default is 3; the 0.2 m rock stays where it was seen (see the recentring test);
    # the footprint rule's cells (the per-cell model: its own test)
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
    with pytest.raises(InputError, match="frame 99: T_map_rover is not finite"):
        m.add_frame(99, np.full((4, 4), np.nan))
    with pytest.raises(
        InputError, match="frame 99: T_map_rover must be a 4x4 transform, got shape"
    ):
        m.add_frame(99, np.eye(3))
    with pytest.raises(
        InputError, match="frame 99: T_map_rover: the rotation block is not a rotation"
    ):
        m.add_frame(99, np.diag([1.1, 1.1, 1.1, 1.0]))  # a scale is not a pose
    assert not m.repose(99, np.eye(4)) and 99 not in m.frame_ids  # nothing refused was added
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
    assert (
        main(
            [
                "score",
                str(tmp_path / "map.npy"),
                str(tmp_path / "truth.npy"),
                "--json",
                "--seen-only",
            ]
        )
        == 0
    )
    seen = json.loads(capsys.readouterr().out)
    assert seen["cells"] == int(est.observed.sum()) and seen["geometric"] > 0.95
    assert (
        main(
            [
                "score",
                str(tmp_path / "map.npy"),
                str(tmp_path / "truth.npy"),
                "--mission-time",
                "600",
                "--figure",
                str(tmp_path / "cmp.png"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "LAC points" in out and (tmp_path / "cmp.png").stat().st_size > 10_000
    (tmp_path / "other.npy").write_bytes((tmp_path / "truth.npy").read_bytes())
    assert (
        main(["score", str(tmp_path / "other.npy"), str(tmp_path / "truth.npy"), "--seen-only"])
        == 2
    )
    assert "cells.npz" in capsys.readouterr().err


# --------------------------------------------------------------------------- from images


@pytest.fixture(scope="module")
def tiny_sim(tmp_path_factory):
    """6 s of a simulated traverse, front pair at 2 Hz, 640x360, with its 16-ray truth."""
    from lunarloc.sim.simulate import SimulationConfig, simulate_dataset

    out = tmp_path_factory.mktemp("lacmap")
    cfg = SimulationConfig(
        duration_s=6.0,
        image_rate_hz=2.0,
        width=640,
        height=360,
        cameras=("FrontLeft", "FrontRight"),
        semantic=False,
    )
    simulate_dataset(0, 1, out, cfg)
    return out


def test_run_writes_the_lac_map_and_score_reads_it(tiny_sim, tmp_path, capsys):
    from lunarloc.cli import main

    lac = tmp_path / "lac.npy"
    assert (
        main(
            [
                "run",
                str(tiny_sim / "traverse_0.lac"),
                "--reference",
                str(tiny_sim / "rocks.csv"),
                "-o",
                str(tmp_path / "run"),
                "--lac-map",
                str(lac),
                "--no-plot",
            ]
        )
        == 0
    )
    assert "LAC map:" in capsys.readouterr().out
    assert lac.is_file() and (tmp_path / "lac.cells.npz").is_file()
    # --lac-map turns the detector's small-rock stage on (the rock map needs it)
    ran = json.loads((tmp_path / "run" / "config.json").read_text())
    assert ran["detector"]["small_rocks"]["enabled"] is True
    assert (
        main(["score", str(lac), str(tiny_sim / "geometric_map.npy"), "--json", "--seen-only"]) == 0
    )
    s = json.loads(capsys.readouterr().out)
    # a few metres of a traverse: the cells the cameras saw are mostly right in height
    assert s["cells"] > 200 and s["geometric"] > 0.7, s
    assert s["cells_filled"] == 180 * 180  # fill=all
    # an existing map is refused before anything runs
    assert (
        main(
            [
                "run",
                str(tiny_sim / "traverse_0.lac"),
                "--reference",
                str(tiny_sim / "rocks.csv"),
                "-o",
                str(tmp_path / "run2"),
                "--lac-map",
                str(lac),
                "--no-plot",
            ]
        )
        == 2
    )
    assert "exists" in capsys.readouterr().err


def test_small_rock_stage_follows_lac_map_unless_told():
    from lunarloc.cli.commands_run import with_small_rocks
    from lunarloc.config.run import RunConfig

    base = RunConfig()
    assert base.detector.small_rocks.enabled  # the detector's default
    off = base.with_options(detector__small_rocks=replace(base.detector.small_rocks, enabled=False))

    def on(cfg):
        return cfg.detector.small_rocks.enabled

    assert on(with_small_rocks(off, None, lac_map=True))  # a configuration's off: --lac-map wins
    assert not on(with_small_rocks(off, None, lac_map=False))
    assert on(with_small_rocks(base, None, lac_map=False))
    assert not on(with_small_rocks(base, False, lac_map=True))  # --no-small-rocks wins
    assert on(with_small_rocks(off, True, lac_map=False))
    # the rest of the detector's small-rock settings are kept
    assert with_small_rocks(off, None, True).detector.small_rocks == replace(
        off.detector.small_rocks, enabled=True
    )


def test_online_localizer_feeds_its_mapper(tiny_sim):
    from lunarloc import OnlineLocalizer, PlaybackAgent, load_reference
    from lunarloc.online.component import CameraRig

    truth = np.load(tiny_sim / "geometric_map.npy")
    mapper = LacMapper()
    kfs = 0
    with PlaybackAgent(tiny_sim / "traverse_0.lac") as env:
        loc = OnlineLocalizer(
            load_reference(tiny_sim / "rocks.csv"),
            env.get_initial_position(),
            rig=CameraRig.from_sensors(env.sensors()),
            mapper=mapper,
        )
        while True:
            e = loc.update(
                env.get_mission_time(),
                env.input_data(),
                env.get_imu_data(),
                env.get_linear_speed(),
                env.get_angular_speed(),
            )
            kfs += e.keyframe
            if env.at_end():
                break
            env.step_frame()
    assert len(mapper) == kfs > 3
    # the mapper's frames sit where the pose graph has its keyframes
    for kf in loc.loop.keyframes:
        if kf.frame in mapper.frame_ids:
            placed = mapper._frames[kf.frame].T_map_rover
            assert np.linalg.norm(placed[:2, 3] - kf.estimate_pose4[:2]) < 0.5
    est = mapper.grid()
    ok = np.abs(est.array[:, :, 2] - truth[:, :, 2]) < 0.05
    assert est.observed.sum() > 200 and ok[est.observed].mean() > 0.6


def test_a_bump_in_the_heights_is_a_rock_without_any_detection(rng):
    """A 10 cm block 0.3 m across on smooth terrain (on the rover's circle), never detected: its cells are flagged."""

    def bumped(P_map):
        inside = (np.abs(P_map[:, 0] - 0.075) < 0.15) & (np.abs(P_map[:, 1] - 3.075) < 0.15)
        return np.where(inside, 0.10, 0.0)

    m = LacMapper(LacMapperConfig(size_m=15.0, fill="none", rock_bump_m=0.05))
    for k, T in enumerate(circle_poses(20, radius=3.0)):
        pts = frame_points(T, rng, outliers=0.0)
        P = (T @ np.c_[pts, np.ones(len(pts))].T).T[:, :3]
        P[:, 2] += bumped(P)
        m.add_frame(k, T, (invert_transform(T) @ np.c_[P, np.ones(len(P))].T).T[:, :3])
    est = m.grid()
    flags = est.array[:, :, 3] == 1
    x, y = est.array[:, :, 0], est.array[:, :, 1]
    block = (np.abs(x - 0.075) < 0.1) & (np.abs(y - 3.075) < 0.1)
    assert est.observed[block].all()
    assert flags[block].all()
    assert flags.sum() <= 16  # nothing beyond the block and the cells it reaches into
    off = LacMapper(LacMapperConfig(size_m=15.0, fill="none"))  # the default: off
    off._frames = m._frames
    assert not (off.grid().array[:, :, 3] == 1).any()


def test_small_rocks_have_their_own_sightings_floor_and_footprint_margin():
    T = np.eye(4)
    rock = [1.0, 0.2, 0.02, 0.03]  # a 3 cm rock (under small_rock_m)
    big = [1.5, -0.6, 0.1, 0.2]

    def mapper(**kw):
        # the 0.2 m rock not recentred: this is about floors and footprints
        m = LacMapper(LacMapperConfig(size_m=9.0, fill="none", rock_recentre_min_m=None, **kw))
        for k in range(2):
            m.add_frame(k, T, None, np.array([rock, big]))
        return m.grid()

    est = mapper(
        rock_min_sightings=2,
        small_rock_min_sightings=2,
        small_rock_margin_m=0.01,
        rock_radius_scale=1.1,
    )
    r = {(round(x, 2), round(y, 2)): rad for x, y, rad in est.rocks}
    assert r[(1.0, 0.2)] == pytest.approx(0.04) and r[(1.5, -0.6)] == pytest.approx(
        0.22
    )  # r + margin; 1.1 x r
    est3 = mapper(rock_min_sightings=2, small_rock_min_sightings=3)
    assert len(est3.rocks) == 1 and est3.rocks[0, :2] == pytest.approx(
        [1.5, -0.6]
    )  # two sightings: not enough
    default = mapper()  # 3 sightings for the larger rock, 2 for the small one
    assert len(default.rocks) == 1 and default.rocks[0, :2] == pytest.approx([1.0, 0.2])
    with pytest.raises(ConfigError):
        LacMapperConfig(small_rock_min_sightings=0)


def test_frame_inputs_puts_a_levelled_height_map_back_in_the_rover_frame(rng):
    """DetectorConfig.level_from_stereo builds a tilted rover's height map in a frame levelled
    on the ground: its points_rover are then not rover-frame points."""
    from lunarloc.mapping.lac_map import frame_inputs

    P_rover = rng.uniform(-2, 2, (50, 3))
    T_level_rover = pose_to_matrix(0.0, 0.0, 0.0, 0.2, -0.15, 0.0)
    P_level = (T_level_rover[:3, :3] @ P_rover.T).T
    det = SimpleNamespace(p_rover=np.array([1.0, 0.0, 0.1]), radius_m=0.1)
    fd = SimpleNamespace(
        pairs=[
            SimpleNamespace(
                height=SimpleNamespace(points_rover=P_level, T_level_rover=T_level_rover)
            )
        ],
        detections=[det],
    )
    pts, rocks = frame_inputs(fd)
    np.testing.assert_allclose(pts, P_rover, atol=1e-5)
    np.testing.assert_allclose(rocks, [[1.0, 0.0, 0.1, 0.1]])
    fd.pairs[0].height.T_level_rover = None  # not levelled: as given
    np.testing.assert_allclose(frame_inputs(fd)[0], P_level, atol=1e-6)


def test_live_cells_are_bounded_handed_out_once_and_again_when_changed(rng):
    poses = circle_poses(12)
    m = LacMapper(LacMapperConfig(size_m=15.0))
    p_rock = poses[2] @ [2.0, 0.0, 0.1, 1.0]  # a rock 2 m ahead of frame 2, detected by frames 1-3
    for k, T in enumerate(poses[:6]):
        rocks = np.array([[*(invert_transform(T) @ p_rock)[:3], 0.15]]) if 1 <= k <= 3 else None
        m.add_frame(k, T, frame_points(T, rng, outliers=0.0), rocks)
    i, j, h, rock = m.live_cells(min_weight=2.0, max_cells=100)
    assert len(i) == 100
    rest = m.live_cells(min_weight=2.0)
    assert len(rest[0]) > 100 and m.live_cells(min_weight=2.0)[0].size == 0  # each once
    grid0 = m.grid()
    ii, jj = np.r_[i, rest[0]], np.r_[j, rest[1]]
    hh = np.r_[h, rest[2]]
    truth = true_cells(grid0.array)[ii, jj]
    assert np.mean(np.abs(hh - truth) < 0.05) > 0.95  # confident cells hold the right heights
    assert np.r_[rock, rest[3]].any()  # the rock seen by several frames
    assert np.all(grid0.weight[ii, jj] >= 2.0)
    T = poses[6]
    m.add_frame(6, T, frame_points(T, rng, outliers=0.0))
    again = m.live_cells(min_weight=2.0)
    assert 0 < len(again[0])  # the new frame's cells, and only cells it touched
    assert np.all(m.grid().weight[again[0], again[1]] > grid0.weight[again[0], again[1]])
    with pytest.raises(InputError):
        m.live_cells(min_weight=-1.0)


def test_map_writer_writes_bounded_steps_then_the_whole_map(rng):
    from lunarloc.mapping.lac_map import LacMapWriter

    m = LacMapper(LacMapperConfig())
    gm = FakeGeometricMap()
    w = LacMapWriter(m, gm, min_weight=2.0, max_cells_per_step=150)
    assert w.step() == 0  # nothing seen yet
    steps = []
    for k, T in enumerate(circle_poses(10)):
        m.add_frame(k, T, frame_points(T, rng), np.array([[2.0, 0.0, 0.1, 0.15]]))
        steps.append(w.step())
    assert max(steps) == 150 and 0 < w.cells_written <= sum(
        steps
    )  # a cell a new frame changed is written again
    arr = gm.get_map_array()
    done = np.isfinite(arr[:, :, 2])
    assert done.sum() == w.cells_written and np.all(np.isfinite(arr[done, 3]))
    n = w.finish()
    assert n == 180 * 180 and np.isfinite(arr[:, :, 2:]).all() and w.cells_written == 180 * 180
    np.testing.assert_array_equal(arr[:, :, 2], m.grid().array[:, :, 2])
    with pytest.raises(InputError, match="cells a side"):
        LacMapWriter(m, FakeGeometricMap(60))
    with pytest.raises(InputError):
        LacMapWriter("not a mapper", gm)


def test_large_rocks_move_away_from_where_they_were_seen():
    """A large rock's median centre moves rock_recentre_scale x radius along its sightings'
    mean viewing direction (rover -> rock); seen from opposite sides it stays; small ones stay."""
    big, small = [2.0, 0.0, 0.1, 0.4], [1.0, 1.0, 0.02, 0.1]

    def grid(poses, **kw):
        m = LacMapper(LacMapperConfig(size_m=9.0, fill="none", rock_min_sightings=2, **kw))
        for k, T in enumerate(poses):
            Ti = invert_transform(T)
            dets = [[*(Ti @ np.r_[p[:3], 1.0])[:3], p[3]] for p in (big, small)]
            m.add_frame(k, T, None, np.array(dets))
        return {round(r, 2): (x, y) for x, y, r in m.grid().rocks}

    # two views from the west, the rover turned differently: the rock moves 0.1 x 0.4 m east
    west = [pose_to_matrix(0.0, 0.0, 0.0, 0.0, 0.0, 0.0), pose_to_matrix(0.0, 0.0, 0.0, 0, 0, 0.3)]
    est = grid(west, rock_recentre_min_m=0.2, rock_recentre_scale=0.1)
    assert est[0.42] == pytest.approx((2.04, 0.0), abs=1e-6)  # footprint 1.05 x 0.4
    assert est[0.11] == pytest.approx((1.0, 1.0), abs=1e-6)  # under rock_recentre_min_m
    assert grid(west, rock_recentre_min_m=None)[0.42] == pytest.approx((2.0, 0.0), abs=1e-6)
    # one view from the west, one from the east: the viewing directions cancel
    east = pose_to_matrix(4.0, 0.0, 0.0, 0.0, 0.0, math.pi)
    both = grid([west[0], east], rock_recentre_min_m=0.2, rock_recentre_scale=0.1)
    assert both[0.42] == pytest.approx((2.0, 0.0), abs=1e-6)
    with pytest.raises(ConfigError):
        LacMapperConfig(rock_recentre_min_m=-0.1)


def test_rock_cell_probability_evaluates_boosted_trees(tmp_path):
    """rock_cell_probability sums the trees' leaves (left when feature <= threshold) onto the
    baseline log-odds; a model file with other features is refused."""
    from lunarloc.mapping.lac_map import ROCK_CELL_FEATURES, rock_cell_probability

    F = len(ROCK_CELL_FEATURES)
    tree = dict(
        feature=np.array([[2, 0, 0]]),
        threshold=np.array([[0.5, 0.0, 0.0]]),
        left=np.array([[1, 0, 0]]),
        right=np.array([[2, 0, 0]]),
        is_leaf=np.array([[False, True, True]]),
        value=np.array([[0.0, 2.0, -2.0]]),
    )
    path = tmp_path / "m.npz"
    np.savez(path, baseline=-0.5, max_depth=1, features=np.array(ROCK_CELL_FEATURES), **tree)
    X = np.zeros((3, F))
    X[:, 2] = [0.0, 0.5, 0.6]  # left, left (at the threshold), right
    p = rock_cell_probability(X, path)
    assert p == pytest.approx(1 / (1 + np.exp(-np.array([1.5, 1.5, -2.5]))))
    bad = tmp_path / "bad.npz"
    np.savez(bad, baseline=0.0, max_depth=1, features=np.array(["x"] * F), **tree)
    with pytest.raises(ConfigError, match="features"):
        rock_cell_probability(X, bad)
    with pytest.raises(ConfigError, match="cannot be read"):
        rock_cell_probability(X, tmp_path / "missing.npz")


def test_the_per_cell_model_flags_a_rock_seen_often_and_not_one_seen_once(rng):
    """rock_cells="model": cells near detection clusters get P(rock) from the shipped model;
    a 15 cm rock detected in ten frames is flagged at its centre, a detection seen once 4.5 m
    away is not; the flags are P >= rock_cell_min_p; the footprint rule gives no P."""
    from lunarloc.mapping.lac_map import ROCK_CELL_FEATURES

    with pytest.raises(ConfigError):
        LacMapperConfig(rock_cells="votes")
    with pytest.raises(ConfigError):
        LacMapperConfig(rock_cell_min_p=1.0)
    rock, lone = np.array([1.0, 0.5, 0.1]), np.array([3.5, 0.0, 0.05])
    maps = {}
    for mode in ("footprint", "model"):
        m = LacMapper(LacMapperConfig(size_m=9.0, rock_cells=mode))
        for k in range(10):
            T = pose_to_matrix(-1.0 + 0.1 * k, -0.5, 0.0, 0.0, 0.0, 0.3)
            Ti = invert_transform(T)
            dets = [[*(Ti @ np.r_[rock, 1.0])[:3] + rng.normal(0, 0.01, 3), 0.15]]
            if k == 0:
                dets.append([*(Ti @ np.r_[lone, 1.0])[:3], 0.12])
            m.add_frame(k, T, frame_points(T, rng, n=3000, max_range=3.0), np.array(dets))
        maps[mode] = m.grid()
        if mode == "model":
            est = maps[mode]
            cells, X = m.rock_cell_features(est.array[:, :, 2], est.height_sigma_m, est.weight)
            assert X.shape == (len(cells), len(ROCK_CELL_FEATURES)) and np.all(np.isfinite(X))
    est = maps["model"]
    assert maps["footprint"].rock_probability is None
    n = est.array.shape[0]
    cell = lambda p: (  # noqa: E731
        int((p[0] - est.array[0, 0, 0]) / LAC_CELL_M + 0.5),
        int((p[1] - est.array[0, 0, 1]) / LAC_CELL_M + 0.5),
    )
    P = est.rock_probability
    assert P.shape == (n, n) and np.all((P >= 0) & (P <= 1))
    assert est.array[cell(rock)][3] == 1 and P[cell(rock)] >= 0.4
    assert est.array[cell(lone)][3] == 0 and P[cell(lone)] < 0.4
    assert np.array_equal(est.array[:, :, 3] == 1, P >= est.array.dtype.type(0.4))
    # both rules map the same rocks; the model's flags stay near them
    assert len(est.rocks) == len(maps["footprint"].rocks) == 1
    i, j = np.nonzero(est.array[:, :, 3] == 1)
    d = np.hypot(est.array[i, j, 0] - rock[0], est.array[i, j, 1] - rock[1])
    assert d.max() < 0.15 + 0.1 + LAC_CELL_M
