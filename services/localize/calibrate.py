"""A camera's intrinsics refined against the scan (``cristal calibrate``).

Poses are no better than the intrinsics they are solved with, and the gates do not see a wrong camera: the
poses absorb the error consistently. Office walk (Render & Match, 2026-12-01): with the focal length 1 % off
and the principal point 3 px off, 264/300 frames passed every gate at **4.0 cm / 0.41 deg** (0.38 cm /
0.048 deg with the right camera); with the focal length 2 % long and 5 px, 262 frames at 8.8 cm / 0.52 deg.
Phones refocus, and headset calibrations drift. From that camera, two rounds here gave the focal length 0.23 %
long and the principal point within 0.2 px, and the walk 269 frames at 0.84 cm / 0.058 deg.

The scan is a calibration target that fills the view. Each localized frame, rendered at its pose with the
camera as currently estimated, gives hundreds of 2D-3D correspondences: XFeat matches, re-aligned by
Lucas-Kanade, with the scan points behind the render's keypoints. fx, fy, cx and cy are fitted to all of them
(OpenCV's ``calibrateCamera`` from the current guess, one pose per frame, the lens distortion kept), alternating
with each frame's PnP-RANSAC inliers under the estimate so far. The correspondences come from renders made
with the camera being corrected, which biases them toward it (on the office walk one such round took a 2 % /
5 px error to 0.3 % / 0.1 px), so the sequence is tracked and rendered again with the refined camera
(``rounds``).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Callable, Iterable

import cv2
import numpy as np

from services.geometry.camera import Camera
from services.geometry.pnp import solve_pnp

__all__ = ["CalibrationResult", "fit_intrinsics", "calibrate", "check_camera"]

log = logging.getLogger(__name__)


@dataclass
class CalibrationResult:
    camera: Camera
    frames: int  # frames whose correspondences the last fit used
    points: int  # their inlier correspondences
    rms_px: float  # the last fit's reprojection RMSE
    rounds: list[dict] = field(default_factory=list)  # per round: the camera found and the fit's numbers


def fit_intrinsics(pairs: list[tuple[np.ndarray, np.ndarray]], camera: Camera, ransac_px: float = 2.0,
                   min_inliers: int = 30, iterations: int = 8, distortion: bool = False) -> tuple[Camera, int, int, float]:
    """fx, fy, cx, cy fitted to per-frame correspondences ``pairs`` = [(uv (N, 2) distorted pixels, X (N, 3) world
    points)], starting from ``camera`` (its distortion is kept, or with ``distortion`` k1 fitted too).
    Alternates each frame's PnP-RANSAC inliers under the current estimate with a joint fit; returns (camera,
    frames used, inliers, RMSE px)."""
    cam, used, n, rms = camera, 0, 0, float("nan")
    free = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3 | cv2.CALIB_FIX_TANGENT_DIST
    # with ``distortion`` k1 only: k2 is barely constrained by a walk's frames (960x540 walk, k1 and k2 fitted:
    # k1 -0.137 k2 0.088 for the lens's -0.12 / 0.03, then 94 frames at 2.3 cm; k1 alone: 97 frames at 1.2 cm)
    free |= cv2.CALIB_FIX_K2 if distortion else cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
    # the first fit only scales the focal length (principal point, aspect and lens held): from a camera 15 % short and
    # 10 px off, fitting everything at once on the few frames it localized diverged (fx 2.8, fy < 0)
    first = free | cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2
    for it in range(iterations):
        flags = first if it == 0 else free
        obj, img = [], []
        for uv, X in pairs:
            r = solve_pnp(uv, X, cam, ransac_px)
            if r is not None and r.n_inliers >= min_inliers:  # each frame's points centred: OpenCV's initial pose of
                P = X[r.inliers]  # a non-planar view is ill-conditioned metres from the origin (42 px RMSE, 0.96 centred)
                obj.append(np.ascontiguousarray(P - P.mean(axis=0), np.float32))
                img.append(np.ascontiguousarray(uv[r.inliers], np.float32))
        if len(obj) < 2:
            raise ValueError(f"{len(obj)} frames with {min_inliers} inliers: too few to calibrate from")
        rms, K, D, _, _ = cv2.calibrateCamera(obj, img, (cam.width, cam.height), cam.K.astype(np.float64).copy(),
                                              np.asarray(cam.dist, np.float64).reshape(-1).copy(), flags=flags)
        D = np.asarray(D, float).ravel()
        if not (np.all(np.isfinite(K)) and 0.5 < K[0, 0] / camera.fx < 2 and 0.5 < K[1, 1] / camera.fy < 2
                and 0 <= K[0, 2] < cam.width and 0 <= K[1, 2] < cam.height and np.all(np.abs(D) < 10)):
            raise ValueError(f"the fit diverged (fx {K[0, 0]:.1f}, fy {K[1, 1]:.1f}, cx {K[0, 2]:.1f}, cy {K[1, 2]:.1f} "
                             f"from {camera.fx:.1f} {camera.fy:.1f} {camera.cx:.1f} {camera.cy:.1f})")
        new = dataclasses.replace(cam, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                                  distortion=tuple(float(x) for x in D[:5]) if distortion else cam.distortion)
        moved = max(abs(new.fx - cam.fx), abs(new.fy - cam.fy), abs(new.cx - cam.cx), abs(new.cy - cam.cy),
                    1e3 * max(abs(a - b) for a, b in zip(new.distortion, cam.distortion)))
        cam, used, n = new, len(obj), sum(len(o) for o in obj)
        if moved < 0.01:
            break
    return cam, used, n, float(rms)


def calibrate(track: Callable[[Camera], Iterable[tuple[np.ndarray, np.ndarray]]], camera: Camera, rounds: int = 2,
              ransac_px: float = 2.0, distortion: bool = False) -> CalibrationResult:
    """Refine ``camera`` over ``rounds`` of: ``track(camera)`` (the sequence localized with that camera, yielding
    each chosen frame's correspondences) and :func:`fit_intrinsics` (``distortion``: k1 too)."""
    out = CalibrationResult(camera, 0, 0, float("nan"))
    for k in range(rounds):
        pairs = [p for p in track(out.camera) if len(p[0]) >= 6]
        cam, used, n, rms = fit_intrinsics(pairs, out.camera, ransac_px, distortion=distortion)
        out.rounds.append({"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "distortion": list(cam.distortion),
                           "frames": used, "points": n, "rms_px": rms})
        log.info("calibration round %d/%d: fx %.2f fy %.2f cx %.2f cy %.2f from %d frames, %d points, %.2f px",
                 k + 1, rounds, cam.fx, cam.fy, cam.cx, cam.cy, used, n, rms)
        out.camera, out.frames, out.points, out.rms_px = cam, used, n, rms
    return out


def check_camera(tracker, seq, traj, max_frames: int = 12, focal_tol: float = 0.006,
                 centre_tol_px: float = 2.5) -> dict:
    """Whether the frames agree with the camera they were localized with: the intrinsics implied by up to
    ``max_frames`` localized frames (spread over ``traj``; one fit, distortion kept) against ``seq.camera``.
    ``ok`` is False when a focal length is off by more than ``focal_tol`` or the principal point by more than
    ``centre_tol_px`` (at 640 px wide; scaled with the image). With the right camera the fit lands 0.12 % / 0.3 px
    off on the office walk, 0.34 % / 1.6 px on the sparse 8-frame test walk; from a camera 2 % / 5 px off it finds
    1.6 % / 4.9 px (one fit with renders made by the wrong camera sees most, not all, of the error). So errors of
    ~1 % and more, which cost centimetres, are flagged. Raises ValueError when too few frames match to tell."""
    cam = seq.camera
    index = {s: i for i, s in enumerate(seq.stamps)}
    picks = np.unique(np.linspace(0, len(traj) - 1, min(max_frames, len(traj))).round().astype(int))
    pairs = [tracker.correspondences(seq.read(index[traj.stamps[k]]).image, cam, traj.poses[k]) for k in picks]
    got, used, n, rms = fit_intrinsics([p for p in pairs if len(p[0]) >= 6], cam)
    focal_off = max(abs(got.fx / cam.fx - 1), abs(got.fy / cam.fy - 1))
    centre_off = float(np.hypot(got.cx - cam.cx, got.cy - cam.cy)) * 640.0 / cam.width
    return {"ok": bool(focal_off <= focal_tol and centre_off <= centre_tol_px), "fx": got.fx, "fy": got.fy,
            "cx": got.cx, "cy": got.cy, "focal_off": float(focal_off), "centre_off_px_at_640": centre_off,
            "frames": used, "points": n, "rms_px": rms}
