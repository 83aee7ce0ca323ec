"""Motion blur of a render on the renderer's torch device: the GPU server's :func:`motion_blur_linear`.

Render & Match blurs the keyframe render with the frame's motion on every fast frame. In numpy and OpenCV that
is two projections of every pixel and up to ten remaps: 0.2 s a call at 1280x720 on the H200 machine's CPU, the
largest share of a GPU frame (benchmarks/RESULTS.md, "GPU"). Here the same warp is one batched ``grid_sample``.
Same geometry as :mod:`services.geometry.blur`: the render's pixels back-projected with its depth (pixels without
depth far away), projected into the camera at the exposure's two ends, the sampling maps interpolated linearly
between them and the sharp image averaged over ``n`` of them.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F

from services.geometry.camera import Camera
from services.geometry.se3 import Pose

__all__ = ["motion_blur_linear_torch"]

@functools.lru_cache(maxsize=8)
def _rays(camera: Camera, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(camera.pixel_rays().reshape(-1, 3), dtype=torch.float32, device=device)


def _grid(points: torch.Tensor, camera: Camera, T_ck: Pose) -> torch.Tensor:
    """(H*W, 2) sampling positions, normalised for grid_sample (align_corners=True: -1 and 1 are the border
    pixels' centres, as OpenCV's remap reads pixel coordinates), clamped as the numpy path clamps them."""
    R = torch.tensor(np.asarray(T_ck.R, np.float32), device=points.device)
    t = torch.tensor(np.asarray(T_ck.t, np.float32), device=points.device)
    X = points @ R.T + t
    z = X[:, 2]
    x, y = camera._distort(X[:, 0] / z, X[:, 1] / z)
    W, H = camera.width, camera.height
    u = torch.nan_to_num(camera.fx * x + camera.cx, nan=-1.0, posinf=-1.0, neginf=-1.0).clamp(-W, 2 * W - 1)
    v = torch.nan_to_num(camera.fy * y + camera.cy, nan=-1.0, posinf=-1.0, neginf=-1.0).clamp(-H, 2 * H - 1)
    return torch.stack([2 * u / max(W - 1, 1) - 1, 2 * v / max(H - 1, 1) - 1], dim=1)


@torch.no_grad()
def motion_blur_linear_torch(sharp: np.ndarray, depth: np.ndarray, camera: Camera, T_wc: Pose, T_start: Pose,
                             T_end: Pose, n: int, device: str | torch.device) -> np.ndarray:
    """:func:`services.geometry.blur.motion_blur_linear` on ``device``: ``sharp`` (H, W) or (H, W, C) taken at
    ``T_wc`` with z-depth ``depth``, averaged over ``n`` views spread from ``T_start`` to ``T_end``.
    Returns float32 on the host, like the numpy path (borders reflected about the edge pixels)."""
    src = np.asarray(sharp, dtype=np.float32)
    if n <= 1:
        return src
    dev = torch.device(device)
    H, W = src.shape[:2]
    img = torch.as_tensor(src, device=dev)
    img = img[None, None] if img.ndim == 2 else img.permute(2, 0, 1)[None]
    d = torch.as_tensor(np.asarray(depth, dtype=np.float32), device=dev).reshape(-1, 1)
    points = _rays(camera, dev) * torch.where(d > 0, d, torch.full_like(d, 50.0))
    T_cw = T_wc.inverse()
    g0, g1 = _grid(points, camera, T_cw @ T_start), _grid(points, camera, T_cw @ T_end)
    w = torch.linspace(0.0, 1.0, n, device=dev)[:, None, None]
    grids = (g0 + (g1 - g0) * w).reshape(n, H, W, 2)
    out = F.grid_sample(img.expand(n, -1, -1, -1), grids, mode="bilinear", padding_mode="reflection",
                        align_corners=True).mean(dim=0)
    out = out[0] if out.shape[0] == 1 else out.permute(1, 2, 0)
    return out.cpu().numpy()
