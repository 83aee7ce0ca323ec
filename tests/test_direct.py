"""Direct tracking's motion-only pose solve (services.localize.direct.solve_motion_only), compiled and in numpy."""

import numpy as np

from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.localize.direct import solve_motion_only

CAM = Camera(width=640, height=480, fx=500.0, fy=500.0, cx=319.5, cy=239.5)


def _problem(seed=0, n=200, outliers=0.2, noise_px=0.3):
    rng = np.random.default_rng(seed)
    truth = Pose.from_rotvec_t(np.radians([3.0, -20.0, 1.0]), [0.4, -0.1, 1.2]).inverse()  # world-to-camera
    uv = rng.uniform([20, 20], [620, 460], (n, 2))
    z = rng.uniform(1.0, 6.0, n)
    Xc = np.column_stack([(uv[:, 0] - CAM.cx) / CAM.fx * z, (uv[:, 1] - CAM.cy) / CAM.fy * z, z])
    P = (Xc - truth.t) @ truth.R  # world points
    obs = uv + rng.normal(0, noise_px, uv.shape)
    bad = rng.random(n) < outliers
    obs[bad] += rng.uniform(-40, 40, (bad.sum(), 2))
    # anisotropic information, as an edge-like alignment gives: trace 2, mostly across its edge
    ang = rng.uniform(0, np.pi, n)
    c, s = np.cos(ang), np.sin(ang)
    lam = rng.uniform(0.1, 1.9, n)
    info = np.stack([np.stack([lam * c * c + (2 - lam) * s * s, (2 * lam - 2) * c * s], 1),
                     np.stack([(2 * lam - 2) * c * s, lam * s * s + (2 - lam) * c * c], 1)], 1) / noise_px ** 2
    start = (Pose.from_rotvec_t(np.radians([0.8, -0.5, 0.3]), [0.03, -0.02, 0.05]) @ truth.inverse()).inverse()
    return P, obs, info, start, truth, bad


def test_motion_only_solve_recovers_the_pose_and_drops_outliers(kernels):
    P, obs, info, start, truth, bad = _problem()
    R, t, inl, rmse = solve_motion_only(P, obs, info, CAM.K, start.R, start.t)
    got = Pose(R.T, -R.T @ t)
    err = got.inverse() @ truth.inverse()
    assert np.linalg.norm(got.t - truth.inverse().t) < 0.005 and np.degrees(np.linalg.norm(err.rotvec())) < 0.05
    assert not (inl & bad).any() or (inl & bad).sum() <= 2  # an outlier can land near its own truth
    assert inl[~bad].mean() > 0.9 and 0.5 < rmse < 1.5, (inl[~bad].mean(), rmse)


def test_compiled_and_numpy_motion_only_solves_agree(use_kernels):
    out = {}
    for backend in ("numpy", "numba"):
        use_kernels(backend)
        P, obs, info, start, _, _ = _problem(seed=3)
        out[backend] = solve_motion_only(P, obs, info, CAM.K, start.R, start.t)
    (Ra, ta, ia, ra), (Rb, tb, ib, rb) = out["numpy"], out["numba"]
    assert np.array_equal(ia, ib) and abs(ra - rb) < 1e-9
    np.testing.assert_allclose(Ra, Rb, atol=1e-10)
    np.testing.assert_allclose(ta, tb, atol=1e-10)
