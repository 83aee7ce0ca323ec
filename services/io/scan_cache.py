"""Parsed-scan cache: ``xyz.npy``, ``rgb.npy``, ``meta.json`` beside the scan, memory-mapped on reload.

Parsing a 100 M-point PLY/E57/LAZ takes tens of seconds; mapping two ``.npy`` files takes
milliseconds. The cache lives in ``<scan file>.cristal-cache/`` or, when that folder cannot be
written, in ``~/.cache/cristal/<hash of the absolute path>/`` (``$XDG_CACHE_HOME`` honoured).
It is valid while the source's size and mtime_ns and the reader version are unchanged; anything
else (stale, unreadable, wrong shapes) means re-parse and rewrite. A cache folder is written
under a temporary name, fsynced, then renamed into place, so readers never see half of one.
Cached arrays are read-only memory maps.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from services.geometry.se3 import Pose
from services.io.atomic import fsync_dir
from services.io.scan import Scan

__all__ = ["cache_dirs", "load", "save", "CACHE_SUFFIX"]

log = logging.getLogger(__name__)

CACHE_SUFFIX = ".cristal-cache"
TRANSIENT = ("from_cache", "load_seconds", "cache_dir")  # meta keys describing one load, not the scan


def cache_dirs(path: Path) -> list[Path]:
    """Where the cache of ``path`` may live, in the order tried: beside the file, then the user cache."""
    p = Path(path).resolve()
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return [p.with_name(p.name + CACHE_SUFFIX), base / "cristal" / hashlib.sha1(str(p).encode()).hexdigest()[:24]]


def load(path: Path, version: int) -> Scan | None:
    """The cached scan of ``path`` if a valid cache exists, else None (never raises for a bad cache)."""
    st = path.stat()
    for d in cache_dirs(path):
        if not (d / "meta.json").is_file():
            continue
        try:
            m = json.loads((d / "meta.json").read_text())
            key = (m.get("source_size"), m.get("source_mtime_ns"), m.get("reader_version"))
            if key != (st.st_size, st.st_mtime_ns, version):
                log.info("%s: cache %s is stale, re-parsing", path, d)
                continue
            xyz = np.load(d / "xyz.npy", mmap_mode="r")
            rgb = np.load(d / "rgb.npy", mmap_mode="r")
            n = m["points"]
            if xyz.shape != (n, 3) or rgb.shape != (n, 3) or xyz.dtype != np.float32 or rgb.dtype != np.uint8:
                raise ValueError(f"arrays {xyz.shape}/{xyz.dtype}, {rgb.shape}/{rgb.dtype} do not match {n} points")
            stations = [Pose.from_tum(s) for s in m["stations"]]
            meta = {**m["meta"], "from_cache": True, "cache_dir": str(d)}
            return Scan(xyz, rgb, np.asarray(m["origin"], np.float64), stations, path, meta)
        except Exception as e:  # corrupt or foreign cache: fall back to parsing
            log.warning("%s: ignoring unreadable cache %s (%s: %s)", path, d, type(e).__name__, e)
    return None


def save(path: Path, scan: Scan, version: int, stat: os.stat_result) -> Path | None:
    """Write the cache of ``path`` (``stat`` taken before parsing). Returns its folder, or None if nowhere writable."""
    meta = {
        "source": str(Path(path).resolve()),
        "source_size": stat.st_size,
        "source_mtime_ns": stat.st_mtime_ns,
        "reader_version": version,
        "points": len(scan),
        "origin": [float(v) for v in scan.origin],
        "stations": [[float(v) for v in s.to_tum()] for s in scan.stations],
        "meta": {k: v for k, v in scan.meta.items() if k not in TRANSIENT},
    }
    for d in cache_dirs(path):
        try:
            _write_dir(d, scan, meta)
        except OSError as e:
            log.info("%s: cannot write a cache in %s (%s)", path, d.parent, e)
            continue
        scan.meta["cache_dir"] = str(d)
        return d
    log.warning("%s: no writable place for a cache; the next load parses the file again", path)
    return None


def _write_dir(d: Path, scan: Scan, meta: dict) -> None:
    """Write into a temporary sibling folder, fsync, then swap it in with renames."""
    d.parent.mkdir(parents=True, exist_ok=True)
    tmp = d.with_name(f".{d.name}.{uuid.uuid4().hex[:12]}.tmp")
    tmp.mkdir()  # honours the umask (tempfile.mkdtemp would make it private)
    try:
        for name, write in (("xyz.npy", lambda f: np.save(f, scan.xyz)), ("rgb.npy", lambda f: np.save(f, scan.rgb)),
                            ("meta.json", lambda f: f.write(json.dumps(meta, indent=1).encode()))):
            with open(tmp / name, "wb") as f:
                write(f)
                f.flush()
                os.fsync(f.fileno())
        fsync_dir(tmp)
        old = d.with_name(f".{d.name}.old-{uuid.uuid4().hex[:12]}") if d.exists() else None
        try:
            if old is not None:
                os.rename(d, old)
            os.rename(tmp, d)
        except OSError:
            if not (d / "meta.json").is_file():
                raise
            shutil.rmtree(tmp, ignore_errors=True)  # a concurrent load put its (equivalent) cache in place first
        else:
            fsync_dir(d.parent)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise

