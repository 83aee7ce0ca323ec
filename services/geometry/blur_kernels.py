"""Compiled (numba) kernel for :mod:`services.geometry.blur`: where each pixel finds its colour from a camera at
another pose, a pixel at a time.

A blurred render takes two such sampling maps per frame, and numpy spends ~7 ms on each at 480x360 (a matrix
product, a projection and clipping over whole arrays of float64); compiled, well under a millisecond.
Optional (:mod:`services.kernels`): without numba, numpy.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from services.geometry.distortion_kernel import distort

__all__ = ["sampling_maps"]


@nb.njit(cache=True, nogil=True)
def sampling_maps(points, R, t, fx, fy, cx, cy, dist, W, H):
    """Pixel maps (H, W) x and y, float32, of ``points`` (H*W, 3) moved by (``R``, ``t``) and projected with the
    pinhole + OpenCV distortion (``dist``: k1, k2, p1, p2, k3); a point behind the camera or not finite maps to -1,
    others are kept within a width (height) of the image (OpenCV walks an outside coordinate back a width at a time)."""
    mx = np.empty(H * W, np.float32)
    my = np.empty(H * W, np.float32)
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for i in range(H * W):
        X = R[0, 0] * points[i, 0] + R[0, 1] * points[i, 1] + R[0, 2] * points[i, 2] + t[0]
        Y = R[1, 0] * points[i, 0] + R[1, 1] * points[i, 1] + R[1, 2] * points[i, 2] + t[1]
        Z = R[2, 0] * points[i, 0] + R[2, 1] * points[i, 1] + R[2, 2] * points[i, 2] + t[2]
        u = v = -1.0
        if Z > 0:
            x, y = distort(X / Z, Y / Z, k1, k2, p1, p2, k3)
            u = fx * x + cx
            v = fy * y + cy
            if not (np.isfinite(u) and np.isfinite(v)):
                u = v = -1.0
        mx[i] = min(max(u, -W), 2 * W - 1)
        my[i] = min(max(v, -H), 2 * H - 1)
    return mx.reshape(H, W), my.reshape(H, W)
