"""Constellation index of a large reference map, for a lost-in-space fix.

A star tracker without a prior does not compare every star with every catalogue
star: it hashes small constellations (triangles of nearby stars by their side
lengths), looks up the constellations it sees, and lets the matches vote for an
attitude. The same works for rocks:

1. **Index** (once per reference map, O(N_ref)): every triangle of rocks whose
   horizontal sides lie in ``[min_side, max_side]`` (``max_side`` from the map's own
   density: the median distance to the ``neighbours``-th nearest rock, so a rock
   takes part in a bounded number of triangles whatever the map's size). Each
   triangle is put in canonical vertex order (the vertex opposite the shortest side
   first) and keyed by its sorted side lengths quantised to the pairwise tolerance
   epsilon, plus its orientation (clockwise or not: a mirror image never matches).
2. **Vote** (per vehicle map): the vehicle map's triangles look up the reference
   triangles whose three sides agree within epsilon (27 neighbouring key cells) and
   whose two height differences agree within the height tolerance. Each match fixes
   a yaw and a horizontal translation (the 2D Kabsch fit of the three vertices); it
   votes for where the vehicle map's centre lands and at which yaw, in cells of
   ``translation_cell_m`` x ``yaw_cell_deg``.
3. **Candidates**: the best-supported cells (summed over their 3 x 3 x 3
   neighbourhood), separated by non-maximum suppression; each candidate pose is the
   median of the votes around its cell.

Nothing here is of size N_ref x N_veh or N x N: the index holds O(N_ref) triangles,
the vote O(matches). The exact search and verification then run on the reference
cropped around each candidate (:mod:`lunarloc.localization.large`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from lunarloc.core.errors import ConfigError, InputError

__all__ = ["IndexConfig", "ReferenceIndex", "Candidate", "Votes", "triangles"]


@dataclass
class IndexConfig:
    """Parameters of the constellation index and the candidate search (metres, degrees)."""

    neighbours: int = 12  # max triangle side = median distance to this many-th nearest rock
    max_side_m: float | None = None  # fixed max triangle side instead (None: from density)
    min_side_ratio: float = 0.2  # shortest allowed side, as a share of the longest allowed
    translation_cell_m: float = 2.0  # vote cell for the vehicle map's centre
    yaw_cell_deg: float = 10.0  # vote cell for the yaw
    # candidate regions checked by the exact search at most: enough that a repeated world (a
    # lattice, a copied map) shows its repeats among them, so the answer is judged against them
    # (with 3, 2 m jittered lattices were claimed at the wrong copy in 15 of 40 runs,
    # docs/verification.md)
    max_candidates: int = 8
    competitor_vote_ratio: float = (
        0.1  # the runner-up region is checked exactly from this share of the winner's votes
    )
    min_votes: int = 4  # a candidate needs this many (neighbourhood-summed) votes
    candidate_separation_m: float = (
        4.0  # candidates closer than this (and within 2 yaw cells) are one
    )
    # reference rocks within this of the placed vehicle map are kept: at least the separation of
    # two candidates, so that a competitor merged into a candidate by the non-maximum
    # suppression (a copy shifted by less than the separation) lies inside its crop, where the
    # exact search's own ambiguity test sees it
    crop_margin_m: float = 4.0
    auto_min_reference: int = 2000  # search="auto" uses the index from this many reference rocks
    chunk_pairs: int = 200_000  # triangles are enumerated this many rock pairs at a time (memory)

    def __post_init__(self) -> None:
        if self.neighbours < 3:
            raise ConfigError(f"neighbours must be >= 3, got {self.neighbours}")
        if self.max_side_m is not None and not self.max_side_m > 0:
            raise ConfigError(f"max_side_m must be positive, got {self.max_side_m}")
        if not 0 <= self.min_side_ratio < 1:
            raise ConfigError(f"min_side_ratio must be in [0, 1), got {self.min_side_ratio}")
        for name in (
            "translation_cell_m",
            "yaw_cell_deg",
            "candidate_separation_m",
            "crop_margin_m",
        ):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")
        if self.max_candidates < 1 or self.min_votes < 1 or self.chunk_pairs < 1:
            raise ConfigError("max_candidates, min_votes and chunk_pairs must be >= 1")
        if not 0 <= self.competitor_vote_ratio <= 1:
            raise ConfigError(
                f"competitor_vote_ratio must be in [0, 1], got {self.competitor_vote_ratio}"
            )

    def to_dict(self) -> dict:
        return asdict(self)


# --------------------------------------------------------------------------- triangles


def triangles(
    xy: np.ndarray, max_side: float, min_side: float, chunk_pairs: int = 200_000
) -> np.ndarray:
    """Every triangle (i, j, k), i < j < k, of points whose three horizontal sides lie
    in [min_side, max_side], as an (T, 3) int64 array. Work and memory are linear in
    the number of close pairs, enumerated `chunk_pairs` pairs at a time."""
    n = len(xy)
    pairs = cKDTree(xy).query_pairs(max_side, output_type="ndarray").astype(np.int64)
    if len(pairs) == 0:
        return np.zeros((0, 3), np.int64)
    d = np.linalg.norm(xy[pairs[:, 0]] - xy[pairs[:, 1]], axis=1)
    pairs = pairs[d >= min_side]
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]  # CSR of forward neighbours
    i, j = pairs[:, 0], pairs[:, 1]
    keys = i * n + j  # sorted
    ptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(i, minlength=n), out=ptr[1:])
    pos = np.arange(len(pairs))
    cnt = ptr[i + 1] - pos - 1  # third vertices k > j among i's forward neighbours
    out = []
    start = 0
    while start < len(pairs):
        stop = min(len(pairs), start + chunk_pairs)
        c = cnt[start:stop]
        total = int(c.sum())
        if total:
            rep = np.repeat(pos[start:stop], c)
            within = np.arange(total) - np.repeat(np.cumsum(c) - c, c)
            k = pairs[rep + 1 + within, 1]
            q = j[rep] * n + k
            s = np.minimum(np.searchsorted(keys, q), len(keys) - 1)
            ok = keys[s] == q  # (j, k) is a close pair too
            out.append(np.stack([i[rep[ok]], j[rep[ok]], k[ok]], axis=1))
        start = stop
    return np.concatenate(out) if out else np.zeros((0, 3), np.int64)


def _canonical(xyz: np.ndarray, tri: np.ndarray):
    """Vertices reordered so that vertex r is opposite the r-th shortest side; returns
    (vertices (T,3), sorted sides (T,3), counter-clockwise (T,) bool)."""
    xy = xyz[:, :2]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    opp = np.stack(
        [
            np.linalg.norm(xy[b] - xy[c], axis=1),
            np.linalg.norm(xy[a] - xy[c], axis=1),
            np.linalg.norm(xy[a] - xy[b], axis=1),
        ],
        axis=1,
    )
    o = np.argsort(opp, axis=1)
    v = np.take_along_axis(tri, o, axis=1)
    s = np.take_along_axis(opp, o, axis=1)
    return v, s, _ccw(xy, v)


def _ccw(xy, v):
    e1 = xy[v[:, 1]] - xy[v[:, 0]]
    e2 = xy[v[:, 2]] - xy[v[:, 0]]
    return e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0


@dataclass
class Candidate:
    """A candidate pose from the vote: where the vehicle map's centre lands (x, y) in the
    reference frame, at which yaw (rad), and how many votes support it."""

    x_m: float
    y_m: float
    yaw_rad: float
    votes: int

    def to_dict(self) -> dict:
        return {
            "x_m": round(self.x_m, 3),
            "y_m": round(self.y_m, 3),
            "yaw_deg": round(math.degrees(self.yaw_rad), 2),
            "votes": int(self.votes),
        }


@dataclass
class Votes:
    """Outcome of :meth:`ReferenceIndex.vote`: the candidates (best first) and how much
    work it took (triangle lookups and matches)."""

    candidates: list
    vehicle_triangles: int
    lookups: int
    matches: int
    centre_xy: np.ndarray  # the vehicle-frame point whose reference position was voted for
    votes_xy_yaw: np.ndarray | None = (
        None  # (matches, 3): every match's vote (x, y of the centre, yaw rad)
    )


class ReferenceIndex:
    """Triangle index of a reference map (see the module docstring). Build it once per
    reference map and reuse it for every vehicle map localized against it."""

    def __init__(self, ref_xyz: np.ndarray, epsilon_m: float, config: IndexConfig | None = None):
        cfg = config or IndexConfig()
        P = np.ascontiguousarray(ref_xyz, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 3 or len(P) < 3:
            raise InputError(
                "the reference index needs an (N >= 3, 3) array of rock positions, got shape "
                f"{P.shape}"
            )
        if not np.all(np.isfinite(P)):
            raise InputError("reference positions must be finite")
        if not epsilon_m > 0:
            raise ConfigError(f"epsilon_m must be positive, got {epsilon_m}")
        self.config = cfg
        self.xyz = P
        self.epsilon_m = float(epsilon_m)
        self.tree_xy = cKDTree(P[:, :2])
        if cfg.max_side_m is not None:
            self.max_side_m = float(cfg.max_side_m)
        else:
            k = min(cfg.neighbours, len(P) - 1)
            sample = P[:: max(1, len(P) // 2000), :2]  # the median of a sample is enough
            d, _ = self.tree_xy.query(sample, k=k + 1)
            self.max_side_m = float(np.median(d[:, k]))
        self.min_side_m = cfg.min_side_ratio * self.max_side_m
        tri = triangles(P[:, :2], self.max_side_m, self.min_side_m, cfg.chunk_pairs)
        v, s, ccw = _canonical(P, tri)
        self.nq = int(math.ceil((self.max_side_m + 2 * self.epsilon_m) / self.epsilon_m)) + 3
        key = self._key(s, ccw)
        o = np.argsort(key, kind="stable")
        self.keys = key[o]
        self.vertices = v[o].astype(np.int32)
        self.sides = s[o]

    @property
    def num_triangles(self) -> int:
        return len(self.keys)

    @property
    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.vertices.nbytes + self.sides.nbytes + self.xyz.nbytes)

    def _key(self, sides: np.ndarray, ccw: np.ndarray, offset=(0, 0, 0)) -> np.ndarray:
        """Integer key of the side-length cell (cells of epsilon); the orientation is the
        most significant part so that neighbouring cells along the longest side are
        contiguous in key order."""
        q = np.floor(sides / self.epsilon_m).astype(np.int64) + 1 + np.asarray(offset, np.int64)
        q = np.clip(q, 0, self.nq - 1)
        return ((ccw.astype(np.int64) * self.nq + q[:, 0]) * self.nq + q[:, 1]) * self.nq + q[:, 2]

    def vote(
        self,
        veh_xyz: np.ndarray,
        epsilon_z_m: float,
        tan_tilt: float,
        max_triangles: int | None = None,
    ) -> Votes:
        """Match the vehicle map's triangles against the index and vote for poses.
        `max_triangles`: vote with at most this many of the vehicle map's triangles (evenly
        spread over its list; a quick look at a dense map, whose true pose keeps the same
        share of the votes)."""
        cfg = self.config
        V = np.ascontiguousarray(veh_xyz, dtype=np.float64)
        eps = self.epsilon_m
        centre = np.median(V[:, :2], axis=0)
        tri = triangles(
            V[:, :2], self.max_side_m + eps, max(self.min_side_m - eps, 0.0), cfg.chunk_pairs
        )
        if max_triangles is not None and len(tri) > max_triangles:
            tri = tri[np.linspace(0, len(tri) - 1, max(int(max_triangles), 1)).astype(np.int64)]
        v, s, ccw = _canonical(V, tri)
        # near-equal sides may sort the other way in the reference: look those up swapped too
        extra_v, extra_s, extra_c = [v], [s], [ccw]
        for a, b in ((0, 1), (1, 2)):
            amb = s[:, b] - s[:, a] < 2 * eps
            if np.any(amb):
                vs, ss = v[amb].copy(), s[amb].copy()
                vs[:, [a, b]] = vs[:, [b, a]]
                ss[:, [a, b]] = ss[:, [b, a]]
                extra_v.append(vs)
                extra_s.append(ss)
                extra_c.append(~ccw[amb])
        v, s, ccw = np.concatenate(extra_v), np.concatenate(extra_s), np.concatenate(extra_c)
        n_tri = len(v)
        # look up the 27 neighbouring key cells of each vehicle triangle (9 key ranges:
        # the three cells along the longest side are contiguous)
        tv_all, tr_all = [], []
        lookups = 0
        for o0, o1 in np.ndindex(3, 3):
            lo = np.searchsorted(self.keys, self._key(s, ccw, (o0 - 1, o1 - 1, -1)), "left")
            hi = np.searchsorted(self.keys, self._key(s, ccw, (o0 - 1, o1 - 1, 1)), "right")
            c = hi - lo
            total = int(c.sum())
            lookups += total
            if total == 0:
                continue
            tv = np.repeat(np.arange(n_tri), c)
            tr = np.repeat(lo, c) + (np.arange(total) - np.repeat(np.cumsum(c) - c, c))
            ok = np.all(np.abs(s[tv] - self.sides[tr]) < eps, axis=1)
            tv, tr = tv[ok], tr[ok]
            # height differences of the canonical vertices agree (allowing the residual tilt)
            vz = V[v[tv], 2]
            rz = self.xyz[self.vertices[tr], 2]
            ztol = epsilon_z_m + tan_tilt * self.max_side_m
            ok = (np.abs((vz[:, 1] - vz[:, 0]) - (rz[:, 1] - rz[:, 0])) < ztol) & (
                np.abs((vz[:, 2] - vz[:, 0]) - (rz[:, 2] - rz[:, 0])) < ztol
            )
            tv_all.append(tv[ok])
            tr_all.append(tr[ok])
        tv = np.concatenate(tv_all) if tv_all else np.zeros(0, np.int64)
        tr = np.concatenate(tr_all) if tr_all else np.zeros(0, np.int64)
        if len(tv) == 0:
            return Votes([], n_tri, lookups, 0, centre)
        # 2D Kabsch of each matched triangle: yaw and where the vehicle centre lands
        pv = V[v[tv], :2]
        pr = self.xyz[self.vertices[tr], :2]
        cv, cr = pv.mean(axis=1), pr.mean(axis=1)
        a, b = pv - cv[:, None], pr - cr[:, None]
        yaw = np.arctan2(
            np.sum(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0], axis=1),
            np.sum(a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1], axis=1),
        )
        cy, sy = np.cos(yaw), np.sin(yaw)
        dx, dy = centre[0] - cv[:, 0], centre[1] - cv[:, 1]
        x = cr[:, 0] + cy * dx - sy * dy
        y = cr[:, 1] + sy * dx + cy * dy
        return Votes(self._candidates(x, y, yaw), n_tri, lookups, len(tv), centre, np.c_[x, y, yaw])

    def _candidates(self, x, y, yaw) -> list:
        cfg = self.config
        cell = cfg.translation_cell_m
        nk = max(1, int(round(360.0 / cfg.yaw_cell_deg)))
        bx = np.floor(x / cell).astype(np.int64)
        by = np.floor(y / cell).astype(np.int64)
        bk = np.floor((yaw + math.pi) / (2 * math.pi) * nk).astype(np.int64) % nk
        bx0, by0 = bx.min() - 1, by.min() - 1
        ny = int(by.max() - by0) + 2
        key = ((bx - bx0) * ny + (by - by0)) * nk + bk
        uk, counts = np.unique(key, return_counts=True)
        ux, rest = np.divmod(uk, ny * nk)
        uy, uyaw = np.divmod(rest, nk)
        score = np.zeros(len(uk), np.int64)
        for ox, oy, ok_ in np.ndindex(3, 3, 3):
            nb = ((ux + ox - 1) * ny + (uy + oy - 1)) * nk + (uyaw + ok_ - 1) % nk
            s = np.minimum(np.searchsorted(uk, nb), len(uk) - 1)
            score += np.where(uk[s] == nb, counts[s], 0)
        # the votes of a cell's 3 x 3 x 3 neighbourhood, by slices of the votes sorted by cell
        order = np.argsort(key, kind="stable")
        skey = key[order]
        offs = np.array([((ox - 1) * ny + (oy - 1)) * nk for ox, oy in np.ndindex(3, 3)], np.int64)
        out: list[Candidate] = []
        for t in np.argsort(-score, kind="stable")[: 50 * cfg.max_candidates]:
            if score[t] < cfg.min_votes or len(out) >= cfg.max_candidates:
                break
            cells = (uk[t] - uyaw[t] + offs)[:, None] + (uyaw[t] + np.arange(-1, 2)) % nk
            near = order[
                np.concatenate(
                    [
                        np.arange(lo, hi)
                        for lo, hi in zip(
                            np.searchsorted(skey, cells.ravel(), "left"),
                            np.searchsorted(skey, cells.ravel(), "right"),
                        )
                    ]
                )
            ]
            c = Candidate(
                float(np.median(x[near])),
                float(np.median(y[near])),
                float(np.angle(np.mean(np.exp(1j * yaw[near])))),
                int(score[t]),
            )
            if any(
                math.hypot(c.x_m - o.x_m, c.y_m - o.y_m) < cfg.candidate_separation_m
                and abs((c.yaw_rad - o.yaw_rad + math.pi) % (2 * math.pi) - math.pi)
                < math.radians(2 * cfg.yaw_cell_deg)
                for o in out
            ):
                continue
            out.append(c)
        return out

    def crop(self, veh_xyz: np.ndarray, centre_xy: np.ndarray, candidate: Candidate) -> np.ndarray:
        """Indices of reference rocks within `crop_margin_m` of the vehicle map placed at
        the candidate pose (sorted)."""
        c, s = math.cos(candidate.yaw_rad), math.sin(candidate.yaw_rad)
        d = veh_xyz[:, :2] - centre_xy
        placed = np.c_[
            candidate.x_m + c * d[:, 0] - s * d[:, 1], candidate.y_m + s * d[:, 0] + c * d[:, 1]
        ]
        hits = self.tree_xy.query_ball_point(placed, self.config.crop_margin_m, return_sorted=False)
        idx = (
            np.unique(np.concatenate([np.asarray(h, np.int64) for h in hits]))
            if len(hits)
            else np.zeros(0, np.int64)
        )
        return idx
