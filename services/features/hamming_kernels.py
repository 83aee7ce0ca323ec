"""Compiled (numba) brute-force nearest two by Hamming distance, for binary descriptors (ORB).

P&L's relocalization matches a frame's strongest 600 keypoints against every landmark of the map (33 k on the
office, 327 k on the survey-density warehouse). OpenCV's ``BFMatcher.knnMatch`` took 276 ms for 600 x 33 k (one
thread) and returns Python objects per match; this loop, on the descriptors as 64-bit words, 46 ms. Optional like the
other kernels (:mod:`services.kernels`): without numba, :func:`services.localize.pnl.knn2_hamming` uses OpenCV.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["knn2"]

NONE = 1 << 30  # a distance no descriptor pair reaches: "no such neighbour"


@nb.njit(cache=True, inline="always")
def _popcount(x):
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return np.int64((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


@nb.njit(cache=True, nogil=True)
def knn2(query, train, best, d1, d2):
    """For each row of ``query`` (n, w) uint64 (descriptors as words), the first of its nearest rows in ``train`` (m, w)
    and the Hamming distances to the nearest and second nearest, into ``best`` (-1 when none), ``d1``, ``d2``
    (:data:`NONE` when missing), all (n,) int64."""
    for i in range(query.shape[0]):
        b1, b2, bi = NONE, NONE, -1
        for j in range(train.shape[0]):
            d = 0
            for w in range(query.shape[1]):
                d += _popcount(query[i, w] ^ train[j, w])
            if d < b1:
                b1, b2, bi = d, b1, j
            elif d < b2:
                b2 = d
        best[i], d1[i], d2[i] = bi, b1, b2
