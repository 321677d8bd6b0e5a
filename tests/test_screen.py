"""The screen before a large exhaustive search (localize._screen) and the triangle index at
the search's own tolerance (localize_large.build_index)."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest

from conftest import make_pair, rock_field
from lunarloc.association.graph import sweep_yaw_bins, vehicle_pairs
from lunarloc.association.putative import putative_associations
from lunarloc.sim.fields import uniform_rock_field, vehicle_window
from lunarloc.core.errors import ConfigError
from lunarloc.core.geometry import invert_transform, transform_points
from lunarloc.localization.config import LocalizationConfig
from lunarloc.localization.localize import localize
from lunarloc.localization.search import predicted_incidences
from lunarloc.localization.large import build_index, localize_large
from lunarloc.io.maps import LandmarkMap

loc_search = importlib.import_module("lunarloc.localization.search")
Q_SIGMA = 0.15 / math.sqrt(12)  # a 0.15 m grid's quantisation sigma


def _grid_reference(P: np.ndarray) -> LandmarkMap:
    n = len(P)
    return LandmarkMap(P, sigma_xy_m=np.full(n, Q_SIGMA), sigma_z_m=np.full(n, Q_SIGMA))


@pytest.fixture(scope="module")
def overhead_pair():
    rng = np.random.default_rng(3)
    ref, veh, T, _ = make_pair(rng, n_ref=300, n_common=60, n_outliers=20, noise=0.03)
    return _grid_reference(ref.positions_xyz), veh, T, LandmarkMap(rock_field(rng, 80))


# a small stand-in for the 600-rock benchmark: the screen runs from this graph size
SMALL = dict(epsilon_m=0.15, epsilon_z_m=0.15, screen_min_incidences=1e5)


def test_unrelated_map_is_refused_by_the_screen_without_the_exhaustive_search(overhead_pair):
    ref, _, _, unrelated = overhead_pair
    res = localize(ref, unrelated, LocalizationConfig(**SMALL))
    assert not res.success
    assert "no consistent set large enough" in res.reason
    assert res.checks[0].name == "screen" and not res.checks[0].passed
    assert res.checks[0].value < res.checks[0].limit
    assert "screen" in res.timings and "search" not in res.timings
    assert not np.any(np.isfinite(res.T_ref_veh))


def test_true_pair_passes_the_screen_and_the_exact_search_decides(overhead_pair):
    ref, veh, T, _ = overhead_pair
    res = localize(ref, veh, LocalizationConfig(**SMALL))
    assert "screen" in res.timings and "search" in res.timings
    assert res.success, res.reason
    E = res.T_ref_veh @ invert_transform(T)
    assert np.linalg.norm(E[:3, 3]) < 0.05
    # the same decision and pose as without the screen
    plain = localize(ref, veh, LocalizationConfig(**{**SMALL, "screen_min_incidences": 0}))
    assert "screen" not in plain.timings
    assert plain.success and np.allclose(plain.T_ref_veh, res.T_ref_veh)
    assert np.array_equal(plain.inliers, res.inliers)


def test_screen_does_not_run_below_its_graph_size(overhead_pair):
    ref, veh, _, _ = overhead_pair
    res = localize(
        ref, veh, LocalizationConfig(epsilon_m=0.15, epsilon_z_m=0.15)
    )  # default: 3e7, far above
    assert "screen" not in res.timings and res.success


def test_predicted_incidences_bound_the_real_graph_size():
    """An over-estimate of the yaw-bin graphs' size (it skips the height test), but of the
    right order: the screen's trigger follows the real work."""
    rng = np.random.default_rng(5)
    ref = LandmarkMap(rock_field(rng, 120))
    veh = LandmarkMap(rock_field(rng, 40, size=12.0))
    for eps in (0.05, 0.15):
        cfg = LocalizationConfig(epsilon_m=eps, epsilon_z_m=eps, threads=1)
        Pv, Pr = veh.positions_xyz, ref.positions_xyz
        _, node_of = putative_associations(len(Pv), len(Pr), None, None, None)
        real = sweep_yaw_bins(
            vehicle_pairs(Pv),
            loc_search._ref_index(Pr, cfg),
            node_of,
            loc_search._n_bins(cfg),
            loc_search._chunk_bins(cfg),
            *loc_search._graph_args(cfg),
            lambda *a: None,
            weights=False,
            workers=1,
        )
        pred = predicted_incidences(Pv, Pr, cfg)
        assert real <= pred <= 3 * real, (eps, real, pred)


def test_screen_config_is_checked():
    with pytest.raises(ConfigError, match="screen_fraction"):
        LocalizationConfig(screen_fraction=0)
    with pytest.raises(ConfigError, match="screen_min_incidences"):
        LocalizationConfig(screen_min_incidences=-1)
    cfg = LocalizationConfig(screen_candidates=3)
    assert LocalizationConfig(**cfg.to_dict()).screen_candidates == 3


def test_vote_mode_finds_the_dense_place():
    rng = np.random.default_rng(0)
    true = np.array([2.0, -1.0, 0.5])
    votes = np.vstack(
        [
            true + rng.normal(0, [0.02, 0.02, 0.003], (200, 3)),
            np.c_[rng.uniform(-4, 8, (2000, 2)), rng.uniform(-math.pi, math.pi, 2000)],
        ]
    )
    x, y, yaw = loc_search._vote_mode(votes, 2.4, -1.3, 0.55)  # a candidate 0.5 m and 3 degrees off
    assert abs(x - 2.0) < 0.02 and abs(y + 1.0) < 0.02 and abs(yaw - 0.5) < 0.005


# ---------------------------------------------------------------- the index's tolerance


def test_index_is_built_at_the_derived_tolerance():
    rng = np.random.default_rng(2)
    ref = _grid_reference(uniform_rock_field(rng, 400).positions_xyz)
    cfg = LocalizationConfig()
    index = build_index(ref, cfg)
    derived = cfg.for_maps(ref, LandmarkMap(ref.positions_xyz[:3])).epsilon_m
    assert index.epsilon_m == pytest.approx(derived) and index.epsilon_m > 0.1  # not the fixed 5 cm
    plain = LandmarkMap(ref.positions_xyz)  # no stated sigma: the configured floor
    assert build_index(plain, cfg).epsilon_m == pytest.approx(cfg.epsilon_m)


def test_indexed_search_on_a_quantised_map_uses_the_derived_tolerance(caplog):
    """Rock positions quantised to a 0.15 m grid: triangle sides are off by up to ~15 cm,
    which an index at 5 cm does not match; at the derived tolerance it does, and an index
    given at the wrong tolerance is rebuilt."""
    rng = np.random.default_rng(11)
    field = uniform_rock_field(rng, 2500)
    quantised = np.c_[
        np.floor(field.positions_xyz[:, :2] / 0.15) * 0.15 + 0.075, field.positions_xyz[:, 2]
    ]
    ref = _grid_reference(quantised)
    win = vehicle_window(np.random.default_rng(1), field, 150)
    cfg = LocalizationConfig()
    narrow = build_index(LandmarkMap(quantised), cfg)  # 5 cm: what the index used to be built at
    assert narrow.epsilon_m == pytest.approx(0.05)
    with caplog.at_level("INFO", logger="lunarloc.localization.large"):
        res = localize_large(ref, win.vehicle, cfg, index=narrow, search="indexed")
    assert "rebuilt" in caplog.text
    assert res.success, res.reason
    d = np.linalg.norm(
        transform_points(res.T_ref_veh, win.vehicle.positions_xyz)
        - transform_points(win.T_ref_veh, win.vehicle.positions_xyz),
        axis=1,
    )
    assert d.max() < 0.15
