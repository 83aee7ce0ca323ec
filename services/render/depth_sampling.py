"""Depth at sub-pixel keypoints of a render, from the scan points around them.

A render of a sparse or nearby part of a scan has its points several pixels apart: most keypoints
of the hole-filled image fall between points, where no depth was measured. The surface there is
still known from the points around it. ``plane_depth`` fits a plane, in inverse depth (which is
affine in the pixel coordinates for any plane seen by a pinhole camera), to the measured pixels
within a small window and evaluates it at the keypoint. It refuses to guess where that is not an
interpolation: too few points, points only on one side of the keypoint, or points that do not lie
on one plane (a depth edge, where the keypoint's surface is ambiguous). It also puts keypoints on
measured pixels at their sub-pixel position on the surface, not at the centre of the pixel.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["hole_depth", "invented_near", "plane_depth", "plane_normals", "support_fraction"]


def plane_depth(depth: np.ndarray, uv: np.ndarray, radius: int = 4, max_residual: float = 0.01,
                min_points: int = 4, return_plane: bool = False):
    """Depth (N,) at pixels ``uv`` (N,2) of ``depth`` (H,W; 0 = not measured) and a validity mask.

    ``radius``: half-size of the square window; ``max_residual``: the largest misfit of a window
    point to the plane, relative to its depth; ``min_points``: measured pixels needed in the window.
    ``return_plane``: also return the fitted planes (N,3): 1/z = a (u - u0) + b (v - v0) + c around
    each keypoint (u0, v0); see ``plane_normals``.
    """
    H, W = depth.shape
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return (np.zeros(0), np.zeros(0, bool), np.zeros((0, 3))) if return_plane else (np.zeros(0), np.zeros(0, bool))
    px = np.clip(np.round(uv).astype(np.int64), 0, [W - 1, H - 1])
    o = np.arange(-radius, radius + 1)
    du, dv = (a.ravel() for a in np.meshgrid(o, o))
    U, V = px[:, :1] + du, px[:, 1:] + dv
    inside = (U >= 0) & (U < W) & (V >= 0) & (V < H)
    z = np.where(inside, depth[np.clip(V, 0, H - 1), np.clip(U, 0, W - 1)], 0.0).astype(np.float64)
    m = z > 0
    x = np.where(m, U - uv[:, :1], 0.0)
    y = np.where(m, V - uv[:, 1:], 0.0)
    iz = np.where(m, 1.0 / np.where(m, z, 1.0), 0.0)
    A = np.stack([x, y, m.astype(np.float64)], -1)  # (N, K, 3); rows of unmeasured pixels are zero
    ok = m.sum(1) >= min_points
    # interpolation only: measured pixels on both sides of the keypoint, in u and in v
    ok &= (np.where(m, x, np.inf).min(1) <= 0) & (np.where(m, x, -np.inf).max(1) >= 0)
    ok &= (np.where(m, y, np.inf).min(1) <= 0) & (np.where(m, y, -np.inf).max(1) >= 0)
    N = np.einsum("nki,nkj->nij", A, A)
    b = np.einsum("nki,nk->ni", A, iz)
    ok &= np.abs(np.linalg.det(N)) > 1e-6  # points on one line leave the plane undetermined
    a = np.zeros((len(uv), 3))
    if ok.any():
        a[ok] = np.linalg.solve(N[ok], b[ok][..., None])[..., 0]
    ok &= a[:, 2] > 0
    fit = np.einsum("nki,ni->nk", A, a)
    misfit = np.where(m & (fit > 0), np.abs(1.0 - fit * np.where(m, z, 0.0)), np.where(m, np.inf, 0.0))
    ok &= misfit.max(1) <= max_residual  # |z_fit - z| / z_fit
    z_at = np.where(ok, 1.0 / np.where(ok, a[:, 2], 1.0), 0.0)
    return (z_at, ok, a) if return_plane else (z_at, ok)


def plane_normals(uv: np.ndarray, planes: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Unit surface normals (N,3), camera axes, facing the camera, of the planes ``plane_depth`` fitted
    around pixels ``uv``. A plane n.X = d seen by a pinhole camera has 1/z = (n . ((u-cx)/fx, (v-cy)/fy, 1)) / d."""
    a, b, c = planes[:, 0], planes[:, 1], planes[:, 2]
    n = np.column_stack([a * fx, b * fy, c - a * (uv[:, 0] - cx) - b * (uv[:, 1] - cy)])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    ray = np.column_stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(len(uv))])
    return np.where((np.einsum("ij,ij->i", n, ray) > 0)[:, None], -n, n)


def support_fraction(measured: np.ndarray, radius: int) -> float:
    """Fraction of pixels with a measured pixel within ``radius`` (the share of a render where
    ``plane_depth`` can work; 1 - hole fraction for ``radius`` 0)."""
    if radius <= 0:
        return float(measured.mean())
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * radius + 1, 2 * radius + 1))
    return float(cv2.dilate(measured.astype(np.uint8), k).mean())


def hole_depth(measured: np.ndarray, uv: np.ndarray, radius: int) -> np.ndarray:
    """(N,) float32: for each of ``uv`` (N, 2), how far (px) the pixel within ``radius`` of it that lies farthest
    from the render's measured pixels (``measured``) is from one: 0 where every pixel near is measured, half a
    hole's width for a hole within reach."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if not len(uv):
        return np.zeros(0, np.float32)
    dt = cv2.distanceTransform((~measured.astype(bool)).astype(np.uint8), cv2.DIST_L2, 3)
    deepest = cv2.dilate(dt, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    h, w = measured.shape
    px = np.clip(np.round(uv).astype(int), 0, [w - 1, h - 1])
    return deepest[px[:, 1], px[:, 0]]


def invented_near(measured: np.ndarray, uv: np.ndarray, radius: int, gap_px: float) -> np.ndarray:
    """Whether a hole wider than 2 x ``gap_px`` lies within ``radius`` pixels of each of ``uv`` (N, 2): there the
    render's colours are not the scan's but what hole filling made up (a part of the room the scanner never saw,
    behind a rack, filled with the rack's colour: its edge there is drawn where no edge is)."""
    return hole_depth(measured, uv, radius) > gap_px
