"""A scan prepared for rendering: points in spatially coherent chunks with bounding boxes.

Sorting points along a Morton (Z-order) curve of a coarse voxel grid makes each chunk a
compact blob of space, so (a) the CPU splat can skip whole chunks outside the view
frustum and (b) points that land on neighbouring pixels are processed together (cache
friendly). Prepared once per scan; every render reuses it, nothing is copied per frame.

Level of detail: inside each chunk the points are shuffled (one fixed permutation), so the first k
points of a chunk are a uniform sample of it. A render that would put many points on each pixel of
a chunk (a 64 M-point office seen from a few metres) reads only the prefix it needs
(``chunk_spacing`` says how dense each chunk is), and the splat's cost follows the image, not the scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.io.scan import Scan

__all__ = ["PreparedCloud", "prepare_cloud"]

CHUNK = 8192  # points per chunk


@dataclass
class PreparedCloud:
    xyz: np.ndarray  # (N, 3) float32, relative to ``origin``, Morton-sorted
    rgb: np.ndarray  # (N, 3) uint8
    origin: np.ndarray  # (3,) float64
    chunk_lo: np.ndarray  # (C, 3) float32 bbox min per chunk
    chunk_hi: np.ndarray  # (C, 3) float32 bbox max per chunk
    chunk: int = CHUNK
    chunk_spacing: np.ndarray | None = None  # (C,) float32 metres: the mean distance between a chunk's points

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def n_chunks(self) -> int:
        return int(self.chunk_lo.shape[0])


def _part1by2(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.uint64) & np.uint64(0x1FFFFF)
    x = (x | (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    x = (x | (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    x = (x | (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    x = (x | (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    x = (x | (x << np.uint64(2))) & np.uint64(0x1249249249249249)
    return x


def prepare_cloud(scan: Scan, cell: float = 0.05, chunk: int = CHUNK) -> PreparedCloud:
    """Morton-sort the scan on a ``cell``-sized grid and cut it into chunks of ``chunk`` points."""
    xyz = scan.xyz
    n = len(xyz)
    if n == 0:
        raise ValueError("cannot render an empty scan")
    lo = xyz.min(axis=0)
    q = np.floor((xyz - lo) / cell).astype(np.int64)
    code = _part1by2(q[:, 0]) | (_part1by2(q[:, 1]) << np.uint64(1)) | (_part1by2(q[:, 2]) << np.uint64(2))
    order = np.argsort(code, kind="stable")
    del code, q
    # one fixed shuffle inside every chunk (the last, partial one its own): any prefix of a chunk is a uniform sample
    rng = np.random.default_rng(0)
    full = n // chunk * chunk
    order[:full] = order[:full].reshape(-1, chunk)[:, rng.permutation(chunk)].ravel()
    order[full:] = order[full:][rng.permutation(n - full)]
    xyz_s = np.ascontiguousarray(xyz[order])
    rgb_s = np.ascontiguousarray(scan.rgb[order])
    n_chunks = (n + chunk - 1) // chunk
    pad = n_chunks * chunk - n
    padded = np.concatenate([xyz_s, np.repeat(xyz_s[-1:], pad, axis=0)]) if pad else xyz_s
    blocks = padded.reshape(n_chunks, chunk, 3)
    lo, hi = blocks.min(axis=1), blocks.max(axis=1)
    counts = np.full(n_chunks, chunk, np.float64)
    counts[-1] = n - (n_chunks - 1) * chunk
    return PreparedCloud(xyz_s, rgb_s, scan.origin.copy(), lo, hi, chunk, chunk_spacing(lo, hi, counts))


def chunk_spacing(lo: np.ndarray, hi: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The mean point spacing of each chunk, taking its points as a surface patch spanning the bounding box's
    two largest sides (a Morton chunk is a compact piece of one or two surfaces). Errs on the dense side only
    where a chunk folds over a corner (area under-counted up to ~2x); a chunk that jumps across space looks
    sparser than it is, which only costs speed. Never below the spacing along the longest side (a line of points)."""
    d = np.sort((hi - lo).astype(np.float64), axis=1)[:, ::-1]
    return np.maximum(np.sqrt(d[:, 0] * d[:, 1] / counts), d[:, 0] / counts).astype(np.float32)
