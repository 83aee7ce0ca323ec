"""OpenCV's distortion polynomial, one point at a time, for compiled (numba) kernels.

The same arithmetic as :meth:`services.geometry.camera.Camera._distort` does over numpy arrays, written once for the
kernels that project a point at a time: the renderer's splat (:mod:`services.render.splat`) and the blur's sampling
maps (:mod:`services.geometry.blur_kernels`). Inlined where it is called: no call in the hot loop.

numba's on-disk cache (``cache=True``) is keyed on the *caller's* source file only (numba/numba#8396 would extend
it): after editing this function, touch those two files, or delete their ``__pycache__``, or they keep running the
old arithmetic compiled in.
"""

from __future__ import annotations

import numba as nb

__all__ = ["distort"]


@nb.njit(cache=True, inline="always")
def distort(x, y, k1, k2, p1, p2, k3):
    """Normalised image coordinates (x/z, y/z) through OpenCV's radial (k1, k2, k3) and tangential (p1, p2) terms."""
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
