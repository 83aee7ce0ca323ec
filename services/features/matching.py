"""Descriptor matching: mutual nearest neighbours with a cosine-similarity threshold."""

from __future__ import annotations

import numpy as np

__all__ = ["mutual_nn"]


def mutual_nn(d0: np.ndarray, d1: np.ndarray, min_cos: float = 0.82) -> np.ndarray:
    """Indices (M, 2) of pairs (i in d0, j in d1) that are each other's nearest neighbour with cosine >= ``min_cos``.

    Descriptors must be L2-normalised rows. ``min_cos`` 0.82 is XFeat's own default.
    """
    if len(d0) == 0 or len(d1) == 0:
        return np.zeros((0, 2), np.int64)
    sim = d0 @ d1.T
    j = sim.argmax(axis=1)
    i = sim.argmax(axis=0)
    a = np.arange(len(d0))
    keep = (i[j] == a) & (sim[a, j] >= min_cos)
    return np.stack([a[keep], j[keep]], axis=1)
