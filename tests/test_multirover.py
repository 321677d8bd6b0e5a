"""Several rovers on one clock (lunarloc.pipeline.multirover, `lunarloc run A.lac B.lac`): per-rover run
folders, the combined figure, mission-time order, sharing that never makes a rover worse
than a failing bound, and clear errors for bad input."""

import json
from dataclasses import replace

import numpy as np
import pytest

from lunarloc.cli import main
from lunarloc.core.errors import ConfigError, InputError

W, H = 320, 180


def _cfg(**kw):
    """MultiRoverConfig with the archives' recorded odometry (as ``--odometry record:odometry``)."""
    from lunarloc.config.run import RunConfig
    from lunarloc.pipeline.multirover import MultiRoverConfig

    return MultiRoverConfig(run=RunConfig().with_options(odometry__source="record:odometry"), **kw)


def _sim(out, seed, n, duration, width=W, rover=None):
    from lunarloc.sim.rover import RoverConfig
    from lunarloc.sim.simulate import SimulationConfig, simulate_dataset
    from lunarloc.sim.site import SiteConfig

    cfg = SimulationConfig(
        site=SiteConfig(n_rocks=800),
        duration_s=duration,
        image_rate_hz=2.0,
        width=width,
        height=width * 9 // 16,
        cameras=("FrontLeft", "FrontRight"),
        semantic=False,
        rover=rover or RoverConfig(),
    )
    return simulate_dataset(seed, n, out, cfg)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Two 8 s traverses of site 3 (they start at one place), 320x180 front pair at 2 Hz."""
    out = tmp_path_factory.mktemp("rovers")
    paths = _sim(out, 3, 2, 8.0)
    return out, paths


def test_two_rovers_write_one_run_folder_each(tiny, tmp_path, capsys):
    out_dir, (a, b) = tiny
    from lunarloc.config.run import RunConfig

    out = tmp_path / "out"
    given = tmp_path / "given.json"  # --config applies to every rover; options given override it
    given.write_text(
        json.dumps(RunConfig().with_options(loop__window_m=6.5, odometry__source="imu").to_dict())
    )
    rc = main(
        [
            "run",
            str(a),
            str(b),
            "--reference",
            str(out_dir / "rocks.csv"),
            "--share-maps",
            "-o",
            str(out),
            "--config",
            str(given),
            "--odometry",
            "record:odometry",
        ]
    )
    assert rc == 0, capsys.readouterr().err
    doc = json.loads((out / "rovers.json").read_text())
    assert [r["name"] for r in doc["rovers"]] == ["traverse_0", "traverse_1"]
    assert (out / "map_all.png").is_file()
    for name, lac in (("traverse_0", a), ("traverse_1", b)):
        d = out / name
        for f in (
            "trajectory.tum",
            "trajectory_odometry.tum",
            "trajectory_groundtruth.tum",
            "attempts.csv",
            "summary.json",
            "config.json",
            "map.png",
        ):
            assert (d / f).is_file(), f
        s = json.loads((d / "summary.json").read_text())
        assert (
            s["frames"] == 161 and s["image_frames"] == 17
        )  # every tick of its archive, images at 2 Hz
        cfg_doc = json.loads(
            (d / "config.json").read_text()
        )  # a single run's config.json: RunConfig + info
        assert (
            cfg_doc["info"]["archive"] == str(lac)
            and cfg_doc["info"]["multirover"]["share_maps"] is True
        )
        used = RunConfig.from_dict(cfg_doc)
        assert used.loop.window_m == 6.5 and used.odometry.source == "record:odometry"
        # the failing bound: whatever the fixes, a rover ends no worse than its odometry + 5 cm
        assert s["ate_corrected"]["rmse_m"] <= s["ate_odometry"]["rmse_m"] + 0.05
    # a second run into the same folder is refused without --overwrite
    assert main(["run", str(a), str(b), "--share-maps", "-o", str(out)]) == 2
    assert "previous run" in capsys.readouterr().err


def test_mission_time_order_and_names(tiny):
    """Ticks of both rovers interleave in mission time; equal stems get distinct names."""
    from lunarloc.pipeline.multirover import rover_names

    from pathlib import Path

    assert rover_names([Path("a/t.lac"), Path("b/t.lac"), Path("c/t x.lac")]) == ["t", "t_2", "t_x"]
    import lunarloc.pipeline.multirover as mr

    order = []
    orig = mr._Rover.tick

    def spy(self):
        order.append((float(self.agent.get_mission_time()), self.name))
        return orig(self)

    out_dir, paths = tiny
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mr._Rover, "tick", spy)
        res = mr.run_rovers(paths, None, _cfg(share_maps=True))
    times = [t for t, _ in order]
    assert times == sorted(times) and len(order) == 2 * 161
    assert [n for _, n in order[:4]] == ["traverse_0", "traverse_1"] * 2
    # no reference: attempts against the (absent) reference are not reported, only shared ones
    for r in res.rovers:
        assert all(a.reason.startswith("map of") for a in r.result.attempts)
        assert len(r.result.reference) == 0


def test_live_map_uncertainty_grows_with_the_owner_drift(tiny):
    """A rover's live map carries, per landmark, the owner's sigma where it placed it; with no
    fix that is the drift model since the start: non-decreasing along the traverse."""
    import lunarloc.pipeline.multirover as mr

    out_dir, paths = tiny
    r = mr._Rover("a", paths[0], None, _cfg(share_maps=True))
    try:
        while True:
            r.tick()
            if r.agent.at_end():
                break
            r.agent.step_frame()
        s_m, s_yaw = r.owner_sigmas()
        assert len(s_m) == len(r.loc.loop.keyframes) > 5
        assert np.all(np.diff(s_m) >= -1e-12) and s_m[-1] > s_m[0]
        # under stated bounds (visual's) the sigma follows them, at most the gate's model; per window
        # (independent windows) it grows more slowly than linearly once past one window
        k = len(r.loc.loop.keyframes) - 1
        gate = r.loc.loop.graph.predicted_sigma(k)
        r.map_bounds = (0.01, 0.06)
        lin = (r.__setattr__("sigma_model", "source"), r.sigma(k))[1]
        win = (r.__setattr__("sigma_model", "windows"), r.sigma(k))[1]
        assert win[0] <= lin[0] <= gate[0] + 1e-12 and win[1] <= lin[1] <= gate[1] + 1e-12
        if r.loc.loop.graph.distance_since_fix(k) > r.loc.loop.config.window_m:
            assert win[0] < lin[0]
        r.map_bounds = (0.0, 0.0)  # the record source is stated rigid: the gate's model
        assert r.sigma(k) == gate
        r.anchor = (0.3, 0.01)  # its last fix was a shared one of 30 cm: every landmark inherits it
        s2, _ = r.owner_sigmas()
        assert np.all(s2 >= 0.3) and np.allclose(s2, np.hypot(s_m, 0.3))
        live = r.live_map(1e9, 0.0)
        if live is not None and len(live.landmarks):
            assert live.owner_sigma_m.shape == (len(live.landmarks),) and np.all(
                live.owner_sigma_m >= 0.3
            )
    finally:
        r.close()


def test_bad_input_is_a_clear_error(tiny, tmp_path, capsys):
    from lunarloc.sim.rover import RoverConfig
    from lunarloc.pipeline.multirover import MultiRoverConfig, check_archives, run_rovers

    out_dir, (a, b) = tiny
    with pytest.raises(InputError, match="given twice"):
        check_archives([a, out_dir / ".." / out_dir.name / a.name])
    copy = tmp_path / "copy.lac"
    copy.write_bytes(a.read_bytes())
    with pytest.raises(InputError, match="same traverse"):
        check_archives([a, copy])
    other_site = _sim(tmp_path / "site4", 4, 1, 2.0)[0]
    with pytest.raises(InputError, match="site seed 4.*site seed 3"):
        check_archives([a, other_site])
    other_clock = _sim(tmp_path / "clock", 3, 1, 2.0, rover=RoverConfig(rate_hz=10.0))[0]
    with pytest.raises(InputError, match="different clocks"):
        check_archives([a, other_clock])
    with pytest.raises(ConfigError, match="share_maps"):
        run_rovers([a, b], None, MultiRoverConfig(share_maps=False))
    bad = tmp_path / "bad.lac"
    bad.write_bytes(b"not an archive")
    o = str(tmp_path / "o")
    for argv, msg in (
        (["run", str(a), str(bad), "--share-maps"], "bad.lac"),
        (["run", str(a), str(a), "--share-maps"], "given twice"),
        (["run", str(a), str(other_site), "--share-maps"], "site seed"),
        (["run", str(a), str(b)], "--reference MAP, --share-maps"),
        (["run", str(a), "--share-maps"], "several archives"),
        (["run", str(a)], "--reference MAP is required"),
    ):
        assert main([*argv, "-o", o]) == 2, argv
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()  # nothing written before the inputs were checked


def test_config_is_checked_and_serialised():
    from lunarloc.pipeline.multirover import MultiRoverConfig

    c = MultiRoverConfig(share_maps=True, share_refresh_s=2.0)
    d = c.to_dict()
    assert d["share_maps"] is True and d["run"]["loop"]["window_m"] == c.run.loop.window_m
    assert MultiRoverConfig.from_dict(json.loads(json.dumps(d))) == c
    with pytest.raises(ConfigError, match="run.loop.window_m"):
        MultiRoverConfig.from_dict({**d, "run": {**d["run"], "loop": {"window_m": "x"}}})
    with pytest.raises(ConfigError):
        replace(c, share_refresh_s=0.0)
    for bad in (
        {"shared_bounds": "max"},
        {"sigma_model": "x"},
        {"shared_fusion": "both"},
        {"min_shared_weight": 1.5},
        {"max_exchange_overlap": -0.1},
    ):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            replace(c, **bad)


def test_a_shared_attempt_states_both_maps_bounds():
    """The window's stated bounds (its odometry source's) combined with the owner map's: a sum
    (or in quadrature); either unknown: none stated (fitted); the precision limits raised to
    the owner's sigma only where that is larger."""
    from lunarloc.online.loop import image_localization_config
    from lunarloc.pipeline.multirover import shared_localization

    w = replace(
        image_localization_config(),
        odometry_scale_error=0.01,
        odometry_heading_drift_deg_per_m=0.06,
    )
    s = shared_localization(w, (0.01, 0.06), "sum")
    assert (s.odometry_scale_error, s.odometry_heading_drift_deg_per_m) == pytest.approx(
        (0.02, 0.12)
    )
    assert s.max_tilt_deg == pytest.approx(2 * w.max_tilt_deg)
    r = shared_localization(w, (0.01, 0.06), "rss")
    assert r.odometry_heading_drift_deg_per_m == pytest.approx(0.06 * 2**0.5)
    o = shared_localization(w, (0.01, 0.06), "own")
    assert o.max_rmse_m == pytest.approx(w.max_rmse_m * 2**0.5)  # two noisy maps
    assert replace(o, max_rmse_m=w.max_rmse_m) == w
    f = shared_localization(w, None, "sum")  # the owner's odometry is not known: the bend is fitted
    assert not f.odometry_bounds_stated
    fitted = replace(w, odometry_scale_error=None, odometry_heading_drift_deg_per_m=None)
    assert not shared_localization(fitted, (0.01, 0.06), "sum").odometry_bounds_stated
    lo = shared_localization(
        w, (0.01, 0.06), "sum", owner_sigma=(0.05, 0.5)
    )  # a precise owner: limits kept
    assert (lo.max_predicted_error_m, lo.max_predicted_rotation_deg) == (
        w.max_predicted_error_m,
        w.max_predicted_rotation_deg,
    )
    hi = shared_localization(w, (0.01, 0.06), "sum", owner_sigma=(0.4, 3.0))
    assert (hi.max_predicted_error_m, hi.max_predicted_rotation_deg) == (0.4, 3.0)


def test_caller_odometry_states_its_source_bounds():
    """OnlineLocalizer fed the run's odometry source states that source's bounds, as `lunarloc
    run` does; a caller's odometry of unknown accuracy leaves the windows' bend to be fitted."""
    from lunarloc.online.component import OnlineLocalizer
    from lunarloc.online.loop import OdometryBounds, stated_window_bounds

    loc = OnlineLocalizer(None, np.eye(4))
    loc.set_caller_odometry("visual")
    b = loc.loop.config.odometry_bounds.visual
    assert stated_window_bounds(loc.loop.localization) == (b.scale_error, b.heading_drift_deg_per_m)
    img = {"Grayscale": {}}
    loc.update(0.0, img, np.array([0, 0, 1.62, 0, 0, 0.0]), 0.0, 0.0, odometry=np.eye(4))
    assert stated_window_bounds(loc.loop.localization) == (
        b.scale_error,
        b.heading_drift_deg_per_m,
    )  # kept
    loc.set_caller_odometry(OdometryBounds(0.02, 0.1))
    assert stated_window_bounds(loc.loop.localization) == (0.02, 0.1)
    loc.set_caller_odometry(None)
    assert stated_window_bounds(loc.loop.localization) is None
    with pytest.raises(InputError):
        loc.set_caller_odometry(3)


# --------------------------------------------------------------------------- sharing, with detections from the rock list
# Rendering and detecting enough rocks for fixes takes minutes; these tests keep the archives'
# clock, poses, IMU and drifting odometry record (tiny images) and replace the detector by the
# ground-truth rocks seen from the true pose (5 cm noise), so the sharing logic runs for real.


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """Two 45 s traverses of site 3 (2 Hz, 160x90 front pair), which overlap."""
    out = tmp_path_factory.mktemp("pair")
    return out, _sim(out, 3, 2, 45.0, width=160)


def _rock_detector(mp, rocks_csv, noise_m=0.05, max_range_m=6.0, hfov_deg=70.0):
    import lunarloc.pipeline.multirover as mr
    from lunarloc.core.geometry import invert_transform, transform_points
    from lunarloc.online.component import OnlineLocalizer
    from lunarloc.pipeline.reference import rocks_to_reference

    rocks = rocks_to_reference(np.loadtxt(rocks_csv, delimiter=",", skiprows=1)).positions_xyz
    rng = np.random.default_rng(0)
    orig_tick = mr._Rover.tick

    def tick(self):
        self.loc._T_true = self.agent.get_transform_matrix()
        return orig_tick(self)

    def detect(self, images):
        p = transform_points(invert_transform(self._T_true), rocks)
        r = np.hypot(p[:, 0], p[:, 1])
        seen = (
            (p[:, 0] > 0.5)
            & (r < max_range_m)
            & (np.abs(np.degrees(np.arctan2(p[:, 1], p[:, 0]))) < hfov_deg / 2)
        )
        return p[seen] + rng.normal(0, noise_m, (int(seen.sum()), 3))

    mp.setattr(mr._Rover, "tick", tick)
    mp.setattr(OnlineLocalizer, "_detect", detect)


def _run(paths, rocks_csv, reference=None, shift_owner_m=None):
    import lunarloc.pipeline.multirover as mr

    with pytest.MonkeyPatch.context() as mp:
        _rock_detector(mp, rocks_csv)
        if (
            shift_owner_m is not None
        ):  # traverse_0's live map is off by a rigid shift its sigma does not admit
            orig = mr._Rover.live_map

            def live_map(self, t, refresh_s):
                m = orig(self, t, refresh_s)
                if m is None or self.name != "traverse_0":
                    return m
                lm = m.landmarks
                shifted = mr.LandmarkMap(
                    lm.positions_xyz + [shift_owner_m, 0.0, 0.0],
                    lm.sizes,
                    lm.sightings,
                    lm.frame,
                    lm.sigma_xy_m,
                    lm.sigma_z_m,
                )
                return mr._LiveMap(
                    shifted, m.owner_sigma_m, m.owner_sigma_yaw_rad, m.key, m.built_t
                )

            mp.setattr(mr._Rover, "live_map", live_map)
        return mr.run_rovers(paths, reference, _cfg(share_maps=True))


@pytest.fixture(scope="module")
def pair_shared(pair):
    """The pair with shared maps, no reference, the default configuration."""
    out, paths = pair
    return _run(paths, out / "rocks.csv")


def test_shared_maps_align_rovers_without_a_reference(pair_shared):
    res = pair_shared
    shared = [a for r in res.rovers for a in r.shared if a.accepted]
    assert len(shared) >= 2  # the rovers did align to each other
    for a in shared:
        # a fix is as good as the owner's estimate: never off by more than twice its stated sigma
        assert a.fix_error_m < 2 * a.fix_sigma_m, a
        assert a.fix_sigma_m >= a.owner_sigma_m > 0  # the owner's uncertainty is in the fix
    for r in res.rovers:
        s = r.result.summary()
        assert s["ate_corrected"]["rmse_m"] <= s["ate_odometry"]["rmse_m"] + 0.02, (r.name, s)


def test_a_wrong_live_map_does_not_pull_a_rover(pair):
    """traverse_0's live map shifted 4 m, far more than its and traverse_1's sigmas admit (the
    gate's drift model allows ~0.7 m after these 13 m): traverse_1 does not follow it. (Within
    that envelope a map that misstates its accuracy can pull a rover, as a wrong reference can.)"""
    out, paths = pair
    res = _run(paths, out / "rocks.csv", shift_owner_m=4.0)
    r1 = next(r for r in res.rovers if r.name == "traverse_1")
    # its own registrations in traverse_0's (shifted) map; rows of traverse_0's registrations in
    # traverse_1's own map (mirror) are the other side of an exchange, not a pull by the shift
    tried = [a for a in r1.shared if a.success and not a.mirror]
    assert tried, "the shifted map was never matched: the test would prove nothing"
    assert not any(a.accepted for a in tried), [(a.fix_error_m, a.gate_d2) for a in tried]
    s = r1.result.summary()
    assert s["ate_corrected"]["max_m"] <= s["ate_odometry"]["max_m"] + 0.02, s


# --------------------------------------------------------------------------- fusing two rovers


def test_equal_sigmas_move_both_rovers_about_halfway():
    """A registration between two rovers is a relative constraint: equal sigmas move each
    halfway (less the registration's own share) and leave each with about sigma / sqrt(2); a
    rover far more certain than the other hardly moves while the other takes nearly all."""
    from lunarloc.pipeline.multirover import split_shared_fix

    s = split_shared_fix((0.2, 0.02), (0.2, 0.02), (0.0, 0.0))
    assert (s.rover_weight_m, s.owner_weight_m) == pytest.approx((0.5, 0.5))
    assert (s.rover_weight_yaw, s.owner_weight_yaw) == pytest.approx((0.5, 0.5))
    assert s.rover_sigma_m == pytest.approx(0.2 / 2**0.5)
    assert s.owner_sigma_yaw_rad == pytest.approx(0.02 / 2**0.5)
    n = split_shared_fix((0.2, 0.02), (0.2, 0.02), (0.05, 0.005))  # a noisy registration
    assert n.rover_weight_m == pytest.approx(n.owner_weight_m)
    assert 0.4 < n.rover_weight_m < 0.5 and n.rover_sigma_m > s.rover_sigma_m
    r = split_shared_fix((0.30, 0.03), (0.03, 0.003), (0.02, 0.002))  # owner with a reference
    assert r.rover_weight_m > 0.9 and r.owner_weight_m < 0.01
    assert r.rover_sigma_m < 0.04  # the rover is then about as good as the owner
    flipped = split_shared_fix((0.03, 0.003), (0.30, 0.03), (0.02, 0.002))
    assert flipped.owner_weight_m == pytest.approx(r.rover_weight_m)
    with pytest.raises(ConfigError):
        split_shared_fix((float("nan"), 0.0), (0.1, 0.0), (0.0, 0.0))


def test_the_exchange_guard_refuses_the_same_registration_and_its_mirror():
    """Once two rovers are tied at a place (window keyframes of one, inlier keyframes of the
    other), the same tie again, or its mirror (the other rover's window in the first one's
    map), would count the same information twice: refused; new keyframes on one side, or
    another pair of rovers, are not."""
    from lunarloc.pipeline.multirover import Exchange, repeated_exchange

    ledger = [Exchange(0, 10.0, {"a": (10, 30), "b": (40, 55)}, ("a", "b"))]
    assert repeated_exchange(ledger, "a", (12, 32), "b", (42, 56), 0.5) is ledger[0]  # again
    assert repeated_exchange(ledger, "b", (40, 58), "a", (14, 30), 0.5) is ledger[0]  # mirror
    assert repeated_exchange(ledger, "a", (28, 48), "b", (42, 56), 0.5) is None  # new window
    assert repeated_exchange(ledger, "a", (12, 32), "b", (70, 90), 0.5) is None  # new place of b
    assert repeated_exchange(ledger, "a", (12, 32), "c", (40, 55), 0.5) is None  # another rover
    assert repeated_exchange(ledger, "a", (12, 32), "b", (42, 56), 1.0) is None  # guard off


def test_split_fusion_moves_both_rovers_once_per_place(pair_shared):
    """With the default "split", an accepted registration moves the rover and, the other way,
    the owner (a mirror row in the owner's attempts, the same exchange id); the mirror of an
    exchange and the same registration again are refused as already exchanged; neither rover
    ends worse than its odometry by more than the test bound."""
    res = pair_shared
    rows = [a for r in res.rovers for a in r.shared]
    acc = [a for a in rows if a.accepted]
    mirrors = [a for a in acc if a.mirror]
    assert mirrors, "no exchange moved the owner: the test would prove nothing"
    for m in mirrors:
        own = [a for a in acc if a.exchange == m.exchange and not a.mirror]
        assert len(own) <= 1 and all(a.rover == m.owner and a.owner == m.rover for a in own)
        assert 0 < m.weight < 1 and m.applied_sigma_m < m.own_sigma_m
    for r in res.rovers:
        ids = [a.exchange for a in r.shared if a.accepted]
        assert len(ids) == len(set(ids)), ids  # one exchange moves a rover once
    assert any(a.reason.startswith("already exchanged") for a in rows if a.success)
    for r in res.rovers:
        s = r.result.summary()
        assert s["ate_corrected"]["rmse_m"] <= s["ate_odometry"]["rmse_m"] + 0.02, (r.name, s)
        assert s["final_error_corrected_m"] <= s["final_error_odometry_m"] + 0.03, (r.name, s)
