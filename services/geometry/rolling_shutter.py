"""Rolling shutter: a frame whose rows were read one after another, re-sampled as if read all at once.

Phones (and many robot cameras) read their sensor row by row, top to bottom, over 10-30 ms. While the camera
turns, each row sees the scene from a slightly different orientation: at 180 deg/s and 20 ms, the bottom row is
3.6 deg further on than the top one. A pose solved as if the frame were taken at one instant is then off by
centimetres and tenths of a degree (`cristal sim --rolling-shutter 20`: office walk, 0.46 -> 1.23 cm, 0.044 ->
0.251 deg, frames reported 5 cm / 1.4 deg off). :func:`unroll` re-samples the frame into the view of its middle
row, from the camera's motion (the localizer's motion model or the device's odometry), so the frame's stamp and
pose are the middle row's. A turn moves the image by tens of pixels over a readout, the same for near and far; the
travel (1.2 m/s over 10 ms at 1.5 m: 4 px) shrinks with distance and is undone at the depth of each part of the
frame (:func:`depth_field`: the scene points the localizer expects there), or at one depth, the scene's median.
numpy + OpenCV, no torch.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from services.geometry.camera import Camera
from services.geometry.se3 import Pose, rotmat_to_rotvec

__all__ = ["row_time", "unroll", "angular_velocity", "unroll_moving", "rate_changed", "depth_field", "ShutterTrack",
           "NOT_UNDONE"]

NOT_UNDONE = "rolling shutter not undone yet (the motion is measured over the next frames)"


def row_time(v: np.ndarray, height: int, readout_s: float) -> np.ndarray:
    """Seconds from the middle row's time to when sensor row(s) ``v`` (pixel centres at integers) were read."""
    return ((np.asarray(v, np.float64) + 0.5) / height - 0.5) * readout_s


def angular_velocity(R_prev_now: np.ndarray, dt: float) -> np.ndarray:
    """Rad/s in the camera frame from the rotation between two frames (``T_prev^-1 @ T_now``'s) ``dt`` apart."""
    return rotmat_to_rotvec(R_prev_now) / max(dt, 1e-6)


def unroll(image: np.ndarray, camera: Camera, omega: np.ndarray, readout_s: float, grid_px: int = 8,
           velocity: np.ndarray | None = None, depth_m: float | np.ndarray | None = None) -> np.ndarray:
    """``image`` re-sampled as if every row had been read at the middle row's time, the camera turning at
    ``omega`` (rad/s, camera frame: x right, y down, z forward) while ``readout_s`` passed from the first row to the
    last, and travelling at ``velocity`` (m/s, camera frame) through a scene at ``depth_m``: one depth (m), or a grid
    of them over the frame (:func:`depth_field`). Same size, same lens (distortion kept). The displacement is
    computed on a grid of ``grid_px`` cells and interpolated bilinearly (it is smooth: a hundredth of a pixel from the
    exact one at 8 px cells)."""
    omega = np.asarray(omega, np.float64).reshape(3)
    travels = velocity is not None and depth_m is not None and bool(np.any(velocity)) and bool(np.all(depth_m))
    if readout_s <= 0 or not (np.any(omega) or travels):
        return image
    H, W = camera.height, camera.width
    gw, gh = -(-W // grid_px), -(-H // grid_px)
    # cell centres, where cv2.resize's bilinear interpolation puts the grid's samples
    u, v = np.meshgrid((np.arange(gw) + 0.5) * W / gw - 0.5, (np.arange(gh) + 0.5) * H / gh - 0.5)
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    rays = np.concatenate([camera.undistort_points(uv), np.ones((len(uv), 1))], axis=1)  # the middle row's view
    src_v = uv[:, 1].copy()
    if travels and np.ndim(depth_m) == 2:  # the depth in each cell's direction
        g = np.asarray(depth_m, np.float64)
        iy = np.clip((uv[:, 1] + 0.5) * g.shape[0] / H, 0, g.shape[0] - 1).astype(int)
        ix = np.clip((uv[:, 0] + 0.5) * g.shape[1] / W, 0, g.shape[1] - 1).astype(int)
        depth_m = g[iy, ix][:, None]
    for _ in range(2):  # the source row decides its time: one fixed-point step is within a hundredth of a pixel
        R = _rotations(omega, row_time(src_v, H, readout_s))  # row camera -> middle-row camera
        X = np.einsum("nji,nj->ni", R, rays)  # R^T r: the direction in the row's camera
        if travels:
            X = X * depth_m - row_time(src_v, H, readout_s)[:, None] * np.asarray(velocity, np.float64)[None, :]
        src, _ = camera.project(X)
        src_v = np.clip(src[:, 1], 0, H - 1)
    d = cv2.resize((src - uv).reshape(gh, gw, 2).astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
    px, py = _pixels(W, H)
    return cv2.remap(image, px + d[..., 0], py + d[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


@lru_cache(maxsize=4)
def _pixels(W: int, H: int) -> tuple[np.ndarray, np.ndarray]:
    return tuple(np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32)))


def unroll_moving(image: np.ndarray, camera: Camera, D: Pose, dt: float, readout_s: float,
                  depth_m: float | np.ndarray | None) -> np.ndarray:
    """:func:`unroll` for a camera moving by ``D`` (``T_prev^-1 @ T_now``) over ``dt`` seconds: its turn, and its
    travel at ``depth_m`` (a :func:`depth_field`, or the scene's median depth; None: the turn only)."""
    return unroll(image, camera, angular_velocity(D.R, dt), readout_s, velocity=D.t / max(dt, 1e-6), depth_m=depth_m)


def depth_field(Xc: np.ndarray, camera: Camera, cell_px: int = 16) -> np.ndarray | None:
    """The scene's depth (m) over the frame, on a grid of ``cell_px`` cells, from points ``Xc`` (N, 3) in the camera
    frame: each cell the harmonic mean of the points it sees (the travel's skew goes as 1 / depth), a cell with none
    that of its nearest neighbours', and beyond them all the points'. None without points in front of the camera.
    A camera walking at 1 m/s with a 20 ms readout skews a point 1 m away by 5 px over the frame and one 5 m away by
    1 px at VGA: undone at one depth, the near and far ends of a room keep 2-3 px of it."""
    Xc = np.asarray(Xc, np.float64).reshape(-1, 3)
    Xc = Xc[(Xc[:, 2] > 0.1) & (np.abs(Xc[:, 0]) < 2 * Xc[:, 2]) & (np.abs(Xc[:, 1]) < 2 * Xc[:, 2])]  # (ahead: a lens model
    if not len(Xc):  # folds back far outside its field of view)
        return None
    uv, _ = camera.project(Xc)
    gh, gw = max(1, -(-camera.height // cell_px)), max(1, -(-camera.width // cell_px))
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    if not ok.any():
        return None
    cell = (uv[ok, 1] * gh / camera.height).astype(int) * gw + (uv[ok, 0] * gw / camera.width).astype(int)
    inv = 1.0 / Xc[ok, 2]
    n = np.bincount(cell, minlength=gh * gw).reshape(gh, gw).astype(np.float32)
    s = np.bincount(cell, inv, minlength=gh * gw).reshape(gh, gw).astype(np.float32)
    kernel = np.ones((3, 3), np.float32)
    for _ in range(max(gh, gw)):  # empty cells take their neighbours' mean, ring by ring
        empty = n == 0
        if not empty.any():
            break
        n2, s2 = cv2.filter2D(n, -1, kernel, borderType=cv2.BORDER_CONSTANT), cv2.filter2D(s, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        fill = empty & (n2 > 0)
        if not fill.any():
            break
        s[fill], n[fill] = s2[fill] / n2[fill], 1.0
    mean_inv = float(inv.mean())
    return 1.0 / np.where(n > 0, s / np.maximum(n, 1e-9), mean_inv)


def rate_changed(D_then: Pose, dt_then: float, D_now: Pose, dt_now: float, camera: Camera, readout_s: float,
                 px: float = 0.5) -> bool:
    """Whether the turn rate of motion ``D_now`` (over ``dt_now``) differs from ``D_then``'s enough to move the
    frame's first and last rows by more than ``px`` pixels: a frame unrolled with the older motion is worth
    unrolling again."""
    dw = angular_velocity(D_now.R, dt_now) - angular_velocity(D_then.R, dt_then)
    return float(np.linalg.norm(dw)) * readout_s / 2 * max(camera.fx, camera.fy) > px


class ShutterTrack:
    """Whether a tracker's frames may be reported under a rolling shutter (both localizers keep one). A frame is
    unrolled with the motion between the two frames before it; that motion is only right once those frames were
    unrolled too, or when the device's odometry gives it: a cold frame turning at 90 deg/s with a 30 ms readout was
    relocalized 12.6 cm / 1.5 deg off, and the motion from it skewed the next frames (tests/test_pnl.py)."""

    def __init__(self):
        self.run = 0  # frames in a row that were unrolled

    def reset(self) -> None:
        self.run = 0

    def step(self, readout_s: float, unrolled: bool, from_device: bool) -> bool:
        """After deciding whether this frame was ``unrolled`` (with the device's motion: ``from_device``): whether its
        pose may be reported. Always with a global shutter (``readout_s`` 0)."""
        settled = readout_s <= 0 or (unrolled and (from_device or self.run >= 2))
        self.run = self.run + 1 if unrolled else 0
        return settled


def _rotations(omega: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """(N, 3, 3): the rotation turned through in each ``tau`` at ``omega`` (camera frame)."""
    if len(tau) == 0:
        return np.zeros((0, 3, 3))
    # Rodrigues, vectorised (rotvec_to_rotmat one at a time would dominate the cost)
    rv = omega[None, :] * tau[:, None]
    th = np.linalg.norm(rv, axis=1)
    k = np.where(th[:, None] > 1e-12, rv / np.maximum(th, 1e-12)[:, None], 0.0)
    Kx = np.zeros((len(tau), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 0] = -k[:, 2], k[:, 1], k[:, 2]
    Kx[:, 1, 2], Kx[:, 2, 0], Kx[:, 2, 1] = -k[:, 0], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3)[None] + s * Kx + (1 - c) * (Kx @ Kx)
