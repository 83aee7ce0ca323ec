"""Image quality of renders against ground truth: PSNR, SSIM, holes and background leakage.

Used by training (validation), the benchmarks and the tests, always against the
simulator's mesh render at the same pose (``SimSite.render``).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["ssim", "psnr", "leakage", "ssim_loss_map"]


def _gauss(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - size // 2
    g = torch.exp(-x ** 2 / (2 * sigma ** 2))
    g /= g.sum()
    return g[:, None] * g[None, :]


def ssim_loss_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM of (B,C,H,W) images in [0,1] (Gaussian 11x11, sigma 1.5; per channel)."""
    C = a.shape[1]
    w = _gauss().to(a)[None, None].repeat(C, 1, 1, 1)
    mu_a = F.conv2d(a, w, padding=5, groups=C)
    mu_b = F.conv2d(b, w, padding=5, groups=C)
    saa = F.conv2d(a * a, w, padding=5, groups=C) - mu_a ** 2
    sbb = F.conv2d(b * b, w, padding=5, groups=C) - mu_b ** 2
    sab = F.conv2d(a * b, w, padding=5, groups=C) - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (saa + sbb + c2))


def _t(img: np.ndarray) -> torch.Tensor:
    x = torch.from_numpy(np.ascontiguousarray(img)).float()
    if x.max() > 1.0:
        x = x / 255.0
    return x.permute(2, 0, 1)[None] if x.dim() == 3 else x[None, None]


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM of two uint8 (H,W,3) images."""
    with torch.no_grad():
        return float(ssim_loss_map(_t(a), _t(b)).mean())


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float(10 * np.log10(255.0 ** 2 / max(mse, 1e-10)))


def leakage(depth: np.ndarray, gt_depth: np.ndarray, rel: float = 0.05) -> float:
    """Fraction of valid pixels whose depth is more than ``rel`` behind the true surface (background seen through holes)."""
    valid = (depth > 0) & (gt_depth > 0)
    if not valid.any():
        return 0.0
    return float(((depth > gt_depth * (1 + rel)) & valid).sum() / valid.sum())
