"""Where a vehicle saw each landmark from (sighting arc length along its path): carried by
LandmarkMap and its files, used by the bend model when no odometry bounds are stated, and the
registration counted once in the predicted error."""

import importlib
import math

import numpy as np
import pytest

from conftest import random_T, rock_field
from lunarloc.core.errors import InputError
from lunarloc.core.geometry import invert_transform, transform_points
from lunarloc.localization.config import LocalizationConfig
from lunarloc.localization.localize import localize
from lunarloc.io.maps import (
    LandmarkMap,
    Traverse,
    aggregate_detections,
    detection_arcs_m,
    load_map,
    path_arc_length_m,
    save_map,
    traverse_map,
)


def _arc_map(rng, n=12):
    mean = rng.uniform(0, 40, n)
    return LandmarkMap(
        rock_field(rng, n),
        sigma_xy_m=np.full(n, 0.01),
        sighting_arc_m=mean,
        sighting_arc_min_m=mean - rng.uniform(0, 2, n),
        sighting_arc_max_m=mean + rng.uniform(0, 2, n),
    )


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_sighting_arcs_round_trip_and_old_files_load(tmp_path, rng, suffix):
    m = _arc_map(rng)
    m.sighting_arc_min_m = np.maximum(m.sighting_arc_min_m, 0.0)
    back = load_map(save_map(m, tmp_path / f"m{suffix}"))
    for name in ("sighting_arc_m", "sighting_arc_min_m", "sighting_arc_max_m"):
        assert np.allclose(getattr(back, name), getattr(m, name), atol=1e-6), name
    assert back.has_sighting_arcs
    sub = back.subset([2, 0])  # subsets and frame changes keep them
    assert np.allclose(sub.sighting_arc_m, m.sighting_arc_m[[2, 0]], atol=1e-6)
    assert back.transformed(random_T(rng)).has_sighting_arcs
    # a file written before the columns existed loads, without them
    old = tmp_path / "old.csv"
    old.write_text("x,y,z,sigma_xy\n0,0,0,0.01\n1,0,0,0.01\n0,1,0,0.01\n")
    assert not load_map(old).has_sighting_arcs and load_map(old).sighting_arc_max_m is None


def test_sighting_arcs_are_checked(rng):
    P = rock_field(rng, 3)
    with pytest.raises(InputError, match="all three or none"):
        LandmarkMap(P, sighting_arc_m=np.ones(3))
    with pytest.raises(InputError, match="min <= mean <= max"):
        LandmarkMap(
            P,
            sighting_arc_m=np.ones(3),
            sighting_arc_min_m=np.full(3, 2.0),
            sighting_arc_max_m=np.full(3, 3.0),
        )
    with pytest.raises(InputError, match="sighting_arc_m"):
        LandmarkMap(
            P,
            sighting_arc_m=np.array([1.0, -1, 1]),
            sighting_arc_min_m=np.zeros(3),
            sighting_arc_max_m=np.ones(3),
        )
    with pytest.raises(InputError, match="detection's frame"):
        detection_arcs_m(np.zeros((2, 3)), [0, 1], [0, 5])


def test_aggregation_keeps_where_each_landmark_was_seen_from():
    # a straight 10 m drive, one pose a metre; rock A seen from metres 2-4, rock B from 1 and 9
    path = np.c_[np.arange(11.0), np.zeros(11), np.zeros(11)]
    frames = np.arange(100, 111)
    det_frame = np.r_[[102, 103, 104] * 2, [101, 109] * 3]
    det = np.r_[np.tile([[5.0, 2.0, 0.0]], (6, 1)), np.tile([[1.0, -2.0, 0.0]], (6, 1))]
    arcs = detection_arcs_m(path, frames, det_frame)
    assert np.allclose(arcs, det_frame - 100)
    m = aggregate_detections(det, det_frame, detection_arc_m=arcs)
    a, b = np.argsort(m.positions_xyz[:, 0])[::-1]
    assert m.sighting_arc_m[a] == pytest.approx(3.0) and (
        m.sighting_arc_min_m[a],
        m.sighting_arc_max_m[a],
    ) == (2, 4)
    assert m.sighting_arc_m[b] == pytest.approx(5.0) and (
        m.sighting_arc_min_m[b],
        m.sighting_arc_max_m[b],
    ) == (1, 9)
    assert not aggregate_detections(
        det, det_frame
    ).has_sighting_arcs  # without arcs: None, as before
    trav = Traverse(frames, path, det, det_frame, "t")
    assert np.allclose(traverse_map(trav).sighting_arc_m, m.sighting_arc_m)
    assert np.allclose(path_arc_length_m(path), np.arange(11.0))


def _revisit_case(seed, drift_deg_per_m=0.1):
    """A drive 30 m out, a U-turn and 30 m back 3 m to the side, its odometry drifting in
    heading; the camera (6 m, +-60 deg) works only on the way back. The reference holds the
    rocks of x 7-15 m (most of which lie between the two legs, several nearer the outbound
    one that never saw them) and unrelated rocks. Returns (reference, vehicle map with
    sighting arcs, odometry path, true path)."""
    from lunarloc.pipeline.evaluation import DriftModel, drifted_path

    rng = np.random.default_rng(seed)
    th = np.linspace(-np.pi / 2, np.pi / 2, 20)[1:-1]
    xy = np.vstack(
        [
            np.c_[np.arange(0, 30, 0.25), np.zeros(120)],
            np.c_[30 + 1.5 * np.cos(th), 1.5 + 1.5 * np.sin(th)],
            np.c_[np.arange(30, -0.01, -0.25), np.full(121, 3.0)],
        ]
    )
    g = np.c_[xy, np.zeros(len(xy))]
    o, psi = drifted_path(g, DriftModel(drift_deg_per_m, 0.0))
    arc = path_arc_length_m(o)
    heading = np.arctan2(np.gradient(g[:, 1]), np.gradient(g[:, 0]))
    rocks = np.c_[rng.uniform(-2, 32, 260), rng.uniform(-2.5, 5.5, 260), rng.normal(0, 0.1, 260)]
    dets, frames, arcs = [], [], []
    for f in range(120 + len(th), len(g)):
        rel = rocks - g[f]
        bearing = (np.arctan2(rel[:, 1], rel[:, 0]) - heading[f] + np.pi) % (2 * np.pi) - np.pi
        r = rel[(np.linalg.norm(rel[:, :2], axis=1) < 6) & (np.abs(bearing) < np.radians(60))]
        c, s = math.cos(psi[f]), math.sin(psi[f])
        dets.append(
            o[f]
            + np.c_[c * r[:, 0] - s * r[:, 1], s * r[:, 0] + c * r[:, 1], r[:, 2]]
            + rng.normal(0, 0.004, (len(r), 3))
        )
        frames.append(np.full(len(r), f))
        arcs.append(np.full(len(r), arc[f]))
    veh = aggregate_detections(
        np.vstack(dets), np.concatenate(frames), frame="veh", detection_arc_m=np.concatenate(arcs)
    )
    patch = (rocks[:, 0] > 7) & (rocks[:, 0] < 15)
    others = np.c_[rng.uniform(-20, 50, (150, 2)) + [0, 20], rng.normal(0, 0.1, 150)]
    return LandmarkMap(np.vstack([rocks[patch], others])), veh, o, g


def test_revisited_landmarks_placed_where_seen_refuse_the_wrong_pose(monkeypatch):
    """The vehicle map of a patch seen from the return leg only, localized at the rover's end
    without odometry bounds. Placed at their nearest path points (the old model, forced here on
    a map without sighting arcs by a sighting range of 0: one pass within sight), the patch's
    landmarks fall on both legs, 40 m of arc apart: nothing there bent, says the fit, and with
    the registration counted once and no floor on the fitted distortion the pose is claimed
    12-16 cm and 5 deg off. Placed where they were seen from, the fit finds the 0.1 deg/m
    drift and refuses, with or without the floor; without sighting arcs, the landmarks both
    legs come within sight of are left out and the bend is not determined: refused."""
    ref, veh, o, g = _revisit_case(0)
    noarcs = LandmarkMap(
        veh.positions_xyz, veh.sizes, veh.sightings, veh.frame, veh.sigma_xy_m, veh.sigma_z_m
    )
    module = importlib.import_module("lunarloc.localization.bending")

    # the bend fit from the maps alone (no odometry prior): what the floor and the placement are about
    unconstrained = LocalizationConfig(
        odometry_prior_drift_deg_per_m=None, odometry_prior_scale_error=None
    )

    def run(v, cfg=unconstrained):
        r = localize(ref, v, cfg, query_xyz=o[-1:], path_xyz=o)
        return r, float(np.linalg.norm(transform_points(r.T_ref_veh, o[-1:])[0] - g[-1]))

    # the default, the fit under the odometry prior, refuses the 0.1 deg/m map too: the
    # drift the maps show is well beyond what the prior allows, and the fit finds it
    prior, err_prior = run(veh, LocalizationConfig())
    assert not prior.success or err_prior < 0.10, (prior.reason, err_prior)
    assert math.degrees(prior.distortion_fit["drift_rad_per_m"]) > 0.03

    with monkeypatch.context() as mp:
        mp.setattr(module, "DRIFT_FLOOR_DEG_PER_M", 0.0)
        mp.setattr(module, "SCALE_FLOOR", 0.0)
        new, err_new = run(veh)
        mp.setattr(module, "SIGHTING_RANGE_M", 0.0)
        mp.setattr(module, "PASS_MARGIN_M", 0.0)
        old, err = run(noarcs)
    assert (
        old.success and err > 0.10 and old.distortion_fit["placement"] == "nearest path point"
    )  # confident, wrong
    assert abs(math.degrees(old.distortion_fit["drift_rad_per_m"])) < 0.01  # sure that nothing bent
    for r in (new, run(veh)[0]):
        assert r.distortion_fit["placement"] == "sightings" and r.distortion_fit["left_out"] == 0
        assert (
            abs(math.degrees(r.distortion_fit["drift_rad_per_m"]) - 0.1) < 0.02
        )  # the drift is found
        assert not r.success and "fitted from the maps" in r.reason, (r.reason, err_new)
    fallback, _ = run(noarcs)
    assert not fallback.success and fallback.distortion_fit["left_out"] > 0


def test_compact_rigid_map_in_a_lac_grid_localizes_without_bounds():
    """A 6 m vehicle map of true rock positions against the site's LAC grid (4.3 cm
    quantisation), no odometry bounds stated: the registration's uncertainty counted once,
    the fitted bend's own beside it, the pose is claimed (the triple count refused it)."""
    from lunarloc.sim.simulate import simulate_site
    from lunarloc.io.overhead import grid_landmarks, site_geometric_map
    from lunarloc.pipeline.reference import rocks_to_reference

    site = simulate_site(0)
    ref = grid_landmarks(site_geometric_map(site))
    truth = rocks_to_reference(site.rocks.table())
    rng = np.random.default_rng(0)
    sel = np.linalg.norm(truth.positions_xyz[:, :2] - np.array([3.0, -2.0]), axis=1) < 6
    P = truth.positions_xyz[sel] + rng.normal(0, 0.01, (int(sel.sum()), 3))
    T = random_T(rng, max_tilt_deg=0.3)
    r = localize(ref, LandmarkMap(transform_points(invert_transform(T), P)))
    assert r.success, r.reason
    assert r.distortion_fit["placement"] == "straight stand-in"
    err = np.linalg.norm(transform_points(r.T_ref_veh @ invert_transform(T), P) - P, axis=1).max()
    assert err < r.predicted_error_m < 0.10


def test_max_sighting_span_is_a_run_setting(tmp_path):
    import json

    from lunarloc.config.run import RunConfig, load_config_file
    from lunarloc.core.errors import ConfigError

    assert RunConfig().localization.max_sighting_span_m == 10.0
    p = tmp_path / "config.json"
    p.write_text(json.dumps({"localization": {"max_sighting_span_m": 25.0}}))
    cfg, _ = load_config_file(p)
    assert (
        cfg.localization.max_sighting_span_m == 25.0 and RunConfig.from_dict(cfg.to_dict()) == cfg
    )
    with pytest.raises(ConfigError, match="max_sighting_span_m"):
        LocalizationConfig(max_sighting_span_m=0.0)
