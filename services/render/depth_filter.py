"""Hierarchical depth filter (after Vanherck et al. 2025) and depth hole filling, in torch (CPU or CUDA).

A sparse splat shows background through the gaps between foreground points. The filter
builds a min-depth pyramid (2x2 min pooling) and walks it coarse to fine: a pixel more than
``rel_tol`` behind the coarser level's depth is background seen through a hole and is
removed. Near real depth edges (large Laplacian of the coarse depth) the pixel is compared
with the farthest of its 3x3 coarse neighbours instead, so the far side of a true edge
survives. At intermediate levels removed and empty pixels take the upsampled coarse depth,
so foreground depth propagates into holes before the next, finer test.

Known trade-off (as in the original): within about one coarse pixel (2^levels pixels) of a true
depth edge, e.g. beside a doorway, background leaking through the wall next to it is kept,
because it is indistinguishable from the far side of the edge at that scale. A slope allowance
keeps slanted surfaces (floors seen at grazing angles) that a plain ratio test would erode.

``fill_depth`` then closes the remaining holes with push-pull interpolation, and the caller
gets a ``measured`` mask: localization back-projects only measured depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = ["FilterConfig", "hierarchical_depth_filter", "fill_depth"]

INF = float("inf")


@dataclass(frozen=True)
class FilterConfig:
    levels: int = 4  # pyramid levels above full resolution
    rel_tol: float = 0.025  # a pixel > 2.5 % behind the coarse depth is background
    edge_rel: float = 0.15  # |Laplacian| / depth above this marks a depth edge in the coarse level
    slope_cap: float = 0.15  # slanted surfaces: allow the coarse level's local depth slope, up to this fraction


def _minpool(d: torch.Tensor) -> torch.Tensor:
    """2x2 min pooling of (B,1,H,W) with inf for empty; odd sizes padded with inf."""
    H, W = d.shape[-2:]
    if H % 2 or W % 2:
        d = F.pad(d, (0, W % 2, 0, H % 2), value=INF)
    return -F.max_pool2d(-d, 2)


def _up(d: torch.Tensor, size) -> torch.Tensor:
    return d.repeat_interleave(2, dim=-2).repeat_interleave(2, dim=-1)[..., : size[0], : size[1]]


def _slope(d: torch.Tensor) -> torch.Tensor:
    """Largest depth step to a 4-neighbour (finite neighbours only): how much a slanted surface changes per pixel."""
    p = F.pad(d, (1, 1, 1, 1), mode="replicate")
    best = torch.zeros_like(d)
    for nb in (p[..., :-2, 1:-1], p[..., 2:, 1:-1], p[..., 1:-1, :-2], p[..., 1:-1, 2:]):
        diff = (nb - d).abs()
        best = torch.maximum(best, torch.where(torch.isfinite(diff), diff, torch.zeros_like(diff)))
    return best


def _edges(d: torch.Tensor, edge_rel: float) -> torch.Tensor:
    """Depth edges of a coarse level: |4 d - sum of 4 neighbours| > edge_rel * d (empty neighbours count as edges)."""
    p = F.pad(d, (1, 1, 1, 1), mode="replicate")
    nb = p[..., :-2, 1:-1] + p[..., 2:, 1:-1] + p[..., 1:-1, :-2] + p[..., 1:-1, 2:]
    lap = (4 * d - nb).abs()
    return ~(lap <= edge_rel * d)  # NaN/inf (empty around) -> edge


def hierarchical_depth_filter(depth: torch.Tensor, cfg: FilterConfig = FilterConfig()) -> torch.Tensor:
    """``depth`` (B,1,H,W) or (H,W) with 0 for empty -> boolean ``keep`` mask of the same shape."""
    squeeze = depth.dim() == 2
    d0 = depth[None, None] if squeeze else depth
    d0 = torch.where(d0 > 0, d0, torch.full_like(d0, INF))
    pyr = [d0]
    for _ in range(cfg.levels):
        pyr.append(_minpool(pyr[-1]))
    k = 1.0 + cfg.rel_tol
    filled = pyr[-1]
    keep = None
    for lvl in range(cfg.levels - 1, -1, -1):
        d = pyr[lvl]
        size = d.shape[-2:]
        coarse = filled
        ref_min = _up(coarse, size)
        # at depth edges: the farthest finite coarse neighbour (so the far side of a true edge is kept)
        cf = torch.where(torch.isfinite(coarse), coarse, torch.full_like(coarse, -INF))
        ref_max = _up(F.max_pool2d(cf, 3, stride=1, padding=1), size)
        ref_max = torch.where(torch.isfinite(ref_max), ref_max, ref_min)
        edge = _up(_edges(coarse, cfg.edge_rel), size)
        ref = torch.where(edge, torch.maximum(ref_min, ref_max), ref_min)
        slope = _up(torch.minimum(_slope(coarse), cfg.slope_cap * coarse), size)
        valid = torch.isfinite(d)
        keep = valid & (d <= ref * k + torch.where(torch.isfinite(slope), slope, torch.zeros_like(slope)))
        if lvl > 0:  # propagate foreground depth into removed and empty pixels
            filled = torch.where(keep, d, ref_min)
    return keep[0, 0] if squeeze else keep


def fill_depth(depth: torch.Tensor, valid: torch.Tensor, levels: int = 8) -> torch.Tensor:
    """Push-pull fill of ``depth`` (B,1,H,W) where ``valid`` is False; returns a dense depth (0 only if nothing valid)."""
    w = valid.to(depth.dtype)
    num, den = [depth * w], [w]
    for _ in range(levels):
        if min(num[-1].shape[-2:]) < 2:
            break
        num.append(F.avg_pool2d(num[-1], 2, ceil_mode=True))
        den.append(F.avg_pool2d(den[-1], 2, ceil_mode=True))
    est = num[-1] / den[-1].clamp_min(1e-12)
    for lvl in range(len(num) - 2, -1, -1):
        size = num[lvl].shape[-2:]
        up = F.interpolate(est, size=size, mode="bilinear", align_corners=False)
        own = num[lvl] / den[lvl].clamp_min(1e-12)
        a = den[lvl].clamp(0, 1)
        est = a * own + (1 - a) * up
    return torch.where(valid, depth, est)
