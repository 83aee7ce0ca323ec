"""Pose algebra, quaternions and the camera model against independent references (OpenCV, scipy)."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.geometry.camera import Camera, CameraError
from services.geometry.se3 import Pose, look_at, quat_to_rotmat, rotmat_to_quat, rotation_angle_deg


def random_pose(rng):
    return Pose(Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(0, 5, 3))


def test_quaternion_matches_scipy_hamilton_xyzw():
    rng = np.random.default_rng(0)
    for _ in range(200):
        q = Rotation.random(random_state=rng.integers(1 << 31)).as_quat()  # scipy: x, y, z, w
        np.testing.assert_allclose(quat_to_rotmat(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
        q2 = rotmat_to_quat(quat_to_rotmat(q))
        assert q2[3] >= 0
        np.testing.assert_allclose(q2, q if q[3] >= 0 else -q, atol=1e-10)


def test_compose_inverse_and_direction():
    rng = np.random.default_rng(1)
    T_wc, T_cb = random_pose(rng), random_pose(rng)
    X_b = rng.normal(size=(10, 3))
    # composition applies right to left, like matrices
    np.testing.assert_allclose((T_wc @ T_cb).transform(X_b), T_wc.transform(T_cb.transform(X_b)), atol=1e-12)
    np.testing.assert_allclose((T_wc @ T_wc.inverse()).matrix(), np.eye(4), atol=1e-12)
    np.testing.assert_allclose((T_wc @ T_cb).matrix(), T_wc.matrix() @ T_cb.matrix(), atol=1e-12)
    # camera-to-world: t is the camera centre
    np.testing.assert_allclose(T_wc.transform(np.zeros(3)), T_wc.t)


def test_tum_roundtrip_and_interpolation():
    rng = np.random.default_rng(2)
    T = random_pose(rng)
    T2 = Pose.from_tum(T.to_tum())
    np.testing.assert_allclose(T2.matrix(), T.matrix(), atol=1e-12)
    U = random_pose(rng)
    assert T.interpolate(U, 0.0).distance_to(T)[0] < 1e-12
    assert T.interpolate(U, 1.0).distance_to(U)[1] < 1e-6
    mid = T.interpolate(U, 0.5)
    assert abs(T.distance_to(mid)[1] - U.distance_to(mid)[1]) < 1e-6


def test_pose_rejects_garbage():
    with pytest.raises(ValueError):
        Pose(np.eye(3) * 2, np.zeros(3))
    with pytest.raises(ValueError):
        Pose(np.eye(3), [np.nan, 0, 0])
    with pytest.raises(ValueError):
        Pose.from_tum([1, 2, 3])
    with pytest.raises(ValueError):
        quat_to_rotmat([0, 0, 0, 0])


def test_look_at_is_opencv_camera():
    T_wc = look_at((1, 2, 1.5), (5, 2, 1.5))  # looking along +x, z up
    np.testing.assert_allclose(T_wc.R[:, 2], [1, 0, 0], atol=1e-12)  # camera z forward
    np.testing.assert_allclose(T_wc.R[:, 1], [0, 0, -1], atol=1e-12)  # camera y down
    np.testing.assert_allclose(T_wc.R[:, 0], [0, -1, 0], atol=1e-12)  # camera x right
    assert rotation_angle_deg(T_wc.R @ T_wc.R.T) < 1e-9


def test_camera_projection_matches_opencv_and_inverts():
    cam = Camera(640, 480, 520.0, 515.0, 321.3, 238.7, (-0.21, 0.07, 0.001, -0.0015, -0.01))
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-1, 1, 500), rng.uniform(-0.7, 0.7, 500), rng.uniform(1.5, 4, 500)])
    uv, z = cam.project(X)
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(cam.backproject(uv, z), X, atol=1e-9)


def test_camera_scaled_keeps_pixel_centres():
    cam = Camera(640, 480, 500, 500, 319.5, 239.5)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    assert half.cx == pytest.approx(159.5) and half.fx == pytest.approx(250)


@pytest.mark.parametrize("bad,msg", [
    ({"fx": 0}, "focal"), ({"fx": -5}, "focal"), ({"fy": float("nan")}, "finite"), ({"width": 0}, "width"),
    ({"height": 2.5}, "height"), ({"cx": 1e6}, "principal"), ({"distortion": [0, 0, float("inf"), 0, 0]}, "distortion"),
    ({"distortion": [0.1, 0, 0, 0, 0, 0.02, 0, 0]}, "further terms zero"),  # a rational model: not ours
])
def test_camera_rejects_absurd_intrinsics(bad, msg):
    d = {"width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 320, "cy": 240, "distortion": [0, 0, 0, 0, 0]}
    d.update(bad)
    with pytest.raises(CameraError, match=msg):
        Camera.from_dict(d)


def test_camera_takes_opencvs_longer_distortion_lists_when_their_extra_terms_are_zero():
    """A ROS camera_info of the rational_polynomial model lists 8 coefficients; with k4-k6 zero it is the 5-term model."""
    d = {"width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 320, "cy": 240}
    assert Camera.from_dict({**d, "distortion": [0.1, -0.02, 0.001, 0, 0.003, 0, 0, 0]}).distortion == (0.1, -0.02, 0.001, 0, 0.003)
    assert Camera.from_dict({**d, "distortion": [0.1, -0.02]}).distortion == (0.1, -0.02, 0, 0, 0)


def test_camera_json_roundtrip(tmp_path):
    cam = Camera(800, 600, 610, 612, 401, 299, (0.1, -0.02, 0, 0, 0.003))
    cam.save(tmp_path / "camera.json")
    assert Camera.load(tmp_path / "camera.json") == cam
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(CameraError, match="bad.json"):
        Camera.load(tmp_path / "bad.json")
    with pytest.raises(CameraError, match="missing fields: fy"):
        Camera.from_dict({"width": 1, "height": 1, "fx": 1, "cx": 0, "cy": 0})


def test_linear_motion_blur_matches_the_sub_pose_blur_for_a_short_exposure(kernels):
    from services.geometry.blur import blur_length_px, motion_blur, motion_blur_linear

    rng = np.random.default_rng(0)
    cam = Camera(160, 120, 120.0, 120.0, 79.5, 59.5)
    img = cv2.GaussianBlur(rng.integers(0, 255, (120, 160), dtype=np.uint8), (0, 0), 2)  # texture, not noise
    depth = np.full((120, 160), 2.0, np.float32)
    T = Pose.identity()
    a, b = Pose.from_rotvec_t([0, -0.02, 0.005], [-0.01, 0, 0]), Pose.from_rotvec_t([0, 0.02, -0.005], [0.01, 0, 0])
    n = 8
    subs = [a.interpolate(b, j / (n - 1)) for j in range(n)]
    exact = motion_blur(img, depth, cam, T, subs)
    fast = motion_blur_linear(img, depth, cam, T, a, b, n)
    assert blur_length_px(cam, a, b) > 4  # a real blur ...
    assert np.abs(exact - img).mean() > 3 * np.abs(exact - fast).mean()  # ... reproduced far closer than it moves
    assert np.abs(exact - fast)[10:-10, 10:-10].max() < 2.0


def test_motion_blur_with_a_wild_pose_stays_finite_and_fast(kernels):
    """A motion guess that puts points behind the camera, through a lens model far beyond its range, must blur
    to something finite at once (OpenCV walks an outside coordinate back one image width at a time: a NaN or a
    1e9 px map once made one blur take minutes)."""
    import time

    from services.geometry.blur import motion_blur_linear

    cam = Camera(160, 120, 100.0, 100.0, 79.5, 59.5, (-0.3, 0.1, 0.0, 0.0, 0.0))
    img = np.full((120, 160), 100, np.uint8)
    depth = np.full((120, 160), 2.0, np.float32)
    t0 = time.perf_counter()
    out = motion_blur_linear(img, depth, cam, Pose.identity(), Pose.identity(), Pose.from_rotvec_t([0, 1.2, 0], [0, 0, 0.5]), 10)
    assert time.perf_counter() - t0 < 5.0
    assert np.isfinite(out).all()


def test_blur_sampling_maps_are_the_same_compiled_and_in_numpy(use_kernels):
    """The server blurs renders with the compiled sampling maps, a light client would with numpy: the same maps, to
    1e-4 px, through a distorted lens, with pixels without depth and a motion that puts some points behind the camera."""
    from services.geometry.blur import _Warp

    rng = np.random.default_rng(1)
    cam = Camera(200, 150, 150.0, 150.0, 99.5, 74.5, (-0.2, 0.05, 0.001, -0.001, 0.0))
    depth = (1.0 + 3.0 * rng.random((150, 200))).astype(np.float32)
    depth[60:80, 90:120] = 0.0
    warp = _Warp(depth, cam, Pose.from_rotvec_t([0.1, -0.2, 0.05], [1.0, 2.0, 1.5]))
    maps = {}
    for name in ("numpy", "numba"):
        use_kernels(name)
        maps[name] = [warp.maps(warp.T_cw.inverse() @ Pose.from_rotvec_t(w, t))
                      for w, t in (([0, 0.03, 0.01], [0.02, 0, 0]), ([0, 1.9, 0], [0, 0, 2.5]))]
    for (ax, ay), (bx, by) in zip(maps["numpy"], maps["numba"]):
        assert ax.dtype == bx.dtype == np.float32 and ax.shape == (150, 200)
        np.testing.assert_allclose(ax, bx, rtol=0, atol=1e-4)  # (a matrix product's rounding may differ in the last bit)
        np.testing.assert_allclose(ay, by, rtol=0, atol=1e-4)
    wild_x = maps["numba"][1][0]
    assert (wild_x == -1).any() and (wild_x > 0).any()  # behind the camera: -1; the rest still maps


def test_odometry_check_stops_using_an_odometry_that_disagrees_with_the_tracked_motion():
    """A device's odometry is used while its frame-to-frame motions agree with the tracked ones (a good or a poor
    VIO); a broken one (a degree of error a frame) is not, and is used again once it agrees."""
    import numpy as np

    from services.geometry.se3 import Pose
    from services.localize.odometry_check import OdometryCheck

    rng = np.random.default_rng(0)
    step = Pose.from_rotvec_t(np.radians([0.0, 1.5, 0.2]), [0.03, 0.0, 0.01])  # a walking camera's frame-to-frame motion

    def noisy(rot_deg: float, frac: float) -> Pose:
        return Pose.from_rotvec_t(np.radians(rng.normal(0, rot_deg, 3)), step.t * frac * rng.normal(0, 1, 3)) @ step

    chk = OdometryCheck()
    for _ in range(30):  # tracked motions carry ~0.05 deg / 5 mm of their own noise; a poor VIO 0.1 deg and 3 %
        chk.update(noisy(0.05, 0.1), noisy(0.1, 0.03))
        assert chk.trusted
    assert chk.use(step) is step and chk.unused == 0
    for _ in range(10):  # broken: a degree a frame
        chk.update(noisy(0.05, 0.1), noisy(1.0, 0.2))
    assert not chk.trusted
    assert chk.use(step) is None and chk.use(None) is None and chk.unused == 1  # set aside, and counted
    for _ in range(10):  # recovered
        chk.update(noisy(0.05, 0.1), noisy(0.03, 0.01))
    assert chk.trusted
