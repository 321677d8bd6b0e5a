"""CLIPPER relaxation for the densest consistent set (Lusk, Fathian & How, ICRA 2021).

Maximises ``u^T M_d u`` over the non-negative unit sphere, where ``M`` is the
weighted consistency matrix (ones on the diagonal) and
``M_d = M - d (1 1^T - C)`` penalises pairs that are not consistent (C: binary
consistency with ones on the diagonal). Projected gradient ascent with a backtracking
step (paper, Alg. 1), increasing the penalty ``d`` until the support of ``u`` is a
clique; then rounding keeps the ``round(u^T M u)`` largest entries (paper, eq. 9) and
drops any that break consistency. Everything is sparse: ``(1 1^T - C) u`` is
``sum(u) - u - A u`` with A the sparse adjacency.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["clipper_clique"]


def clipper_clique(
    n: int,
    eu: np.ndarray,
    ev: np.ndarray,
    ew: np.ndarray,
    *,
    max_outer: int = 40,
    max_inner: int = 200,
    tol: float = 1e-7,
    kappa: float = 10.0,
    seed: int = 0,
) -> np.ndarray:
    """Vertices of the densest consistent set found by the CLIPPER relaxation (a clique,
    not necessarily the maximum one)."""
    if n == 0:
        return np.empty(0, dtype=np.int32)
    if len(eu) == 0:
        return np.array([0], dtype=np.int32)
    # work on the vertices that have edges only (relabelled 0..n'-1)
    used, inv = np.unique(np.r_[eu, ev], return_inverse=True)
    eu, ev = inv[: len(eu)], inv[len(eu) :]
    n = len(used)
    W = sp.coo_matrix(
        (np.r_[ew, ew].astype(float), (np.r_[eu, ev], np.r_[ev, eu])), shape=(n, n)
    ).tocsr()
    A = W.copy()
    A.data[:] = 1.0
    rng = np.random.default_rng(seed)
    u = rng.random(n) + 0.5
    u /= np.linalg.norm(u)

    def Md(x, d):
        return W @ x + x - d * (x.sum() - x - A @ x)

    d = 0.0
    for _ in range(max_outer):
        F = u @ Md(u, d)
        for _ in range(max_inner):
            g = 2.0 * Md(u, d)
            alpha = 1.0
            improved = False
            for _ in range(30):
                v = np.maximum(u + alpha * g, 0.0)
                nv = np.linalg.norm(v)
                if nv == 0:
                    alpha *= 0.5
                    continue
                v /= nv
                Fv = v @ Md(v, d)
                if Fv > F:
                    improved = True
                    break
                alpha *= 0.5
            if not improved:
                break
            delta = np.linalg.norm(v - u)
            u, F = v, Fv
            if delta < tol:
                break
        supp = np.flatnonzero(u > 1e-8)
        # is the support a clique? count support pairs that are adjacent
        sub = A[supp][:, supp]
        if sub.nnz == len(supp) * (len(supp) - 1):
            break
        d = kappa * d if d > 0 else 1.0 / n
    omega = max(1, int(round(u @ (W @ u + u))))
    order = np.argsort(-u)
    chosen: list[int] = []
    Acsr = A.tocsr()
    for idx in order[: max(omega, 1) * 2]:
        if len(chosen) >= omega:
            break
        row = Acsr.indices[Acsr.indptr[idx] : Acsr.indptr[idx + 1]]
        if all(c in row for c in chosen):
            chosen.append(int(idx))
    return np.sort(used[np.asarray(chosen, dtype=np.int64)].astype(np.int32))
