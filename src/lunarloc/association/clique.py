"""Exact maximum clique on a sparse graph (compiled with numba).

Algorithm (the parallel maximum-clique scheme of Rossi et al., "Parallel maximum
clique algorithms with applications to network analysis", SISC 2015, run serially):

1. k-core decomposition (Batagelj & Zaversnik 2003, O(E)) gives each vertex's core
   number and a degeneracy ordering; a clique of size k lies in the (k-1)-core, so
   vertices with core number < current best are pruned.
2. A greedy clique along the degeneracy order gives the first lower bound.
3. For each vertex v, its later neighbours in the degeneracy order (at most the
   degeneracy, small for consistency graphs) form a small candidate set; a
   branch-and-bound search with greedy colouring bounds (Tomita & Seki's MCQ,
   2003) finds the largest clique containing v there, or proves none beats the bound.

The result is a maximum clique (exact), or an empty one if none is larger than the
lower bound passed in.
"""

from __future__ import annotations

import numpy as np
from lunarloc.association.aot import njit

__all__ = ["max_clique", "peel", "csr_from_edges", "core_numbers", "bin_clique_bounds"]


@njit(cache=True, nogil=True)
def _csr_into(m, tu, tv, ne, indptr, fill, indices):
    """Symmetric CSR adjacency of the first `ne` edges (tu, tv) on m vertices, written into
    indptr (m + 1), fill (m) and indices (2 ne); rows in edge order."""
    indptr[: m + 1] = 0
    for t in range(ne):
        indptr[tu[t] + 1] += 1
        indptr[tv[t] + 1] += 1
    for t in range(m):
        indptr[t + 1] += indptr[t]
        fill[t] = indptr[t]
    for t in range(ne):
        a = tu[t]
        b = tv[t]
        indices[fill[a]] = b
        fill[a] += 1
        indices[fill[b]] = a
        fill[b] += 1


@njit(cache=True, nogil=True)
def csr_from_edges(n: int, eu: np.ndarray, ev: np.ndarray):
    """Symmetric CSR adjacency (indptr, indices) of an undirected edge list on n vertices."""
    indptr = np.empty(n + 1, dtype=np.int64)
    fill = np.empty(n, dtype=np.int64)
    indices = np.empty(2 * eu.shape[0], dtype=np.int32)
    _csr_into(n, eu, ev, eu.shape[0], indptr, fill, indices)
    for i in range(n):
        indices[indptr[i] : indptr[i + 1]].sort()
    return indptr, indices


@njit(cache=True, nogil=True)
def core_numbers(n: int, indptr: np.ndarray, indices: np.ndarray):
    """Core number of each vertex and a degeneracy order (Batagelj & Zaversnik 2003)."""
    deg = np.empty(n, dtype=np.int64)
    md = 0
    for v in range(n):
        deg[v] = indptr[v + 1] - indptr[v]
        if deg[v] > md:
            md = deg[v]
    bin_ = np.zeros(md + 2, dtype=np.int64)
    for v in range(n):
        bin_[deg[v]] += 1
    start = 0
    for d in range(md + 1):
        num = bin_[d]
        bin_[d] = start
        start += num
    pos = np.empty(n, dtype=np.int64)
    vert = np.empty(n, dtype=np.int64)
    for v in range(n):
        pos[v] = bin_[deg[v]]
        vert[pos[v]] = v
        bin_[deg[v]] += 1
    for d in range(md, 0, -1):
        bin_[d] = bin_[d - 1]
    bin_[0] = 0
    for i in range(n):
        v = vert[i]
        for k in range(indptr[v], indptr[v + 1]):
            u = indices[k]
            if deg[u] > deg[v]:
                du = deg[u]
                pu = pos[u]
                pw = bin_[du]
                w = vert[pw]
                if u != w:
                    pos[u] = pw
                    vert[pu] = w
                    pos[w] = pu
                    vert[pw] = u
                bin_[du] += 1
                deg[u] -= 1
    return deg, vert  # deg now holds core numbers; vert is the degeneracy order


@njit(cache=True, nogil=True)
def _colour_sort(cand, nc, adj, order_out, colour_out):
    """Greedy sequential colouring of cand[:nc] (Tomita & Seki 2003): writes vertices in
    non-decreasing colour order and their colour numbers (1-based). Returns nothing."""
    s = adj.shape[0]
    colour_of = np.zeros(nc, dtype=np.int32)
    ncol = 0
    for idx in range(nc):
        v = cand[idx]
        c = 1
        while True:
            ok = True
            for j in range(idx):
                if colour_of[j] == c and adj[v, cand[j]]:
                    ok = False
                    break
            if ok:
                break
            c += 1
        colour_of[idx] = c
        if c > ncol:
            ncol = c
    k = 0
    for c in range(1, ncol + 1):
        for idx in range(nc):
            if colour_of[idx] == c:
                order_out[k] = cand[idx]
                colour_out[k] = c
                k += 1
    _ = s


@njit(cache=True, nogil=True)
def _dense_max_clique(adj: np.ndarray, lb: int):
    """Largest clique of a small dense graph (boolean s x s adjacency) larger than lb.

    Iterative MCQ branch and bound. Returns (size, members) with size 0 if none > lb.
    """
    s = adj.shape[0]
    best = lb
    best_set = np.empty(s, dtype=np.int32)
    found = 0
    if s == 0:
        return 0, best_set[:0]
    order = np.empty((s + 1, s), dtype=np.int32)
    colour = np.empty((s + 1, s), dtype=np.int32)
    nlev = np.zeros(s + 1, dtype=np.int64)  # remaining candidates at each depth
    clique = np.empty(s + 1, dtype=np.int32)
    init = np.arange(s).astype(np.int32)
    _colour_sort(init, s, adj, order[0], colour[0])
    nlev[0] = s
    depth = 0
    while depth >= 0:
        k = nlev[depth]
        if k == 0 or depth + colour[depth, k - 1] <= best:
            depth -= 1
            if depth >= 0:
                nlev[depth] -= 1  # done with the vertex chosen at this depth
            continue
        v = order[depth, k - 1]
        clique[depth] = v
        # candidates for the next level: earlier entries adjacent to v
        nxt = np.empty(k - 1, dtype=np.int32)
        m = 0
        for j in range(k - 1):
            w = order[depth, j]
            if adj[v, w]:
                nxt[m] = w
                m += 1
        if m == 0:
            if depth + 1 > best:
                best = depth + 1
                found = best
                best_set[:best] = clique[:best]
            nlev[depth] -= 1
            continue
        _colour_sort(nxt, m, adj, order[depth + 1], colour[depth + 1])
        nlev[depth + 1] = m
        depth += 1
    if found == 0:
        return 0, best_set[:0]
    return found, best_set[:found].copy()


@njit(cache=True, nogil=True)
def _max_clique_csr(n: int, indptr: np.ndarray, indices: np.ndarray, lb: int):
    core, order = core_numbers(n, indptr, indices)
    rank = np.empty(n, dtype=np.int64)
    for i in range(n):
        rank[order[i]] = i
    best = lb
    best_set = np.empty(0, dtype=np.int32)
    # greedy lower bound: from the highest-core vertices, add neighbours by core number
    mark = np.zeros(n, dtype=np.int32)
    stamp = 0
    for t in range(min(n, 32)):
        v = order[n - 1 - t]
        if core[v] + 1 <= best:
            break
        stamp += 1
        cl = [v]
        cand = []
        for k in range(indptr[v], indptr[v + 1]):
            cand.append(indices[k])
        # sort candidates by decreasing core number
        cand_arr = np.array(cand, dtype=np.int64)
        keys = np.empty(len(cand_arr), dtype=np.int64)
        for i in range(len(cand_arr)):
            keys[i] = -core[cand_arr[i]]
        cand_arr = cand_arr[np.argsort(keys, kind="mergesort")]
        for u in cand_arr:
            ok = True
            for w in cl:
                # binary search u in N(w)
                lo = indptr[w]
                hi = indptr[w + 1]
                pos = lo + np.searchsorted(indices[lo:hi], u)
                if pos >= hi or indices[pos] != u:
                    ok = False
                    break
            if ok:
                cl.append(u)
        if len(cl) > best:
            best = len(cl)
            best_set = np.array(cl, dtype=np.int32)
    _ = mark
    _ = stamp
    # exact search over each vertex's later neighbourhood
    local = np.full(n, -1, dtype=np.int64)
    for i in range(n - 1, -1, -1):
        v = order[i]
        if core[v] + 1 <= best:
            continue
        cnt = 0
        for k in range(indptr[v], indptr[v + 1]):
            u = indices[k]
            if rank[u] > i and core[u] >= best:
                cnt += 1
        if cnt + 1 <= best:
            continue
        nbr = np.empty(cnt, dtype=np.int64)
        c = 0
        for k in range(indptr[v], indptr[v + 1]):
            u = indices[k]
            if rank[u] > i and core[u] >= best:
                nbr[c] = u
                local[u] = c
                c += 1
        adj = np.zeros((cnt, cnt), dtype=np.bool_)
        for a in range(cnt):
            u = nbr[a]
            for k in range(indptr[u], indptr[u + 1]):
                w = indices[k]
                b = local[w]
                if b >= 0:
                    adj[a, b] = True
        size, members = _dense_max_clique(adj, best - 1)
        for a in range(cnt):
            local[nbr[a]] = -1
        if size + 1 > best:
            best = size + 1
            best_set = np.empty(best, dtype=np.int32)
            best_set[0] = v
            for a in range(size):
                best_set[a + 1] = nbr[members[a]]
    if best_set.shape[0] <= lb:
        return np.empty(0, dtype=np.int32)
    return best_set


@njit(cache=True, nogil=True)
def _relabel_into(eu, ev, keep, scratch, su, sv, oldid):
    """Relabel the kept edges' endpoints 0..m-1 in order of appearance, into su/sv (edges)
    and oldid (old id of each new one); scratch (int32 of -1) is restored. Returns m."""
    m = 0
    t = 0
    for k in range(eu.shape[0]):
        if not keep[k]:
            continue
        a = eu[k]
        b = ev[k]
        if scratch[a] < 0:
            scratch[a] = m
            oldid[m] = a
            m += 1
        if scratch[b] < 0:
            scratch[b] = m
            oldid[m] = b
            m += 1
        su[t] = scratch[a]
        sv[t] = scratch[b]
        t += 1
    for k in range(m):
        scratch[oldid[k]] = -1
    return m


@njit(cache=True, nogil=True)
def _compact(eu, ev, keep, scratch):
    """Relabel the kept edges' endpoints 0..m-1 (scratch: int32 array of -1, restored)."""
    ne = 0
    for k in range(eu.shape[0]):
        if keep[k]:
            ne += 1
    su = np.empty(ne, dtype=np.int32)
    sv = np.empty(ne, dtype=np.int32)
    oldid = np.empty(2 * ne, dtype=np.int32)
    m = _relabel_into(eu, ev, keep, scratch, su, sv, oldid)
    return m, su, sv, oldid[:m].copy()


@njit(cache=True, nogil=True)
def _peel(su, sv, m, lb):
    """Keep-mask of edges after repeatedly dropping vertices of degree < lb (they cannot
    be in a clique larger than lb): the lb-core, found in O(E) with a stack of the
    vertices to drop (unique, whatever the order)."""
    ne = su.shape[0]
    deg = np.zeros(m, dtype=np.int64)
    for k in range(ne):
        deg[su[k]] += 1
        deg[sv[k]] += 1
    ptr = np.zeros(m + 1, dtype=np.int64)
    for v in range(m):
        ptr[v + 1] = ptr[v] + deg[v]
    fill = ptr[:-1].copy()
    inc = np.empty(2 * ne, dtype=np.int64)  # edge ids incident to each vertex
    for k in range(ne):
        inc[fill[su[k]]] = k
        fill[su[k]] += 1
        inc[fill[sv[k]]] = k
        fill[sv[k]] += 1
    keep = np.ones(ne, dtype=np.bool_)
    dropped = np.zeros(m, dtype=np.bool_)
    stack = np.empty(m, dtype=np.int64)
    top = 0
    for v in range(m):
        if deg[v] < lb:
            dropped[v] = True
            stack[top] = v
            top += 1
    kept = ne
    while top > 0:
        top -= 1
        v = stack[top]
        for t in range(ptr[v], ptr[v + 1]):
            k = inc[t]
            if not keep[k]:
                continue
            keep[k] = False
            kept -= 1
            w = sv[k] if su[k] == v else su[k]
            deg[w] -= 1
            if not dropped[w] and deg[w] < lb:
                dropped[w] = True
                stack[top] = w
                top += 1
    return keep, kept


@njit(cache=True, nogil=True)
def _peeled_graph(eu, ev, lb, scratch):
    """Compact relabelling + peeling at lb. Returns (m, su, sv, oldid, keep-mask over
    the original edges)."""
    keep_all = np.ones(eu.shape[0], dtype=np.bool_)
    m, su, sv, oldid = _compact(eu, ev, keep_all, scratch)
    keep, ne = _peel(su, sv, m, lb)
    return m, su, sv, oldid, keep, ne


@njit(cache=True, nogil=True)
def _peeled_max_clique(eu: np.ndarray, ev: np.ndarray, lb: int, scratch: np.ndarray):
    """Relabel compactly, peel at lb, then search. Cheap on the sparse, mostly random
    consistency graphs."""
    m, su, sv, oldid, keep, ne = _peeled_graph(eu, ev, lb, scratch)
    if ne == 0 or ne < lb * (lb + 1) // 2:
        return np.empty(0, dtype=np.int32)
    m2, tu, tv, old2 = _compact(su, sv, keep, scratch)
    indptr, indices = csr_from_edges(m2, tu, tv)
    c = _max_clique_csr(m2, indptr, indices, lb)
    out = np.empty(c.shape[0], dtype=np.int32)
    for k in range(c.shape[0]):
        out[k] = oldid[old2[c[k]]]
    return out


def peel(
    eu: np.ndarray, ev: np.ndarray, lower_bound: int, scratch: np.ndarray | None = None
) -> np.ndarray:
    """Boolean mask of the edges that survive removing, repeatedly, every vertex of
    degree < lower_bound: only those can belong to a clique larger than lower_bound."""
    eu = np.ascontiguousarray(eu, dtype=np.int32)
    ev = np.ascontiguousarray(ev, dtype=np.int32)
    if eu.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    n = int(max(eu.max(), ev.max())) + 1
    if scratch is None or scratch.shape[0] < n:
        scratch = np.full(n, -1, dtype=np.int32)
    m, su, sv, oldid, keep, ne = _peeled_graph(eu, ev, int(lower_bound), scratch)
    # su/sv are in the same order as eu/ev (compaction keeps every edge), so keep aligns
    return keep


def max_clique(
    n: int, eu: np.ndarray, ev: np.ndarray, lower_bound: int = 0, scratch: np.ndarray | None = None
) -> np.ndarray:
    """Vertices of a maximum clique of an undirected graph with `n` vertices and edges
    (eu[k], ev[k]); empty if no clique has more than `lower_bound` vertices.

    `scratch` (optional, reused across calls for speed): int32 array of size >= n filled with -1.
    """
    eu = np.ascontiguousarray(eu, dtype=np.int32)
    ev = np.ascontiguousarray(ev, dtype=np.int32)
    if n == 0:
        return np.empty(0, dtype=np.int32)
    if eu.shape[0] == 0:
        return np.array([0], dtype=np.int32) if lower_bound < 1 else np.empty(0, dtype=np.int32)
    if scratch is None or scratch.shape[0] < n:
        scratch = np.full(n, -1, dtype=np.int32)
    return np.sort(_peeled_max_clique(eu, ev, int(lower_bound), scratch))


@njit(cache=True, nogil=True)
def _bin_bounds(ptr: np.ndarray, su: np.ndarray, sv: np.ndarray, scratch: np.ndarray):
    """Upper and lower bounds on the maximum clique of each of the graphs whose edges are
    su/sv[ptr[k]:ptr[k+1]] (the yaw bins of one chunk): degeneracy + 1 (a clique of size s
    lies in the (s-1)-core) and the size of a greedy clique grown from the vertex of highest
    core number. A graph with no edge gives (0, 0); its caller knows whether it has vertices."""
    nb = ptr.shape[0] - 1
    upper = np.zeros(nb, dtype=np.int64)
    lower = np.zeros(nb, dtype=np.int64)
    ne_max = 0
    for k in range(nb):
        ne_max = max(ne_max, ptr[k + 1] - ptr[k])
    n_max = 2 * ne_max
    oldid = np.empty(n_max, dtype=np.int32)
    tu = np.empty(ne_max, dtype=np.int32)
    tv = np.empty(ne_max, dtype=np.int32)
    indptr = np.empty(n_max + 1, dtype=np.int64)
    fill = np.empty(n_max, dtype=np.int64)
    indices = np.empty(2 * ne_max, dtype=np.int32)
    stamp = np.zeros(n_max, dtype=np.int64)
    cand = np.empty(n_max, dtype=np.int32)
    keep_all = np.ones(ne_max, dtype=np.bool_)
    for k in range(nb):
        e0 = ptr[k]
        ne = ptr[k + 1] - e0
        if ne <= 0:
            continue
        m = _relabel_into(su[e0 : e0 + ne], sv[e0 : e0 + ne], keep_all[:ne], scratch, tu, tv, oldid)
        _csr_into(m, tu, tv, ne, indptr, fill, indices)
        core, order = core_numbers(m, indptr[: m + 1], indices[: indptr[m]])
        top = order[m - 1]
        upper[k] = core[top] + 1
        # greedy clique from the top vertex: keep the candidates adjacent to every member,
        # taking the candidate of highest core number each time
        nc = 0
        for t in range(indptr[top], indptr[top + 1]):
            cand[nc] = indices[t]
            nc += 1
        size = 1
        run = 0
        while nc > 0:
            pick = 0
            for t in range(1, nc):
                if core[cand[t]] > core[cand[pick]]:
                    pick = t
            u = cand[pick]
            size += 1
            run += 1
            for t in range(indptr[u], indptr[u + 1]):
                stamp[indices[t]] = run
            keep = 0
            for t in range(nc):
                w = cand[t]
                if w != u and stamp[w] == run:
                    cand[keep] = w
                    keep += 1
            nc = keep
        stamp[:m] = 0
        lower[k] = size
    return upper, lower


def bin_clique_bounds(ptr: np.ndarray, su: np.ndarray, sv: np.ndarray, scratch: np.ndarray):
    """(upper, lower) bounds on the maximum clique of each bin's graph of one chunk
    (edges su/sv[ptr[k]:ptr[k+1]], association ids < len(scratch); scratch: int32 filled
    with -1, restored). Bins without edges give (0, 0)."""
    return _bin_bounds(
        np.asarray(ptr, dtype=np.int64),
        np.ascontiguousarray(su, dtype=np.int32),
        np.ascontiguousarray(sv, dtype=np.int32),
        scratch,
    )
