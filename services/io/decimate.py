"""Thin a scan: a deterministic random subset, or one point per voxel.

Both keep the origin and the stations; ``meta`` records what was done. Vectorised for
10 M+ points: voxels are found by sorting packed integer keys, never by a Python loop.
"""

from __future__ import annotations

import numpy as np

from services.io.scan import Scan, ScanError

__all__ = ["random_decimate", "voxel_decimate"]


def random_decimate(scan: Scan, fraction: float, seed: int = 0) -> Scan:
    """Exactly ``round(fraction * N)`` points drawn without replacement, in their original order; same seed, same subset."""
    if not 0.0 < fraction <= 1.0:
        raise ScanError(f"fraction must be in (0, 1], got {fraction}")
    n = len(scan)
    k = int(round(fraction * n))
    idx = np.sort(np.random.default_rng(seed).choice(n, size=k, replace=False, shuffle=False))
    out = scan.subset(idx)
    out.meta["decimation"] = {"method": "random", "fraction": fraction, "seed": seed, "points_before": n}
    return out


def voxel_decimate(scan: Scan, voxel_size: float) -> Scan:
    """One point per occupied cube of ``voxel_size`` metres (grid anchored at the scan's minimum corner).

    The kept position is the voxel's *measured point nearest to the mean* of its points (so points stay on
    the scanned surfaces, unlike the mean, which cuts corners); its colour is the *mean* colour of the voxel.
    Output order: by voxel key. Cost: one argsort of N int64 keys.
    """
    if not voxel_size > 0:
        raise ScanError(f"voxel size must be positive, got {voxel_size}")
    n = len(scan)
    if n == 0:
        return scan.subset(np.zeros(0, np.int64))
    q = ((scan.xyz - scan.xyz.min(axis=0)) * np.float32(1.0 / voxel_size)).astype(np.int64)  # (N, 3) >= 0, floor
    dims = q.max(axis=0) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
        raise ScanError(f"voxel size {voxel_size} m is too small for a scan of extent {(dims * voxel_size).round(1)} m")
    key = (q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2]
    del q
    order = np.argsort(key, kind="stable")
    key = key[order]
    new = np.r_[True, key[1:] != key[:-1]]  # first point of each voxel, in sorted order
    del key
    gid = np.cumsum(new) - 1  # voxel id of each sorted point
    starts = np.flatnonzero(new)
    inv = np.empty(n, np.int64)
    inv[order] = gid  # voxel id of each point, in the original order
    g = len(starts)
    counts = np.bincount(inv, minlength=g)

    def mean(a: np.ndarray) -> np.ndarray:  # per-voxel mean of each column, float64
        return np.stack([np.bincount(inv, weights=a[:, k], minlength=g) for k in range(3)], axis=1) / counts[:, None]

    d2 = ((scan.xyz - mean(scan.xyz)[inv]) ** 2).sum(axis=1)[order]  # squared distance to the voxel mean, sorted
    best = np.minimum.reduceat(d2, starts)
    hit = np.flatnonzero(d2 == best[gid])  # the nearest point(s) of each voxel, sorted positions
    keep = order[hit[np.r_[True, gid[hit][1:] != gid[hit][:-1]]]]  # ties: the first one
    xyz = scan.xyz[keep]
    rgb = np.rint(mean(scan.rgb))

    meta = {k: v for k, v in scan.meta.items() if k != "station_points"}  # (a voxel's point stands for every station's)
    out = Scan(xyz, rgb.astype(np.uint8), scan.origin.copy(), list(scan.stations), scan.source, meta)
    out.meta["decimation"] = {"method": "voxel", "voxel_size": voxel_size, "points_before": n}
    return out
