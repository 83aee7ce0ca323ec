"""The in-memory scan: float32 xyz relative to a float64 origin, uint8 rgb.

``world = xyz.astype(float64) + origin``. Survey coordinates are large (e.g. UTM
eastings of 10^5..10^6 m), so float32 alone would lose millimetres; the origin keeps
them exact while the bulk data stays 15 bytes per point.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.geometry.se3 import Pose

__all__ = ["Scan", "ScanError", "level_warning"]


class ScanError(ValueError):
    """A scan file that cannot be used; the message names the file and the problem."""


@dataclass
class Scan:
    xyz: np.ndarray  # (N, 3) float32, relative to ``origin``
    rgb: np.ndarray  # (N, 3) uint8
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) float64, world coordinates of xyz == 0
    stations: list[Pose] = field(default_factory=list)  # scanner poses T_w_scanner in world, when the file has them
    source: Path | None = None
    meta: dict = field(default_factory=dict)  # e.g. {"dropped_nonfinite": 12, "format": "ply"}

    def __post_init__(self) -> None:
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float32)
        self.rgb = np.ascontiguousarray(self.rgb, dtype=np.uint8)
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise ScanError(f"xyz must be (N, 3), got {self.xyz.shape}")
        if self.rgb.shape != self.xyz.shape:
            raise ScanError(f"rgb must match xyz {self.xyz.shape}, got {self.rgb.shape}")

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def world_xyz(self, index: np.ndarray | slice | None = None) -> np.ndarray:
        """Points in the world (scan) frame, float64. Pass an index to avoid converting everything."""
        xyz = self.xyz if index is None else self.xyz[index]
        return xyz.astype(np.float64) + self.origin

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners in world coordinates."""
        if len(self) == 0:
            raise ScanError("empty scan has no bounds")
        return self.xyz.min(axis=0).astype(np.float64) + self.origin, self.xyz.max(axis=0).astype(np.float64) + self.origin

    def subset(self, index: np.ndarray) -> "Scan":
        """The points at ``index``; its meta no longer names the file's cache (a decimated scan kept its render order
        there, over the full scan's, which the next full load then recomputed)."""
        meta = {k: v for k, v in self.meta.items() if k not in ("cache_dir", "from_cache", "station_points")}
        counts = _subset_counts(self.meta.get("station_points"), index, len(self))
        if counts is not None:
            meta["station_points"] = counts
        return Scan(self.xyz[index], self.rgb[index], self.origin.copy(), list(self.stations), self.source, meta)


def _subset_counts(counts: list[int] | None, index, n: int) -> list[int] | None:
    """Each station's points (``meta["station_points"]``) after ``Scan.subset(index)``: kept for a mask or increasing
    indices (the order kept), None otherwise."""
    if counts is None or sum(counts) != n:
        return None
    edges = np.concatenate([[0], np.cumsum(counts)])
    index = np.asarray(index)
    if index.dtype == bool and index.shape == (n,):
        return [int(np.count_nonzero(index[a:b])) for a, b in zip(edges[:-1], edges[1:])]
    if index.ndim == 1 and index.dtype.kind in "iu" and (len(index) < 2 or bool(np.all(index[1:] > index[:-1]))):
        return np.diff(np.searchsorted(index, edges)).tolist()
    return None


def level_warning(scan: Scan, max_tilt_deg: float = 30.0) -> str | None:
    """Why the scan looks exported on its side, or None. A scanner stands levelled, its z axis up; when every station
    of a scan has its z axis over ``max_tilt_deg`` from the world's z (a registration exported y-up), positions set
    above the floor along z and views levelled to z face walls and floors, and nothing matches. Stations with no
    pose (identity) say nothing; nor does a scan without stations."""
    if not scan.stations:
        return None
    ups = np.array([s.R[:, 2] for s in scan.stations])
    tilt = np.degrees(np.arccos(np.clip(ups[:, 2], -1.0, 1.0)))
    if not (tilt > max_tilt_deg).all():
        return None
    mean = ups.mean(axis=0)
    k = int(np.argmax(np.abs(mean)))
    axis = ("-" if mean[k] < 0 else "+") + "xyz"[k]
    return (f"the scan's {len(ups)} station(s) stand {tilt.min():.0f}-{tilt.max():.0f} deg from upright: their up axis "
            f"is the world's {axis}, not +z. cristal takes z as up (camera heights above the floor, levelled views); "
            f"export the registration z-up, as levelled scanners record it")
