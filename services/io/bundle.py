"""The P&L map bundle: a map directory (``map.msg`` + ``config.yaml`` [+ ``patches.npz``, ``scan_accuracy.json``]) as one
checksummed byte string.

The server packs the directory once (an uncompressed tar: msgpack maps do not compress much
and clients unpack with the standard library), serves it in chunks over Zenoh
(:mod:`protocol.keys`), and a client verifies every chunk and the whole before unpacking it,
atomically, into a cache directory named after the bundle's version. No torch.
"""

from __future__ import annotations

import hashlib
import io
import tarfile
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Bundle", "BundleError", "pack_map_dir", "unpack_bundle", "MAP_FILES"]

MAP_FILES = ("map.msg", "config.yaml")
OPTIONAL_FILES = ("patches.npz",  # landmark patches for the light localizer's alignment (services.prebuild.patches)
                  "scan_accuracy.json")  # the scan's registration error prebuild measured (services.localize.scan_error)
DEFAULT_CHUNK = 512 * 1024


class BundleError(ValueError):
    """A map directory that cannot be bundled, or a bundle that fails its checksum."""


@dataclass(frozen=True)
class Bundle:
    data: bytes
    sha256: str
    files: tuple[str, ...]
    chunk_size: int = DEFAULT_CHUNK

    @property
    def version(self) -> str:
        return self.sha256[:16]

    @property
    def chunks(self) -> int:
        return (len(self.data) + self.chunk_size - 1) // self.chunk_size

    def chunk(self, i: int) -> tuple[int, bytes]:
        if not 0 <= i < self.chunks:
            raise IndexError(f"chunk {i} is outside 0..{self.chunks - 1}")
        off = i * self.chunk_size
        return off, self.data[off: off + self.chunk_size]


def pack_map_dir(map_dir: str | Path, chunk_size: int = DEFAULT_CHUNK) -> Bundle:
    """Tar the map files of ``map_dir`` (deterministically: fixed mtimes and owners)."""
    d = Path(map_dir)
    if not d.is_dir():
        raise BundleError(f"{d}: not a map directory")
    missing = [f for f in MAP_FILES if not (d / f).is_file()]
    if missing:
        raise BundleError(f"{d}: missing {', '.join(missing)} (a P&L map directory holds {' + '.join(MAP_FILES)})")
    files = MAP_FILES + tuple(f for f in OPTIONAL_FILES if (d / f).is_file())
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for name in files:
            data = (d / name).read_bytes()
            ti = tarfile.TarInfo(name)
            ti.size, ti.mtime, ti.mode = len(data), 0, 0o644
            tar.addfile(ti, io.BytesIO(data))
    data = buf.getvalue()
    return Bundle(data, hashlib.sha256(data).hexdigest(), files, chunk_size)


def unpack_bundle(data: bytes, sha256: str, out_dir: str | Path) -> Path:
    """Verify ``data`` against ``sha256`` and unpack its map files into ``out_dir`` (atomically)."""
    from services.io.atomic import atomic_write_bytes

    got = hashlib.sha256(data).hexdigest()
    if got != sha256:
        raise BundleError(f"map bundle checksum mismatch: got {got[:12]}, expected {sha256[:12]}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        for m in tar.getmembers():
            if m.name not in MAP_FILES + OPTIONAL_FILES or not m.isfile():
                raise BundleError(f"map bundle holds an unexpected entry {m.name!r}")
            atomic_write_bytes(out / m.name, tar.extractfile(m).read())
    return out
