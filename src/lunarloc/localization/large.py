"""Global localization in a large reference map without a prior (lost in space).

``localize_large(reference, vehicle, config, index_config, search=...)``:

1. **Index** the reference's rock triangles (:class:`lunarloc.association.index.ReferenceIndex`,
   O(N_ref); pass a prebuilt ``index`` to reuse it for every vehicle map).
2. **Vote**: the vehicle map's triangles look up matching reference triangles; each
   match votes for a pose; the best-supported poses are the candidate regions.
3. **Exact search on crops**: the reference cropped around each candidate region goes
   through the ordinary :func:`lunarloc.localization.localize.localize` (exact maximum clique over
   yaw bins, registration, every verification check), so the answer is exactly as
   trustworthy as on a small map.
4. **Judge globally**: the winner's inliers must beat what chance produces against the
   WHOLE reference (the chance envelope at n_veh x n_ref associations, not the crop's),
   and the best competing hypothesis found anywhere must be clearly smaller
   (``competitor_ratio``), like against like: the winner's refined inliers against every
   other region's refined inliers, and its consistent set (clique) against every other
   consistent set (the other regions', and the competitor inside its own crop, which is
   cropped wide enough to hold a copy shifted by less than the candidates' separation).
   Else the answer is refused as ambiguous: a repeated world is refused, not guessed.

``search="full"`` is the plain :func:`localize` on the whole map; ``"auto"`` uses the
index when the reference holds at least ``IndexConfig.auto_min_reference`` rocks (and the
mode is gravity-aware).
"""

from __future__ import annotations

import enum
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from lunarloc.association.index import IndexConfig, ReferenceIndex
from lunarloc.core.errors import ConfigError
from lunarloc.core.geometry import yaw_of
from lunarloc.io.maps import LandmarkMap
from lunarloc.localization.chance import chance_clique_size
from lunarloc.localization.config import LocalizationConfig, Mode
from lunarloc.localization.localize import _check_map, localize
from lunarloc.localization.provenance import resolve_odometry_bounds
from lunarloc.localization.result import LocalizationResult
from lunarloc.localization.verify import Check

log = logging.getLogger(__name__)

__all__ = ["Search", "LargeResult", "localize_large", "build_index"]


class Search(str, enum.Enum):
    """How the reference map is searched."""

    AUTO = "auto"  # indexed for large references (gravity mode), full otherwise
    FULL = "full"  # every association against the whole reference (exact, quadratic)
    INDEXED = "indexed"  # constellation index -> candidate regions -> exact search on crops


@dataclass
class LargeResult(LocalizationResult):
    """A :class:`LocalizationResult` plus how the indexed search got there.

    search : "full" or "indexed" (what ran).
    candidates : per candidate region checked: its vote pose and votes, the crop size,
        and the exact search's outcome there (inliers, clique, reason).
    winner : index into `candidates` of the answer (-1: none).
    considered : associations considered in all (triangle lookups + the crops' putative
        associations); n_veh x n_ref for the full search.
    """

    search: str = "full"
    candidates: list = field(default_factory=list)
    winner: int = -1
    considered: int = 0

    def to_dict(self) -> dict:
        d = super().to_dict()
        d.update(
            search=self.search,
            candidates=self.candidates,
            winner=self.winner,
            considered=self.considered,
        )
        return d


def build_index(
    reference: LandmarkMap,
    config: LocalizationConfig | None = None,
    index_config: IndexConfig | None = None,
    vehicle: LandmarkMap | None = None,
) -> ReferenceIndex:
    """The constellation index of `reference` for localization with `config`, at the
    search's tolerance: `config`'s epsilon raised to what the maps' uncertainty needs
    (:meth:`LocalizationConfig.for_maps`; without `vehicle`, a vehicle map that states no
    sigma of its own). :func:`localize_large` rebuilds an index whose tolerance is not the
    one the pair needs."""
    cfg = config or LocalizationConfig()
    P = _check_map(reference, "reference")
    return ReferenceIndex(P, _index_epsilon(reference, vehicle, cfg), index_config)


def _index_epsilon(
    reference: LandmarkMap, vehicle: LandmarkMap | None, cfg: LocalizationConfig
) -> float:
    """The horizontal search tolerance of this pair of maps (the vehicle map stating no
    sigma when it is not given): what the triangle sides are compared at."""
    if vehicle is None:
        # no stated sigma: the config's landmark sigma
        vehicle = LandmarkMap(reference.positions_xyz[:1])
    return cfg.for_maps(reference, vehicle).search.epsilon_m


def _from(res: LocalizationResult, **extra) -> LargeResult:
    base = {k: getattr(res, k) for k in LocalizationResult.__dataclass_fields__}
    return LargeResult(**base, **extra)


def localize_large(
    reference: LandmarkMap,
    vehicle: LandmarkMap,
    config: LocalizationConfig | None = None,
    index_config: IndexConfig | None = None,
    *,
    search: Search | str = Search.AUTO,
    index: ReferenceIndex | None = None,
    query_xyz: np.ndarray | None = None,
    path_xyz: np.ndarray | None = None,
) -> LargeResult:
    """Find ``T_ref_veh`` of `vehicle` in a possibly very large `reference` (see the
    module docstring). Inputs are checked as by :func:`localize`; a failure to localize
    is ``success=False`` with a reason, never an exception. `query_xyz` and `path_xyz`
    (vehicle frame) are passed to every :func:`localize` call: where the pose is judged,
    and the odometry path that built the vehicle map."""
    cfg = config or LocalizationConfig()
    icfg = index.config if index is not None else (index_config or IndexConfig())
    # 1. the maps, and which search runs: the plain localize() on the whole map, or the index
    search, Pr, Pv = _resolve_search(search, reference, vehicle, cfg, icfg, index)
    if search is Search.FULL:
        return _from(
            localize(reference, vehicle, cfg, query_xyz=query_xyz, path_xyz=path_xyz),
            search="full",
            considered=len(Pr) * len(Pv),
        )
    # 2. the index of the reference's rock triangles, at the tolerance the crops are searched at
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    # the crops are searched at the maps' tolerances: so are index and chance
    fm = cfg.for_maps(reference, vehicle)
    index = _index_at(index, Pr, fm.search.epsilon_m, icfg)
    timings["index"] = time.perf_counter() - t0
    # 3. the vehicle's triangles vote for poses: the candidate regions
    t0 = time.perf_counter()
    votes = index.vote(Pv, fm.search.epsilon_z_m, math.tan(math.radians(cfg.search.max_tilt_deg)))
    timings["vote"] = time.perf_counter() - t0
    # 4. the acceptance the whole reference needs: chance at n_veh x n_ref associations
    m_full = len(Pr) * len(Pv)
    required = _required_whole_reference(m_full, cfg, fm)
    # 5. the exact search (localize()) on the reference cropped around each candidate region
    t0 = time.perf_counter()
    crops = _search_crops(reference, vehicle, cfg, icfg, index, votes, Pv, query_xyz, path_xyz)
    timings["exact"] = time.perf_counter() - t0
    if not crops.checked():
        out = _no_region(votes, icfg, crops, required, m_full, timings)
        out.odometry_bounds = resolve_odometry_bounds(cfg, vehicle)[1].to_dict()
        return out
    # 6. the winner, checked against chance in the whole reference and every competing hypothesis
    return _judge(crops, cfg, required, m_full, timings)


def _resolve_search(search, reference, vehicle, cfg, icfg, index):
    """The search that runs (auto resolved) and the maps' checked positions; the indexed
    search's preconditions (gravity mode, an index of this reference) raise ConfigError."""
    try:
        search = Search(search)
    except ValueError:
        raise ConfigError(
            f"search must be one of {[s.value for s in Search]}, got {search!r}"
        ) from None
    Pr = _check_map(reference, "reference")
    Pv = _check_map(vehicle, "vehicle")
    if search is Search.AUTO:
        search = (
            Search.INDEXED
            if (len(Pr) >= icfg.auto_min_reference and cfg.mode is Mode.GRAVITY)
            else Search.FULL
        )
    if search is Search.INDEXED:
        if cfg.mode is not Mode.GRAVITY:
            raise ConfigError(
                "the indexed search needs the gravity-aware mode (rover maps levelled by the IMU)"
            )
        if index is not None and (len(index.xyz) != len(Pr) or not np.array_equal(index.xyz, Pr)):
            raise ConfigError("the given index was built for another reference map")
    return search, Pr, Pv


def _index_at(
    index: ReferenceIndex | None, Pr: np.ndarray, epsilon_m: float, icfg: IndexConfig
) -> ReferenceIndex:
    """`index` if it was built at `epsilon_m`, else a new index of `Pr` at that tolerance."""
    if index is not None and math.isclose(index.epsilon_m, epsilon_m, rel_tol=1e-9):
        return index
    if index is not None:
        log.info(
            "localize_large: index built at %.4f m, the maps need %.4f m: rebuilt",
            index.epsilon_m,
            epsilon_m,
        )
    return ReferenceIndex(Pr, epsilon_m, icfg)


def _required_whole_reference(m_full: int, cfg: LocalizationConfig, fm: LocalizationConfig) -> int:
    """The inliers an answer needs to beat chance against the whole reference."""
    return max(
        cfg.acceptance.min_inliers,
        int(
            math.ceil(
                chance_clique_size(m_full, cfg.mode, fm.search.epsilon_m, fm.search.epsilon_z_m)
                + cfg.acceptance.chance_margin
            )
        ),
    )


@dataclass
class _Crops:
    """The exact search's outcome per candidate region: `results[i]` (None: not searched,
    or fewer than 3 rocks in the crop), the rows of :attr:`LargeResult.candidates`, and the
    associations considered in all."""

    results: list = field(default_factory=list)
    rows: list = field(default_factory=list)
    considered: int = 0

    def skip(self, row: dict) -> None:
        self.rows.append(row)
        self.results.append(None)

    def checked(self) -> list:
        """(index, result) of every region the exact search ran on."""
        return [(i, r) for i, r in enumerate(self.results) if r is not None]


def _search_crops(reference, vehicle, cfg, icfg, index, votes, Pv, query_xyz, path_xyz) -> _Crops:
    """localize() on the reference cropped around each candidate region, best-voted first;
    once one region has succeeded, regions with too few votes to compete are skipped."""
    crops = _Crops(considered=votes.lookups)
    for cand in votes.candidates:
        if any(r is not None and r.success for r in crops.results) and (
            cand.votes < icfg.competitor_vote_ratio * votes.candidates[0].votes
        ):
            # too few votes to compete: votes grow as the cube of a region's consistent
            # set, so a region with 1/competitor_ratio of the inliers has ~30 % of the votes
            crops.skip({**cand.to_dict(), "checked": False})
            continue
        crop = index.crop(Pv, votes.centre_xy, cand)
        row = {**cand.to_dict(), "checked": True, "crop_rocks": int(len(crop))}
        if len(crop) < 3:
            crops.skip(
                {
                    **row,
                    "success": False,
                    "inliers": 0,
                    "clique": 0,
                    "reason": "fewer than 3 rocks in the crop",
                }
            )
            continue
        r = localize(reference.subset(crop), vehicle, cfg, query_xyz=query_xyz, path_xyz=path_xyz)
        crops.considered += r.num_associations
        if len(r.inliers):
            r.inliers = np.c_[r.inliers[:, 0], crop[r.inliers[:, 1]]]  # crop rows -> reference rows
        row.update(
            success=bool(r.success), inliers=r.num_inliers, clique=r.clique_size, reason=r.reason
        )
        crops.rows.append(row)
        crops.results.append(r)
    return crops


def _no_region(
    votes, icfg: IndexConfig, crops: _Crops, required: int, m_full: int, timings: dict
) -> LargeResult:
    """The refusal when no candidate region could be searched."""
    why = (
        "no candidate region: no vehicle triangle matched the reference index"
        if not votes.matches
        else f"no candidate region with {icfg.min_votes} or more votes ({votes.matches} triangle "
        "matches)"
    )
    return LargeResult(
        False,
        np.full((4, 4), np.nan),
        np.zeros((0, 2), int),
        float("nan"),
        why,
        required_inliers=required,
        num_associations=m_full,
        timings=timings,
        search="indexed",
        candidates=crops.rows,
        considered=crops.considered,
    )


def _judge(
    crops: _Crops, cfg: LocalizationConfig, required: int, m_full: int, timings: dict
) -> LargeResult:
    """The winner (a verified answer first, then the largest inlier set) with the chance
    and margin checks again, against the whole reference and every competing hypothesis;
    a failed check turns a success into a refusal."""
    done = crops.checked()
    w, best = max(done, key=lambda ir: (ir[1].success, ir[1].num_inliers, ir[1].clique_size))
    comp_clique, comp_refined, comp_region = _competitors(done, w, best, cfg)
    out = _from(
        best, search="indexed", candidates=crops.rows, winner=w, considered=crops.considered
    )
    out.timings = timings
    out.required_inliers = max(required, best.required_inliers)
    out.num_associations = m_full
    out.competitor_size = int(max(comp_clique, comp_refined))
    whole = _whole_reference_checks(
        out, best.clique_size, comp_clique, comp_refined, comp_region, m_full, cfg
    )
    out.checks = list(out.checks) + whole
    if out.success and not all(c.passed for c in whole):
        out.success = False
        out.reason = next(c.detail for c in whole if not c.passed)
    log.info("localize_large: %s (candidate %d of %d)", out.reason, w, len(crops.rows))
    return out


def _competitors(
    done: list, w: int, best: LocalizationResult, cfg: LocalizationConfig
) -> tuple[int, int, int]:
    """The best competing hypothesis found anywhere, like against like: (largest competing
    consistent set, largest competing refined inlier count, the region holding that count
    or -1). The other regions' refined counts are set against the winner's refined count,
    and every consistent set (the other regions' cliques, the competitor inside the winner's
    crop) against the winner's clique. A refined count against a raw clique flatters the
    winner: on a lattice every copy refines to nearly all the vehicle map's landmarks
    (docs/verification.md)."""
    comp_clique, comp_refined, comp_region = best.competitor_size, 0, -1
    for i, r in done:
        if i != w and not _same_pose(r, best, cfg):
            comp_clique = max(comp_clique, r.clique_size)
            if r.num_inliers > comp_refined:
                comp_refined, comp_region = r.num_inliers, i
    return comp_clique, comp_refined, comp_region


def _whole_reference_checks(
    out: LargeResult,
    clique: int,
    comp_clique: int,
    comp_refined: int,
    comp_region: int,
    m_full: int,
    cfg: LocalizationConfig,
) -> list[Check]:
    """The chance check against the whole reference and the two winner-margin checks."""
    k = out.num_inliers
    ratio = cfg.acceptance.competitor_ratio
    ok_chance = k >= out.required_inliers
    ok_refined = k >= ratio * comp_refined
    ok_clique = clique >= ratio * comp_clique
    return [
        Check(
            "inliers_vs_chance_whole_reference",
            k,
            out.required_inliers,
            ok_chance,
            ">=",
            "inliers against the chance envelope of the whole reference"
            if ok_chance
            else f"{k} inliers is too few to beat chance in the whole reference ({m_full} "
            f"associations; need {out.required_inliers})",
        ),
        Check(
            "winner_margin_regions",
            k,
            ratio * comp_refined,
            ok_refined,
            ">=",
            f"refined inliers against {ratio:g} x the best competing candidate region's"
            if ok_refined
            else f"ambiguous: {k} inliers vs {comp_refined} in a competing candidate region "
            f"(candidate {comp_region + 1}; a repeated pattern)",
        ),
        Check(
            "winner_margin_cliques",
            clique,
            ratio * comp_clique,
            ok_clique,
            ">=",
            f"consistent set against {ratio:g} x the best competing one (inside the crop and in "
            "other regions)"
            if ok_clique
            else f"ambiguous: a consistent set of {clique} vs a competing one of {comp_clique}",
        ),
    ]


def _same_pose(a: LocalizationResult, b: LocalizationResult, cfg: LocalizationConfig) -> bool:
    """Two answers that are the same hypothesis (overlapping candidate crops)."""
    if not (np.all(np.isfinite(a.T_ref_veh)) and np.all(np.isfinite(b.T_ref_veh))):
        return False
    dyaw = abs(
        (yaw_of(a.T_ref_veh[:3, :3]) - yaw_of(b.T_ref_veh[:3, :3]) + math.pi) % (2 * math.pi)
        - math.pi
    )
    return bool(
        np.linalg.norm(a.T_ref_veh[:2, 3] - b.T_ref_veh[:2, 3]) < 1.0
        and dyaw < math.radians(cfg.acceptance.competitor_yaw_sep_deg)
    )
