"""LAS/LAZ reader (laspy, lazrs backend for LAZ), streamed with ``chunk_iterator``.

Coordinates are scaled integers in the file; laspy applies scale and offset. LAS colour is
16-bit by the specification, but many writers store 8-bit values: if the first chunk has
any value above 255 the colours are taken as 16-bit and divided by 256, else kept as they are.
A file without colour gets grey levels from its points' intensity (``services.io.scans.PointSink``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.io.scan import Scan, ScanError
from services.io.scans import CHUNK, ColourChoice, PointSink
from services.log import progress

__all__ = ["read_las"]


def read_las(path: Path) -> Scan:
    import laspy

    with laspy.open(str(path)) as f:
        n = int(f.header.point_count)
        dims = set(f.header.point_format.dimension_names)
        colour = {"red", "green", "blue"} <= dims
        intensity = "intensity" in dims  # (every point format has it; a writer may leave it zero)
        choice = ColourChoice(path.name)
        sink = PointSink(n)
        shift = None  # 8 for 16-bit colour, 0 for 8-bit; decided on the first chunk
        for pts in progress(f.chunk_iterator(CHUNK), desc=f"reading {path.name}", total=-(-n // CHUNK), unit="chunk"):
            xyz = np.stack([np.asarray(pts.x), np.asarray(pts.y), np.asarray(pts.z)], axis=1)
            rgb = None
            if colour:
                rgb = np.stack([np.asarray(pts.red), np.asarray(pts.green), np.asarray(pts.blue)], axis=1)
                if shift is None:
                    shift = 8 if len(rgb) and rgb.max() > 255 else 0
                rgb = (rgb >> shift).astype(np.uint8)
            sink.add(xyz, *choice.pick(rgb, np.asarray(pts.intensity) if intensity else None))
    if sink.n + sink.dropped != n:
        raise ScanError(f"{path}: truncated LAS file: the header announces {n} points, the file holds {sink.n + sink.dropped}")
    return sink.scan(path, "las", (), has_color=colour and not choice.use_intensity)
