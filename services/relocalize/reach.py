"""Where a camera can have walked: a floor plan of the scan's obstacles, and the distance between two places through
free space (numpy + OpenCV).

A relocalization near a recent pose accepts places within the distance the camera can have covered since. In a
warehouse of identical aisles the next aisle over is a few metres away in a straight line but much further on foot:
the racks between them reach from the floor to above head height. Render & Match uses this to refuse a relocalized
pose that the camera could not have walked to (simulated warehouse seed 3: frame 288, 2.3 s after a pose in its
own aisle, fitted the next aisle 6.3 m over as well as its own, and was tracked there for 77 frames).

The plan is a grid of ``cell`` metres over the scan's footprint. A cell is blocked when scan points in it stand
between ``low`` and ``high`` metres above the local floor (the lowest point within ``floor_radius``): shelves, walls,
desks. Parts the scan did not see count as free, so a gap in the scan never makes a place unreachable. The walk
grows by one cell a step, in 8 directions and in 4 on alternate steps (the octagonal distance: at most 6 % shorter
than the shortest walk, never longer, so a place it calls out of reach is).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["FloorPlan"]


@dataclass
class FloorPlan:
    blocked: np.ndarray  # (H, W) bool, row = y, column = x
    origin: np.ndarray  # world (x, y) of cell (0, 0)'s corner
    cell: float  # metres

    @classmethod
    def from_points(cls, xyz: np.ndarray, offset=(0.0, 0.0, 0.0), cell: float = 0.2, low: float = 0.3,
                    high: float = 1.9, floor_radius: float = 1.0, max_points: int = 4_000_000, seed: int = 0) -> "FloorPlan":
        """The plan of scan points ``xyz`` (N, 3; world = xyz + ``offset``, z up: services.io.scan.Scan's xyz and
        origin, so survey coordinates keep their precision)."""
        xyz = np.asarray(xyz, np.float32)
        if len(xyz) > max_points:
            xyz = xyz[np.random.default_rng(seed).choice(len(xyz), max_points, replace=False)]
        offset = np.asarray(offset, np.float64).reshape(3)[:2]
        if len(xyz) == 0:
            return cls(np.zeros((1, 1), bool), offset.copy(), cell)
        lo = xyz[:, :2].min(axis=0) - cell
        ij = np.floor((xyz[:, :2] - lo) / cell).astype(np.int64)
        h, w = int(ij[:, 1].max()) + 2, int(ij[:, 0].max()) + 2
        zmin = np.full((h, w), np.inf, np.float32)
        np.minimum.at(zmin, (ij[:, 1], ij[:, 0]), xyz[:, 2])
        k = 2 * int(math.ceil(floor_radius / cell)) + 1
        big = float(xyz[:, 2].max()) + 100.0
        floor = cv2.erode(np.where(np.isfinite(zmin), zmin, big).astype(np.float32), np.ones((k, k), np.uint8))
        above = xyz[:, 2] - floor[ij[:, 1], ij[:, 0]]
        blocked = np.zeros((h, w), bool)
        s = (above > low) & (above < high)
        blocked[ij[s, 1], ij[s, 0]] = True
        return cls(blocked, offset + lo.astype(np.float64), cell)

    def _cell(self, p: np.ndarray) -> tuple[int, int]:
        c = np.floor((np.asarray(p, np.float64)[:2] - self.origin) / self.cell).astype(int)
        return int(c[1]), int(c[0])

    def walkable_within(self, a: np.ndarray, b: np.ndarray, max_m: float, clearance: float = 0.3) -> bool:
        """Whether a walk through free space from ``a`` to ``b`` (world points; z ignored) of at most ``max_m`` exists.
        Cells within ``clearance`` of either end count as free (a camera stands close to a shelf)."""
        if np.linalg.norm(np.asarray(b, float)[:2] - np.asarray(a, float)[:2]) > max_m:
            return False
        steps = int(math.ceil(max_m / self.cell))
        (ra, ca), (rb, cb) = self._cell(a), self._cell(b)
        r0, c0 = ra - steps - 1, ca - steps - 1  # a window around a that holds every cell within max_m
        H, W = self.blocked.shape
        win = np.zeros((2 * steps + 3, 2 * steps + 3), bool)  # outside the plan: free (not scanned)
        y0, y1, x0, x1 = max(r0, 0), min(r0 + win.shape[0], H), max(c0, 0), min(c0 + win.shape[1], W)
        if y0 < y1 and x0 < x1:
            win[y0 - r0:y1 - r0, x0 - c0:x1 - c0] = self.blocked[y0:y1, x0:x1]
        free = ~win
        m = int(math.ceil(clearance / self.cell))
        for r, c in ((ra, ca), (rb, cb)):
            free[max(r - r0 - m, 0):r - r0 + m + 1, max(c - c0 - m, 0):c - c0 + m + 1] = True
        tr, tc = rb - r0, cb - c0
        front = np.zeros_like(free, np.uint8)
        front[ra - r0, ca - c0] = 1
        free8 = free.astype(np.uint8)
        square, cross = np.ones((3, 3), np.uint8), cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
        for k in range(steps):
            grown = cv2.dilate(front, square if k % 2 == 0 else cross) & free8
            if grown[tr, tc]:
                return True
            if np.array_equal(grown, front):
                return False
            front = grown
        return bool(front[tr, tc])
