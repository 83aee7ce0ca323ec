"""How densely a scan samples what a camera sees: the distance between neighbouring scan points, in the camera's pixels.

A scan places an edge between two surfaces or two materials only to within its sample spacing (each ray hits one
side or the other), and the render draws it where the last sample on its side fell. Where the spacing exceeds the
pixels the tracker renders at, the render rather than the method limits accuracy. benchmarks/RESULTS.md, stop 37:
tracked from the simulator's raytrace of the mesh instead of the render, direct alignment was 2.3-3.5x more
accurate, and the 960x540 walk gained 36 of 150 frames on a scan twice as dense. ``spacing_map`` measures it for
one view; ``survey`` for views all over the region where cameras go (``cristal density``).

Measured from the splat: a point per pixel and pixels without any on a surface sampled every s px apart is 1 / s^2
points per pixel of surface, several points per pixel where it is denser. Counted over a window of the surface
(the pixels that hold a point, with the gaps between them closed), s = sqrt(surface pixels / points). Background
seen through the gaps is dropped first (the renderer's depth filter), so it does not count as surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.render.depth_filter import hierarchical_depth_filter
from services.render.splat import SplatConfig, splat

__all__ = ["ViewSpacing", "spacing_map", "survey_poses", "survey", "floor_plan"]


@dataclass
class ViewSpacing:
    spacing: np.ndarray  # (H, W) float32: scan sample spacing in pixels, NaN where no surface
    surface: float  # share of the image that shows the scan's surface

    @property
    def median(self) -> float:
        v = self.spacing[np.isfinite(self.spacing)]
        return float(np.median(v)) if len(v) else float("nan")

    def share_above(self, px: float) -> float:
        """Share of the surface sampled coarser than ``px`` pixels."""
        v = self.spacing[np.isfinite(self.spacing)]
        return float(np.mean(v > px)) if len(v) else float("nan")


def spacing_map(renderer, T_wc: Pose, camera: Camera, window: int = 15, gap_px: int = 4) -> ViewSpacing:
    """The scan's sample spacing (camera pixels) seen by ``camera`` at camera-to-world ``T_wc``, per pixel over a
    ``window`` x ``window`` neighbourhood of the surface. ``gap_px``: gaps between points up to 2 x this wide are
    surface (a scan sparser than that shows as holes, and its spacing as at least that wide). Every point counts
    (no level of detail)."""
    cfg = SplatConfig(delta_abs=renderer.cfg.splat.delta_abs, delta_rel=renderer.cfg.splat.delta_rel,
                      near=renderer.cfg.splat.near, lod_points_per_px=0.0)
    if renderer.device.type == "cuda":
        from services.render.splat_torch import splat_torch

        _, depth_t, cnt_t = splat_torch(renderer.cloud, T_wc, camera, cfg)
        depth, count = depth_t.cpu(), cnt_t.cpu().numpy()
    else:
        r = splat(renderer.cloud, T_wc, camera, cfg)
        depth, count = torch.from_numpy(r.depth), r.count
    keep = hierarchical_depth_filter(depth, renderer.cfg.filter).numpy()
    points = np.where(keep, count, 0).astype(np.float32)
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * gap_px + 1, 2 * gap_px + 1))
    surface = cv2.morphologyEx(keep.astype(np.uint8), cv2.MORPH_CLOSE, k) > 0
    area = cv2.boxFilter(surface.astype(np.float32), -1, (window, window), normalize=False)
    n = cv2.boxFilter(points, -1, (window, window), normalize=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.sqrt(area / n)
    s[~surface | (n <= 0)] = np.nan
    return ViewSpacing(s.astype(np.float32), float(surface.mean()))


def survey_poses(positions: np.ndarray, yaws: int = 8, pitch_deg: float = 0.0) -> list[Pose]:
    """Camera-to-world poses looking out level (world z up, pitched by ``pitch_deg``) at ``yaws`` headings from each
    position: where a person or robot would hold a camera."""
    poses = []
    p = math.radians(pitch_deg)
    for c in np.asarray(positions, float).reshape(-1, 3):
        for k in range(yaws):
            a = 2 * math.pi * k / yaws
            z = np.array([math.cos(a) * math.cos(p), math.sin(a) * math.cos(p), math.sin(p)])  # viewing direction
            x = np.array([math.sin(a), -math.cos(a), 0.0])  # right, level
            y = np.cross(z, x)  # down
            poses.append(Pose(np.stack([x, y, z], 1), c))
    return poses


def survey(renderer, positions: np.ndarray, camera: Camera, yaws: int = 8, progress=None) -> np.ndarray:
    """(N, yaws) median sample spacing (``camera``'s pixels) of the views from each position (NaN: no surface seen).
    ``progress``: wraps the iteration over views (a progress bar)."""
    poses = survey_poses(positions, yaws)
    it = progress(poses) if progress is not None else poses
    return np.array([spacing_map(renderer, T, camera).median for T in it], float).reshape(len(positions), yaws)


BANDS = ((0.7, (80, 175, 60)), (1.0, (40, 200, 230)), (1.5, (30, 130, 245)), (float("inf"), (40, 40, 220)))  # BGR


def band_colour(px: float) -> tuple[int, int, int]:
    """Green below 0.7 px, yellow to 1, orange to 1.5, red beyond; grey for no surface."""
    if not math.isfinite(px):
        return (150, 150, 150)
    return next(c for hi, c in BANDS if px <= hi)


def floor_plan(xy_points: np.ndarray, positions: np.ndarray, spacing: np.ndarray, title: str,
               stations: np.ndarray | None = None, width_px: int = 1100) -> np.ndarray:
    """A top-down picture (BGR): the scan's points in grey (stray ones beyond the 0.2-99.8 percentiles left out), the
    scanner ``stations`` (world x, y) as black triangles, each surveyed position as a disc in the colour of its views'
    median spacing and a spoke per heading in that heading's colour."""
    lo = np.minimum(np.percentile(xy_points, 0.2, axis=0), positions[:, :2].min(0))
    hi = np.maximum(np.percentile(xy_points, 99.8, axis=0), positions[:, :2].max(0))
    xy_points = xy_points[np.all((xy_points >= lo) & (xy_points <= hi), axis=1)]
    margin, head = 30, 70
    scale = min((width_px - 2 * margin) / max(hi[0] - lo[0], 1e-6), 1400 / max(hi[1] - lo[1], 1e-6))  # a long site
    h = int((hi[1] - lo[1]) * scale) + 2 * margin + head
    img = np.full((h, width_px, 3), 255, np.uint8)

    def px(p):  # world x right, world y up
        return int(margin + (p[0] - lo[0]) * scale), int(h - margin - (p[1] - lo[1]) * scale)

    q = np.column_stack([margin + (xy_points[:, 0] - lo[0]) * scale, h - margin - (xy_points[:, 1] - lo[1]) * scale])
    q = np.clip(q.astype(int), 0, [width_px - 1, h - 1])
    img[q[:, 1], q[:, 0]] = (205, 205, 205)
    yaws = spacing.shape[1]
    r = max(4, int(0.18 * scale))
    for c, row in zip(positions, spacing):
        u, v = px(c)
        for k, val in enumerate(row):
            a = 2 * math.pi * k / yaws
            cv2.line(img, (u, v), (int(u + 2.2 * r * math.cos(a)), int(v - 2.2 * r * math.sin(a))), band_colour(val), 2,
                     cv2.LINE_AA)
        cv2.circle(img, (u, v), r, band_colour(float(np.nanmedian(row)) if np.isfinite(row).any() else float("nan")),
                   -1, cv2.LINE_AA)
    for st in [] if stations is None else stations:
        u, v = px(st)
        tri = np.array([[u, v - 9], [u - 8, v + 6], [u + 8, v + 6]], np.int32)
        cv2.fillPoly(img, [tri], (0, 0, 0), cv2.LINE_AA)
    cv2.putText(img, title, (margin, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    x = margin
    for (_, col), name in zip(BANDS, ("<= 0.7 px", "0.7-1 px", "1-1.5 px", "> 1.5 px")):
        cv2.circle(img, (x + 8, 52), 7, col, -1, cv2.LINE_AA)
        cv2.putText(img, name, (x + 20, 57), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        x += 130
    if stations is not None and len(stations):
        tri = np.array([[x + 8, 43], [x, 58], [x + 16, 58]], np.int32)
        cv2.fillPoly(img, [tri], (0, 0, 0), cv2.LINE_AA)
        cv2.putText(img, "scanner stations", (x + 22, 57), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return img
