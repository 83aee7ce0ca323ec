"""The neural point renderer: splat -> hierarchical depth filter -> colour growing -> U-Net hole filling.

``Renderer(scan).render(T_wc, camera)`` returns what a camera at ``T_wc`` would see of the
scan: a hole-filled RGB image, the background-filtered *measured* depth (0 where no point
survived), a dense depth where holes are filled by push-pull, and the mask telling the two
apart. Localization must take depth from ``measured`` pixels only (or accept filled depth
knowingly; ``services.render.depth_sampling`` interpolates between measured points). Before the
U-Net, points' colours grow a few pixels into the holes around them (``grow_colours``), so a
surface splatted as rows of separate points comes out solid. The scan is prepared once (Morton-sorted chunks on the CPU, a 16-byte-per-point
tensor on CUDA); renders never copy it.

CPU path: numba splat and colour growing + torch filter/U-Net. CUDA path: torch throughout. Both give the
same images (tests compare them).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.io.scan import Scan
from services.render.cloud import prepare_cloud
from services.render.depth_filter import FilterConfig, fill_depth, hierarchical_depth_filter
from services.render.depth_sampling import plane_depth
from services.render.grow import grow_colours
from services.render.splat import SplatConfig, splat
from services.render.supersample import block_min_depth, pool_colours
from services.render.unet import load_holefill

__all__ = ["RenderConfig", "Render", "Renderer", "STAGES", "cubemap_poses", "grow_colours"]

log = logging.getLogger(__name__)
STAGES = ("splat", "filter", "full")


@dataclass(frozen=True)
class RenderConfig:
    splat: SplatConfig = field(default_factory=SplatConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    weights: str | None = None  # hole-filling weights; None = the shipped default
    holefill_scale: float | None = None  # U-Net at this fraction of the resolution; None: 0.5 on every device (it was
    #                                       trained on 320x240 views: at 640x480 its holes are twice what it learned).
    #                                       At 1 on CUDA three Render & Match tests failed replayed on the CPU (a
    #                                       relocalization, the blur probe's noisy render, a 960x720 query)
    grow_px: float = 6.0  # before the U-Net, points' colours grow into holes up to this far (px at 640 wide; 0 = off)


@dataclass
class Render:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres, measured (filtered) depth, 0 where none
    depth_filled: np.ndarray  # (H, W) float32 metres, dense (push-pull in holes)
    measured: np.ndarray  # (H, W) bool, True where depth comes from scan points
    T_wc: Pose
    camera: Camera
    timings: dict[str, float] = field(default_factory=dict)  # milliseconds per stage

    @property
    def hole_fraction(self) -> float:
        return float(1.0 - self.measured.mean())

    def backproject(self, uv: np.ndarray, filled: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """World points (N,3) of pixels ``uv`` (N,2) and a validity mask (measured depth, unless ``filled``)."""
        px = np.clip(np.round(uv).astype(int), 0, [self.camera.width - 1, self.camera.height - 1])
        d = (self.depth_filled if filled else self.depth)[px[:, 1], px[:, 0]]
        ok = d > 0
        Xc = self.camera.backproject(uv, d)
        return self.T_wc.transform(Xc), ok

    def surface_points(self, uv: np.ndarray, radius: int = 4, max_residual: float = 0.01
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points (N,3) of sub-pixel ``uv`` (N,2) on the surface of the measured points around them, a
        validity mask, and the fitted planes (``services.render.depth_sampling.plane_depth``): unlike
        ``backproject``, a keypoint between the points of a sparse render gets a depth, one on a depth edge none."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        z, ok, planes = plane_depth(self.depth, uv, radius, max_residual, return_plane=True)
        return self.T_wc.transform(self.camera.backproject(uv, z)), ok, planes


def _device(device: str | None) -> torch.device:
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


class Renderer:
    def __init__(self, scan: Scan, cfg: RenderConfig = RenderConfig(), device: str | None = None, holefill: bool = True,
                 stage: str | None = None):
        """``stage``: what ``render`` produces by default: "full" (with hole filling), "filter" or "splat" (ablations)."""
        if stage is not None and stage not in STAGES:
            raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
        self.stage = stage or ("full" if holefill else "filter")
        self.cfg = cfg
        self.device = _device(device)
        self.origin = scan.origin.copy()
        # the share of the points grey from the laser's intensity (no colour): its renders agree less with photographs
        self.intensity_share = float(scan.meta.get("intensity_grey", 0)) / max(1, len(scan))
        t0 = time.perf_counter()
        self.cloud = prepare_cloud(scan)
        if self.device.type == "cuda":
            from services.render.splat_torch import DeviceCloud

            self.cloud = DeviceCloud(self.cloud, self.device)
        log.info("renderer: %d points prepared on %s in %.2f s", len(scan), self.device, time.perf_counter() - t0)
        self.net = load_holefill(cfg.weights, self.device) if holefill and self.stage == "full" else None
        self.holefill_scale = cfg.holefill_scale or 0.5

    # ---- stages ----------------------------------------------------------
    def _splat(self, T_wc: Pose, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
        if self.device.type == "cuda":
            from services.render.splat_torch import splat_torch

            rgb, depth, _ = splat_torch(self.cloud, T_wc, camera, self.cfg.splat)
            return rgb, depth
        r = splat(self.cloud, T_wc, camera, self.cfg.splat)
        return torch.from_numpy(r.rgb), torch.from_numpy(r.depth)

    @torch.no_grad()
    def render(self, T_wc: Pose, camera: Camera, stage: str | None = None, supersample: int = 1) -> Render:
        """Render the scan from camera-to-world ``T_wc`` with ``camera``'s intrinsics and distortion.

        ``supersample`` k > 1: the points are splatted at k times the resolution; each pixel gets the nearest of
        its k x k sub-pixels' depths (a plain render's depth, filtered as one) and the mean colour of its sub-pixels
        (``services.render.supersample``); growing and the U-Net run at the camera's resolution. A point then lands
        within a (2k)-th of a pixel instead of half a pixel, and a pixel on an edge between two surfaces or materials
        takes each side's share: direct alignment from such a keyframe lands about as close as from a perfect
        picture of the scan (office walk at the true pose: 0.25 -> 0.15 cm median; benchmarks/RESULTS.md, stop 38).
        """
        stage = stage or self.stage
        if stage not in STAGES:
            raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
        if stage == "full" and self.net is None:
            raise ValueError("this renderer was built without hole filling; use stage='filter'")
        k = int(supersample)
        if k < 1 or k != supersample:
            raise ValueError(f"supersample must be a whole number >= 1, got {supersample!r}")
        fine = camera.scaled(k) if k > 1 else camera  # whole multiples: its pixels tile the camera's exactly
        tm: dict[str, float] = {}
        sync = torch.cuda.synchronize if self.device.type == "cuda" else (lambda: None)  # true per-stage times on a GPU
        t0 = time.perf_counter()
        rgb, depth = self._splat(T_wc, fine)
        sync()
        tm["splat_ms"] = 1e3 * (time.perf_counter() - t0)
        if k > 1:  # the depth a plain render gets (the nearest point in each pixel), filtered at that resolution
            fine_rgb, fine_depth, depth = rgb, depth, block_min_depth(depth, k)
        if stage == "splat":
            keep = depth > 0
        else:
            t0 = time.perf_counter()
            keep = hierarchical_depth_filter(depth, self.cfg.filter)
            sync()
            tm["filter_ms"] = 1e3 * (time.perf_counter() - t0)
        depth = torch.where(keep, depth, torch.zeros_like(depth))
        t0 = time.perf_counter()
        radius = round(self.cfg.grow_px * camera.width / 640) if stage == "full" else 0
        if k > 1:  # colours pooled from the sub-pixels, grown shut between neighbouring points first
            steps = min(radius * k, 2 * (k - 1))
            rgb01, mask = pool_colours(fine_rgb, fine_depth, depth, k, self.cfg.splat.delta_abs,
                                       self.cfg.splat.delta_rel, steps)
            radius -= steps // k
        else:
            rgb01 = rgb.permute(2, 0, 1)[None] / 255.0 * keep[None, None]
            mask = keep[None, None].float()
        if radius > 0:
            rgb01, mask = grow_colours(rgb01, mask, radius)
        if stage == "full":
            rgb01 = self._holefill(rgb01, mask, depth[None, None])
            sync()
            tm["holefill_ms"] = 1e3 * (time.perf_counter() - t0)
            t0 = time.perf_counter()
        dense = fill_depth(depth[None, None], keep[None, None])[0, 0]
        tm["depthfill_ms"] = 1e3 * (time.perf_counter() - t0)
        out = (rgb01[0].permute(1, 2, 0) * 255.0 + 0.5).clamp(0, 255).to(torch.uint8)
        return Render(out.cpu().numpy(), depth.cpu().numpy().astype(np.float32), dense.cpu().numpy().astype(np.float32),
                      keep.cpu().numpy(), T_wc, camera, tm)

    def _holefill(self, rgb01: torch.Tensor, mask: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        s = self.holefill_scale
        if s >= 1.0:
            return self._net_fill(rgb01, mask, depth)
        # the network at reduced resolution; measured pixels keep their full-resolution colour
        H, W = rgb01.shape[-2:]
        size = (max(8, round(H * s)), max(8, round(W * s)))
        m_s = F.adaptive_avg_pool2d(mask, size)
        rgb_s = F.adaptive_avg_pool2d(rgb01, size) / m_s.clamp_min(1e-6)
        d_s = F.adaptive_avg_pool2d(depth, size) / m_s.clamp_min(1e-6)
        ms = (m_s > 0.2).float()
        filled = self._net_fill(rgb_s * ms, ms, d_s * ms)
        up = F.interpolate(filled, size=(H, W), mode="bilinear", align_corners=False)
        return mask * rgb01 + (1 - mask) * up

    def _net_fill(self, rgb01: torch.Tensor, mask: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        out = self.net(rgb01, mask, depth)
        # a grey scan's holes filled grey (the network, trained on colour, tints them)
        return out.mean(dim=1, keepdim=True).expand_as(out) if self.intensity_share > 0.5 else out

    def render_batch(self, poses: list[Pose], camera: Camera, stage: str | None = None) -> list[Render]:
        """Several views with the same intrinsics (cubemaps, many clients). Shares the prepared scan."""
        return [self.render(T, camera, stage) for T in poses]

    def cubemap(self, position: np.ndarray, size: int = 256, stage: str | None = None) -> list[Render]:
        """Six 90-degree faces around ``position`` (world), each a ``size`` x ``size`` pinhole view."""
        cam = Camera(size, size, size / 2.0, size / 2.0, (size - 1) / 2.0, (size - 1) / 2.0)
        return self.render_batch(cubemap_poses(position), cam, stage)


def cubemap_poses(position) -> list[Pose]:
    """Camera-to-world poses of the six cube faces (+x, -x, +y, -y, +z, -z viewing directions; world z up)."""
    p = np.asarray(position, dtype=np.float64)
    faces = []
    for fwd, down in (((1, 0, 0), (0, 0, -1)), ((-1, 0, 0), (0, 0, -1)), ((0, 1, 0), (0, 0, -1)),
                      ((0, -1, 0), (0, 0, -1)), ((0, 0, 1), (0, 1, 0)), ((0, 0, -1), (0, -1, 0))):
        z = np.asarray(fwd, float)
        y = np.asarray(down, float)
        x = np.cross(y, z)
        faces.append(Pose(np.stack([x, y, z], 1), p))
    return faces
