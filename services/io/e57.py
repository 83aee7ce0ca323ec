"""E57 reader (pye57/libE57): every scan of the file, moved into the common world frame.

Each E57 scan stores points in its scanner's frame plus a pose (rotation quaternion
w, x, y, z and a translation) mapping them to the file's frame: ``X_world = R X_scan + t``.
We apply it per chunk, concatenate all scans and record each pose as a ``Pose``
(scanner-to-world) in ``scan.stations``. Cartesian and spherical coordinates are read;
points flagged invalid by the scanner are dropped and counted in ``meta["dropped_invalid"]``. A scan without colour
gets grey levels from its ``intensity`` field (``services.io.scans.PointSink``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from services.geometry.se3 import Pose
from services.io.scan import Scan, ScanError
from services.io.scans import ColourChoice, PointSink
from services.log import progress

__all__ = ["read_e57"]

log = logging.getLogger(__name__)

E57_CHUNK = 1_000_000
CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
COLOURS = ("colorRed", "colorGreen", "colorBlue")
INTENSITY = "intensity"


def read_e57(path: Path) -> Scan:
    import pye57
    from pye57 import libe57

    with pye57.E57(str(path)) as e57:
        headers = [e57.get_header(i) for i in range(e57.scan_count)]
        if not headers:
            raise ScanError(f"{path}: the E57 file contains no scans (data3D is empty)")
        has_colour = [all(c in h.point_fields for c in COLOURS) for h in headers]
        if any(has_colour) and not all(has_colour):
            log.warning("%s: %d of %d E57 scans have no colour; their points are grey (from intensity where they have "
                        "it)", path, has_colour.count(False), len(headers))
        sink = PointSink(sum(h.point_count for h in headers))
        stations, invalid, counts = [], 0, []
        for i, h in enumerate(headers):
            pose = _pose(h) if h.has_pose() else Pose.identity()
            stations.append(pose)
            before = sink.n
            dropped, has_colour[i] = _read_one(e57, libe57, h, pose, sink, f"{path.name} scan {i + 1}/{len(headers)}",
                                               has_colour[i])
            invalid += dropped
            counts.append(sink.n - before)
    if invalid:
        log.info("%s: dropped %d points the scanner flagged invalid", path, invalid)
    return sink.scan(path, "e57", stations, has_color=any(has_colour), dropped_invalid=invalid, e57_scans=len(headers),
                     station_points=counts)


def _pose(h) -> Pose:
    """E57 pose: quaternion (w, x, y, z) and translation, scanner-to-world; read by name (child order is free)."""
    node = h.node["pose"]
    q = [node["rotation"][k].value() for k in "xyzw"] if node.isDefined("rotation") else [0.0, 0.0, 0.0, 1.0]
    t = [node["translation"][k].value() for k in "xyz"] if node.isDefined("translation") else [0.0, 0.0, 0.0]
    return Pose.from_quat_t(q, t)


def _read_one(e57, libe57, h, pose: Pose, sink: PointSink, desc: str, colour: bool) -> tuple[int, bool]:
    """Stream one E57 scan into ``sink``; returns the number of invalid points dropped, and whether its colour was
    kept (not blank)."""
    fields = h.point_fields
    coords = CARTESIAN if all(c in fields for c in CARTESIAN) else SPHERICAL if all(c in fields for c in SPHERICAL) else None
    if coords is None:
        raise ScanError(f"scan '{h.node['name'].value() if 'name' in h.scan_fields else '?'}' has neither cartesian "
                        f"nor spherical coordinates (fields: {', '.join(fields)})")
    grey = INTENSITY in fields  # where no pictures were taken (no or blank colour): grey from the laser's intensity
    names = list(coords) + (list(COLOURS) if colour else []) + ([INTENSITY] if grey else [])
    choice = ColourChoice(desc)
    state = "cartesianInvalidState" if coords is CARTESIAN else "sphericalInvalidState"
    if state in fields:
        names.append(state)
    # Every field is read as float64 (doConversion; doScaling applies ScaledInteger factors). Not int64: pye57's
    # binding takes numpy's 'l' (int64 on Linux) for a 32-bit type and scrambles such buffers.
    bufs = {n: np.empty(E57_CHUNK, np.float64) for n in names}
    vec = libe57.VectorSourceDestBuffer()
    for n in names:
        vec.append(libe57.SourceDestBuffer(e57.image_file, n, bufs[n], E57_CHUNK, True, True))
    cmax = _colour_max(h) if colour else 255.0
    R, t = pose.R, pose.t
    reader = h.points.reader(vec)
    invalid = 0
    try:
        chunks = iter(reader.read, 0)  # read() fills the buffers and returns the count, 0 at the end
        for m in progress(chunks, desc=f"reading {desc}", total=-(-h.point_count // E57_CHUNK), unit="chunk"):
            keep = slice(None) if state not in bufs else bufs[state][:m] == 0
            c = [bufs[n][:m][keep] for n in coords]
            invalid += m - len(c[0])
            local = np.stack(c, axis=1) if coords is CARTESIAN else _spherical_to_cartesian(*c)
            rgb = None
            if colour:
                rgb = np.stack([bufs[n][:m][keep] for n in COLOURS], axis=1)
                rgb = np.clip(np.rint(rgb * (255.0 / cmax)), 0, 255).astype(np.uint8)
            sink.add(local @ R.T + t, *choice.pick(rgb, bufs[INTENSITY][:m][keep] if grey else None))
    finally:
        reader.close()
    return invalid, colour and not choice.use_intensity


def _spherical_to_cartesian(r: np.ndarray, azimuth: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """E57 spherical (range, azimuth, elevation; radians) to the scanner's cartesian frame."""
    rc = r * np.cos(elevation)
    return np.stack([rc * np.cos(azimuth), rc * np.sin(azimuth), r * np.sin(elevation)], axis=1)


def _colour_max(h) -> float:
    """The colour range's maximum from ``colorLimits`` (255 for 8-bit, 65535 for 16-bit); 255 when absent."""
    try:
        return max(float(h.node["colorLimits"][k].value()) for k in ("colorRedMaximum", "colorGreenMaximum", "colorBlueMaximum")) or 255.0
    except Exception:  # no colorLimits node: assume 8-bit
        return 255.0
