"""The search for the densest consistent association set: the screen (is a fix possible at all), 3D
and gravity-aware yaw-bin sweeps, competitors."""

from __future__ import annotations

import functools
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from lunarloc.association.clipper import clipper_clique
from lunarloc.association.clique import bin_clique_bounds, max_clique, peel
from lunarloc.association.graph import (
    RefPairIndex,
    graph_3d,
    sweep_bin_chunks,
    sweep_yaw_bins,
    vehicle_pairs,
    yaw_bin_chunks,
)
from lunarloc.core.errors import DegenerateGeometryError, InputError
from lunarloc.core.geometry import (
    transform_points,
)
from lunarloc.localization.chance import chance_refined
from lunarloc.localization.config import LocalizationConfig, Solver
from lunarloc.localization.register import _refine


def _solve(
    solver: Solver, n: int, eu, ev, ew, lower_bound: int, seed: int, scratch=None
) -> np.ndarray:
    if solver is Solver.EXACT:
        return max_clique(n, eu, ev, lower_bound, scratch)
    if lower_bound > 0 and len(eu):
        keep = peel(eu, ev, lower_bound, scratch)  # vertices of degree < lb cannot beat lb
        eu, ev, ew = eu[keep], ev[keep], ew[keep]
        if len(eu) < lower_bound * (lower_bound + 1) // 2:
            return np.empty(0, dtype=np.int32)
    c = clipper_clique(n, eu, ev, ew, seed=seed)
    return c if len(c) > lower_bound else np.empty(0, dtype=np.int32)


def _search_3d(Pv, Pr, node_of, assoc, cfg):
    g = graph_3d(Pv, Pr, node_of, cfg.search.epsilon_m, cfg.sigma, cfg.search.max_edges)
    if g is None:
        raise InputError(
            f"the 6-DoF consistency graph of {len(assoc)} associations exceeds "
            f"{cfg.search.max_edges} edges; use the gravity-aware mode, a smaller epsilon, size "
            "pruning, or raise max_edges"
        )
    eu, ev, ew = g
    best = _solve(cfg.solver, len(assoc), eu, ev, ew, 0, cfg.search.seed)
    return best, 0, len(eu)


def _explained(T, Pv, Pr, assoc, radius):
    """Associations consistent with T (their landmarks land within `radius`)."""
    # each landmark moved once
    d = np.linalg.norm(transform_points(T, Pv)[assoc[:, 0]] - Pr[assoc[:, 1]], axis=1)
    return d < radius


def _competitor_3d(T, Pv, Pr, node_of, assoc, cfg):
    explained = _explained(T, Pv, Pr, assoc, 3 * cfg.search.epsilon_m)
    node2 = node_of.copy()
    node2[assoc[explained, 0], assoc[explained, 1]] = -1
    keep = node2[assoc[:, 0], assoc[:, 1]] >= 0
    g = graph_3d(Pv, Pr, node2, cfg.search.epsilon_m, cfg.sigma, cfg.search.max_edges)
    if g is None or not np.any(keep):
        return 0
    eu, ev, ew = g
    return len(_solve(cfg.solver, len(assoc), eu, ev, ew, 0, cfg.search.seed))


def _n_bins(cfg) -> int:
    return max(1, int(round(360.0 / cfg.search.yaw_step_deg)))


def _sweep(Pv, Pr, node_of, cfg, visit, bin_start: int = 0, bin_count: int | None = None) -> int:
    """Run `visit(bin, theta, eu, ev, ew)` on the consistency graph of every yaw bin."""
    n_bins = _n_bins(cfg)
    return sweep_yaw_bins(
        vehicle_pairs(Pv),
        _ref_index(Pr, cfg),
        node_of,
        n_bins,
        _chunk_bins(cfg),
        *_graph_args(cfg),
        visit,
        weights=cfg.solver is Solver.CLIPPER,
        bin_start=bin_start,
        bin_count=bin_count,
        workers=cfg.search.threads,
    )


def _chunk_bins(cfg) -> int:
    return max(1, _n_bins(cfg) // 8)


def _graph_args(cfg) -> tuple:
    """(eps_h, eps_z, tan_tilt, k_yaw, sigma) of the yaw-bin consistency graphs."""
    return (
        cfg.search.epsilon_m,
        cfg.search.epsilon_z_m,
        math.tan(math.radians(cfg.search.max_tilt_deg)),
        cfg.search.yaw_noise_factor,
        cfg.sigma,
    )


_PARALLEL_MIN_WORK = (
    2e8  # vehicle pairs x reference pairs below which a sweep runs on the calling thread
)


def _workers(cfg, vp, index: RefPairIndex, share: float = 1.0) -> int:
    """Threads for a sweep over `share` of the yaw circle: one when the work is small
    (handing chunks to other threads then costs more than it saves)."""
    return cfg.search.threads if len(vp[0]) * len(index.a) * share >= _PARALLEL_MIN_WORK else 1


def _ref_index(Pr, cfg) -> RefPairIndex:
    return RefPairIndex(
        Pr, dist_cell_m=max(cfg.search.epsilon_m / 2, 0.01), angle_cell_rad=math.radians(1.0)
    )


class _Scratch(threading.local):
    """Per-thread scratch array for the clique solver (int32, filled with -1)."""

    def __init__(self, n: int):
        self.arr = np.full(n, -1, dtype=np.int32)


# Bin bounds: the vehicle landmarks are split into groups (round robin) and the graphs of
# the pairs inside each group are built for every yaw bin (1/groups of the work); a clique
# of the whole graph splits into cliques of the group graphs, so the sum over the groups of
# (degeneracy + 1) bounds each bin's maximum clique. More groups cost less but bound less
# tightly; measured on the 136 real pairs (benchmarks/pair_speed.py), by association count:
_BOUND_GROUPS = ((2_500, 1), (10_000, 2), (50_000, 4))  # (fewer associations than, groups); else 8


def _bound_groups(n_assoc: int) -> int:
    for limit, groups in _BOUND_GROUPS:
        if n_assoc < limit:
            return groups
    return 8


def _bin_bounds(Pv, vp, index, node_of, cfg) -> tuple[np.ndarray, np.ndarray, int]:
    """(upper, lower) bound on the maximum clique of every yaw bin's consistency graph, and
    the edges generated to find them. Upper: sum over groups of vehicle landmarks of the
    group graph's degeneracy + 1 (any clique of the bin puts at most that many of its
    members in each group); lower: the largest greedy clique of a group graph (a clique of
    the bin's graph too). Without groups (small vehicle maps): (inf, 0)."""
    n_bins = _n_bins(cfg)
    groups = min(_bound_groups(int(np.count_nonzero(node_of >= 0))), max(1, len(Pv) // 8))
    if groups == 1:
        return (
            np.full(n_bins, np.iinfo(np.int64).max, dtype=np.int64),
            np.zeros(n_bins, dtype=np.int64),
            0,
        )
    upper = np.zeros(n_bins, dtype=np.int64)
    lower = np.ones(n_bins, dtype=np.int64)
    scratch = _Scratch(int(node_of.size))
    lock = threading.Lock()
    chunks = yaw_bin_chunks(n_bins, _chunk_bins(cfg), range(n_bins))
    pi, pj = vp[0], vp[1]
    # threads by the bounds' whole work (every group's pairs against the reference pairs), as
    # the groups run one after another: many small group sweeps add up to one large one
    workers = _workers(cfg, vp, index, 1.0 / groups)
    edges = 0
    for g in range(groups):
        sel = (pi % groups == g) & (pj % groups == g)
        vpg = tuple(x[sel] for x in vp)

        def visit_chunk(bins, ptr, su, sv, _sw):
            ub, lb = bin_clique_bounds(ptr, su, sv, scratch.arr)
            with lock:
                # a group with no edge in a bin still holds one member
                upper[bins] += np.maximum(ub, 1)
                np.maximum.at(lower, bins, lb)

        edges += sweep_bin_chunks(
            vpg,
            index,
            node_of,
            n_bins,
            chunks,
            *_graph_args(cfg),
            visit_chunk,
            weights=False,
            workers=workers,
        )
    return upper, lower, edges


class _BestYaw(float):
    """The winning relative yaw (rad), carrying what the search learnt (reference pair index,
    per-bin clique bounds, winning size) so that the same-yaw competitor search reuses it."""

    index: RefPairIndex
    upper: np.ndarray
    best_size: int
    # bin -> (eu, ev) of the bins the search built (exact solver, up to _EDGE_CACHE_MAX)
    edges: dict | None


_EDGE_CACHE_MAX = 8_000_000


def _far_pairs_floor(values: np.ndarray, n_bins: int, sep_bins: float) -> int:
    """Largest min(v_x, v_y) over bins x, y more than 2 * sep apart: whatever the winning
    yaw, one of the two is more than sep from it, so the competitor is at least this."""
    far = _far_mask(n_bins, 2 * sep_bins)
    if not far.any():
        return 0
    return int(np.minimum(values[:, None], values[None, :])[far].max())


@functools.lru_cache(maxsize=8)
def _far_mask(n_bins: int, min_sep_bins: float) -> np.ndarray:
    """Boolean (n_bins, n_bins): bins more than `min_sep_bins` apart around the circle."""
    b = np.arange(n_bins)
    d = np.abs(b[:, None] - b[None, :])
    return np.minimum(d, n_bins - d) > min_sep_bins


def _search_yaw_bins(Pv, Pr, node_of, cfg, required: int | None = None, report: dict | None = None):
    """Max consistent set over relative-yaw bins; also the best set whose yaw differs
    by more than competitor_yaw_sep_deg (the competing hypothesis).

    Exact, bin by bin, but only where a bin can matter: cheap per-bin clique bounds
    (:func:`_bin_bounds`) order the bins; the most promising bin is solved first, and
    then only bins whose bound exceeds ``lb = max(floor(best / competitor_ratio), known
    competitor floor)`` are built and searched, each for a clique larger than lb. Hence:
    the winner is the largest clique of any bin (ties: smallest yaw), found exactly; the
    competitor is exact whenever it exceeds best / competitor_ratio (when it can decide
    the ambiguity test, as the inlier count is at least the clique size), otherwise a
    lower bound on it (a clique found in a far bin).

    With `required` (the inliers acceptance needs), a search that would be large is screened
    first (:func:`_screen`, its outcome in ``report["screen"]``); when the screen refuses,
    nothing is built and no set is returned."""
    n_assoc = int(node_of.size)
    n_bins = _n_bins(cfg)
    step = 2 * math.pi / n_bins
    sep_bins = math.radians(cfg.acceptance.competitor_yaw_sep_deg) / step
    index = _ref_index(Pr, cfg)
    vp = vehicle_pairs(Pv)
    if required is not None:
        t0 = time.perf_counter()
        screen = _screen(Pv, Pr, cfg, required, vp, index)
        if report is not None and screen is not None:
            report["screen"], report["screen_s"] = screen, time.perf_counter() - t0
        if screen is not None and not screen.passed:
            return np.empty(0, dtype=np.int32), 0, None, 0
    upper, lower, total_edges = _bin_bounds(Pv, vp, index, node_of, cfg)
    found: dict[int, np.ndarray] = {}
    state = {"best": 0, "floor": _far_pairs_floor(lower, n_bins, sep_bins)}
    lock = threading.Lock()
    scratch = _Scratch(n_assoc)

    def lb_now() -> int:
        return max(int(state["best"] // cfg.acceptance.competitor_ratio), state["floor"])

    edges = {} if cfg.solver is Solver.EXACT else None  # clique sizes do not depend on edge order
    kept = [0]

    def visit_chunk(bins, ptr, su, sv, sw):
        if edges is not None:
            with lock:
                if kept[0] + len(su) <= _EDGE_CACHE_MAX:
                    kept[0] += len(su)
                    for t, b in enumerate(bins):
                        edges[b] = (su[ptr[t] : ptr[t + 1]], sv[ptr[t] : ptr[t + 1]])
        for t in sorted(range(len(bins)), key=lambda t: -upper[bins[t]]):
            b = bins[t]
            with lock:
                lb = lb_now()
            if upper[b] <= lb or ptr[t + 1] - ptr[t] < lb * (lb + 1) // 2:
                continue
            sl = slice(ptr[t], ptr[t + 1])
            c = _solve(
                cfg.solver, n_assoc, su[sl], sv[sl], sw[sl], lb, cfg.search.seed, scratch.arr
            )
            if len(c) == 0:
                continue
            with lock:
                found[b] = c
                state["best"] = max(state["best"], len(c))
                for b2, c2 in found.items():
                    d = abs(b - b2)
                    if min(d, n_bins - d) > 2 * sep_bins:
                        state["floor"] = max(state["floor"], min(len(c), len(c2)))

    def sweep(bins) -> int:
        chunks = yaw_bin_chunks(n_bins, _chunk_bins(cfg), bins)
        chunks.sort(key=lambda c: -int(upper[c[0] + c[1] : c[0] + c[2] + 1].max()))
        share = sum(c[2] - c[1] + 1 for c in chunks) / n_bins
        return sweep_bin_chunks(
            vp,
            index,
            node_of,
            n_bins,
            chunks,
            *_graph_args(cfg),
            visit_chunk,
            weights=cfg.solver is Solver.CLIPPER,
            workers=_workers(cfg, vp, index, share),
        )

    top = int(np.argmax(upper))
    if upper[top] < np.iinfo(np.int64).max:
        # the most promising bin first: its clique raises lb for the rest
        total_edges += sweep([top])
    lb = lb_now()
    rest = [b for b in np.flatnonzero(upper > lb).tolist() if b not in found]
    total_edges += sweep(rest)

    if not found:
        return np.empty(0, dtype=np.int32), 0, None, total_edges
    size = max(len(c) for c in found.values())
    b_best = min(b for b, c in found.items() if len(c) == size)

    far = _far_mask(n_bins, sep_bins)[b_best]
    second = max(
        [state["floor"], int(lower[far].max(initial=0))]
        + [len(c) for b, c in found.items() if far[b]]
    )
    best_yaw = _BestYaw(-math.pi + (b_best + 0.5) * step)
    best_yaw.index, best_yaw.upper, best_yaw.best_size, best_yaw.edges = index, upper, size, edges
    return found[b_best], int(second), best_yaw, total_edges


def _competitor_same_yaw(T, Pv, Pr, node_of, assoc, cfg, best_yaw, floor: int = 0):
    """Best set near the winner's yaw among associations the winner does not explain
    (a shifted copy of the pattern at the same heading). Like the main search, exact when
    it exceeds best / competitor_ratio (or `floor`), otherwise `floor` is returned."""
    if best_yaw is None:
        return 0
    explained = _explained(T, Pv, Pr, assoc, 3 * cfg.search.epsilon_m)
    node2 = node_of.copy()
    node2[assoc[explained, 0], assoc[explained, 1]] = -1
    n_bins = _n_bins(cfg)
    step = 2 * math.pi / n_bins
    centre = int(math.floor((best_yaw + math.pi) / step))
    reach = int(math.ceil(math.radians(cfg.acceptance.competitor_yaw_sep_deg) / step))
    bins = [(centre + t) % n_bins for t in range(-reach, reach + 1)]
    lb0 = floor
    index = None
    if isinstance(best_yaw, _BestYaw):  # reuse the main search's index and bounds
        index = best_yaw.index
        lb0 = max(floor, int(best_yaw.best_size // cfg.acceptance.competitor_ratio))
        bins = [
            b for b in bins if best_yaw.upper[b] > lb0
        ]  # removing associations only lowers the bound
    if not bins:
        return floor
    state = {"best": lb0}  # only a set larger than this can matter
    lock = threading.Lock()
    scratch = _Scratch(int(node_of.size))
    n_assoc = int(node_of.size)

    def visit_chunk(bins_, ptr, su, sv, sw):
        for t in range(len(bins_)):
            if ptr[t + 1] > ptr[t]:
                sl = slice(ptr[t], ptr[t + 1])
                c = _solve(
                    cfg.solver,
                    n_assoc,
                    su[sl],
                    sv[sl],
                    sw[sl],
                    state["best"],
                    cfg.search.seed,
                    scratch.arr,
                )
                with lock:
                    state["best"] = max(state["best"], len(c))

    cached = best_yaw.edges if isinstance(best_yaw, _BestYaw) and best_yaw.edges is not None else {}
    if any(b in cached for b in bins):
        # a bin the search built: its graph without the explained associations is its edges
        # minus those touching them (the same edges the rebuild below would give, in
        # another order: the maximum clique's size, all that is kept, is the same)
        removed = np.zeros(n_assoc, dtype=bool)
        removed[node_of[assoc[explained, 0], assoc[explained, 1]]] = True
        for b in [b for b in bins if b in cached]:
            eu, ev = cached[b]
            keep = ~(removed[eu] | removed[ev])
            if keep.any():
                eu, ev = eu[keep], ev[keep]
                c = _solve(
                    cfg.solver, n_assoc, eu, ev, eu, state["best"], cfg.search.seed, scratch.arr
                )
                state["best"] = max(state["best"], len(c))
        bins = [b for b in bins if b not in cached]
        if not bins:
            return state["best"] if state["best"] > lb0 else floor
    vp = vehicle_pairs(Pv)
    index = index if index is not None else _ref_index(Pr, cfg)
    sweep_bin_chunks(
        vp,
        index,
        node2,
        n_bins,
        yaw_bin_chunks(n_bins, _chunk_bins(cfg), bins),
        *_graph_args(cfg),
        visit_chunk,
        weights=cfg.solver is Solver.CLIPPER,
        workers=_workers(cfg, vp, index, len(bins) / n_bins),
    )
    return state["best"] if state["best"] > lb0 else floor


def predicted_incidences(
    Pv: np.ndarray,
    Pr: np.ndarray,
    cfg: LocalizationConfig,
    vp=None,
    index: RefPairIndex | None = None,
) -> float:
    """Estimated size of the gravity-aware search's yaw-bin consistency graphs: edge
    incidences summed over the bins, before the height test (so an over-estimate).

    A vehicle pair of horizontal distance d meets the ordered reference pairs within
    epsilon of d (counted from the distance rows of the search's :class:`RefPairIndex`,
    interpolated within a row), and such a match lands in the ``2 tol / step`` bins around
    its yaw (tol: the generator's yaw tolerance). O(vehicle pairs) given the search's own
    `vp` and `index`. Measured on the 600-rock overhead benchmark at 15 cm: about 1.5x the
    real incidences (``tests/test_screen.py`` checks it stays within 3x)."""
    eps = cfg.search.epsilon_m
    vp = vehicle_pairs(Pv) if vp is None else vp
    index = _ref_index(Pr, cfg) if index is None else index
    dh, dz = vp[2], vp[4]
    if len(dh) == 0:
        return 0.0
    cum = index.row_ptr.astype(float)  # ordered pairs closer than each distance cell's start
    cells = np.arange(len(cum)) * index.dist_cell
    within = np.interp(dh + eps, cells, cum) - np.interp(np.maximum(dh - eps, 0.0), cells, cum)
    step = 2 * math.pi / _n_bins(cfg)
    dmin = dh - eps
    k_eps = cfg.search.yaw_noise_factor * eps
    tan_tilt = math.tan(math.radians(cfg.search.max_tilt_deg))
    with np.errstate(divide="ignore", invalid="ignore"):
        tol = np.where(
            dmin > k_eps,
            0.5 * step + np.arcsin(np.minimum(k_eps / dmin, 1.0)) + tan_tilt * np.abs(dz) / dmin,
            math.pi,
        )
    bins = np.minimum(np.maximum(2 * tol / step, 1.0), _n_bins(cfg))
    return float(np.sum(within * bins))


_SCREEN_TRIANGLES = 800


@dataclass
class Screen:
    """Outcome of :func:`_screen`: the best candidate pose's inliers beyond chance
    (``score``), what passing needs (``needed``), how many candidates were refined, and
    the predicted graph size that made the screen run."""

    passed: bool
    score: float
    needed: float
    candidates: int
    incidences: float
    inliers: int = 0


def _screen(
    Pv: np.ndarray,
    Pr: np.ndarray,
    cfg: LocalizationConfig,
    required: int,
    vp=None,
    index: RefPairIndex | None = None,
) -> Screen | None:
    """Cheap refusal before an exhaustive search that would be large.

    Runs only when the yaw-bin graphs would hold at least ``screen_min_incidences``
    edge incidences (:func:`predicted_incidences`; a 600-rock overhead map at 15 cm holds
    about 70 million, 5-10 s of CPU), else returns None. The reference's rock triangles
    (:class:`~lunarloc.association.index.ReferenceIndex`, at the search's own tolerance)
    vote for poses; each of the ``screen.candidates`` best-voted poses is refined as the
    final hypothesis is (:func:`_refine`, mutual nearest neighbours within the refinement
    radius), and scored by its inliers less the matches chance gives at that pose
    (:func:`chance_refined`). The screen passes when a score reaches ``screen.fraction``
    of the inliers acceptance requires; then the exhaustive search runs as without the
    screen, so the screen can only refuse, never accept, and whatever is accepted is what
    the exact search and verification accept. A vehicle map without a matching triangle
    gives no candidate: the screen passes (it cannot judge) and the exact search decides."""
    if not cfg.screen.min_incidences > 0:
        return None
    incidences = predicted_incidences(Pv, Pr, cfg, vp, index)
    if incidences < cfg.screen.min_incidences:
        return None
    from lunarloc.association.index import IndexConfig, ReferenceIndex

    needed = cfg.screen.fraction * required
    # rock triangles
    tri = ReferenceIndex(
        Pr, cfg.search.epsilon_m, IndexConfig(max_candidates=cfg.screen.candidates)
    )
    votes = tri.vote(
        Pv,
        cfg.search.epsilon_z_m,
        math.tan(math.radians(cfg.search.max_tilt_deg)),
        _SCREEN_TRIANGLES,
    )
    if not votes.candidates:
        return Screen(True, float("nan"), needed, 0, incidences)
    best, best_inliers = 0.0, 0  # inliers beyond chance: none until a candidate shows some
    for cand in votes.candidates:
        x, y, yaw = _vote_mode(votes.votes_xy_yaw, cand.x_m, cand.y_m, cand.yaw_rad)
        c, s = math.cos(yaw), math.sin(yaw)
        T = np.eye(4)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = np.array([x, y]) - T[:2, :2] @ votes.centre_xy
        Pt = transform_points(T, Pv)
        # the vote fixes x, y and yaw; the height from the nearest rocks
        d, j = tri.tree_xy.query(Pt[:, :2])
        near = d < cfg.refinement.radius_m
        if near.sum() < 3:  # nothing to refine from: no more than chance here
            continue
        T[2, 3] = float(np.median((Pr[j, 2] - Pt[:, 2])[near]))
        try:
            T, inl = _refine(T, Pv, Pr, np.zeros((0, 2), np.int64), cfg)
        # fewer than 3 (or collinear) mutual neighbours in 3D
        except (DegenerateGeometryError, InputError):
            continue
        score = len(inl) - chance_refined(T, Pv, Pr, np.zeros(0, np.int64), cfg.refinement.radius_m)
        if score > best:
            best, best_inliers = score, len(inl)
        if best >= needed:
            break
    return Screen(best >= needed, best, needed, len(votes.candidates), incidences, best_inliers)


def _vote_mode(
    votes: np.ndarray,
    x: float,
    y: float,
    yaw: float,
    windows=((1.0, 10.0), (0.5, 5.0), (0.25, 2.5), (0.25, 2.5)),
) -> tuple[float, float, float]:
    """The densest place of the triangle votes (x, y, yaw rad) near a candidate: the median
    of the votes within a window around the estimate, the window shrinking (metres,
    degrees). A candidate is the median of a 6 m x 30 deg neighbourhood that chance votes
    share: 0.4 m and 4 degrees off the true pose on the 600-rock benchmark, too far for
    refinement to lock on; the true votes agree within centimetres."""
    for half_m, half_deg in windows:
        dyaw = (votes[:, 2] - yaw + math.pi) % (2 * math.pi) - math.pi
        near = (
            (np.abs(votes[:, 0] - x) < half_m)
            & (np.abs(votes[:, 1] - y) < half_m)
            & (np.abs(dyaw) < math.radians(half_deg))
        )
        if near.sum() < 3:
            break
        x, y = float(np.median(votes[near, 0])), float(np.median(votes[near, 1]))
        yaw = float(yaw + np.median(dyaw[near]))
    return x, y, yaw
