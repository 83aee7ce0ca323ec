"""The three-pass splat in torch, for CUDA (and, for testing, the CPU): same maths as ``splat.py``.

Pass 1 is a ``scatter_reduce(amin)`` of camera z into a flat depth buffer, pass 2 an
``index_add`` of the colours of points within delta of that minimum, pass 3 a division.
The cloud stays on the device as float32 xyz + uint8 rgba (16 bytes per point), in the prepared
cloud's chunk order, so frustum culling and the level of detail pick the same points as on the CPU.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.render.cloud import PreparedCloud
from services.render.splat import SplatConfig, _r2max, chunk_limits, visible_chunks

__all__ = ["DeviceCloud", "splat_torch"]


class DeviceCloud:
    """A prepared scan resident on a torch device: xyz float32 (relative to ``origin``) and rgb uint8 padded to
    4 bytes; the chunk boxes and spacings stay on the host (``prepared``) for culling and level of detail."""

    def __init__(self, prepared: PreparedCloud, device: str | torch.device):
        self.device = torch.device(device)
        self.xyz = torch.tensor(np.asarray(prepared.xyz, dtype=np.float32)).to(self.device)
        rgba = torch.zeros((len(prepared), 4), dtype=torch.uint8)
        rgba[:, :3] = torch.tensor(np.asarray(prepared.rgb))
        self.rgba = rgba.to(self.device)
        self.origin = prepared.origin
        # the host keeps only what culling and level of detail read (chunk boxes, spacings), not a second scan
        self.prepared = dataclasses.replace(prepared, xyz=np.empty((0, 3), np.float32), rgb=np.empty((0, 3), np.uint8))

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def bytes_per_point(self) -> float:
        return (self.xyz.element_size() * self.xyz.shape[1] + self.rgba.shape[1]) * 1.0


@torch.no_grad()
def splat_torch(cloud: DeviceCloud, T_wc: Pose, camera: Camera, cfg: SplatConfig = SplatConfig(),
                chunk: int = 1 << 24) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Returns (rgb (H,W,3) float32 0..255, depth (H,W) float32 with 0 for empty, count (H,W) int32) on the cloud's device."""
    dev = cloud.device
    T_cw = Pose(T_wc.R, T_wc.t - cloud.origin).inverse()
    R = torch.tensor(T_cw.R, dtype=torch.float32, device=dev)
    t = torch.tensor(T_cw.t, dtype=torch.float32, device=dev)
    W, H = camera.width, camera.height
    k1, k2, p1, p2, k3 = camera.distortion
    r2max = _r2max(camera)
    zbuf = torch.full((H * W,), float("inf"), device=dev)
    # the points to splat: each visible chunk's first ``lims`` points (as the CPU splat reads them)
    chunks = visible_chunks(cloud.prepared, T_cw, camera, cfg.near)
    lims = np.minimum(chunk_limits(cloud.prepared, chunks, T_cw, camera, cfg.lod_points_per_px),
                      len(cloud) - chunks * cloud.prepared.chunk)
    starts = torch.as_tensor(chunks * cloud.prepared.chunk, device=dev)
    lens = torch.as_tensor(lims, device=dev)
    total = int(lims.sum())
    offsets = torch.cumsum(lens, 0) - lens
    pick = torch.arange(total, device=dev) + torch.repeat_interleave(starts - offsets, lens, output_size=total)
    parts = []
    for s in range(0, total, chunk):  # bounded temporaries for 100 M-point scans
        pid = pick[s:s + chunk]
        X = cloud.xyz[pid] @ R.T + t
        z = X[:, 2]
        ok = z >= cfg.near
        x = X[:, 0] / z
        y = X[:, 1] / z
        if camera.is_distorted:
            r2 = x * x + y * y
            ok &= r2 <= r2max
            rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            x, y = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        u = camera.fx * x + camera.cx + 0.5
        v = camera.fy * y + camera.cy + 0.5
        ok &= (u >= 0) & (v >= 0) & (u < W) & (v < H)
        idx = v[ok].long() * W + u[ok].long()
        zs = z[ok]
        zbuf.scatter_reduce_(0, idx, zs, reduce="amin")
        parts.append((idx, zs, pid[ok]))
    acc = torch.zeros((H * W, 3), device=dev)
    cnt = torch.zeros((H * W,), dtype=torch.int32, device=dev)
    for idx, zs, pid in parts:
        zm = zbuf[idx]
        sel = zs <= zm + cfg.delta_abs + cfg.delta_rel * zm
        acc.index_add_(0, idx[sel], cloud.rgba[pid[sel], :3].float())
        cnt.index_add_(0, idx[sel], torch.ones_like(idx[sel], dtype=torch.int32))
    rgb = acc / cnt.clamp_min(1)[:, None]
    depth = torch.where(cnt > 0, zbuf, torch.zeros_like(zbuf))
    return rgb.view(H, W, 3), depth.view(H, W), cnt.view(H, W)
