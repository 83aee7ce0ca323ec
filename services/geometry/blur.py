"""Motion blur as camera geometry: what an image looks like when the camera moves during the exposure.

The simulator blurs its camera frames with it, and Render & Match blurs its renders with it so that a
render matches a blurred live frame: features detected on a blurred image sit at different places than
on a sharp one (measured: a systematic 2-3 px shift and a third of the matches lost in a fast pan),
which no robust estimator removes. Blurring the render with the frame's own motion restores both.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.kernels import optional_kernels

__all__ = ["motion_blur", "motion_blur_linear", "blur_length_px"]


@functools.lru_cache(maxsize=8)
def _rays(camera: Camera) -> np.ndarray:
    return camera.pixel_rays().reshape(-1, 3)


class _Warp:
    """Where each pixel of a camera at another pose finds its colour in the sharp image (via the sharp depth)."""

    def __init__(self, depth: np.ndarray, camera: Camera, T_wc: Pose):
        d = depth.reshape(-1, 1).astype(np.float64)
        self.points = _rays(camera) * np.where(d > 0, d, 50.0)  # pixels without depth: far away
        self.camera, self.T_cw = camera, T_wc.inverse()

    def maps(self, T_k: Pose) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) float32 sampling maps, x and y, for the camera at ``T_k``."""
        T_ck = self.T_cw @ T_k  # sub-pose camera -> sharp camera
        W, H = self.camera.width, self.camera.height
        kern = optional_kernels("services.geometry.blur_kernels")
        if kern is not None:  # the same arithmetic a pixel at a time, ~10x faster
            c = self.camera
            return kern.sampling_maps(self.points, T_ck.R, T_ck.t, c.fx, c.fy, c.cx, c.cy,
                                      np.asarray(c.distortion, np.float64), W, H)
        with np.errstate(all="ignore"):
            uv, z = self.camera.project(self.points @ T_ck.R.T + T_ck.t)
        # points behind the camera or far outside the image (a wild motion guess, a lens model beyond its range)
        # project anywhere, NaN included; OpenCV reflects an outside coordinate into the image one image width at
        # a time, so one at 1e9 px costs millions of steps (a render blurred for an HD frame took minutes)
        uv = np.where(np.isfinite(uv).all(axis=1, keepdims=True) & (z[:, None] > 0), uv, -1.0)
        mx = np.clip(uv[:, 0], -W, 2 * W - 1).reshape(H, W).astype(np.float32)
        my = np.clip(uv[:, 1], -H, 2 * H - 1).reshape(H, W).astype(np.float32)
        return mx, my


def _average(src: np.ndarray, maps) -> np.ndarray:
    acc = np.zeros_like(src)
    for n, (mx, my) in enumerate(maps, 1):
        acc += cv2.remap(src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return acc / n


def motion_blur(sharp: np.ndarray, depth: np.ndarray, camera: Camera, T_wc: Pose, sub_poses: list[Pose]) -> np.ndarray:
    """Average of ``sharp`` (taken at ``T_wc``, z-depth ``depth``) as seen from each sub-exposure pose.

    Returns float32 (the caller rounds). Pixels without depth are treated as far away.
    """
    src = sharp.astype(np.float32)
    if len(sub_poses) <= 1:
        return src
    warp = _Warp(depth, camera, T_wc)
    return _average(src, (warp.maps(T) for T in sub_poses))


def motion_blur_linear(sharp: np.ndarray, depth: np.ndarray, camera: Camera, T_wc: Pose, T_start: Pose, T_end: Pose,
                       n: int) -> np.ndarray:
    """``motion_blur`` with the image motion interpolated linearly between the exposure's two ends.

    Two projections instead of ``n``: ~10x faster, and exact for a short exposure (the image motion
    over a few milliseconds is linear to a fraction of a pixel). Returns float32.
    """
    src = sharp.astype(np.float32)
    if n <= 1:
        return src
    warp = _Warp(depth, camera, T_wc)
    (x0, y0), (x1, y1) = warp.maps(T_start), warp.maps(T_end)
    dx, dy = x1 - x0, y1 - y0
    return _average(src, ((x0 + dx * (j / (n - 1)), y0 + dy * (j / (n - 1))) for j in range(n)))


def blur_length_px(camera: Camera, T_a: Pose, T_b: Pose, depth_m: float = 1.5) -> float:
    """Approximate image motion (pixels) between two poses of a camera looking at things ``depth_m`` away."""
    dt, dr = T_a.distance_to(T_b)
    return float(np.deg2rad(dr) * camera.fx + dt * camera.fx / depth_m)
