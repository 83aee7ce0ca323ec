"""Camera pose from 2D-3D correspondences: PnP inside RANSAC with non-linear refinement (poselib).

Keypoints are undistorted with the frame's own lens model first, so the solver sees an ideal
pinhole camera with the same focal lengths and principal point (thresholds stay in pixels).
Returns a camera-to-world ``Pose`` and quality figures; ``None`` when there is too little to solve.
Chosen by measurement: see benchmarks/RESULTS.md (poselib vs OpenCV USAC).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.camera import Camera
from services.geometry.se3 import Pose, quat_to_rotmat

__all__ = ["PnpResult", "solve_pnp", "reprojection_errors"]


@dataclass
class PnpResult:
    T_wc: Pose
    inliers: np.ndarray  # (N,) bool
    reproj_rmse_px: float  # over the inliers
    iterations: int
    cov: np.ndarray | None = None  # (6, 6) covariance of a right perturbation of T_wc: (translation m, rotation rad), camera axes
    # set by a caller that gates on the result (Render & Match): the scale its features were matched at
    px_factor: float = 1.0  # frame pixels per feature pixel, relative to the caller's base resolution
    px_deg: float = 0.0  # the frame camera's angle per pixel (degrees)
    source: str = "features"  # what solved it: "features" (matched keypoints), "direct" (aligned patches), "fused"
    disputed: str | None = None  # why a pose to track from is not to be reported, where another estimate contradicts it

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def sigma_t_m(self) -> float:
        """1-sigma uncertainty of the camera centre (metres, largest axis)."""
        return float(np.sqrt(np.linalg.eigvalsh(self.cov[:3, :3]).max())) if self.cov is not None else float("inf")

    @property
    def sigma_r_deg(self) -> float:
        """1-sigma uncertainty of the orientation (degrees, largest axis)."""
        return float(np.degrees(np.sqrt(np.linalg.eigvalsh(self.cov[3:, 3:]).max()))) if self.cov is not None else float("inf")


def pose_covariance(T_wc: Pose, camera: Camera, X_w: np.ndarray, sigma_px: float) -> np.ndarray | None:
    """First-order covariance of the pose from its inlier geometry: sigma^2 (J^T J)^-1.

    Parametrisation: T_wc' = T_wc exp(delta), delta = (rho, phi) in camera axes, so rho is the motion of the
    camera centre. Few, distant or clustered points give a large covariance even at a small reprojection error.
    """
    Xc = T_wc.inverse().transform(X_w)
    X, Y, Z = Xc[:, 0], Xc[:, 1], np.maximum(Xc[:, 2], 1e-6)
    du = np.stack([camera.fx / Z, np.zeros_like(Z), -camera.fx * X / Z ** 2], 1)  # d(u)/d(Xc)
    dv = np.stack([np.zeros_like(Z), camera.fy / Z, -camera.fy * Y / Z ** 2], 1)
    # d(Xc)/d(delta) = [-I, [Xc]x]
    def rows(d):
        rot = np.cross(Xc, d)  # d . ([Xc]x phi) = (Xc x d) . phi ... sign: d^T [Xc]x = -(Xc x d)^T
        return np.concatenate([-d, -rot], 1)
    J = np.concatenate([rows(du), rows(dv)], 0)
    H = J.T @ J
    if np.linalg.cond(H) > 1e12:
        return None
    return sigma_px ** 2 * np.linalg.inv(H)


def reprojection_errors(T_wc: Pose, camera: Camera, uv_undist: np.ndarray, X_w: np.ndarray) -> np.ndarray:
    """Pixel distances between undistorted keypoints and the projections (pinhole, same K) of world points."""
    Xc = T_wc.inverse().transform(X_w)
    z = np.maximum(Xc[:, 2], 1e-9)
    u = camera.fx * Xc[:, 0] / z + camera.cx
    v = camera.fy * Xc[:, 1] / z + camera.cy
    err = np.hypot(u - uv_undist[:, 0], v - uv_undist[:, 1])
    return np.where(Xc[:, 2] > 0, err, np.inf)


def undistort_pixels(camera: Camera, uv: np.ndarray) -> np.ndarray:
    xy = camera.undistort_points(uv)
    return np.column_stack([camera.fx * xy[:, 0] + camera.cx, camera.fy * xy[:, 1] + camera.cy])


SOFT_GATE = 5.0  # the soft refinement weighs every match within this many RANSAC thresholds of the RANSAC pose ...
SOFT_SCALE = 0.5  # ... with a Cauchy loss of this many thresholds' scale (1 px at the tracker's 2 px)


def _pose_wc(pose) -> Pose:
    """Camera-to-world from a poselib (world-to-camera, quaternion w, x, y, z) pose."""
    return Pose(quat_to_rotmat([pose.q[1], pose.q[2], pose.q[3], pose.q[0]]), np.asarray(pose.t)).inverse()


def _poselib_pose(T_wc: Pose):
    """A camera-to-world pose as poselib's (world-to-camera, quaternion w, x, y, z): :func:`_pose_wc`'s inverse."""
    import poselib

    T_cw = T_wc.inverse()
    q = T_cw.quat_xyzw()
    pose = poselib.CameraPose()
    pose.q = [q[3], q[0], q[1], q[2]]
    pose.t = T_cw.t
    return pose


def _poselib_camera(camera: Camera) -> dict:
    """The pinhole camera poselib solves in (keypoints undistorted to it first)."""
    return {"model": "PINHOLE", "width": camera.width, "height": camera.height,
            "params": [camera.fx, camera.fy, camera.cx, camera.cy]}


def _soft_refine(T_wc: Pose, inl: np.ndarray, camera: Camera, uvu: np.ndarray, X_w: np.ndarray,
                 max_error_px: float) -> tuple[Pose, np.ndarray]:
    """RANSAC's pose refined once more over every match within SOFT_GATE thresholds of it, with a Cauchy loss
    (scale SOFT_SCALE thresholds) instead of its hard inlier set; the inliers then re-counted at the threshold.

    Why: with ~1 px of matching noise a 2 px threshold cuts the true matches' tail, and where it cuts depends on
    the pose; where the geometry is weak (one textured wall filling a 75 degree view) the inlier set RANSAC kept
    holds the pose it found, up to 1.3 cm / 0.36 deg along the translation-rotation ambiguity, while the same
    matches solved softly land 0.3-0.5 cm / 0.1 deg from the truth from any start (benchmarks/RESULTS.md, stop
    36). Kept only when it keeps at least 80 % of RANSAC's inlier count (a soft loss an outlier cluster pulled
    away keeps fewer)."""
    import poselib

    near = reprojection_errors(T_wc, camera, uvu, X_w) < SOFT_GATE * max_error_px
    if near.sum() < 6:
        return T_wc, inl
    pose, _ = poselib.refine_absolute_pose(uvu[near], X_w[near], _poselib_pose(T_wc), _poselib_camera(camera), {
        "loss_type": "CAUCHY", "loss_scale": SOFT_SCALE * max_error_px, "max_iterations": 50})
    T_soft = _pose_wc(pose)
    inl_soft = reprojection_errors(T_soft, camera, uvu, X_w) < max_error_px
    if not np.all(np.isfinite(T_soft.t)) or inl_soft.sum() < 0.8 * inl.sum():
        return T_wc, inl
    return T_soft, inl_soft


def solve_pnp(uv: np.ndarray, X_w: np.ndarray, camera: Camera, max_error_px: float = 2.0, min_points: int = 6,
              max_iterations: int = 2000, initial: Pose | None = None, min_iterations: int = 1000,
              soft: bool = True) -> PnpResult | None:
    """RANSAC-PnP (P3P minimal solver, local optimisation, Cauchy-loss refinement on its inliers), then with
    ``soft`` a last Cauchy refinement over every match within SOFT_GATE x ``max_error_px`` (:func:`_soft_refine`)."""
    import poselib

    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    X_w = np.asarray(X_w, np.float64).reshape(-1, 3)
    if len(uv) < max(min_points, 4):
        return None
    uvu = undistort_pixels(camera, uv) if camera.is_distorted else uv
    # min_iterations: poselib's default 1000 even when the inlier ratio says 70 suffice; tracking with
    # many inliers can stop early (4.5 -> 1.2 ms on 300 matches), hard relocalizations gain from the rest
    ransac = {"max_reproj_error": float(max_error_px), "max_iterations": int(max_iterations),
              "min_iterations": int(min(min_iterations, max_iterations)),
              "success_prob": 0.9999}
    bundle = {"loss_type": "CAUCHY", "loss_scale": float(max_error_px) * 0.5, "max_iterations": 50}
    kw = {} if initial is None else {"initial_pose": _poselib_pose(initial)}
    pose, info = poselib.estimate_absolute_pose(uvu, X_w, _poselib_camera(camera), ransac, bundle, **kw)
    inl = np.asarray(info.get("inliers", []), bool)
    if inl.sum() < min_points:
        return None
    T_wc = _pose_wc(pose)
    if soft:
        T_wc, inl = _soft_refine(T_wc, inl, camera, uvu, X_w, float(max_error_px))
    err = reprojection_errors(T_wc, camera, uvu, X_w)
    rmse = float(np.sqrt(np.mean(err[inl] ** 2)))
    cov = pose_covariance(T_wc, camera, X_w[inl], max(rmse, 0.3))
    return PnpResult(T_wc, inl, rmse, int(info.get("iterations", 0)), cov)
