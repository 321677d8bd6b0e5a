"""numpy statistics bit for bit, faster on the small 1-D arrays the detector takes many of."""

from __future__ import annotations

import numpy as np

__all__ = ["median"]


def median(a: np.ndarray) -> np.floating:
    """``np.median(a)`` bit for bit, faster for a 1-D float array (one partition, no array
    machinery; `a` is not modified); anything else goes to np.median."""
    if a.ndim != 1 or a.dtype.kind != "f" or a.size == 0:
        return np.median(a)
    n = a.size
    k = n // 2
    if n % 2:
        p = np.partition(a, k if k == n - 1 else (k, n - 1))
        return p.dtype.type(np.nan) if np.isnan(p[-1]) else p[k]
    p = np.partition(a, (k - 1, k) if k == n - 1 else (k - 1, k, n - 1))
    return p.dtype.type(np.nan) if np.isnan(p[-1]) else np.mean(p[k - 1 : k + 1])
