"""Three-pass point splatting on the CPU (numba), after Schütz et al. 2021.

1. depth pass: per-pixel minimum camera z over all points;
2. colour pass: sum the colours of points within ``delta`` of that minimum;
3. average.

No locks: every thread owns private depth and colour buffers that are reduced at the end
(two threads on a laptop, sixteen on a server: the buffers are small next to the scan).
Chunks whose bounding box is outside the view frustum are skipped before any point is
touched. Pixel centres are at integer coordinates: a point lands on ``round(u), round(v)``.

Level of detail (``SplatConfig.lod_points_per_px``): a chunk seen from so far that more than that many of
its points would land on each pixel is read only up to the prefix that gives that many (chunks are shuffled
inside, ``services.render.cloud``): a 64 M-point scan's cubemap costs half of what every point costs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from services.geometry.camera import Camera
from services.geometry.distortion_kernel import distort
from services.geometry.se3 import Pose
from services.render.cloud import PreparedCloud
from services.render.threads import keeps_torch_threads

__all__ = ["SplatConfig", "SplatResult", "splat", "visible_chunks", "chunk_limits"]


@dataclass(frozen=True)
class SplatConfig:
    delta_abs: float = 0.02  # metres: points this far behind the nearest one still blend (the paper's value)
    delta_rel: float = 0.0  # plus this fraction of the nearest depth (useful for long ranges)
    near: float = 0.05  # metres: points closer than this to the camera plane are dropped
    lod_points_per_px: float = 8.0  # level of detail: about this many of a chunk's points per pixel suffice (0 = every point).
    #                                 A 64 M-point office's image is unchanged (SSIM 0.8955 at 8 and with every point); at 4 its
    #                                 renders lose 0.002 SSIM, and a 4 M-point walk that cuts 6 % of its points 18 of 114 frames


@dataclass
class SplatResult:
    rgb: np.ndarray  # (H, W, 3) float32 in [0, 255], 0 where empty
    depth: np.ndarray  # (H, W) float32 camera z of the nearest point, 0 where empty
    count: np.ndarray  # (H, W) int32 points blended per pixel


@nb.njit(cache=True, inline="always")
def _project(p, R, t, fx, fy, cx, cy, k1, k2, p1, p2, k3, distorted, r2max, near, W, H):
    X = R[0, 0] * p[0] + R[0, 1] * p[1] + R[0, 2] * p[2] + t[0]
    Y = R[1, 0] * p[0] + R[1, 1] * p[1] + R[1, 2] * p[2] + t[1]
    Z = R[2, 0] * p[0] + R[2, 1] * p[1] + R[2, 2] * p[2] + t[2]
    if Z < near:
        return -1, Z
    x = X / Z
    y = Y / Z
    if distorted:
        if x * x + y * y > r2max:
            return -1, Z
        x, y = distort(x, y, k1, k2, p1, p2, k3)
    u = fx * x + cx + 0.5
    v = fy * y + cy + 0.5
    if u < 0.0 or v < 0.0 or u >= W or v >= H:
        return -1, Z
    return int(v) * W + int(u), Z


@nb.njit(cache=True, parallel=True, fastmath=True)
def _splat(xyz, rgb, chunks, lims, chunk, R, t, intr, dist, distorted, r2max, near, d_abs, d_rel, W, H, zbuf, acc, cnt):
    n = xyz.shape[0]
    nt = zbuf.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    npx = W * H
    for ti in nb.prange(nt):
        for i in range(npx):
            zbuf[ti, i] = np.inf
    # pass 1: minimum depth
    for ci in nb.prange(chunks.shape[0]):
        tid = nb.get_thread_id()
        s = chunks[ci] * chunk
        e = min(s + lims[ci], n)
        for i in range(s, e):
            idx, z = _project(xyz[i], R, t, fx, fy, cx, cy, k1, k2, p1, p2, k3, distorted, r2max, near, W, H)
            if idx >= 0 and z < zbuf[tid, idx]:
                zbuf[tid, idx] = z
    for i in nb.prange(npx):
        m = zbuf[0, i]
        for ti in range(1, nt):
            if zbuf[ti, i] < m:
                m = zbuf[ti, i]
        zbuf[0, i] = m
    for ti in nb.prange(nt):
        for i in range(npx):
            acc[ti, i, 0] = 0.0
            acc[ti, i, 1] = 0.0
            acc[ti, i, 2] = 0.0
            cnt[ti, i] = 0
    # pass 2: accumulate colours of points within delta of the minimum
    for ci in nb.prange(chunks.shape[0]):
        tid = nb.get_thread_id()
        s = chunks[ci] * chunk
        e = min(s + lims[ci], n)
        for i in range(s, e):
            idx, z = _project(xyz[i], R, t, fx, fy, cx, cy, k1, k2, p1, p2, k3, distorted, r2max, near, W, H)
            if idx >= 0:
                zm = zbuf[0, idx]
                if z <= zm + d_abs + d_rel * zm:
                    acc[tid, idx, 0] += rgb[i, 0]
                    acc[tid, idx, 1] += rgb[i, 1]
                    acc[tid, idx, 2] += rgb[i, 2]
                    cnt[tid, idx] += 1
    # pass 3: average
    for i in nb.prange(npx):
        c = cnt[0, i]
        r = acc[0, i, 0]
        g = acc[0, i, 1]
        b = acc[0, i, 2]
        for ti in range(1, nt):
            c += cnt[ti, i]
            r += acc[ti, i, 0]
            g += acc[ti, i, 1]
            b += acc[ti, i, 2]
        if c > 0:
            acc[0, i, 0] = r / c
            acc[0, i, 1] = g / c
            acc[0, i, 2] = b / c
        else:
            zbuf[0, i] = 0.0
        cnt[0, i] = c


def _r2max(camera: Camera) -> float:
    """Largest undistorted radius^2 inside the image, with margin: beyond it the distortion polynomial folds back."""
    if not camera.is_distorted:
        return np.inf
    W, H = camera.width, camera.height
    border = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1], [W / 2, 0], [0, H / 2], [W - 1, H / 2], [W / 2, H - 1]])
    xy = camera.undistort_points(border)
    return float((xy ** 2).sum(axis=1).max() * 1.5)


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The eight corners (C, 8, 3) of boxes ``lo``..``hi`` (C, 3), in float64."""
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    return np.stack([np.stack([np.where(m & 1, hi[:, 0], lo[:, 0]), np.where(m & 2, hi[:, 1], lo[:, 1]),
                               np.where(m & 4, hi[:, 2], lo[:, 2])], -1) for m in range(8)], 1)


def visible_chunks(cloud: PreparedCloud, T_cw_local: Pose, camera: Camera, near: float) -> np.ndarray:
    """Indices of chunks whose bounding box may intersect the view frustum (conservative)."""
    Xc = _box_corners(cloud.chunk_lo, cloud.chunk_hi) @ T_cw_local.R.T + T_cw_local.t
    X, Y, Z = Xc[..., 0], Xc[..., 1], Xc[..., 2]
    # tangents of the frustum's side planes (through the camera centre), widened for distortion
    W, H = camera.width, camera.height
    xl, xr = (-camera.cx - 1) / camera.fx, (W - camera.cx) / camera.fx
    yt, yb = (-camera.cy - 1) / camera.fy, (H - camera.cy) / camera.fy
    if camera.is_distorted:
        r = np.sqrt(_r2max(camera))
        xl, xr, yt, yb = min(xl, -r), max(xr, r), min(yt, -r), max(yb, r)
    # a box entirely outside one half-space cannot meet the frustum (valid for corners behind the camera too)
    out = (Z < near).all(1) | (X - xl * Z < 0).all(1) | (X - xr * Z > 0).all(1) | (Y - yt * Z < 0).all(1) | (Y - yb * Z > 0).all(1)
    keep = ~out
    return np.flatnonzero(keep).astype(np.int64)


def chunk_limits(cloud: PreparedCloud, chunks: np.ndarray, T_cw_local: Pose, camera: Camera,
                 points_per_px: float) -> np.ndarray:
    """How many of each chunk's (shuffled) points to splat: all, unless about ``points_per_px`` per pixel suffice.

    A chunk of spacing s at depth z puts (f s / z)^-2 points on a pixel; its nearest bounding-box corner
    gives z (a chunk reaching the camera plane keeps every point)."""
    full = np.full(len(chunks), cloud.chunk, np.int64)
    if points_per_px <= 0 or len(chunks) == 0:
        return full
    depths = _box_corners(cloud.chunk_lo[chunks], cloud.chunk_hi[chunks]) @ T_cw_local.R[2] + T_cw_local.t[2]
    z = np.maximum(depths.min(axis=1), 1e-3)
    px = np.maximum(camera.fx, camera.fy) * cloud.chunk_spacing[chunks].astype(np.float64) / z  # point spacing in pixels
    frac = np.minimum(1.0, points_per_px * px * px)
    return np.maximum(1, np.ceil(frac * cloud.chunk)).astype(np.int64)


@keeps_torch_threads  # numba's pool would leave torch on every core (services.render.threads)
def splat(cloud: PreparedCloud, T_wc: Pose, camera: Camera, cfg: SplatConfig = SplatConfig(),
          cull: bool = True) -> SplatResult:
    """Render the raw splat of ``cloud`` seen by ``camera`` at camera-to-world ``T_wc``."""
    # the cloud is stored relative to its origin: move the camera into that local frame
    T_cw_local = Pose(T_wc.R, T_wc.t - cloud.origin).inverse()
    chunks = visible_chunks(cloud, T_cw_local, camera, cfg.near) if cull else np.arange(cloud.n_chunks, dtype=np.int64)
    lims = chunk_limits(cloud, chunks, T_cw_local, camera, cfg.lod_points_per_px)
    W, H = camera.width, camera.height
    nt = nb.get_num_threads()
    zbuf = np.empty((nt, W * H), np.float32)
    acc = np.empty((nt, W * H, 3), np.float32)
    cnt = np.empty((nt, W * H), np.int32)
    intr = np.array([camera.fx, camera.fy, camera.cx, camera.cy], np.float64)
    # one argument signature for every call: numba compiles a kernel per layout and type (a transposed R is
    # Fortran-ordered), and a second compilation costs 7-14 s on a 2-core box in the middle of serving a frame
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    _splat(cloud.xyz, cloud.rgb, np.asarray(chunks, np.int64), np.asarray(lims, np.int64), int(cloud.chunk), f32(T_cw_local.R),
           f32(T_cw_local.t), intr, np.ascontiguousarray(camera.dist, dtype=np.float64), bool(camera.is_distorted),
           float(_r2max(camera)), float(cfg.near), float(cfg.delta_abs), float(cfg.delta_rel), int(W), int(H),
           zbuf, acc, cnt)
    return SplatResult(acc[0].reshape(H, W, 3), zbuf[0].reshape(H, W), cnt[0].reshape(H, W))
