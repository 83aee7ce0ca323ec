"""Ray casting against a triangle mesh: a BVH built once, traversed by many rays in parallel (numba).

The simulator uses one tracer for everything that needs ground truth: LiDAR returns,
camera frames, and depth. Ray casting (rather than rasterising) makes lens distortion
and spherical scanner grids exact, and needs no near-plane clipping.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

__all__ = ["BVH", "build_bvh", "trace"]

_LEAF_SIZE = 4


@dataclass
class BVH:
    """Flattened bounding-volume hierarchy over triangles (float64 for sub-millimetre ground truth).

    Node i is a leaf when ``count[i] > 0``: its triangles are ``order[start[i]:start[i]+count[i]]``;
    otherwise its children are ``left[i]`` and ``right[i]``. Node 0 is the root.
    """

    bmin: np.ndarray  # (nodes, 3)
    bmax: np.ndarray  # (nodes, 3)
    left: np.ndarray  # (nodes,) int32, -1 for leaves
    right: np.ndarray  # (nodes,) int32
    start: np.ndarray  # (nodes,) int32 first index into ``order`` (leaves)
    count: np.ndarray  # (nodes,) int32 number of triangles (leaves), 0 for inner nodes
    order: np.ndarray  # (tris,) int32 triangle ids in leaf order
    v0: np.ndarray  # (tris, 3) first vertex of each triangle
    e1: np.ndarray  # (tris, 3) v1 - v0
    e2: np.ndarray  # (tris, 3) v2 - v0


@nb.njit(cache=True)
def _build(cent, tmin, tmax, leaf_size):
    n = cent.shape[0]
    order = np.arange(n).astype(np.int32)
    max_nodes = 2 * n + 1
    bmin = np.empty((max_nodes, 3))
    bmax = np.empty((max_nodes, 3))
    left = np.full(max_nodes, -1, np.int32)
    right = np.full(max_nodes, -1, np.int32)
    start = np.zeros(max_nodes, np.int32)
    count = np.zeros(max_nodes, np.int32)
    # stack of (node, lo, hi)
    stack = np.empty((max_nodes, 3), np.int64)
    sp = 0
    stack[0, 0] = 0
    stack[0, 1] = 0
    stack[0, 2] = n
    sp = 1
    nodes = 1
    while sp > 0:
        sp -= 1
        node, lo, hi = stack[sp, 0], stack[sp, 1], stack[sp, 2]
        for k in range(3):
            mn = 1e300
            mx = -1e300
            for i in range(lo, hi):
                t = order[i]
                if tmin[t, k] < mn:
                    mn = tmin[t, k]
                if tmax[t, k] > mx:
                    mx = tmax[t, k]
            bmin[node, k] = mn
            bmax[node, k] = mx
        if hi - lo <= leaf_size:
            start[node] = lo
            count[node] = hi - lo
            continue
        # binned surface-area heuristic on the longest axis of the centroid bounds (median split as fallback)
        best_axis = 0
        best_ext = -1.0
        cmin = np.empty(3)
        for k in range(3):
            mn = 1e300
            mx = -1e300
            for i in range(lo, hi):
                c = cent[order[i], k]
                mn = min(mn, c)
                mx = max(mx, c)
            cmin[k] = mn
            if mx - mn > best_ext:
                best_ext = mx - mn
                best_axis = k
        keys = np.empty(hi - lo)
        for i in range(lo, hi):
            keys[i - lo] = cent[order[i], best_axis]
        idx = np.argsort(keys, kind="mergesort")
        sub = order[lo:hi].copy()
        for i in range(hi - lo):
            order[lo + i] = sub[idx[i]]
        mid = (lo + hi) // 2
        if best_ext > 0:
            nbins = 16
            bcount = np.zeros(nbins, np.int64)
            bl = np.full((nbins, 3), 1e300)
            bh = np.full((nbins, 3), -1e300)
            for i in range(lo, hi):
                t = order[i]
                bi = min(int((cent[t, best_axis] - cmin[best_axis]) / best_ext * nbins), nbins - 1)
                bcount[bi] += 1
                for k in range(3):
                    bl[bi, k] = min(bl[bi, k], tmin[t, k])
                    bh[bi, k] = max(bh[bi, k], tmax[t, k])
            best_cost = 1e300
            best_split = -1
            for sidx in range(1, nbins):
                nl = 0
                nr = 0
                ll = np.full(3, 1e300)
                lh = np.full(3, -1e300)
                rl = np.full(3, 1e300)
                rh = np.full(3, -1e300)
                for bi in range(nbins):
                    if bcount[bi] == 0:
                        continue
                    if bi < sidx:
                        nl += bcount[bi]
                        for k in range(3):
                            ll[k] = min(ll[k], bl[bi, k])
                            lh[k] = max(lh[k], bh[bi, k])
                    else:
                        nr += bcount[bi]
                        for k in range(3):
                            rl[k] = min(rl[k], bl[bi, k])
                            rh[k] = max(rh[k], bh[bi, k])
                if nl == 0 or nr == 0:
                    continue
                dl = lh - ll
                dr = rh - rl
                cost = nl * (dl[0] * dl[1] + dl[1] * dl[2] + dl[2] * dl[0]) + nr * (dr[0] * dr[1] + dr[1] * dr[2] + dr[2] * dr[0])
                if cost < best_cost:
                    best_cost = cost
                    best_split = nl
            if best_split > 0:
                mid = lo + best_split  # order is sorted along the axis, bins are contiguous in it
        l_node = nodes
        r_node = nodes + 1
        nodes += 2
        left[node] = l_node
        right[node] = r_node
        stack[sp, 0] = l_node
        stack[sp, 1] = lo
        stack[sp, 2] = mid
        sp += 1
        stack[sp, 0] = r_node
        stack[sp, 1] = mid
        stack[sp, 2] = hi
        sp += 1
    return bmin[:nodes], bmax[:nodes], left[:nodes], right[:nodes], start[:nodes], count[:nodes], order


def build_bvh(vertices: np.ndarray, faces: np.ndarray) -> BVH:
    """BVH over triangles ``vertices[faces]`` (binned SAH split, 4 triangles per leaf)."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if len(F) == 0:
        raise ValueError("cannot build a BVH over an empty mesh")
    tri = V[F]  # (T, 3, 3)
    tmin = tri.min(axis=1)
    tmax = tri.max(axis=1)
    cent = tri.mean(axis=1)
    bmin, bmax, left, right, start, count, order = _build(cent, tmin, tmax, _LEAF_SIZE)
    v0 = np.ascontiguousarray(tri[:, 0])
    return BVH(bmin, bmax, left, right, start, count, order, v0,
               np.ascontiguousarray(tri[:, 1] - tri[:, 0]), np.ascontiguousarray(tri[:, 2] - tri[:, 0]))


@nb.njit(cache=True, inline="always")
def _ray_box(ox, oy, oz, ix, iy, iz, bmin, bmax, node, tbest):
    t1 = (bmin[node, 0] - ox) * ix
    t2 = (bmax[node, 0] - ox) * ix
    tn = min(t1, t2)
    tf = max(t1, t2)
    t1 = (bmin[node, 1] - oy) * iy
    t2 = (bmax[node, 1] - oy) * iy
    tn = max(tn, min(t1, t2))
    tf = min(tf, max(t1, t2))
    t1 = (bmin[node, 2] - oz) * iz
    t2 = (bmax[node, 2] - oz) * iz
    tn = max(tn, min(t1, t2))
    tf = min(tf, max(t1, t2))
    if tf >= max(tn, 0.0) and tn < tbest:
        return tn
    return np.inf


@nb.njit(cache=True, parallel=True, fastmath=False)
def _trace(orig, dirs, tmin_ray, tmax_ray, bmin, bmax, left, right, start, count, order, v0, e1, e2,
           out_t, out_tri, out_u, out_v):
    n = orig.shape[0]
    for r in nb.prange(n):
        ox, oy, oz = orig[r, 0], orig[r, 1], orig[r, 2]
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        ix = 1.0 / dx if dx != 0.0 else 1e300
        iy = 1.0 / dy if dy != 0.0 else 1e300
        iz = 1.0 / dz if dz != 0.0 else 1e300
        best = tmax_ray
        best_tri = -1
        bu = 0.0
        bv = 0.0
        stack = np.empty(64, np.int32)
        sp = 0
        if _ray_box(ox, oy, oz, ix, iy, iz, bmin, bmax, 0, best) < np.inf:
            stack[0] = 0
            sp = 1
        while sp > 0:
            sp -= 1
            node = stack[sp]
            c = count[node]
            if c > 0:
                s = start[node]
                for j in range(s, s + c):
                    t = order[j]
                    # Moller-Trumbore
                    px = dy * e2[t, 2] - dz * e2[t, 1]
                    py = dz * e2[t, 0] - dx * e2[t, 2]
                    pz = dx * e2[t, 1] - dy * e2[t, 0]
                    det = e1[t, 0] * px + e1[t, 1] * py + e1[t, 2] * pz
                    if abs(det) < 1e-14:
                        continue
                    inv = 1.0 / det
                    sx = ox - v0[t, 0]
                    sy = oy - v0[t, 1]
                    sz = oz - v0[t, 2]
                    u = (sx * px + sy * py + sz * pz) * inv
                    if u < 0.0 or u > 1.0:
                        continue
                    qx = sy * e1[t, 2] - sz * e1[t, 1]
                    qy = sz * e1[t, 0] - sx * e1[t, 2]
                    qz = sx * e1[t, 1] - sy * e1[t, 0]
                    v = (dx * qx + dy * qy + dz * qz) * inv
                    if v < 0.0 or u + v > 1.0:
                        continue
                    tt = (e2[t, 0] * qx + e2[t, 1] * qy + e2[t, 2] * qz) * inv
                    if tt > tmin_ray and tt < best:
                        best = tt
                        best_tri = t
                        bu = u
                        bv = v
                continue
            a = left[node]
            b = right[node]
            ta = _ray_box(ox, oy, oz, ix, iy, iz, bmin, bmax, a, best)
            tb = _ray_box(ox, oy, oz, ix, iy, iz, bmin, bmax, b, best)
            # push the far child first so the near one is popped first
            if ta <= tb:
                if tb < np.inf:
                    stack[sp] = b
                    sp += 1
                if ta < np.inf:
                    stack[sp] = a
                    sp += 1
            else:
                if ta < np.inf:
                    stack[sp] = a
                    sp += 1
                if tb < np.inf:
                    stack[sp] = b
                    sp += 1
        out_t[r] = best if best_tri >= 0 else np.inf
        out_tri[r] = best_tri
        out_u[r] = bu
        out_v[r] = bv


def trace(bvh: BVH, origins: np.ndarray, dirs: np.ndarray, tmin: float = 1e-6, tmax: float = 1e9):
    """Nearest hit of each ray. ``origins`` (N,3) or (3,), ``dirs`` (N,3) (any length; t is in units of |dir|).

    Returns ``(t, tri, u, v)``: hit distance along ``dirs`` (inf on a miss), triangle id (-1 on a miss)
    and barycentric coordinates of the hit (``p = v0 + u*e1 + v*e2``).
    """
    dirs = np.ascontiguousarray(dirs, dtype=np.float64).reshape(-1, 3)
    origins = np.asarray(origins, dtype=np.float64)
    if origins.ndim == 1:
        origins = np.broadcast_to(origins, dirs.shape)
    # C-ordered and writable whatever came in (one ray's broadcast origin is a read-only view: the kernel compiled a
    # signature of its own for it)
    origins = np.require(origins.reshape(-1, 3), np.float64, ["C", "W"])
    n = dirs.shape[0]
    t = np.empty(n)
    tri = np.empty(n, np.int32)
    u = np.empty(n)
    v = np.empty(n)
    _trace(origins, dirs, float(tmin), float(tmax), bvh.bmin, bvh.bmax, bvh.left, bvh.right, bvh.start,
           bvh.count, bvh.order, bvh.v0, bvh.e1, bvh.e2, t, tri, u, v)
    return t, tri, u, v
