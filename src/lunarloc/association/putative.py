"""Putative associations between a vehicle map and a reference map."""

from __future__ import annotations

import numpy as np

__all__ = ["putative_associations"]


def putative_associations(
    n_veh: int,
    n_ref: int,
    veh_sizes: np.ndarray | None = None,
    ref_sizes: np.ndarray | None = None,
    max_size_ratio: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """All-to-all associations, optionally pruned by size similarity.

    Returns ``(assoc, node_of)``: ``assoc`` (m, 2) int32 rows ``[veh_index, ref_index]``
    and ``node_of`` (n_veh, n_ref) int32 giving each pair's row in ``assoc`` or -1.
    With sizes on both maps and ``max_size_ratio`` (> 1), pairs whose larger/smaller
    size ratio exceeds it are dropped.
    """
    keep = np.ones((n_veh, n_ref), dtype=bool)
    if max_size_ratio is not None and veh_sizes is not None and ref_sizes is not None:
        sv = np.maximum(np.asarray(veh_sizes, float), 1e-6)[:, None]
        sr = np.maximum(np.asarray(ref_sizes, float), 1e-6)[None, :]
        keep = np.maximum(sv / sr, sr / sv) <= max_size_ratio
    vi, ri = np.nonzero(keep)
    assoc = np.stack([vi, ri], axis=1).astype(np.int32)
    node_of = np.full((n_veh, n_ref), -1, dtype=np.int32)
    node_of[vi, ri] = np.arange(len(assoc), dtype=np.int32)
    return assoc, node_of
