"""Load and save LiDAR scans: ``load_scan`` (PLY, E57, LAS/LAZ, cached), ``save_ply``, ``scan_info``.

Every reader streams its file in chunks into one preallocated float32/uint8 pair
(``PointSink``), so a 100 M-point scan is held once at 15 bytes per point, never as
float64 copies. Large survey coordinates are stored relative to an origin rounded to
whole metres (see ``services.io.scan``). After a successful parse the result is cached
beside the file (``services.io.scan_cache``) and memory-mapped on the next load.

Every failure is a ``ScanError`` whose message names the file and the problem.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from services.io.scan import Scan, ScanError

__all__ = ["load_scan", "save_ply", "scan_info", "station_points", "READER_VERSION", "SUFFIXES", "PointSink", "GREY",
           "intensity_scale", "intensity_grey", "INTENSITY_TAG", "ColourChoice"]

log = logging.getLogger(__name__)

# Bump when a reader's output changes: cached results of older readers are then re-parsed.
READER_VERSION = 3  # 2: station_points (each station's points, in file order) in meta; 3: grey from intensity
SUFFIXES = {".ply": "ply", ".e57": "e57", ".las": "las", ".laz": "las"}
CHUNK = 2_000_000  # points converted at a time: bounds the float64 temporaries to ~50 MB
LARGE = 1e4  # coordinates beyond this (metres) get an origin, so float32 keeps millimetres
GREY = 128  # colour given to every point of a scan with neither colour nor intensity when require_color=False
INTENSITY_WHITE = 99.5  # a colourless scan's laser intensity is white from this percentile on ...
INTENSITY_GAMMA = 2.2  # ... and encoded with a camera's gamma below it (services.io.scans.intensity_grey)
STATION_TAG = "cristal_station"  # PLY comment: "cristal_station tx ty tz qx qy qz qw" (scanner-to-world)
STATION_POINTS_TAG = "cristal_station_points"  # comment: how many points each station has, in file order
INTENSITY_TAG = "cristal_intensity_grey"  # comment: the share of the points whose grey came from intensity


class PointSink:
    """Preallocated float32 xyz / uint8 rgb that readers fill chunk by chunk.

    ``add`` drops non-finite points (counted), fixes the origin from the first chunk
    with finite points, and stores ``xyz - origin`` as float32. Points without colour but with
    the laser's intensity (scanners that took no pictures: many E57 and LAS exports) get a grey
    level from it when the scan is made (:func:`intensity_grey`), not the flat ``GREY`` that
    leaves a render nothing to match.
    """

    def __init__(self, capacity: int):
        self.xyz = np.empty((capacity, 3), np.float32)
        self.rgb = np.empty((capacity, 3), np.uint8)
        self.n = 0
        self.dropped = 0
        self.origin: np.ndarray | None = None
        self.intensity: np.ndarray | None = None  # float32, allocated on first use
        self.grey_runs: list[tuple[int, int]] = []  # (start, end) of the points whose grey comes from intensity

    def add(self, xyz: np.ndarray, rgb: np.ndarray | None, intensity: np.ndarray | None = None) -> None:
        """Append a chunk: ``xyz`` (M, 3) any float dtype in world coordinates, ``rgb`` (M, 3) uint8 or None (grey);
        ``intensity`` (M,) the laser's return strength as the file holds it, used where ``rgb`` is None."""
        finite = np.isfinite(xyz).all(axis=1)
        if not finite.all():
            self.dropped += int((~finite).sum())
            xyz = xyz[finite]
            rgb = None if rgb is None else rgb[finite]
            intensity = None if intensity is None else intensity[finite]
        m = len(xyz)
        if m == 0:
            return
        if self.origin is None:
            big = np.abs(xyz).max() > LARGE
            self.origin = np.round((xyz.min(axis=0).astype(np.float64) + xyz.max(axis=0)) / 2) if big else np.zeros(3)
        if self.n + m > len(self.xyz):
            raise ScanError(f"more points than the header announced ({len(self.xyz)})")
        out = self.xyz[self.n:self.n + m]
        if self.origin.any():
            np.subtract(xyz, self.origin, out=out, casting="unsafe")  # float64 arithmetic, float32 result
        else:
            out[:] = xyz
        self.rgb[self.n:self.n + m] = GREY if rgb is None else rgb
        if rgb is None and intensity is not None:
            if self.intensity is None:
                self.intensity = np.zeros(len(self.xyz), np.float32)
            self.intensity[self.n:self.n + m] = intensity
            if self.grey_runs and self.grey_runs[-1][1] == self.n:
                self.grey_runs[-1] = (self.grey_runs[-1][0], self.n + m)
            else:
                self.grey_runs.append((self.n, self.n + m))
        self.n += m

    def scan(self, path: Path, fmt: str, stations=(), **meta) -> Scan:
        """The filled points as a ``Scan`` (views, no copy); ``meta`` gets format and dropped counts, and
        ``intensity_grey``: how many points' grey came from the laser's intensity."""
        if self.dropped:
            log.warning("%s: dropped %d non-finite points (NaN/inf coordinates)", path, self.dropped)
        meta = {"format": fmt, "dropped_nonfinite": self.dropped, "intensity_grey": 0, **meta}
        if self.grey_runs:
            total = sum(b - a for a, b in self.grey_runs)
            step = max(1, total // 2_000_000)  # the percentiles from ~2 M of them
            scale = intensity_scale(np.concatenate([self.intensity[a:b:step] for a, b in self.grey_runs]))
            if scale is None:
                log.warning("%s: the scan has no colour and its intensity is one value: its points are flat grey", path)
            else:
                for a, b in self.grey_runs:
                    self.rgb[a:b] = intensity_grey(self.intensity[a:b], scale)[:, None]
                meta["intensity_grey"] = int(sum(b - a for a, b in self.grey_runs))
                log.warning("%s: %s points have no colour: grey from the laser's intensity instead (what that changes: "
                            "docs/TROUBLESHOOTING.md)", path, f"{meta['intensity_grey']:,}")
            self.intensity = None
        origin = np.zeros(3) if self.origin is None else self.origin
        return Scan(self.xyz[:self.n], self.rgb[:self.n], origin, list(stations), path, meta)


class ColourChoice:
    """One scan's colour, or its intensity where its colour fields are blank: one value on every point of the first
    chunk (an export that wrote the fields without pictures: all black, or all white) while the intensity varies.
    Decided on the first chunk, then kept: a scan is coloured one way."""

    def __init__(self, desc: str):
        self.desc = desc
        self.use_intensity: bool | None = None

    def pick(self, rgb: np.ndarray | None, intensity: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(rgb, None) or (None, intensity) for ``PointSink.add``."""
        if rgb is None:
            return None, intensity
        if intensity is None:
            return rgb, None
        if self.use_intensity is None and len(rgb):
            finite = intensity[np.isfinite(intensity)]
            self.use_intensity = bool((rgb == rgb[0]).all()) and len(finite) > 0 and finite.max() > finite.min()
            if self.use_intensity:
                log.warning("%s: every point has the colour %s (blank colour fields): grey from the laser's intensity "
                            "instead", self.desc, tuple(int(v) for v in rgb[0]))
        return (None, intensity) if self.use_intensity else (rgb, None)


def intensity_scale(sample: np.ndarray) -> tuple[float, float] | None:
    """(black, white) for a colourless scan's laser intensity, from a ``sample`` of it in whatever range the scanner
    wrote (0..1, 0..255, 12 or 16 bits, signed dB): 0, or the minimum where values go below it, and the
    ``INTENSITY_WHITE`` percentile. None when the intensity is one value (a writer that filled the field with zeros)."""
    finite = sample[np.isfinite(sample)]
    if len(finite) == 0 or finite.max() <= finite.min():
        return None
    lo = min(0.0, float(finite.min()))
    hi = float(np.percentile(finite, INTENSITY_WHITE))
    return lo, hi if hi > lo else float(finite.max())  # (most points at the minimum: white at the maximum)


def intensity_grey(values: np.ndarray, scale: tuple[float, float]) -> np.ndarray:
    """Grey levels (uint8) for laser intensity ``values`` between ``scale``'s black and white
    (:func:`intensity_scale`): taken as proportional to the surface's reflectance, as a camera's linear signal is, and
    encoded with a camera's gamma (``INTENSITY_GAMMA``). A reflectance's ratios stay as a photograph shows them: a
    stretch between percentiles made a plain wall, the bulk of the points, span black to white (office seed 8)."""
    lo, hi = scale
    out = np.empty(len(values), np.uint8)
    for i in range(0, len(values), CHUNK):
        x = np.clip((np.nan_to_num(values[i:i + CHUNK].astype(np.float32), nan=lo) - lo) / (hi - lo), 0.0, 1.0)
        out[i:i + CHUNK] = np.rint(255.0 * x ** (1.0 / INTENSITY_GAMMA))
    return out


def _reader(fmt: str):
    if fmt == "ply":
        from services.io.ply import read_ply as read
    elif fmt == "e57":
        from services.io.e57 import read_e57 as read
    else:
        from services.io.las import read_las as read
    return read


def load_scan(path: str | Path, *, cache: bool = True, require_color: bool = True) -> Scan:
    """Read a ``.ply``, ``.e57``, ``.las`` or ``.laz`` scan into world-frame points (relative to ``scan.origin``).

    ``cache``: reuse / write the parsed arrays in ``<file>.cristal-cache/`` (memory-mapped, read-only arrays).
    ``require_color``: a scan with neither colour channels nor intensity is an error; with False its points are grey
    (128). Points without colour but with intensity get grey levels from it (``PointSink``).
    ``scan.meta`` reports ``format``, ``dropped_nonfinite``, ``has_color``, ``intensity_grey`` (points grey from
    intensity), ``from_cache``, ``load_seconds``.
    """
    t0 = time.perf_counter()
    path = Path(path)
    fmt = SUFFIXES.get(path.suffix.lower())
    if fmt is None:
        raise ScanError(f"{path}: unknown scan format '{path.suffix}' (expected one of {', '.join(SUFFIXES)})")
    if not path.is_file():
        raise ScanError(f"{path}: no such file" if not path.exists() else f"{path}: not a regular file")
    from services.io import scan_cache

    scan = scan_cache.load(path, READER_VERSION) if cache else None
    if scan is None:
        stat = path.stat()  # before parsing: a file rewritten meanwhile will not match the cache
        try:
            scan = _reader(fmt)(path)
        except ScanError as e:
            msg = str(e)
            raise ScanError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
        except MemoryError:
            raise
        except OSError as e:  # permissions, I/O errors (parser format errors are not OSError)
            raise ScanError(f"{path}: cannot read the file ({e.strerror or e})") from e
        except Exception as e:  # a parser's own exception: never let its traceback reach the user
            first = (str(e).strip().splitlines() or [""])[0][:300]  # some parsers add pages of debug text
            raise ScanError(f"{path}: cannot read this {path.suffix[1:].upper()} file, it looks truncated or corrupt "
                            f"({type(e).__name__}: {first})") from e
        if len(scan) == 0:
            dropped = scan.meta.get("dropped_nonfinite", 0)
            raise ScanError(f"{path}: the scan has no points" + (f" ({dropped} non-finite points dropped)" if dropped else ""))
        scan.meta["from_cache"] = False
        if cache:
            scan_cache.save(path, scan, READER_VERSION, stat)
    if not scan.meta.get("has_color", True) and not scan.meta.get("intensity_grey") and require_color:
        raise ScanError(f"{path}: the scan has no colour channels (red/green/blue) and no laser intensity; "
                        "load it with require_color=False to use flat grey points")
    scan.meta["load_seconds"] = round(time.perf_counter() - t0, 4)
    return scan


def save_ply(scan: Scan, path: str | Path, binary: bool = True, intensity: np.ndarray | None = None) -> None:
    """Write ``scan`` as PLY, atomically: world x y z (double when the origin is non-zero, else float), uchar rgb;
    with ``intensity`` (one float per point) a float ``intensity`` property instead of rgb (a scanner's colourless
    export, as ``cristal sim --scan-colour intensity`` makes).

    Station poses go into ``comment cristal_station tx ty tz qx qy qz qw`` lines, which ``load_scan`` reads back, and
    how many points each station has (their points one station after another) into ``comment cristal_station_points``.
    """
    from services.io.atomic import atomic_write

    path = Path(path)
    wide = bool(np.any(scan.origin != 0))
    ftype, fdt = ("double", "f8") if wide else ("float", "f4")
    lines = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", "comment written by cristal"]
    lines += [f"comment {STATION_TAG} " + " ".join(repr(float(v)) for v in s.to_tum()) for s in scan.stations]
    counts = station_points(scan)
    if counts is not None:
        lines += [f"comment {STATION_POINTS_TAG} " + " ".join(str(c) for c in counts)]
    grey = min(1.0, scan.meta.get("intensity_grey", 0) / max(1, len(scan)))  # (a decimated scan kept the count)
    if grey > 0 and intensity is None:  # grey levels from intensity saved as colour: still told apart on reading
        lines += [f"comment {INTENSITY_TAG} {grey:.4f}"]
    lines += [f"element vertex {len(scan)}"] + [f"property {ftype} {a}" for a in "xyz"]
    channels = ([("intensity", "f4", "float")] if intensity is not None else
                [(c, "u1", "uchar") for c in ("red", "green", "blue")])
    lines += [f"property {t} {c}" for c, _, t in channels] + ["end_header", ""]
    dtype = np.dtype([(a, "<" + fdt) for a in "xyz"] + [(c, "<" + d) for c, d, _ in channels])
    values = scan.rgb if intensity is None else np.asarray(intensity, np.float32).reshape(-1, 1)
    with atomic_write(path, "wb") as f:
        f.write("\n".join(lines).encode("ascii"))
        for i in range(0, len(scan), CHUNK):
            sl = slice(i, i + CHUNK)
            xyz = scan.world_xyz(sl) if wide else scan.xyz[sl]
            if binary:
                rec = np.empty(len(xyz), dtype)
                for k, a in enumerate("xyz"):
                    rec[a] = xyz[:, k]
                for k, (c, _, _) in enumerate(channels):
                    rec[c] = values[sl, k]
                f.write(rec.data)
            else:
                fmt = "%.6f" if wide else "%.9g"
                rows = np.column_stack([xyz.astype(np.float64), values[sl]])
                np.savetxt(f, rows, fmt=[fmt] * 3 + (["%.6g"] if intensity is not None else ["%d"] * 3))


def station_points(scan: Scan) -> list[int] | None:
    """How many points each of ``scan.stations`` has, their points one station after another (``meta``'s
    ``station_points``: E57 scans, simulated scans, PLY written by cristal); None when unknown or inconsistent."""
    counts = scan.meta.get("station_points")
    if counts is None or len(counts) != len(scan.stations) or sum(counts) != len(scan) or min(counts, default=0) < 0:
        return None
    return [int(c) for c in counts]


def scan_info(scan: Scan) -> dict:
    """A JSON-able summary: points, world bounds, origin, colour, stations, dropped points, load time, cache use."""
    lo, hi = scan.bounds() if len(scan) else (np.full(3, np.nan), np.full(3, np.nan))
    m = scan.meta
    return {
        "source": None if scan.source is None else str(scan.source),
        "format": m.get("format"),
        "points": len(scan),
        "bounds_min": [round(float(v), 4) for v in lo],
        "bounds_max": [round(float(v), 4) for v in hi],
        "origin": [float(v) for v in scan.origin],
        "has_color": bool(m.get("has_color", True)),
        "intensity_grey": int(m.get("intensity_grey", 0)),
        "stations": [[round(float(v), 6) for v in s.to_tum()] for s in scan.stations],
        "dropped_nonfinite": int(m.get("dropped_nonfinite", 0)),
        "dropped_invalid": int(m.get("dropped_invalid", 0)),
        "load_seconds": m.get("load_seconds"),
        "from_cache": bool(m.get("from_cache", False)),
    }
