"""Where a camera can be: sample positions in free space inside a scan's region of interest.

Default region: derived from the scan itself. A grid of (x, y) positions at ``spacing`` over the
scan's footprint; at each, the floor is the lowest scan point nearby and the candidate sits at
typical camera heights above it; a candidate is kept when it is at least ``margin`` from every
scan point (free space) and, when the scan knows its stations, in the line of sight of one (so
it is inside scanned space, not inside a closed cabinet) and within ``station_dz`` in height of a
station (not on top of a rack whose footprint shows no floor: the simulated warehouse had 3-5 positions
9.5 m up, on its 8 m racks). A box (x, y, z ranges) or a polygon (a floor-plan outline in world x, y;
heights still above the local floor) may restrict it. Shared by the relocalization database and the Prebuild & Localize map builder.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from services.io.scan import Scan, level_warning

__all__ = ["RoiConfig", "sample_positions"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RoiConfig:
    spacing: float = 1.0  # metres between grid positions
    heights: tuple[float, ...] = (1.5,)  # above the local floor
    margin: float = 0.5  # free space around each position
    box: tuple[float, float, float, float, float, float] | None = None  # x0 y0 z0 x1 y1 z1 (world); heights ignored
    polygon: tuple[tuple[float, float], ...] | None = None  # floor-plan outline (world x, y), >= 3 vertices
    station_dz: float = 2.0  # when the scan knows its stations: a position further above or below every station's
    #                          height than this is not where a camera goes (the top of a rack, a shelf); each floor
    #                          of a building scanned from stations on it keeps its positions

    def __post_init__(self) -> None:
        if self.spacing <= 0 or self.margin < 0:
            raise ValueError(f"spacing must be > 0 and margin >= 0 (got {self.spacing}, {self.margin})")
        if self.box is not None and not all(a < b for a, b in zip(self.box[:3], self.box[3:])):
            raise ValueError(f"box {self.box}: each of x0 y0 z0 must be below x1 y1 z1")
        if self.polygon is not None and len(self.polygon) < 3:
            raise ValueError("a polygon needs at least 3 vertices")


def _voxel_points(scan: Scan, voxel: float = 0.05, max_points: int = 2_000_000) -> np.ndarray:
    xyz = scan.xyz
    if len(xyz) > max_points:
        xyz = xyz[np.random.default_rng(0).choice(len(xyz), max_points, replace=False)]
    q = np.unique(np.floor(xyz / voxel).astype(np.int64), axis=0)
    return (q + 0.5) * voxel


def sample_positions(scan: Scan, cfg: RoiConfig = RoiConfig()) -> np.ndarray:
    """World positions (N, 3) in free space inside the region of interest, on a uniform grid."""
    from scipy.spatial import cKDTree

    why = level_warning(scan)
    if why:
        log.warning(why)

    pts = _voxel_points(scan)  # scan-local coordinates
    tree = cKDTree(pts)
    lo, hi = pts.min(0), pts.max(0)
    if cfg.box is not None:
        b = np.asarray(cfg.box, float) - np.concatenate([scan.origin, scan.origin])
        lo, hi = np.maximum(lo, b[:3]), np.minimum(hi, b[3:])
    xs = np.arange(lo[0] + cfg.spacing / 2, hi[0], cfg.spacing)
    ys = np.arange(lo[1] + cfg.spacing / 2, hi[1], cfg.spacing)
    cand = []
    if cfg.box is not None:
        zs = np.arange(lo[2] + cfg.spacing / 2, hi[2], cfg.spacing) if hi[2] - lo[2] > cfg.spacing else [(lo[2] + hi[2]) / 2]
        cand = [(x, y, z) for x in xs for y in ys for z in zs]
    else:
        # floor: lowest point within a 0.5 m column around each grid position
        cell = 0.5
        key = np.floor(pts[:, :2] / cell).astype(np.int64)
        order = np.lexsort((pts[:, 2], key[:, 1], key[:, 0]))
        k = key[order]
        first = np.ones(len(k), bool)
        first[1:] = np.any(k[1:] != k[:-1], axis=1)
        floor = {tuple(kk): z for kk, z in zip(k[first], pts[order][first, 2])}
        for x in xs:
            for y in ys:
                z0 = floor.get((int(np.floor(x / cell)), int(np.floor(y / cell))))
                if z0 is None:
                    continue
                cand += [(x, y, z0 + h) for h in cfg.heights]
    cand = np.asarray(cand, float).reshape(-1, 3)
    if cfg.polygon is not None and len(cand):
        import cv2

        poly = (np.asarray(cfg.polygon, np.float64) - scan.origin[:2]).astype(np.float32).reshape(-1, 1, 2)
        inside = [cv2.pointPolygonTest(poly, (float(x), float(y)), False) >= 0 for x, y in cand[:, :2]]
        cand = cand[np.asarray(inside, bool)]
    if len(cand) == 0:
        return cand
    d, _ = tree.query(cand)
    keep = d >= cfg.margin
    if scan.stations:
        stations = np.array([s.t - scan.origin for s in scan.stations])
        if cfg.box is None:
            keep &= np.abs(cand[:, 2:3] - stations[None, :, 2]).min(1) <= cfg.station_dz
        keep &= np.array([_visible(tree, c, stations) if k else False for c, k in zip(cand, keep)])
    out = cand[keep] + scan.origin
    log.info("region of interest: %d of %d grid positions in free space (spacing %.2f m)", len(out), len(cand), cfg.spacing)
    return out


def _visible(tree, c: np.ndarray, stations: np.ndarray, clearance: float = 0.08) -> bool:
    """True when the straight line to at least one station passes no scan point closer than ``clearance``."""
    for s in stations:
        n = max(2, int(np.linalg.norm(s - c) / 0.05))
        seg = c + (s - c) * np.linspace(0, 1, n)[:, None]
        d, _ = tree.query(seg[:-2] if n > 3 else seg)
        if (d > clearance).all():
            return True
    return False
