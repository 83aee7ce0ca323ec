"""A rolling-shutter frame re-sampled into its middle row's view (services.geometry.rolling_shutter), against
the simulator's own renders: the same pose read by a global shutter, and row by row while the camera turns."""

import numpy as np
import pytest

from services.geometry.rolling_shutter import angular_velocity, row_time, unroll
from services.geometry.se3 import Pose, rotvec_to_rotmat


@pytest.fixture(scope="module")
def turning(small_site):
    """A ground-truth pose of the small site, its global-shutter render, and renders of it read row by row over 30 ms
    while turning at 120 deg/s about the camera's y axis (a pan) plus a little roll, turning one way and the other."""
    from services.io.sequence import open_sequence
    from services.sim.site import SimSite

    root, _, _ = small_site
    seq = open_sequence(root / "seq_00")
    cam = seq.camera.scaled(2.0)  # 400x300, with the fixture's lens distortion
    T = seq.groundtruth_pose(seq.stamps[5])
    site = SimSite(root)
    omega, readout = np.array([0.0, np.radians(120.0), np.radians(15.0)]), 0.030
    gs, _ = site.renderer.render(T, cam, site.camera_lighting)

    def rolled(w):
        rows = [T @ Pose(rotvec_to_rotmat(w * tau), np.zeros(3)) for tau in row_time(np.arange(cam.height), cam.height, readout)]
        return site.renderer.render_rows(rows, cam, site.camera_lighting)[0]

    return cam, gs, rolled(omega), omega, readout


def _misfit(a: np.ndarray, b: np.ndarray) -> float:
    m = (slice(12, -12), slice(12, -12))  # borders: re-sampled from outside the frame
    return float(np.abs(a[m] - b[m]).mean())


def test_unroll_undoes_a_turn_read_row_by_row(turning):
    cam, gs, rs, omega, readout = turning
    before = _misfit(rs, gs)
    after = _misfit(unroll(rs, cam, omega, readout), gs)
    wrong_way = _misfit(unroll(rs, cam, -omega, readout), gs)
    assert after < 0.35 * before, (before, after)  # 3.6 deg from the first row to the last, undone
    assert wrong_way > before, (before, wrong_way)


def test_unroll_leaves_a_still_or_global_shutter_frame_alone(turning):
    cam, gs, _, omega, readout = turning
    assert unroll(gs, cam, np.zeros(3), readout) is gs
    assert unroll(gs, cam, omega, 0.0) is gs
    assert row_time(np.array([-0.5, cam.height - 0.5]), cam.height, readout) == pytest.approx([-readout / 2, readout / 2])


def test_angular_velocity_from_a_frame_to_frame_rotation():
    w = np.array([0.1, -1.2, 0.3])
    assert angular_velocity(rotvec_to_rotmat(w / 30.0), 1 / 30.0) == pytest.approx(w, rel=1e-9)


def test_a_travelling_camera_is_unrolled_at_each_part_s_own_depth(small_site):
    """A camera walking sideways (3 m/s, a 30 ms readout: 9 cm from the first row to the last) skews near things more
    than far ones. Unrolled at the depth of each part of the frame (depth_field of the scene points, as the localizers
    give it), the frame comes closer to the global-shutter one than unrolled at one depth, the scene's median; the
    office walk with a 20 ms readout (benchmarks/RESULTS.md, stop 52): Render & Match 0.46 -> 0.23 cm, P&L 0.57 -> 0.41."""
    from services.geometry.rolling_shutter import depth_field
    from services.io.sequence import open_sequence
    from services.sim.site import SimSite

    root, _, _ = small_site
    seq = open_sequence(root / "seq_00")
    cam = seq.camera.scaled(2.0)
    T = seq.groundtruth_pose(seq.stamps[5])
    site = SimSite(root)
    v, readout = np.array([3.0, 0.0, 0.5]), 0.030  # camera frame: sideways, a little forward
    gs, depth = site.renderer.render(T, cam, site.camera_lighting)
    rows = [T @ Pose(np.eye(3), v * tau) for tau in row_time(np.arange(cam.height), cam.height, readout)]
    rs = site.renderer.render_rows(rows, cam, site.camera_lighting)[0]
    vv, uu = np.mgrid[2:cam.height:4, 2:cam.width:4]
    d = depth[vv, uu]
    Xc = cam.backproject(np.stack([uu[d > 0], vv[d > 0]], axis=1).astype(float), d[d > 0])
    field = depth_field(Xc, cam)
    assert field is not None and field.min() < 0.6 * field.max(), field  # near and far parts in view
    still = np.zeros(3)
    before = _misfit(rs, gs)
    one = _misfit(unroll(rs, cam, still, readout, velocity=v, depth_m=float(np.median(d[d > 0]))), gs)
    each = _misfit(unroll(rs, cam, still, readout, velocity=v, depth_m=field), gs)
    print(f"misfit: rolled {before:.4f}, unrolled at one depth {one:.4f}, at each part's {each:.4f}")
    assert each < one < before, (before, one, each)
