"""PLY reader: binary (little/big endian) or ASCII, float or double xyz, uchar/ushort/float colours (or, without
colour, an intensity property: grey levels from it, ``services.io.scans.PointSink``).

plyfile memory-maps binary files; the vertex table is converted ``CHUNK`` rows at a
time into the preallocated arrays of a ``PointSink``, and the pages already converted
are handed back to the OS, so a 100 M-point file is never resident as a whole or as
float64 copies.
"""

from __future__ import annotations

import logging
import mmap
from pathlib import Path

import numpy as np

from services.geometry.se3 import Pose
from services.io.scan import Scan, ScanError
from services.io.scans import CHUNK, INTENSITY_TAG, STATION_POINTS_TAG, STATION_TAG, ColourChoice, PointSink
from services.log import progress

__all__ = ["read_ply", "to_uint8"]

log = logging.getLogger(__name__)

COLOUR_NAMES = [("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue"), ("r", "g", "b")]
INTENSITY_NAMES = ("intensity", "scalar_intensity", "reflectance", "scalar_reflectance")  # any case (CloudCompare
#                                                                      writes scalar_Intensity): grey where no colour


def read_ply(path: Path) -> Scan:
    """Read the ``vertex`` element of a PLY file; ``comment cristal_station ...`` lines become ``scan.stations``."""
    from plyfile import PlyData

    ply = PlyData.read(str(path), mmap="c")
    if "vertex" not in ply:
        raise ScanError(f"{path}: no 'vertex' element in the PLY header (elements: {[e.name for e in ply.elements]})")
    data = ply["vertex"].data
    names = data.dtype.names or ()
    missing = [a for a in "xyz" if a not in names]
    if missing:
        raise ScanError(f"{path}: the PLY vertices have no {'/'.join(missing)} coordinate (properties: {', '.join(names)})")
    colour = next((c for c in COLOUR_NAMES if all(n in names for n in c)), None)
    lower = {n.lower(): n for n in names}
    intensity = next((lower[n] for n in INTENSITY_NAMES if n in lower), None)
    choice = ColourChoice(path.name)
    stations = [_station(path, c) for c in ply.comments if c.split()[:1] == [STATION_TAG]]

    n = len(data)
    sink = PointSink(n)
    ftype = np.result_type(*(data.dtype[a] for a in "xyz")).newbyteorder("=")
    float_scale: list[float] = []  # decided on the first chunk, then fixed
    for i in progress(range(0, n, CHUNK), desc=f"reading {path.name}", total=-(-n // CHUNK), unit="chunk"):
        rows = data[i:i + CHUNK]
        xyz = np.empty((len(rows), 3), ftype)
        for k, a in enumerate("xyz"):
            xyz[:, k] = rows[a]
        rgb = None if colour is None else np.stack([to_uint8(rows[c], float_scale) for c in colour], axis=1)
        sink.add(xyz, *choice.pick(rgb, None if intensity is None else np.asarray(rows[intensity], np.float32)))
        _release(data)
    counts = _station_points(path, ply.comments)
    if counts is not None and (sink.dropped or sum(counts) != n):
        log.info("%s: station point counts dropped (%d points in the file, %d dropped as non-finite)", path,
                 n, sink.dropped)
        counts = None
    extra = {} if counts is None else {"station_points": counts}
    grey = _intensity_share(path, ply.comments) if colour is not None and not choice.use_intensity else 0.0
    if grey:  # written by cristal from a colourless scan: its grey levels came from the laser's intensity
        extra["intensity_grey"] = int(round(grey * sink.n))
    return sink.scan(path, "ply", stations, has_color=colour is not None and not choice.use_intensity, **extra)


def _intensity_share(path: Path, comments: list[str]) -> float:
    for c in comments:
        if c.split()[:1] == [INTENSITY_TAG]:
            try:
                return min(1.0, max(0.0, float(c.split()[1])))
            except (ValueError, IndexError):
                log.warning("%s: ignoring a bad '%s' comment", path, INTENSITY_TAG)
    return 0.0


def _station_points(path: Path, comments: list[str]) -> list[int] | None:
    for c in comments:
        if c.split()[:1] == [STATION_POINTS_TAG]:
            try:
                return [int(x) for x in c.split()[1:]]
            except ValueError:
                log.warning("%s: ignoring a bad '%s' comment", path, STATION_POINTS_TAG)
    return None


def to_uint8(v: np.ndarray, float_scale: list[float]) -> np.ndarray:
    """One colour channel to uint8: 8-bit as is, 16-bit scaled (65535 -> 255), floats in 0..1 or 0..255.

    Whether floats are 0..1 is decided on the first chunk seen (max <= 1) and kept in ``float_scale``.
    """
    if v.dtype.kind == "f":
        if not float_scale:
            float_scale.append(255.0 if np.nanmax(v, initial=0.0) <= 1.0 else 1.0)
        return np.clip(np.rint(np.nan_to_num(v) * float_scale[0]), 0, 255).astype(np.uint8)
    if v.dtype.itemsize == 1:
        return v.astype(np.uint8)
    if v.dtype.itemsize == 2:
        return ((v.astype(np.uint32) + 128) // 257).astype(np.uint8)  # round(v / 257): 65535 -> 255
    return np.clip(v, 0, 255).astype(np.uint8)


def _station(path: Path, comment: str) -> Pose:
    try:
        return Pose.from_tum([float(x) for x in comment.split()[1:]])
    except ValueError as e:
        raise ScanError(f"{path}: bad station comment '{comment}' (want '{STATION_TAG} tx ty tz qx qy qz qw'): {e}") from None


def _release(data: np.ndarray) -> None:
    """Drop the memory-mapped pages already read, so resident memory stays at the output arrays.

    Clean file-backed pages are reclaimable anyway; this keeps the process's RSS honest. No-op for
    in-memory (ASCII) data.
    """
    mm = getattr(data, "_mmap", None)
    if isinstance(mm, mmap.mmap) and hasattr(mm, "madvise"):
        try:
            mm.madvise(mmap.MADV_DONTNEED)
        except (OSError, ValueError):  # pragma: no cover - platform without madvise
            pass
