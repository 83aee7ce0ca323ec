"""A supersampled splat brought to its camera's pixels (``Renderer.render(..., supersample=k)``).

The points are splatted at k times the camera's resolution. Each pixel then gets:

- the depth a plain render would give it: the nearest point among its k x k sub-pixels (``block_min_depth``);
- after the depth filter has judged that depth, the colour of its sub-pixels that hold a point no further behind it
  than a plain render blends (the splat's delta), grown a few sub-pixels into the gaps between points, averaged over
  the covered sub-pixels (``pool_colours``). A pixel on an edge between two surfaces or materials so takes the share
  of each side that lies nearer its points, instead of the colour of whichever point was rounded into it.

Two paths, the same steps: torch (any device; the CUDA path) and numba (the CPU path, ~3x faster than torch on one
thread there). ``tests/test_render.py`` checks they agree.
"""

from __future__ import annotations

import numba as nb
import numpy as np
import torch
import torch.nn.functional as F

from services.render.grow import _grow_torch, covered_sum, grow_kernel
from services.render.threads import keeps_torch_threads

__all__ = ["block_min_depth", "pool_colours"]


def block_min_depth(depth: torch.Tensor, k: int) -> torch.Tensor:
    """(H*k, W*k) depth, 0 where empty -> (H, W): the nearest in each k x k block, 0 where the block is empty."""
    if depth.device.type == "cpu":
        return torch.from_numpy(_block_min_nb(np.ascontiguousarray(depth.numpy(), dtype=np.float32), k))
    return _block_min_torch(depth, k)


def _block_min_torch(depth: torch.Tensor, k: int) -> torch.Tensor:
    far = torch.where(depth > 0, depth, torch.full_like(depth, float("inf")))
    near = -F.max_pool2d(-far[None, None], k)[0, 0]
    return torch.where(torch.isfinite(near), near, torch.zeros_like(near))


def pool_colours(rgb: torch.Tensor, fine_depth: torch.Tensor, depth: torch.Tensor, k: int, delta_abs: float,
                 delta_rel: float, steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The colours of a k-times supersampled splat at the camera's pixels.

    ``rgb`` (H*k, W*k, 3) in 0..255 and ``fine_depth`` (H*k, W*k) from the splat; ``depth`` (H, W): the filtered
    depth (0 where the filter dropped it). A sub-pixel counts where its pixel kept a depth and it lies within
    ``delta_abs`` + ``delta_rel`` x depth behind it; counted sub-pixels grow ``steps`` sub-pixels into the empty ones
    (``grow_colours``' steps); each pixel takes the mean of its covered sub-pixels. Returns (1, 3, H, W) colours in
    0..1 (0 where no sub-pixel is covered) and the (1, 1, H, W) mask of pixels with any."""
    if rgb.device.type == "cpu":
        return _pool_numba(rgb, fine_depth, depth, k, delta_abs, delta_rel, steps)
    return _pool_torch(rgb, fine_depth, depth, k, delta_abs, delta_rel, steps)


def _pool_torch(rgb, fine_depth, depth, k, delta_abs, delta_rel, steps):
    up = depth.repeat_interleave(k, 0).repeat_interleave(k, 1)
    sub = (fine_depth > 0) & (up > 0) & (fine_depth <= up * (1 + delta_rel) + delta_abs)
    rgb01 = rgb.permute(2, 0, 1)[None] / 255.0 * sub[None, None]
    mask = sub[None, None].float()
    if steps > 0:
        rgb01, mask = _grow_torch(rgb01, mask, steps)
    w = F.avg_pool2d(mask, k)
    mask = (w > 0).float()
    return F.avg_pool2d(rgb01, k) / w.clamp_min(1e-6) * mask, mask


@keeps_torch_threads
def _pool_numba(rgb, fine_depth, depth, k, delta_abs, delta_rel, steps):
    c, m = _pool_nb(np.ascontiguousarray(rgb.numpy(), dtype=np.float32),
                    np.ascontiguousarray(fine_depth.numpy(), dtype=np.float32),
                    np.ascontiguousarray(depth.numpy(), dtype=np.float32), int(k), float(delta_abs), float(delta_rel),
                    int(steps))
    return torch.from_numpy(c)[None], torch.from_numpy(m)[None, None]


@nb.njit(cache=True, parallel=True)
def _block_min_nb(depth, k):
    H, W = depth.shape[0] // k, depth.shape[1] // k
    out = np.zeros((H, W), np.float32)
    for y in nb.prange(H):
        for x in range(W):
            best = np.inf
            for yy in range(y * k, y * k + k):
                for xx in range(x * k, x * k + k):
                    d = depth[yy, xx]
                    if d > 0 and d < best:
                        best = d
            if best < np.inf:
                out[y, x] = best
    return out


@nb.njit(cache=True, parallel=True)
def _pool_nb(rgb, fine_depth, depth, k, delta_abs, delta_rel, steps):
    Hf, Wf = fine_depth.shape
    H, W = depth.shape
    c = np.zeros((3, Hf, Wf), np.float32)
    m = np.zeros((Hf, Wf), np.float32)
    for y in nb.prange(Hf):
        for x in range(Wf):
            d = fine_depth[y, x]
            z = depth[y // k, x // k]
            if d > 0 and z > 0 and d <= z * (1 + delta_rel) + delta_abs:
                m[y, x] = 1.0
                for ch in range(3):
                    c[ch, y, x] = rgb[y, x, ch] / 255.0
    grow_kernel(c, m, steps)
    out = np.zeros((3, H, W), np.float32)
    mask = np.zeros((H, W), np.float32)
    for y in nb.prange(H):
        for x in range(W):
            n, r, g, b = covered_sum(c, m, y * k, y * k + k, x * k, x * k + k)
            if n > 0:
                out[0, y, x] = r / n
                out[1, y, x] = g / n
                out[2, y, x] = b / n
                mask[y, x] = 1.0
    return out, mask
