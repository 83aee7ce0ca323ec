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
