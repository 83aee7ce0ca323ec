"""A scan prepared for rendering: points in spatially coherent chunks with bounding boxes.

Sorting points along a Morton (Z-order) curve of a coarse voxel grid makes each chunk a
compact blob of space, so (a) the CPU splat can skip whole chunks outside the view
frustum and (b) points that land on neighbouring pixels are processed together (cache
friendly). Prepared once per scan; every render reuses it, nothing is copied per frame.

Level of detail: inside each chunk the points are shuffled (one fixed permutation), so the first k
points of a chunk are a uniform sample of it. A render that would put many points on each pixel of
a chunk (a 64 M-point office seen from a few metres) reads only the prefix it needs
(``chunk_spacing`` says how dense each chunk is), and the splat's cost follows the image, not the scan.

The order costs a sort of the whole scan (23 s for 64 M points on 2 cores): for a scan loaded through the
scan cache (``services.io.scan_cache``) it is kept beside the cached arrays (``render-order-*.npy``, written
atomically, 4 bytes a point) and the next start only gathers the points in it (~4 s for 64 M).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np

from services.io.atomic import atomic_write
from services.io.scan import Scan
from services.render.threads import keeps_torch_threads

log = logging.getLogger(__name__)
ORDER_VERSION = 1  # bump when the order changes (sort key, shuffle): kept orders of older versions are ignored

__all__ = ["PreparedCloud", "prepare_cloud", "render_order", "chunk_spacing"]

CHUNK = 8192  # points per chunk


@dataclass
class PreparedCloud:
    xyz: np.ndarray  # (N, 3) float32, relative to ``origin``, Morton-sorted
    rgb: np.ndarray  # (N, 3) uint8
    origin: np.ndarray  # (3,) float64
    chunk_lo: np.ndarray  # (C, 3) float32 bbox min per chunk
    chunk_hi: np.ndarray  # (C, 3) float32 bbox max per chunk
    chunk_spacing: np.ndarray  # (C,) float32 metres: the mean distance between a chunk's points
    chunk: int = CHUNK

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def n_chunks(self) -> int:
        return int(self.chunk_lo.shape[0])


@nb.njit(inline="always")
def _spread3(x):
    x = x & np.uint64(0x1FFFFF)
    x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
    return x


@nb.njit(parallel=True, cache=True)
def _morton_codes(xyz, lo, cell):
    """Morton codes (x, y, z bits interleaved, 21 bits each) of the ``cell`` grid cells of ``xyz`` counted from
    ``lo``, in one parallel pass (in numpy, the same codes took 12 s of temporaries for 64 M points)."""
    out = np.empty(xyz.shape[0], np.uint64)
    for i in nb.prange(xyz.shape[0]):
        c = np.uint64(0)
        for a in range(3):
            q = np.uint64(max(0, np.int64(np.floor((xyz[i, a] - lo[a]) / cell))))  # float32, as numpy would
            c |= _spread3(q) << np.uint64(a)
        out[i] = c
    return out


@keeps_torch_threads  # numba's pool would leave torch on every core (services.render.threads)
def render_order(xyz: np.ndarray, cell: float = 0.05, chunk: int = CHUNK) -> np.ndarray:
    """The preparation order of points ``xyz``: Morton order on a ``cell`` grid, shuffled inside each run of
    ``chunk`` points (the last, partial one its own) so that any prefix of a chunk is a uniform sample of it."""
    n = len(xyz)
    code = _morton_codes(xyz, xyz.min(axis=0).astype(np.float32), np.float32(cell))
    order = np.argsort(code, kind="stable")
    del code
    rng = np.random.default_rng(0)
    full = n // chunk * chunk
    order[:full] = order[:full].reshape(-1, chunk)[:, rng.permutation(chunk)].ravel()
    order[full:] = order[full:][rng.permutation(n - full)]
    return order.astype(np.uint32) if n < 2 ** 32 else order


def _order_file(scan: Scan, cell: float, chunk: int) -> Path | None:
    d = scan.meta.get("cache_dir")
    return Path(d) / f"render-order-v{ORDER_VERSION}-{round(cell * 1000)}mm-{chunk}.npy" if d else None


def _kept_order(scan: Scan, cell: float, chunk: int) -> np.ndarray:
    """The scan's render order: kept beside its scan cache when it has one, else computed."""
    path = _order_file(scan, cell, chunk)
    if path is not None and path.is_file():
        try:
            order = np.load(path, mmap_mode="r")
            if order.shape == (len(scan),) and order.dtype.kind == "u" and (len(order) == 0 or int(order.max()) < len(scan)):
                return order
            log.warning("%s: a render order for another scan, recomputing", path)
        except (OSError, ValueError) as e:
            log.warning("%s: unreadable render order (%s), recomputing", path, e)
    order = render_order(scan.xyz, cell, chunk)
    if path is not None:
        try:
            with atomic_write(path) as f:
                np.save(f, order)
        except OSError as e:
            log.info("%s: cannot keep the render order (%s)", path, e)
    return order


def prepare_cloud(scan: Scan, cell: float = 0.05, chunk: int = CHUNK) -> PreparedCloud:
    """Morton-sort the scan on a ``cell``-sized grid, shuffle inside chunks of ``chunk`` points, box each chunk."""
    n = len(scan)
    if n == 0:
        raise ValueError("cannot render an empty scan")
    order = _kept_order(scan, cell, chunk)
    xyz_s = np.ascontiguousarray(scan.xyz[order])
    rgb_s = np.ascontiguousarray(scan.rgb[order])
    full = n // chunk
    lo = np.empty(((n + chunk - 1) // chunk, 3), np.float32)
    hi = np.empty_like(lo)
    if full:
        blocks = xyz_s[: full * chunk].reshape(full, chunk, 3)
        lo[:full], hi[:full] = blocks.min(axis=1), blocks.max(axis=1)
    if full < len(lo):
        lo[full], hi[full] = xyz_s[full * chunk:].min(axis=0), xyz_s[full * chunk:].max(axis=0)
    counts = np.full(len(lo), chunk, np.float64)
    counts[-1] = n - (len(lo) - 1) * chunk
    return PreparedCloud(xyz_s, rgb_s, scan.origin.copy(), lo, hi, chunk_spacing(lo, hi, counts), chunk)


def chunk_spacing(lo: np.ndarray, hi: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The mean point spacing of each chunk, taking its points as a surface patch spanning the bounding box's
    two largest sides (a Morton chunk is a compact piece of one or two surfaces). Errs on the dense side only
    where a chunk folds over a corner (area under-counted up to ~2x); a chunk that jumps across space looks
    sparser than it is, which only costs speed. Never below the spacing along the longest side (a line of points)."""
    d = np.sort((hi - lo).astype(np.float64), axis=1)[:, ::-1]
    return np.maximum(np.sqrt(d[:, 0] * d[:, 1] / counts), d[:, 0] / counts).astype(np.float32)
