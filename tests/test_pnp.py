"""PnP-RANSAC (services.geometry.pnp): exact recovery through outliers and a distorted lens, honest uncertainty,
and a final estimate that does not depend on which inlier set RANSAC happened to keep."""

import numpy as np

from services.geometry.camera import Camera
from services.geometry.pnp import _soft_refine, reprojection_errors, solve_pnp, undistort_pixels
from services.geometry.se3 import Pose, look_at


def _wall(rng, cam: Camera, n: int, depth: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` pixels spread over the image and the points of a wall ``depth`` ahead behind them (camera at the origin,
    looking along +z): a scene whose pose is only weakly told apart from a sideways shift plus a turn."""
    uv = np.column_stack([rng.uniform(20, cam.width - 20, n), rng.uniform(20, cam.height - 20, n)])
    xy = np.column_stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy])
    return uv, np.column_stack([xy * depth, np.full(n, depth)])


def test_exact_pose_through_outliers_and_a_distorted_lens():
    rng = np.random.default_rng(3)
    cam = Camera.from_fov(960, 540, 75, distortion=(-0.12, 0.03, 0, 0, 0))
    T_wc = look_at([1.0, -2.0, 1.5], [3.0, 1.0, 1.2])
    X = T_wc.transform(np.column_stack([rng.uniform(-2, 2, (300, 2)), rng.uniform(1.5, 6, 300)]))
    uv, z = cam.project(T_wc.inverse().transform(X))
    keep = (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < cam.width) & (uv[:, 1] > 0) & (uv[:, 1] < cam.height)
    uv, X = uv[keep], X[keep]
    bad = rng.random(len(uv)) < 0.4
    uv[bad] += rng.uniform(-60, 60, (bad.sum(), 2))
    wrong = bad & (reprojection_errors(T_wc, cam, undistort_pixels(cam, uv), X) > 2.0)
    for soft in (False, True):
        r = solve_pnp(uv, X, cam, 2.0, soft=soft)
        dt, dr = T_wc.distance_to(r.T_wc)
        assert dt < 1e-4 and dr < 1e-3, (soft, dt, dr)
        assert not np.any(r.inliers & wrong), "a displaced match was kept as an inlier"
        assert r.n_inliers >= (~bad).sum()


def test_noisy_pose_is_within_its_reported_uncertainty():
    rng = np.random.default_rng(5)
    cam = Camera.from_fov(640, 480, 60)
    errors, sigmas = [], []
    for _ in range(20):
        uv, X = _wall(rng, cam, 300)
        X[:, 2] += rng.uniform(0, 2.0, len(X))  # depth variety: a room, not only a wall
        X[:, :2] *= (X[:, 2:] / 2.0)
        uv = uv + rng.normal(0, 0.7, uv.shape)
        r = solve_pnp(uv, X, cam, 2.0)
        errors.append(Pose.identity().distance_to(r.T_wc)[1])
        sigmas.append(r.sigma_r_deg)
    z = np.array(errors) / np.array(sigmas)
    assert np.sqrt(np.mean(z ** 2)) < 2.0, z  # the largest-axis sigma bounds the angle error on average
    assert np.max(z) < 5.0, z


def test_the_final_pose_does_not_depend_on_the_inlier_set_ransac_kept():
    """Two RANSAC outcomes a little apart along the wall's shift-and-turn ambiguity keep different inlier sets at
    the 2 px threshold; the soft refinement over every plausible match lands on one pose from both. (The tracker's
    renders follow its last pose, so a pose held by the inlier set it was found with lets the track slide: a
    960x540 office walk slid 3.4 cm / 0.9 deg along a poster wall that way; benchmarks/RESULTS.md, stop 36.)"""
    rng = np.random.default_rng(11)
    cam = Camera.from_fov(960, 540, 75)
    uv, X = _wall(rng, cam, 400)
    uv = uv + rng.normal(0, 1.0, uv.shape) * np.where(rng.random(len(uv)) < 0.3, 2.5, 0.8)[:, None]
    bad = rng.random(len(uv)) < 0.2
    uv[bad] += rng.uniform(-30, 30, (bad.sum(), 2))
    shift = 0.01  # 1 cm sideways and the turn that keeps the wall's centre in place
    starts = [Pose.from_rotvec_t([0, s * -shift / 2.0, 0], [s * shift, 0, 0]) for s in (-1, 1)]
    results = []
    for T0 in starts:
        inl = reprojection_errors(T0, cam, uv, X) < 2.0
        results.append(_soft_refine(T0, inl, cam, uv, X, 2.0)[0])
    dt, dr = results[0].distance_to(results[1])
    assert dt < 2e-4 and dr < 0.005, (dt, dr)
    for T in results:
        assert Pose.identity().distance_to(T)[0] < 0.006
