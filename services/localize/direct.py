"""Direct tracking: a camera pose from patches aligned into the live frame, no keypoints (numpy + OpenCV only).

Used by the light P&L localizer (patches stored beside the map) and by Render & Match (patches cut from the
keyframe render). Each patch is warped into the live view through its surface's tangent plane and the live
frame is aligned to it (:func:`services.prebuild.patches.align_to_patches`), which returns where each
point appears and that measurement's 2x2 information (its patch's gradient structure: an edge-like patch
says nothing along the edge). The pose is then solved by motion-only Gauss-Newton, whitened by those
informations, and alignment and solve alternate until the pose moves less than half its predicted sigma.
Last, the minimum is probed: aligned and solved again from far along its weakest direction, a pose should come back,
and where it does not, its covariance takes the difference (:func:`_probed`).

Poses here are world-to-camera (R, t) with a left perturbation exp(dx) T_cw, dx = (omega, v) in camera axes.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from services.geometry.se3 import Pose
from services.kernels import optional_kernels
from services.prebuild.patches import LandmarkPatches, align_to_patches

__all__ = ["DirectConfig", "DirectPose", "solve_motion_only", "pose_covariance", "cov_sigmas", "align_and_solve",
           "undistorted_gray", "noise_ratio"]

CHI2_2DOF = 5.991
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DirectConfig:
    passes: int = 3  # alignment and solve alternate until the pose moves less than half its sigma, at most this often
    sigma_px: float = 0.5  # a corner patch's alignment noise (1 sigma, px; 0.2-0.3 px measured at the true pose)
    rmse_floor: float = 1.0  # the covariance assumes at least sigma_px of noise (whitened RMSE floor)
    min_inliers: int = 15
    min_inlier_frac: float = 0.5  # of the converged alignments, this share must agree with the pose
    max_moved_px: float | None = None  # from a keypoint pose: the projections may move at most this far (median)
    warp_noise_ref: float = 0.0  # > 0: weigh each alignment by its warp (services.prebuild.patches.warp_noise_factor)
    probe_sigmas: float = 0.0  # > 0: test the minimum's basin from this many sigmas along its weakest direction (_probed)
    probe_max_px: float = 2.0  # ... a step moving the points at most this far (RMS, px)


@dataclass
class DirectPose:
    R: np.ndarray  # world-to-camera rotation
    t: np.ndarray  # world-to-camera translation
    inliers: int
    rmse: float  # whitened: standard deviations of sigma_px
    cov: np.ndarray  # (6, 6) of dx = (omega, v), left perturbation of T_cw
    converged: bool
    missed: np.ndarray | None = None  # patch indices (of those aligned) that converged but miss the pose grossly

    @property
    def T_wc(self) -> Pose:
        return Pose(self.R.T, -self.R.T @ self.t)

    @property
    def sigma_m(self) -> float:
        """1-sigma camera-centre uncertainty (largest axis); at least the last step when not converged."""
        return cov_sigmas(self.cov)[0]

    @property
    def sigma_deg(self) -> float:
        return cov_sigmas(self.cov)[1]

    def cov_right_wc(self) -> np.ndarray:
        """The covariance as services.geometry.pnp.PnpResult keeps it: a right perturbation of T_wc,
        (translation, rotation) in camera axes (T_wc exp(delta) = (exp(dx) T_cw)^-1: delta = -dx, reordered)."""
        o = [3, 4, 5, 0, 1, 2]
        return self.cov[np.ix_(o, o)]


def noise_ratio(gray: np.ndarray) -> float:
    """The grey frame's pixel noise over its grey-level spread: Immerkaer's estimate of the noise's sigma (the mean
    absolute response to a difference of two Laplacians, blind to smooth shading and first-order edges) divided by
    the frame's standard deviation. Clean frames of the simulated walks: 0.013-0.046; a dim room filmed at a short
    exposure (a third of the light, JPEG) ~0.08; a high-ISO frame ~0.3 (benchmarks/photometric.py)."""
    if gray.shape[0] < 3 or gray.shape[1] < 3:
        return float("inf")
    g = gray if gray.dtype in (np.uint8, np.float32) else gray.astype(np.float32)
    sd = float(cv2.meanStdDev(g)[1][0, 0])  # one pass, float64 sums
    if sd < 1e-6:
        return float("inf")
    k = np.array([1.0, -2.0, 1.0], np.float32)  # the 3x3 difference of Laplacians is this second difference squared
    r = cv2.sepFilter2D(g, cv2.CV_16S if g.dtype == np.uint8 else cv2.CV_32F, k, k)[1:-1, 1:-1]  # exact on uint8
    return math.sqrt(math.pi / 2) * cv2.norm(r, cv2.NORM_L1) / r.size / 6.0 / sd


def undistorted_gray(image: np.ndarray, camera, cache: dict, denoise_above: float = float("inf"),
                     denoise_sigma_px: float = 1.2) -> np.ndarray:
    """``image`` (grey or BGR) in grey, undistorted to ``camera``'s pinhole intrinsics, float32 (what
    :func:`align_and_solve` aligns to). ``cache`` keeps the undistortion maps of the last camera.
    A frame whose :func:`noise_ratio` exceeds ``denoise_above`` is smoothed first (Gaussian, ``denoise_sigma_px``):
    the alignment's templates are noise-free renders, and in a dark or high-ISO frame noise and JPEG blocks
    otherwise decide where a window converges (benchmarks/photometric.py, P&L: dark 84 -> 150 of 150 frames, high
    ISO 145 -> 150). Clean frames are left sharp: smoothed, the office walk lost 1 frame and 0.03 cm of APE."""
    g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if math.isfinite(denoise_above) and noise_ratio(g) > denoise_above:
        g = cv2.GaussianBlur(g.astype(np.float32), (0, 0), denoise_sigma_px)
    if camera.is_distorted:
        key = (camera.width, camera.height, tuple(camera.K.ravel().tolist()), tuple(np.ravel(camera.dist).tolist()))
        if key not in cache:
            cache.clear()
            cache[key] = cv2.initUndistortRectifyMap(camera.K, camera.dist, None, camera.K, (camera.width, camera.height),
                                                     cv2.CV_32FC1)
        g = cv2.remap(g, *cache[key], cv2.INTER_LINEAR)
    return g.astype(np.float32)


def cov_sigmas(C: np.ndarray) -> tuple[float, float]:
    """The largest 1-sigma camera-centre (m) and orientation (deg) uncertainties of a covariance of (omega, v)."""
    if not np.all(np.isfinite(C)):
        return float("inf"), float("inf")
    s = [math.sqrt(max(float(np.linalg.eigvalsh(B).max()), 0.0)) for B in (C[3:, 3:], C[:3, :3])]
    return s[0], math.degrees(s[1])


def _projection_jacobians(Xc: np.ndarray, fx: float, fy: float) -> tuple[np.ndarray, np.ndarray]:
    """d(u, v)/d(omega, v) of camera points Xc under a left perturbation of T_cw."""
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    iz = 1.0 / np.maximum(z, 1e-6)
    a, b = fx * iz, fy * iz
    Ju, Jv = np.empty((len(Xc), 6)), np.empty((len(Xc), 6))
    Ju[:, 0], Ju[:, 1], Ju[:, 2], Ju[:, 3], Ju[:, 4], Ju[:, 5] = -a * x * y * iz, a * (z + x * x * iz), -a * y, a, 0.0, -a * x * iz
    Jv[:, 0], Jv[:, 1], Jv[:, 2], Jv[:, 3], Jv[:, 4], Jv[:, 5] = -b * (z + y * y * iz), b * x * y * iz, b * x, 0.0, b, -b * y * iz
    return Ju, Jv


def _sqrt_info(info: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lower-triangular L with L L^T = info, as (l11, l21, l22): the whitened residual is L^T e."""
    l11 = np.sqrt(np.maximum(info[:, 0, 0], 1e-12))
    l21 = info[:, 1, 0] / l11
    l22 = np.sqrt(np.maximum(info[:, 1, 1] - l21 * l21, 1e-12))
    return l11, l21, l22


def solve_motion_only(P: np.ndarray, uv: np.ndarray, info: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                      rounds=(4, 3, 2)) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Gauss-Newton on the world-to-camera pose (R, t) from world points ``P`` seen at undistorted pixels ``uv``,
    each with information ``info`` (M, 2, 2) in pixels^-2: Huber weights, and after each round of iterations
    the matches are classified again by chi-square (2 dof, 95 %) on their whitened residuals.
    Returns (R, t, inlier mask, whitened RMSE of the inliers); the RMSE is inf when fewer than 6 remain."""
    l11, l21, l22 = _sqrt_info(info)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    R, t = np.array(R, np.float64, order="C"), np.array(t, np.float64)  # (writable, C: the kernel's one signature)

    def whitened(R, t, P, uv, l11, l21, l22):
        Xc = P @ R.T + t
        iz = 1.0 / np.maximum(Xc[:, 2], 1e-6)
        ex = fx * Xc[:, 0] * iz + cx - uv[:, 0]
        ey = fy * Xc[:, 1] * iz + cy - uv[:, 1]
        return l11 * ex + l21 * ey, l22 * ey, Xc

    inl = np.ones(len(P), bool)
    huber = math.sqrt(CHI2_2DOF)
    e2s = np.zeros(len(P))
    kern = optional_kernels("services.localize.direct_kernels")
    H, g = np.empty((6, 6)), np.empty(6)
    for iters in rounds:
        m = (P, uv, l11, l21, l22) if inl.all() else (P[inl], uv[inl], l11[inl], l21[inl], l22[inl])  # this round's
        n = len(m[0])
        if kern is None:  # whitened rows: (l11 Ju + l21 Jv, e1) then (l22 Jv, e2)
            J, e = np.empty((2 * n, 6)), np.empty(2 * n)
        for _ in range(iters):
            if kern is not None:
                kern.normal_equations(*m, R, t, fx, fy, cx, cy, huber, H, g)
            else:
                e[:n], e[n:], Xc = whitened(R, t, *m)
                r = np.sqrt(e[:n] * e[:n] + e[n:] * e[n:])
                w = np.where(r <= huber, 1.0, huber / np.maximum(r, 1e-12))
                Ju, Jv = _projection_jacobians(Xc, fx, fy)
                np.multiply(m[2][:, None], Ju, out=J[:n])
                J[:n] += m[3][:, None] * Jv
                np.multiply(m[4][:, None], Jv, out=J[n:])
                Jw = J * np.concatenate([w, w])[:, None]
                H, g = Jw.T @ J, Jw.T @ e
            try:
                dx = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
            except np.linalg.LinAlgError:
                return R, t, np.zeros(len(P), bool), float("inf")
            dR = cv2.Rodrigues(dx[:3])[0]
            R = dR @ R
            t = dR @ t + dx[3:]
            if np.abs(dx).max() < 1e-6:
                break
        e1, e2, Xc = whitened(R, t, P, uv, l11, l21, l22)
        e2s = e1 * e1 + e2 * e2
        inl = (e2s <= CHI2_2DOF) & (Xc[:, 2] > 0.05)
        if inl.sum() < 6:
            return R, t, inl, float("inf")
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return np.eye(3), np.zeros(3), np.zeros(len(P), bool), float("inf")
    return R, t, inl, float(math.sqrt(e2s[inl].mean()))


def pose_covariance(P: np.ndarray, info: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, rmse: float,
                    floor: float = 0.5) -> np.ndarray:
    """First-order covariance (6, 6) of dx = (omega, v) from the inliers ``P`` with information ``info``
    (M, 2, 2), scaled by max(rmse, floor)^2; all inf when degenerate."""
    bad = np.full((6, 6), np.inf)
    if len(P) < 6 or not math.isfinite(rmse):
        return bad
    Ju, Jv = _projection_jacobians(P @ R.T + t, K[0, 0], K[1, 1])
    w00, w01, w11 = info[:, 0, 0, None], info[:, 0, 1, None], info[:, 1, 1, None]
    cross = (Ju * w01).T @ Jv
    H = (Ju * w00).T @ Ju + cross + cross.T + (Jv * w11).T @ Jv
    try:
        return np.linalg.inv(H) * max(rmse, floor) ** 2
    except np.linalg.LinAlgError:
        return bad


def align_and_solve(lp: LandmarkPatches, pidx: np.ndarray, P: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                    gray: np.ndarray, cfg: DirectConfig = DirectConfig(), blur: list | None = None) -> DirectPose | None:
    """The pose from aligning the live frame (``gray``: undistorted, float32, pinhole ``K``) to the patches
    ``pidx`` of world points ``P``, starting from the world-to-camera pose (R, t). None when too few
    alignments converge or agree; a pose that has not converged after ``cfg.passes`` carries its last step
    in its covariance (it is at least that uncertain). ``blur``: the camera's motion during the exposure
    as camera-frame deltas (R_d, t_d) around the frame's pose (T_cw_i = D_i T_cw): the templates are smeared
    alike. With ``cfg.probe_sigmas`` the result's covariance also covers how far its minimum is flat (:func:`_probed`).
    The result names the patches whose alignments converged but miss its pose grossly (``missed``, :func:`_gross`): what
    they show has moved or gone since the templates were cut."""
    if len(P) < cfg.min_inliers:
        return None
    w = 1.0 / cfg.sigma_px ** 2
    X0 = P @ R.T + t
    u0 = X0[:, :2] / X0[:, 2:3]
    out, step = None, (float("inf"), float("inf"))
    for _ in range(cfg.passes):
        poses = [(Rd @ R, Rd @ t + td) for Rd, td in blur] if blur else None
        q, ok, info = align_to_patches(lp, pidx, P, R, t, K, gray, blur=poses, warp_noise_ref=cfg.warp_noise_ref)
        if ok.sum() < cfg.min_inliers:
            break
        R2, t2, inl, rmse = solve_motion_only(P[ok], q[ok], info[ok] * w, K, R, t, rounds=(4, 2))
        if inl.sum() < max(cfg.min_inliers, cfg.min_inlier_frac * ok.sum()) or not math.isfinite(rmse):
            break
        if cfg.max_moved_px is not None:
            X2 = P @ R2.T + t2
            moved = np.median(np.linalg.norm(K[0, 0] * (u0 - X2[:, :2] / np.maximum(X2[:, 2:3], 1e-6)), axis=1))
            if not moved <= cfg.max_moved_px:  # a degenerate set
                break
        dR = R2 @ R.T
        step = (float(np.linalg.norm(R2.T @ t2 - R.T @ t)), math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(dR) - 1) / 2)))))
        R, t = R2, t2
        cov = pose_covariance(P[ok][inl], info[ok][inl] * w, K, R, t, rmse, cfg.rmse_floor)
        out = DirectPose(R, t, int(inl.sum()), rmse, cov, False)
        fit = (ok, q, info)  # the alignments this pose was solved from
        sigma_m, sigma_deg = cov_sigmas(cov)
        if step[0] <= 0.5 * sigma_m and step[1] <= 0.5 * sigma_deg:
            out.converged = True
            break
    if out is None:
        return None
    if not out.converged:  # at least as uncertain as the last step (isotropically, in both blocks)
        c = out.cov.copy()
        c[3:, 3:] += np.eye(3) * step[0] ** 2
        c[:3, :3] += np.eye(3) * math.radians(step[1]) ** 2
        out.cov = c
    ok, q, info = fit
    out.missed = pidx[ok][_gross(P[ok], q[ok], info[ok] * w, K, out.R, out.t)]
    return _probed(out, lp, pidx, P, K, gray, cfg, blur)


def _gross(P: np.ndarray, uv: np.ndarray, info: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
           factor: float = 3.0) -> np.ndarray:
    """Which alignments ``uv`` of world points ``P`` (information ``info``, px^-2) miss the pose (R, t) grossly: their
    whitened squared residual over ``factor`` x the 95 % chi-square bound, a 1-in-10^4 event for a measurement the
    noise model fits (a corner ~2 px off at 0.5 px 1-sigma; an edge-like patch only across its edge)."""
    Xc = P @ R.T + t
    z = np.maximum(Xc[:, 2], 1e-6)
    e = np.column_stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]]) - uv
    return np.einsum("ni,nij,nj->n", e, info, e) > factor * CHI2_2DOF


def _probed(d: DirectPose, lp: LandmarkPatches, pidx: np.ndarray, P: np.ndarray, K: np.ndarray, gray: np.ndarray,
            cfg: DirectConfig, blur: list | None) -> DirectPose:
    """``d`` with its covariance widened where its minimum is flatter than that covariance says. Aligned and solved
    again from ``cfg.probe_sigmas`` sigmas along its weakest direction (at most ``cfg.probe_max_px`` RMS pixels away),
    the pose should come back; where it stays more than 3 sigma away, the difference is added to the covariance (the
    frame cannot tell the two poses apart). The first-order covariance assumes every alignment lands where its
    template truly is, wherever it starts; a patch cut across an occluding edge holds background that moves by
    parallax, and it aligns near wherever it starts. Facing a wall 7.4 m off through a 52 deg lens (office seed 21,
    frame 161), where a sideways step and a turn look alike on the wall, probes 3 sigma off came back within 0.2 sigma,
    probes 10 and 30 sigma off stayed 9 and 26 sigma off: the patches on a doorway's lintel 1.5 m off moved with the
    start (up to 7 px) and held the pose there. The walk was reported 5-7 cm off at 0.2 cm 1 sigma
    (benchmarks/RESULTS.md, stop 51)."""
    if cfg.probe_sigmas <= 0 or not np.all(np.isfinite(d.cov)):
        return d
    Xc = P @ d.R.T + d.t
    depth = float(np.median(Xc[:, 2]))
    s = np.r_[[depth] * 3, [1.0] * 3]  # rotation as the metres it moves the scene by
    lam, V = np.linalg.eigh(d.cov * np.outer(s, s))
    e = V[:, -1] * math.sqrt(max(lam[-1], 0.0)) / s  # 1 sigma along the weakest direction, in (omega, v)
    Ju, Jv = _projection_jacobians(Xc, K[0, 0], K[1, 1])
    px = math.sqrt(float(np.mean((Ju @ e) ** 2 + (Jv @ e) ** 2)))  # RMS pixels 1 sigma moves the points
    k = min(cfg.probe_sigmas, cfg.probe_max_px / max(px, 1e-9))
    dx = k * e
    dR = cv2.Rodrigues(dx[:3])[0]
    q = align_and_solve(lp, pidx, P, dR @ d.R, dR @ d.t + dx[3:], K, gray,
                        dataclasses.replace(cfg, probe_sigmas=0.0), blur)
    if q is None:
        return d
    dR = q.R @ d.R.T
    diff = np.concatenate([cv2.Rodrigues(dR)[0].ravel(), q.t - dR @ d.t])
    try:
        m2 = float(diff @ np.linalg.solve(d.cov, diff))
    except np.linalg.LinAlgError:
        return d
    if m2 <= 9.0:
        return d
    log.debug("direct: the minimum is flat, a probe %.1f sigma off stayed %.1f sigma off", k, math.sqrt(m2))
    d.cov = d.cov + np.outer(diff, diff)
    return d
