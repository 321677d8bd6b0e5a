"""The bounded yaw-bin search: per-bin clique bounds hold, generating a few bins gives the
same graphs as the full sweep, and the search's answer is the exhaustive one."""

import importlib
import math

import numpy as np

from conftest import make_pair
from lunarloc.association.clique import bin_clique_bounds, max_clique
from lunarloc.association.graph import (
    RefPairIndex,
    sweep_bin_chunks,
    sweep_yaw_bins,
    vehicle_pairs,
    yaw_bin_chunks,
)
from lunarloc.association.putative import putative_associations

loc_chance = importlib.import_module("lunarloc.localization.chance")
loc_config = importlib.import_module("lunarloc.localization.config")
loc_search = importlib.import_module("lunarloc.localization.search")


def _setup(rng, n_ref=90, n_common=25, n_outliers=15):
    ref, veh, _, _ = make_pair(
        rng, n_ref=n_ref, n_common=n_common, n_outliers=n_outliers, noise=0.01
    )
    cfg = loc_config.LocalizationConfig(threads=1)
    Pr, Pv = ref.positions_xyz, veh.positions_xyz
    _, node_of = putative_associations(len(Pv), len(Pr))
    return cfg, Pv, Pr, node_of


def _all_bins(cfg, Pv, Pr, node_of):
    """Every bin's edge list from the plain full sweep."""
    graphs = {}

    def visit(b, _theta, eu, ev, _ew):
        graphs[b] = (eu.copy(), ev.copy())

    sweep_yaw_bins(
        vehicle_pairs(Pv),
        loc_search._ref_index(Pr, cfg),
        node_of,
        loc_search._n_bins(cfg),
        loc_search._chunk_bins(cfg),
        *loc_search._graph_args(cfg),
        visit,
        weights=False,
        workers=1,
    )
    return graphs


def test_bin_bounds_bracket_the_maximum_clique(rng):
    # random graphs: degeneracy + 1 >= max clique >= greedy clique
    for _ in range(30):
        n = int(rng.integers(3, 40))
        A = np.triu(rng.random((n, n)) < rng.uniform(0.05, 0.6), 1)
        eu, ev = (x.astype(np.int32) for x in np.nonzero(A))
        if len(eu) == 0:
            continue
        omega = len(max_clique(n, eu, ev))
        ub, lb = bin_clique_bounds(np.array([0, len(eu)]), eu, ev, np.full(n, -1, np.int32))
        assert lb[0] <= omega <= ub[0]


def test_group_bounds_hold_on_every_yaw_bin(rng):
    cfg, Pv, Pr, node_of = _setup(rng)
    upper, lower, _ = loc_search._bin_bounds(
        Pv, vehicle_pairs(Pv), loc_search._ref_index(Pr, cfg), node_of, cfg
    )
    graphs = _all_bins(cfg, Pv, Pr, node_of)
    for b, (eu, ev) in graphs.items():
        omega = len(max_clique(node_of.size, eu, ev)) if len(eu) else 1
        assert lower[b] <= omega <= upper[b], (b, lower[b], omega, upper[b])


def test_some_bins_give_the_full_sweeps_graphs(rng):
    cfg, Pv, Pr, node_of = _setup(rng)
    graphs = _all_bins(cfg, Pv, Pr, node_of)
    n_bins = loc_search._n_bins(cfg)
    got = {}

    def visit_chunk(bins, ptr, su, sv, _sw):
        for t, b in enumerate(bins):
            got[b] = (su[ptr[t] : ptr[t + 1]].copy(), sv[ptr[t] : ptr[t + 1]].copy())

    wanted = [0, 5, 21, 22, 90, 177, 179]
    sweep_bin_chunks(
        vehicle_pairs(Pv),
        loc_search._ref_index(Pr, cfg),
        node_of,
        n_bins,
        yaw_bin_chunks(n_bins, loc_search._chunk_bins(cfg), wanted),
        *loc_search._graph_args(cfg),
        visit_chunk,
        weights=False,
        workers=1,
    )
    assert set(wanted) <= set(got)  # a grid chunk's span of wanted bins is generated
    assert not set(got) & {30, 100, 150}
    for b in got:
        assert np.array_equal(got[b][0], graphs[b][0]) and np.array_equal(got[b][1], graphs[b][1])


def test_search_finds_the_exhaustive_winner_and_a_deciding_competitor(rng):
    for _ in range(3):
        cfg, Pv, Pr, node_of = _setup(rng)
        graphs = _all_bins(cfg, Pv, Pr, node_of)
        n_bins = loc_search._n_bins(cfg)
        omega = np.array(
            [
                len(max_clique(node_of.size, *graphs[b])) if len(graphs[b][0]) else 0
                for b in range(n_bins)
            ]
        )
        best, competitor, yaw, _ = loc_search._search_yaw_bins(Pv, Pr, node_of, cfg)
        assert len(best) == omega.max()
        step = 2 * math.pi / n_bins
        b_best = int(math.floor((yaw + math.pi) / step))
        assert b_best == int(np.flatnonzero(omega == omega.max())[0])  # ties: the smallest yaw
        d = np.abs(np.arange(n_bins) - b_best)
        far = np.minimum(d, n_bins - d) * step > math.radians(cfg.competitor_yaw_sep_deg)
        true_competitor = int(omega[far].max())
        assert competitor <= true_competitor
        if true_competitor > len(best) // cfg.competitor_ratio:  # where it can decide, it is exact
            assert competitor == true_competitor


def test_reference_pair_index_matches_a_sort(rng):
    q = np.c_[rng.uniform(0, 30, (60, 2)), rng.normal(0, 0.5, 60)]
    idx = RefPairIndex(q, 0.025, math.radians(1.0))
    a, b = np.nonzero(~np.eye(len(q), dtype=bool))
    d = q[b] - q[a]
    dh = np.hypot(d[:, 0], d[:, 1])
    phi = np.arctan2(d[:, 1], d[:, 0])
    dbin = np.minimum((dh / idx.dist_cell).astype(np.int64), idx.n_dist - 1)
    abin = np.minimum(((phi + math.pi) / idx.angle_cell).astype(np.int64), idx.n_angle - 1)
    o = np.argsort(dbin * idx.n_angle + abin, kind="stable")
    assert np.array_equal(idx.a, a[o]) and np.array_equal(idx.b, b[o])
    assert (
        np.array_equal(idx.dh, dh[o])
        and np.array_equal(idx.phi, phi[o])
        and np.array_equal(idx.dz, d[o, 2])
    )
    cells = dbin * idx.n_angle + abin
    assert np.array_equal(idx.abin, abin[o]) and idx.row_ptr[-1] == len(a)
    assert np.array_equal(
        idx.row_ptr[:-1], np.searchsorted(cells[o], np.arange(idx.n_dist) * idx.n_angle)
    )


def test_search_tolerance_follows_the_maps_sigma(rng):
    from lunarloc.io.maps import LandmarkMap

    ref, veh, _, _ = make_pair(rng, n_ref=60, n_common=20, n_outliers=5)
    cfg = loc_config.LocalizationConfig()
    plain = cfg.for_maps(ref, veh)  # default landmark sigma: the fixed tolerances are the floors
    assert plain.epsilon_m == cfg.epsilon_m and plain.epsilon_z_m == cfg.epsilon_z_m
    q = 0.15 / math.sqrt(12)  # a LAC grid's quantisation
    grid = LandmarkMap(
        ref.positions_xyz, sigma_xy_m=np.full(len(ref), q), sigma_z_m=np.full(len(ref), q)
    )
    wide = cfg.for_maps(grid, veh)
    sh, sz = loc_config.combined_sigma(grid, veh, cfg)
    assert math.isclose(wide.epsilon_m, cfg.search_sigmas * math.sqrt(2) * sh)
    assert math.isclose(wide.epsilon_z_m, cfg.search_sigmas * math.sqrt(2) * sz)
    assert wide.epsilon_m > 0.1
    # chance sets grow with the tolerance, and the envelope with them
    m = len(ref) * len(veh)
    assert loc_chance.chance_clique_size(
        m, cfg.mode, wide.epsilon_m, wide.epsilon_z_m
    ) > loc_chance.chance_clique_size(m, cfg.mode)
    fixed = loc_config.LocalizationConfig(search_sigmas=0).for_maps(grid, veh)
    assert fixed.epsilon_m == cfg.epsilon_m


def test_same_yaw_competitor_from_the_kept_edges_equals_the_rebuilt_one(rng):
    """The same-yaw competitor search reuses the edges of the bins the main search built
    (minus the winner's explained associations); it must give what rebuilding them gives,
    with a floor low enough that every bin near the winner is searched."""
    from lunarloc.core.geometry import arun

    for _ in range(3):
        # a repeated pattern at the same heading: a real same-yaw competitor to find
        cfg, Pv, Pr, node_of = _setup(rng, n_common=25, n_outliers=5)
        assoc = np.argwhere(node_of >= 0)
        assoc = assoc[np.argsort(node_of[assoc[:, 0], assoc[:, 1]])]
        best, _competitor, yaw, _ = loc_search._search_yaw_bins(Pv, Pr, node_of, cfg)
        inl = assoc[best]
        T = arun(Pv[inl[:, 0]], Pr[inl[:, 1]])
        assert yaw.edges, "the search keeps the edges of the bins it built"
        yaw.best_size = 2  # lb0 = 1: every bin near the winner holding an edge is searched
        kept = loc_search._competitor_same_yaw(T, Pv, Pr, node_of, assoc, cfg, yaw, 0)
        yaw.edges = None
        rebuilt = loc_search._competitor_same_yaw(T, Pv, Pr, node_of, assoc, cfg, yaw, 0)
        assert kept == rebuilt
