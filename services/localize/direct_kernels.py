"""Compiled (numba) kernel for direct tracking's motion-only pose solve: its normal equations, a point at a time.

:func:`services.localize.direct.solve_motion_only` runs ~6 Gauss-Newton steps per alignment pass on ~200 aligned
landmarks; in numpy each step is some twenty whole-array operations, and the Python around them costs more than the
arithmetic. Optional, like :mod:`services.prebuild.patch_kernels` (:mod:`services.kernels`): without numba, numpy.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["normal_equations"]


@nb.njit(cache=True, nogil=True)
def normal_equations(P, uv, l11, l21, l22, R, t, fx, fy, cx, cy, huber, H, g):
    """The Huber-weighted Gauss-Newton system of the whitened reprojection errors of world points ``P`` (n, 3) seen at
    ``uv`` (n, 2) with square-root information (``l11``, ``l21``, ``l22``), for a left perturbation (omega, v) of the
    world-to-camera pose (``R``, ``t``): ``H`` (6, 6) = sum w J^T J and ``g`` (6,) = sum w J^T e, written in place."""
    H[:] = 0.0
    g[:] = 0.0
    ju = np.empty(6)
    jv = np.empty(6)
    j1 = np.empty(6)
    for p in range(P.shape[0]):
        x = R[0, 0] * P[p, 0] + R[0, 1] * P[p, 1] + R[0, 2] * P[p, 2] + t[0]
        y = R[1, 0] * P[p, 0] + R[1, 1] * P[p, 1] + R[1, 2] * P[p, 2] + t[1]
        z = R[2, 0] * P[p, 0] + R[2, 1] * P[p, 1] + R[2, 2] * P[p, 2] + t[2]
        iz = 1.0 / max(z, 1e-6)
        ex = fx * x * iz + cx - uv[p, 0]
        ey = fy * y * iz + cy - uv[p, 1]
        e1 = l11[p] * ex + l21[p] * ey
        e2 = l22[p] * ey
        r = np.sqrt(e1 * e1 + e2 * e2)
        w = 1.0 if r <= huber else huber / max(r, 1e-12)
        a, b = fx * iz, fy * iz
        ju[0], ju[1], ju[2], ju[3], ju[4], ju[5] = -a * x * y * iz, a * (z + x * x * iz), -a * y, a, 0.0, -a * x * iz
        jv[0], jv[1], jv[2], jv[3], jv[4], jv[5] = -b * (z + y * y * iz), b * x * y * iz, b * x, 0.0, b, -b * y * iz
        for i in range(6):
            j1[i] = l11[p] * ju[i] + l21[p] * jv[i]
        for i in range(6):
            j2i = l22[p] * jv[i]
            g[i] += w * (j1[i] * e1 + j2i * e2)
            for j in range(i, 6):
                H[i, j] += w * (j1[i] * j1[j] + j2i * l22[p] * jv[j])
    for i in range(6):
        for j in range(i):
            H[i, j] = H[j, i]
