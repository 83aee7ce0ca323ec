"""Floating points: returns that lie on no surface, dropped before a scan is rendered.

A LiDAR beam that straddles a range edge (the silhouette of a desk against the wall 2 m behind it) returns a range
between the two surfaces: a *mixed pixel*. Every silhouette so trails a sparse curtain of points in mid-air, as do
dust and people walking past. Scanner software filters most of them, not all. They harm the renderer more than their
number says: a floating point is the nearest thing in its pixel, so it paints its colour and depth over the surface
behind, and the hierarchical depth filter then takes it for foreground and removes the true surface around it as
"background seen through a hole". Measured (`benchmarks/RESULTS.md`, stop 61: the office walk through a scan with 30 %
of its edge returns mixed, 0.36 % of the points): Render & Match 270/300 at 0.34 cm / 0.054°; the scan with the points
this drops, 278 at 0.20 cm / 0.036° (the perfect scan: 281 at 0.19 / 0.030; cleaned, 279 at 0.21 / 0.040).

The test is density against what a surface would have there: a point on a surface has neighbours at the scanner's
ray spacing in every direction; a floating one has few. The spacing grows with the distance from the station, so the
radius searched is ``spacings`` ray spacings at the distance to the nearest station (the angular step read from the
scan itself: the median nearest-neighbour distance over range), never less than ``min_radius_m`` (range noise); a
point with fewer than ``min_neighbours`` others inside is floating. A scan without stations gets one radius,
``spacings`` median nearest-neighbour distances. Spatial tiles bound the memory (one k-d tree per tile).
"""

from __future__ import annotations

import logging

import numpy as np

from services.io.scan import Scan
from services.log import progress

__all__ = ["floating_points", "drop_floating"]

log = logging.getLogger(__name__)


def _nearest_station_range(xyz: np.ndarray, stations: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    return cKDTree(stations).query(xyz, k=1)[0]


def floating_points(scan: Scan, spacings: float = 5.0, min_neighbours: int = 3, min_radius_m: float = 0.01,
                    tile_m: float = 4.0, sample: int = 200_000, workers: int = -1, seed: int = 0) -> np.ndarray:
    """(N,) bool: the points with fewer than ``min_neighbours`` others within their radius (see the module)."""
    from scipy.spatial import cKDTree

    n = len(scan)
    if n < 2:
        return np.zeros(n, bool)
    xyz = scan.xyz  # float32, local frame (the stations are moved into it below)
    st = np.array([s.t for s in scan.stations], np.float64).reshape(-1, 3) - scan.origin
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(n, size=min(n, sample), replace=False))
    probe = cKDTree(xyz[rng.choice(n, size=min(n, 20 * sample), replace=False)])  # the spacing, from a subset's ...
    d1 = probe.query(xyz[pick], k=2, workers=workers)[0][:, 1] * np.sqrt(min(n, 20 * sample) / n)  # ... rescaled
    if len(st):
        step = float(np.median(d1 / np.maximum(_nearest_station_range(xyz[pick], st), 0.1)))
        log.info("floating points: ray spacing %.3f deg at the nearest station", np.degrees(step))
    else:
        step = None
        fixed = max(min_radius_m, spacings * float(np.median(d1)))
        log.info("floating points: no stations, one radius %.3f m", fixed)

    # tiles in x-y, each searched with the tiles around it (a radius never exceeds a tile)
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    ny = int((hi[1] - lo[1]) // tile_m) + 3
    key = np.empty(n, np.int64)
    for a in range(0, n, 10_000_000):  # in chunks: a survey scan's 300 M points would need GBs of temporaries at once
        ij = np.floor((xyz[a:a + 10_000_000, :2] - lo) / np.float32(tile_m)).astype(np.int64)
        key[a:a + 10_000_000] = (ij[:, 0] + 1) * ny + (ij[:, 1] + 1)  # (a ring of empty tiles around: no edge cases)
    order = np.argsort(key, kind="stable")
    keys, starts = np.unique(key[order], return_index=True)
    tiles = dict(zip(keys.tolist(), np.split(order, starts[1:])))
    floating = np.zeros(n, bool)
    for k, idx in progress(tiles.items(), desc="floating points", total=len(tiles), unit="tile"):
        pts = xyz[idx]
        if step is not None:
            radius = np.minimum(tile_m, np.maximum(min_radius_m, spacings * step * _nearest_station_range(pts, st)))
        else:
            radius = np.full(len(idx), min(tile_m, fixed))
        near = np.concatenate([tiles.get(k + dx * ny + dy, np.zeros(0, np.int64)) for dx in (-1, 0, 1) for dy in (-1, 0, 1)])
        # only the points around it within its largest radius (not all nine tiles: each point was in nine trees)
        r_max = float(radius.max())
        lo_t, hi_t = pts.min(axis=0) - r_max, pts.max(axis=0) + r_max
        near = near[np.all((xyz[near] >= lo_t) & (xyz[near] <= hi_t), axis=1)]
        # floating = fewer than min_neighbours others within the radius = the min_neighbours-th nearest other is beyond
        # it (k nearest, not every point in the ball counted: a surface point has ~80 there)
        k_th = min(min_neighbours + 1, len(near))  # (the point itself is the nearest)
        d = cKDTree(xyz[near]).query(pts, k=k_th, workers=workers)[0].reshape(len(pts), -1)
        floating[idx] = d[:, -1] > radius if k_th == min_neighbours + 1 else True
    if floating.mean() > 0.02:
        log.warning("floating points: %.1f %% of the scan has fewer than %d neighbours within %g ray spacings: more than "
                    "mixed pixels make; parts of it may be scanned only from far stations (check before dropping)",
                    100.0 * floating.mean(), min_neighbours, spacings)
    log.info("floating points: %d of %d (%.2f %%)", floating.sum(), n, 100.0 * floating.mean())
    return floating


def drop_floating(scan: Scan, **kw) -> Scan:
    """The scan without its floating points (``floating_points``); ``meta`` records how many went."""
    f = floating_points(scan, **kw)
    out = scan.subset(np.flatnonzero(~f))
    out.meta["floating_dropped"] = int(f.sum())
    return out
