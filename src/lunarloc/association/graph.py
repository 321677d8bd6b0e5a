"""Sparse consistency graphs between putative associations (compiled with numba).

A putative association u = (i, a) pairs vehicle landmark i with reference landmark a.
Two associations u = (i, a), v = (j, b) are *consistent* when the pair preserves the
distance between its landmarks (CLIPPER, Lusk et al. ICRA 2021, eq. 3):

    c = | ||p_i - p_j|| - ||q_a - q_b|| | < epsilon,   weight s(c) = exp(-c^2 / (2 sigma^2)).

The graph is never formed as an m x m matrix: one map's pairwise distances are sorted
and each pair of the other map range-searches them, so work and memory scale with
the number of consistent pairs (edges), not with m^2.

Gravity-aware graphs (rover maps whose "down" is known from the IMU) replace the 3D
distance by two invariants, the horizontal distance and the signed height difference
(allowing a residual tilt), and additionally split the graph by *relative yaw*: each
edge implies a rotation about the vertical, atan2 of the reference pair's horizontal
direction minus the vehicle pair's. A correct inlier set shares one yaw, so the search
runs on one sparse graph per yaw bin. A mirror image (reflection) of the vehicle map
cannot form a yaw-consistent set, because a reflection reverses angles.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from lunarloc.association.aot import njit

__all__ = [
    "graph_3d",
    "RefPairIndex",
    "sweep_bin_chunks",
    "sweep_yaw_bins",
    "vehicle_pairs",
    "yaw_bin_chunks",
]


@njit(cache=True)
def _grow(arr, n):
    out = np.empty(max(2 * arr.shape[0], n), dtype=arr.dtype)
    out[: arr.shape[0]] = arr
    return out


@njit(cache=True)
def _graph_3d(pxyz, qxyz, node_of, eps, sigma, max_edges):
    nv = pxyz.shape[0]
    nr = qxyz.shape[0]
    npr = nr * (nr - 1) // 2
    rd = np.empty(npr, dtype=np.float64)
    ra = np.empty(npr, dtype=np.int32)
    rb = np.empty(npr, dtype=np.int32)
    k = 0
    for a in range(nr):
        for b in range(a + 1, nr):
            dx = qxyz[a, 0] - qxyz[b, 0]
            dy = qxyz[a, 1] - qxyz[b, 1]
            dz = qxyz[a, 2] - qxyz[b, 2]
            rd[k] = math.sqrt(dx * dx + dy * dy + dz * dz)
            ra[k] = a
            rb[k] = b
            k += 1
    o = np.argsort(rd)
    rd = rd[o]
    ra = ra[o]
    rb = rb[o]
    cap = 1024
    eu = np.empty(cap, dtype=np.int32)
    ev = np.empty(cap, dtype=np.int32)
    ew = np.empty(cap, dtype=np.float32)
    ne = 0
    inv2s2 = 1.0 / (2.0 * sigma * sigma)
    for i in range(nv):
        for j in range(i + 1, nv):
            dx = pxyz[i, 0] - pxyz[j, 0]
            dy = pxyz[i, 1] - pxyz[j, 1]
            dz = pxyz[i, 2] - pxyz[j, 2]
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            lo = np.searchsorted(rd, d - eps)
            hi = np.searchsorted(rd, d + eps)
            for t in range(lo, hi):
                c = abs(d - rd[t])
                if c >= eps:
                    continue
                w = math.exp(-c * c * inv2s2)
                a = ra[t]
                b = rb[t]
                for orient in range(2):
                    if orient == 0:
                        u = node_of[i, a]
                        v = node_of[j, b]
                    else:
                        u = node_of[i, b]
                        v = node_of[j, a]
                    if u < 0 or v < 0:
                        continue
                    if ne >= cap:
                        if ne >= max_edges:
                            return eu[:0], ev[:0], ew[:0], -1
                        cap = 2 * cap
                        eu = _grow(eu, cap)
                        ev = _grow(ev, cap)
                        ew = _grow(ew, cap)
                    eu[ne] = u
                    ev[ne] = v
                    ew[ne] = w
                    ne += 1
    return eu[:ne].copy(), ev[:ne].copy(), ew[:ne].copy(), ne


def graph_3d(veh_xyz, ref_xyz, node_of, epsilon: float, sigma: float, max_edges: int):
    """6-DoF consistency graph: edges (eu, ev) between association ids in `node_of`
    (n_veh x n_ref int32, -1 where not a putative association) with weights ew.

    Returns None when the graph would exceed `max_edges` (memory bound)."""
    eu, ev, ew, ne = _graph_3d(
        np.ascontiguousarray(veh_xyz, dtype=np.float64),
        np.ascontiguousarray(ref_xyz, dtype=np.float64),
        np.ascontiguousarray(node_of, dtype=np.int32),
        float(epsilon),
        float(sigma),
        int(max_edges),
    )
    if ne < 0:
        return None
    return eu, ev, ew


def vehicle_pairs(xyz: np.ndarray):
    """Horizontal distance, azimuth (rad), height difference and 3D distance of every
    pair i < j of an (n, 3) array, as arrays (pi, pj, dh, phi, dz, d3)."""
    n = len(xyz)
    pi, pj = np.triu_indices(n, 1)
    d = xyz[pj] - xyz[pi]
    dh = np.hypot(d[:, 0], d[:, 1])
    return (
        pi.astype(np.int32),
        pj.astype(np.int32),
        dh,
        np.arctan2(d[:, 1], d[:, 0]),
        d[:, 2].copy(),
        np.linalg.norm(d, axis=1),
    )


class RefPairIndex:
    """Ordered pairs (a, b), a != b, of the reference map, bucketed on a grid of
    (horizontal distance, azimuth) cells for range search by the yaw-bin generator."""

    def __init__(self, ref_xyz: np.ndarray, dist_cell_m: float, angle_cell_rad: float):
        q = np.ascontiguousarray(ref_xyz, dtype=np.float64)
        n = len(q)
        # row a * n + b: q[b] - q[a] (diagonal dropped below)
        d = (q[None, :, :] - q[:, None, :]).reshape(-1, 3)
        dh = np.hypot(d[:, 0], d[:, 1])
        phi = np.arctan2(d[:, 1], d[:, 0])
        self.dist_cell = float(dist_cell_m)
        self.n_angle = max(1, int(math.ceil(2 * math.pi / angle_cell_rad)))
        self.angle_cell = 2 * math.pi / self.n_angle
        self.n_dist = int(dh.max() / self.dist_cell) + 2 if n > 1 else 1
        self.a, self.b, self.dh, self.phi, self.dz, self.abin, self.row_ptr = _bucket_pairs(
            n,
            dh,
            phi,
            np.ascontiguousarray(d[:, 2]),
            self.dist_cell,
            self.n_dist,
            self.angle_cell,
            self.n_angle,
        )


@njit(cache=True, nogil=True)
def _bucket_starts(keys, n_keys):
    """Start of each key's bucket in a counting sort of `keys` (ints in [0, n_keys)):
    ptr (n_keys + 1), bucket k at ptr[k]:ptr[k + 1]."""
    ptr = np.zeros(n_keys + 1, dtype=np.int64)
    for t in range(keys.shape[0]):
        ptr[keys[t] + 1] += 1
    for k in range(n_keys):
        ptr[k + 1] += ptr[k]
    return ptr


@njit(cache=True)
def _bucket_pairs(n, dh, phi, dz, dist_cell, n_dist, angle_cell, n_angle):
    """Ordered pairs a != b (row-major a * n + b in the inputs) sorted, stably, by their
    (distance, azimuth) cell: a two-pass radix sort (azimuth cell, then distance row).
    Returns a, b, dh, phi, dz, the azimuth cell of each pair and the start of each
    distance row (a row is sorted by azimuth cell)."""
    m = n * (n - 1)
    dbin = np.empty(m, dtype=np.int64)
    abin = np.empty(m, dtype=np.int64)
    src = np.empty(m, dtype=np.int64)
    k = 0
    for a in range(n):
        for b in range(n):
            if a == b:
                continue
            t = a * n + b
            dbin[k] = min(int(dh[t] / dist_cell), n_dist - 1)
            abin[k] = min(int((phi[t] + math.pi) / angle_cell), n_angle - 1)
            src[k] = t
            k += 1
    a_count = _bucket_starts(abin, n_angle)
    by_angle = np.empty(m, dtype=np.int64)  # pass 1: stable by azimuth cell
    for k in range(m):
        c = abin[k]
        by_angle[a_count[c]] = k
        a_count[c] += 1
    row_ptr = _bucket_starts(dbin, n_dist)
    fill = row_ptr[:-1].copy()
    oa = np.empty(m, dtype=np.int32)
    ob = np.empty(m, dtype=np.int32)
    odh = np.empty(m, dtype=np.float64)
    ophi = np.empty(m, dtype=np.float64)
    odz = np.empty(m, dtype=np.float64)
    oab = np.empty(m, dtype=np.int16)
    for s in range(m):  # pass 2: stable by distance row
        k = by_angle[s]
        r = dbin[k]
        o = fill[r]
        fill[r] = o + 1
        t = src[k]
        oa[o] = t // n
        ob[o] = t % n
        odh[o] = dh[t]
        ophi[o] = phi[t]
        odz[o] = dz[t]
        oab[o] = abin[k]
    return oa, ob, odh, ophi, odz, oab, row_ptr


@njit(cache=True, nogil=True, inline="always")
def _row_pos(abin, row_ptr, row, a):
    """Position in the index of the first pair of distance row `row` whose azimuth cell is
    >= a (binary search: the row is sorted by azimuth cell)."""
    lo = row_ptr[row]
    hi = row_ptr[row + 1]
    while lo < hi:
        mid = (lo + hi) >> 1
        if abin[mid] < a:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def _wrap(x):
    return (x + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, nogil=True, boundscheck=False)
def _yaw_chunk_incidences(
    pi,
    pj,
    pdh,
    pphi,
    pdz,
    qa,
    qb,
    qdh,
    qphi,
    qdz,
    abin,
    row_ptr,
    n_dist,
    n_angle,
    dist_cell,
    angle_cell,
    node_of,
    bin0,
    k_first,
    k_last,
    n_bins,
    eps_h,
    eps_z,
    tan_tilt,
    k_yaw,
    sigma,
    want_w,
):
    """Edges of the yaw bins bin0 + k, k in [k_first, k_last], bucketed by bin: (ptr, u, v, w)
    with bin bin0 + k_first + t's edges at ptr[t]:ptr[t + 1].

    Bin b is centred on theta_b = -pi + (b + 0.5) * step; an edge of yaw theta_e and
    tolerance tol belongs to every bin whose centre is within half_step + tol of it. The
    yaw arithmetic is relative to bin0 (callers keep bin0 on a fixed grid of chunk starts,
    so a bin's graph does not depend on which other bins are generated with it)."""
    nb = k_last - k_first + 1
    step = 2.0 * math.pi / n_bins
    half_step = 0.5 * step
    cap = 1 << 16
    iu = np.empty(cap, dtype=np.int32)
    iv = np.empty(cap, dtype=np.int32)
    iw = np.empty(cap, dtype=np.float32)
    ib = np.empty(cap, dtype=np.int16)
    ni = 0
    inv2s2 = 1.0 / (2.0 * sigma * sigma)
    lo_theta = -math.pi + bin0 * step  # bins are centred at lo_theta + (k + 0.5) step
    win_theta = lo_theta + k_first * step  # the wanted bins span [win_theta, win_theta + nb * step)
    two_pi = 2.0 * math.pi
    for p in range(pi.shape[0]):
        i = pi[p]
        j = pj[p]
        dh = pdh[p]
        dzp = pdz[p]
        dmin = dh - eps_h
        # yaw tolerance of this pair, conservative over its candidates (their distance >= dmin)
        if dmin > k_yaw * eps_h:
            tol = half_step + math.asin(k_yaw * eps_h / dmin) + tan_tilt * abs(dzp) / dmin
        else:
            tol = math.pi
        d_lo = int(max(0.0, dh - eps_h) / dist_cell)
        d_hi = min(n_dist - 1, int((dh + eps_h) / dist_cell))
        if tol >= math.pi or nb * step + 2 * tol >= two_pi:
            a_lo = 0
            a_n = n_angle
        else:
            # reference azimuths that can fall in this chunk: phi_p + [lo - tol, hi + tol]
            start = pphi[p] + win_theta - tol
            a_lo = int(math.floor((start + math.pi) / angle_cell))
            a_n = min(n_angle, int(math.ceil((nb * step + 2 * tol) / angle_cell)) + 1)
        ztol = eps_z + tan_tilt * dh
        row_u = node_of[i]
        row_v = node_of[j]
        base_yaw = pphi[p] + lo_theta
        a_lo = a_lo % n_angle
        a_end = a_lo + a_n  # exclusive; may wrap past n_angle
        for db in range(d_lo, d_hi + 1):
            if row_ptr[db + 1] == row_ptr[db]:
                continue
            for seg in range(2):
                # angle cells of one distance row are contiguous in the index: scan them as
                # one range (two when the window wraps around +-pi)
                if seg == 0:
                    t0 = _row_pos(abin, row_ptr, db, a_lo)
                    t1 = _row_pos(abin, row_ptr, db, min(a_end, n_angle))
                else:
                    if a_end <= n_angle:
                        break
                    t0 = row_ptr[db]
                    t1 = _row_pos(abin, row_ptr, db, a_end - n_angle)
                for t in range(t0, t1):
                    ch = abs(qdh[t] - dh)
                    if ch >= eps_h:
                        continue
                    if abs(qdz[t] - dzp) >= ztol:
                        continue
                    u = row_u[qa[t]]
                    v = row_v[qb[t]]
                    if u < 0 or v < 0:
                        continue
                    if tol >= math.pi:
                        k_lo = k_first
                        k_hi = k_last
                    else:
                        # offset of the edge yaw from the chunk start, wrapped to [0, 2pi)
                        off = qphi[t] - base_yaw
                        while off < 0.0:
                            off += two_pi
                        while off >= two_pi:
                            off -= two_pi
                        # bins k with |theta_k - yaw| <= tol, theta_k = lo_theta + (k + 0.5) step
                        k_lo = int(math.ceil((off - tol) / step - 0.5))
                        k_hi = int(math.floor((off + tol) / step - 0.5))
                        if k_hi >= n_bins:  # wrapped around past the chunk start
                            k_lo2 = k_lo - n_bins
                            k_hi2 = k_hi - n_bins
                            if k_hi2 >= 0:
                                k_lo = max(k_lo2, 0)
                                k_hi = k_hi2
                        if k_lo < k_first:
                            k_lo = k_first
                        if k_hi > k_last:
                            k_hi = k_last
                    if k_hi < k_lo:
                        continue
                    w = math.exp(-ch * ch * inv2s2) if want_w else 1.0
                    for k in range(k_lo, k_hi + 1):
                        if ni >= cap:
                            cap *= 2
                            iu = _grow(iu, cap)
                            iv = _grow(iv, cap)
                            iw = _grow(iw, cap)
                            ib = _grow(ib, cap)
                        iu[ni] = u
                        iv[ni] = v
                        iw[ni] = w
                        ib[ni] = k - k_first
                        ni += 1
    # bucket incidences by bin (counting sort)
    ptr = _bucket_starts(ib[:ni], nb)
    fill = ptr[:-1].copy()
    su = np.empty(ni, dtype=np.int32)
    sv = np.empty(ni, dtype=np.int32)
    sw = np.empty(ni, dtype=np.float32)
    for t in range(ni):
        k = ib[t]
        f = fill[k]
        su[f] = iu[t]
        sv[f] = iv[t]
        sw[f] = iw[t]
        fill[k] = f + 1
    return ptr, su, sv, sw


def yaw_bin_chunks(n_bins: int, chunk_bins: int, bins) -> list[tuple[int, int, int]]:
    """Group yaw bins into generator calls: (bin0, k_first, k_last) per call, bin0 on the
    fixed grid of chunk starts (multiples of `chunk_bins`) and bins bin0 + k_first ..
    bin0 + k_last the span of the wanted bins in that grid chunk."""
    chunk_bins = max(1, int(chunk_bins))
    out: dict[int, list[int]] = {}
    for b in sorted({int(b) % n_bins for b in bins}):
        b0 = (b // chunk_bins) * chunk_bins
        out.setdefault(b0, []).append(b - b0)
    return [(b0, ks[0], ks[-1]) for b0, ks in out.items()]


def sweep_bin_chunks(
    vpairs,
    index: RefPairIndex,
    node_of,
    n_bins: int,
    chunks,
    eps_h,
    eps_z,
    tan_tilt,
    k_yaw,
    sigma,
    visit_chunk,
    *,
    weights: bool = True,
    workers: int = 2,
) -> int:
    """Build the consistency graphs of the yaw bins of `chunks` ((bin0, k_first, k_last)
    from :func:`yaw_bin_chunks`, run in the given order) and hand each chunk to
    ``visit_chunk(bins, ptr, eu, ev, ew)``: bin ``bins[t]``'s edges are ``eu/ev/ew[ptr[t]:ptr[t +
    1]]``.

    Chunks run on `workers` threads (the compiled generator releases the GIL), so memory
    is bounded by `workers` chunks; `visit_chunk` runs on the worker threads and must be
    thread-safe. Returns the number of edges generated."""
    pi, pj, pdh, pphi, pdz, _ = vpairs

    def run_chunk(c):
        b0, k_first, k_last = c
        ptr, su, sv, sw = _yaw_chunk_incidences(
            pi,
            pj,
            pdh,
            pphi,
            pdz,
            index.a,
            index.b,
            index.dh,
            index.phi,
            index.dz,
            index.abin,
            index.row_ptr,
            index.n_dist,
            index.n_angle,
            index.dist_cell,
            index.angle_cell,
            node_of,
            b0,
            k_first,
            k_last,
            n_bins,
            float(eps_h),
            float(eps_z),
            float(tan_tilt),
            float(k_yaw),
            float(sigma),
            bool(weights),
        )
        visit_chunk([(b0 + k) % n_bins for k in range(k_first, k_last + 1)], ptr, su, sv, sw)
        return len(su)

    chunks = list(chunks)
    workers = max(1, min(workers, len(chunks)))
    if workers == 1:
        return sum(run_chunk(c) for c in chunks)
    return sum(_thread_pool(workers).map(run_chunk, chunks))


_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _thread_pool(workers: int) -> ThreadPoolExecutor:
    """A process-wide pool of `workers` threads, started once (starting threads for every
    sweep cost more than a small sweep's work)."""
    with _POOLS_LOCK:
        pool = _POOLS.get(workers)
        if pool is None:
            pool = _POOLS[workers] = ThreadPoolExecutor(
                max_workers=workers, thread_name_prefix="lunarloc-yaw"
            )
        return pool


def sweep_yaw_bins(
    vpairs,
    index: RefPairIndex,
    node_of,
    n_bins: int,
    chunk_bins: int,
    eps_h,
    eps_z,
    tan_tilt,
    k_yaw,
    sigma,
    visit,
    *,
    weights: bool = True,
    bin_start: int = 0,
    bin_count: int | None = None,
    workers: int = 2,
) -> int:
    """Build the consistency graph of every relative-yaw bin and hand it to
    ``visit(bin, theta, eu, ev, ew)`` (edges between association ids from `node_of`).

    Bins are generated `chunk_bins` at a time on `workers` threads (the compiled
    generator releases the GIL), so memory is bounded by `workers` chunks, not the whole
    graph; `visit` runs on the worker threads and must be thread-safe.
    `bin_start`/`bin_count` restrict the sweep to a range of bins (wrapping).
    Returns the number of edges generated over all bins."""
    step = 2 * math.pi / n_bins
    bin_count = n_bins if bin_count is None else min(bin_count, n_bins)

    def visit_chunk(bins, ptr, su, sv, sw):
        for t, b in enumerate(bins):
            sl = slice(ptr[t], ptr[t + 1])
            visit(b, -math.pi + (b + 0.5) * step, su[sl], sv[sl], sw[sl])

    chunks = yaw_bin_chunks(n_bins, chunk_bins, range(bin_start, bin_start + bin_count))
    return sweep_bin_chunks(
        vpairs,
        index,
        node_of,
        n_bins,
        chunks,
        eps_h,
        eps_z,
        tan_tilt,
        k_yaw,
        sigma,
        visit_chunk,
        weights=weights,
        workers=workers,
    )
