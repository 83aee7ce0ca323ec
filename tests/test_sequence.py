"""Sequence folders, TUM trajectories and video input: round trips and clear errors."""

import cv2
import numpy as np
import pytest

from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.io.sequence import SequenceError, SequenceWriter, open_sequence
from services.io.trajectory import Trajectory, TrajectoryError, read_tum, write_tum

CAM = Camera(64, 48, 50, 50, 31.5, 23.5)


def _frames(n):
    rng = np.random.default_rng(0)
    return [(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)) for _ in range(n)]


def test_sequence_roundtrip_keeps_timestamp_text(tmp_path):
    stamps = ["1305031102.175304", "1305031102.211214", "1305031102.243211"]
    poses = [Pose.from_rotvec_t([0, 0.1 * i, 0], [i, 0, 1]) for i in range(3)]
    with SequenceWriter(tmp_path / "seq", CAM, ".png") as w:
        for s, img, T in zip(stamps, _frames(3), poses):
            w.add(s, img, T)
    seq = open_sequence(tmp_path / "seq")
    assert seq.stamps == stamps and seq.camera == CAM and len(seq) == 3
    frames = list(seq)
    assert frames[1].stamp == stamps[1] and frames[1].image.shape == (48, 64, 3)
    np.testing.assert_array_equal(frames[2].image, _frames(3)[2])  # PNG is lossless
    assert seq.groundtruth.stamps == stamps
    assert seq.groundtruth_pose(stamps[2]).distance_to(poses[2])[0] < 1e-8


def test_tum_exact_stamps_comments_and_errors(tmp_path):
    p = tmp_path / "t.txt"
    write_tum(p, Trajectory(["1.50", "2.0"], [Pose.identity(), Pose.from_tum([1, 2, 3, 0, 0, 0, 1])]), header="hi")
    t = read_tum(p)
    assert t.stamps == ["1.50", "2.0"] and np.allclose(t.poses[1].t, [1, 2, 3])
    for text, msg in [("1 2 3\n", "8 fields"), ("1 a 0 0 0 0 0 1\n", "not numbers"), ("1 0 0 0 0 0 0 0\n", "zero quaternion"),
                      ("1 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", "duplicate"), ("1 nan 0 0 0 0 0 1\n", "non-finite")]:
        p.write_text(text)
        with pytest.raises(TrajectoryError, match=msg):
            read_tum(p)
    with pytest.raises(TrajectoryError, match="no such"):
        read_tum(tmp_path / "missing.txt")


def test_tum_files_load_in_evo(tmp_path):
    from evo.tools import file_interface

    p = tmp_path / "t.txt"
    poses = [Pose.from_rotvec_t([0.1, 0.2 * i, 0], [i, 2, 3]) for i in range(5)]
    write_tum(p, Trajectory([f"{10 + i / 30:.6f}" for i in range(5)], poses), header="comment")
    traj = file_interface.read_tum_trajectory_file(str(p))
    np.testing.assert_allclose(traj.positions_xyz, [q.t for q in poses], atol=1e-8)
    np.testing.assert_allclose(traj.poses_se3[3], poses[3].matrix(), atol=1e-8)


def test_sequence_errors_name_the_problem(tmp_path):
    with pytest.raises(SequenceError, match="no such"):
        open_sequence(tmp_path / "nope")
    d = tmp_path / "s"
    d.mkdir()
    with pytest.raises(ValueError, match="camera.json"):
        open_sequence(d)
    CAM.save(d / "camera.json")
    with pytest.raises(SequenceError, match="rgb.txt"):
        open_sequence(d)
    (d / "rgb.txt").write_text("# only comments\n")
    with pytest.raises(SequenceError, match="no frames"):
        open_sequence(d)
    (d / "rgb.txt").write_text("0.1 rgb/a.png\n")
    with pytest.raises(SequenceError, match="missing"):
        open_sequence(d)
    (d / "rgb").mkdir()
    (d / "rgb" / "a.png").write_bytes(b"not an image")
    with pytest.raises(SequenceError, match="cannot decode"):
        open_sequence(d).read(0)
    cv2.imwrite(str(d / "rgb" / "a.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(SequenceError, match="camera.json says 64x48"):
        open_sequence(d).read(0)
    (d / "rgb.txt").unlink()  # no rgb.txt: images named otherwise than by timestamp cannot be put in order
    with pytest.raises(SequenceError, match="not named by timestamp"):
        open_sequence(d)


def test_a_folder_without_rgb_txt_is_read_in_the_order_its_image_names_give(tmp_path):
    w = SequenceWriter(tmp_path / "seq", CAM)
    stamps = ["9.5", "10.25", "100.0"]  # (text order is not time order)
    for s, img in zip(stamps, _frames(3)):
        w.add(s, img)
    w.close()
    (tmp_path / "seq" / "rgb.txt").unlink()
    seq = open_sequence(tmp_path / "seq")
    assert seq.stamps == stamps and seq.read(2).image.shape == (48, 64, 3)


def test_a_recording_with_broken_frames_is_read_past_them(tmp_path):
    """A recorder that dropped a write or truncated a file: the sequence still opens (with a warning), strict reading
    names the frame, tolerant iteration hands out every other frame and says what is wrong with the broken ones. A
    frame of another size than camera.json's is a wrong camera, not a broken file: it still ends the iteration."""
    with SequenceWriter(tmp_path / "seq", CAM, ".png") as w:
        for i, img in enumerate(_frames(5)):
            w.add(f"{i}.0", img)
    seq_dir = tmp_path / "seq"
    files = sorted((seq_dir / "rgb").iterdir())
    files[1].unlink()
    files[3].write_bytes(files[3].read_bytes()[:20])  # truncated
    seq = open_sequence(seq_dir)
    assert len(seq) == 5
    with pytest.raises(SequenceError, match="missing"):
        list(seq)  # strict: the first broken frame ends it
    with pytest.raises(SequenceError, match="cannot decode"):
        seq.read(3)
    frames = list(seq.frames(tolerant=True))
    assert [f.stamp for f in frames] == ["0.0", "1.0", "2.0", "3.0", "4.0"]
    assert [f.image is None for f in frames] == [False, True, False, True, False]
    assert "missing" in frames[1].problem and "cannot decode" in frames[3].problem and frames[0].problem is None
    np.testing.assert_array_equal(frames[4].image, _frames(5)[4])
    cv2.imwrite(str(files[2]), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(SequenceError, match="camera.json says 64x48"):
        list(seq.frames(tolerant=True))
    for f in files:
        f.unlink(missing_ok=True)
    with pytest.raises(SequenceError, match="all 5 image"):
        open_sequence(seq_dir)


def test_video_input(tmp_path):
    path = tmp_path / "walk.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    if not vw.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG video")
    for img in _frames(5):
        vw.write(img)
    vw.release()
    CAM.save(tmp_path / "walk.camera.json")
    seq = open_sequence(path)
    assert len(seq) == 5
    frames = list(seq)
    assert len(frames) == 5 and frames[0].image.shape == (48, 64, 3)
    assert [float(f.stamp) for f in frames] == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4], abs=1e-3)
    with pytest.raises(SequenceError, match="not a sequence folder"):
        (tmp_path / "x.txt").write_text("")
        open_sequence(tmp_path / "x.txt")


def test_odometry_logged_at_its_own_rate_is_interpolated_at_the_frames(tmp_path):
    """A VIO logs poses at its own rate and clock: --odometry takes the pose at each frame's time, interpolated
    between the samples around it (none outside the log or across a gap), in the device's own world frame."""
    import numpy as np
    import pytest

    from services.geometry.se3 import Pose
    from services.io.trajectory import Trajectory, TrajectoryError, read_odometry, relative_motions, write_tum

    def truth(t: float) -> Pose:  # a camera turning and walking
        return Pose.from_rotvec_t([0.0, 0.3 * t, 0.05 * t], [0.8 * t, 0.1 * np.sin(t), 0.0])

    offset = Pose.from_rotvec_t([0.2, -0.1, 1.0], [5.0, -3.0, 1.0])  # the device's own world frame
    t_odo = np.arange(0.0, 2.0, 0.01) + 100.004  # 100 Hz, not on the frames' stamps
    t_odo = t_odo[(t_odo < 100.9) | (t_odo > 101.3)]  # a 0.4 s gap in the log
    write_tum(tmp_path / "vio.txt", Trajectory([f"{t:.6f}" for t in t_odo], [offset @ truth(t - 100) for t in t_odo]))
    frames = [f"{100 + k / 30:.6f}" for k in range(-3, 66)]  # 30 fps, starting before the log
    odo = read_odometry(tmp_path / "vio.txt", frames)
    got = set(odo.stamps)
    assert frames[0] not in got and frames[3] not in got and frames[4] in got  # before the log: none
    assert f"{100 + 33 / 30:.6f}" not in got  # in the gap: none
    motions = relative_motions(odo, frames)
    checked = 0
    for k, m in enumerate(motions):
        if m is None:
            continue
        t0, t1 = float(frames[k - 1]) - 100, float(frames[k]) - 100
        dt, dr = m.distance_to(truth(t0).inverse() @ truth(t1))
        assert dt < 2e-4 and dr < 0.02, (k, dt, dr)
        checked += 1
    assert checked > 40
    # the same log in OpenGL camera axes (x right, y up, z backward: ARKit, ARCore) gives the same motions
    gl = Pose(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    write_tum(tmp_path / "vio-gl.txt", Trajectory([f"{t:.6f}" for t in t_odo], [offset @ truth(t - 100) @ gl for t in t_odo]))
    same = relative_motions(read_odometry(tmp_path / "vio-gl.txt", frames, axes="opengl"), frames)
    assert all((a is None) == (b is None) and (a is None or max(a.distance_to(b)) < 1e-6) for a, b in zip(motions, same))
    wrong = relative_motions(read_odometry(tmp_path / "vio-gl.txt", frames), frames)  # read as OpenCV axes: not the motion
    assert max(m.distance_to(w)[1] for m, w in zip(motions, wrong) if m is not None) > 0.5
    write_tum(tmp_path / "bad.txt", Trajectory(["2.0", "1.0"], [Pose.identity(), Pose.identity()]))
    with pytest.raises(TrajectoryError, match="must increase"):
        read_odometry(tmp_path / "bad.txt", frames)


@pytest.mark.parametrize("unit,per_second", [("seconds", 1), ("milliseconds", 10**3), ("microseconds", 10**6),
                                             ("nanoseconds", 10**9)])
def test_timestamps_counted_in_a_finer_unit_are_read_as_seconds(tmp_path, caplog, unit, per_second):
    """A recorder that names frames by nanoseconds (a ROS 2 bag exported frame by frame) or milliseconds: the text is
    kept exactly, but the capture times the localizers and the odometry's clock get are seconds (else every frame
    looks like the first after a long gap, and tracking runs without its motion model)."""
    from services.io.trajectory import read_odometry, relative_motions

    t0 = 1_700_000_000 * per_second  # an epoch stamp, as recorders write them
    step = per_second // 30 if per_second > 1 else None
    stamps = ([str(t0 + k * step) for k in range(6)] if step else [f"{1_700_000_000 + k / 30:.6f}" for k in range(6)])
    w = SequenceWriter(tmp_path / "seq", CAM)
    for s, img in zip(stamps, _frames(len(stamps))):
        w.add(s, img)
    w.close()
    with caplog.at_level("WARNING"):
        seq = open_sequence(tmp_path / "seq")
    assert seq.stamps == stamps and seq.stamp_unit == unit
    frame_dt = step / per_second if step else 1 / 30  # (33 ms when counted in whole milliseconds)
    assert np.allclose(np.diff([seq.seconds(s) for s in stamps]), frame_dt, atol=1e-6)
    assert (unit in caplog.text) == (unit != "seconds"), caplog.text
    # a device's odometry on the same clock, logged at 100 Hz between the frames (walking 1 m/s): interpolated at the
    # frames' times
    odo_t = [t0 + k * (per_second // 100) for k in range(-2, 30)] if step else [1_700_000_000 + k / 100 for k in range(-2, 30)]
    write_tum(tmp_path / "vio.txt", Trajectory([str(t) if step else f"{t:.6f}" for t in odo_t],
                                               [Pose.from_rotvec_t([0, 0, 0], [0.01 * k, 0, 0]) for k in range(32)]))
    motions = relative_motions(read_odometry(tmp_path / "vio.txt", stamps), stamps)
    assert all(m is not None for m in motions[1:]), motions
    assert all(abs(m.t[0] - frame_dt) < 1e-5 for m in motions[1:]), [m.t for m in motions[1:]]


def test_frames_numbered_instead_of_timed_are_taken_at_a_video_rate(tmp_path, caplog):
    """KITTI-style names, 000000.png, 000001.png...: read as seconds they would be a second apart (no motion model)."""
    w = SequenceWriter(tmp_path / "seq", CAM, ext=".png")
    stamps = [f"{k:06d}" for k in range(5)]
    for s, img in zip(stamps, _frames(5)):
        w.add(s, img)
    w.close()
    with caplog.at_level("WARNING"):
        seq = open_sequence(tmp_path / "seq")
    assert seq.stamp_unit == "frames" and "frame numbers" in caplog.text
    assert np.allclose(np.diff([seq.seconds(s) for s in stamps]), 1 / 30)


def test_intrinsics_for_another_resolution_of_the_same_picture_are_scaled(tmp_path, caplog):
    """A phone's intrinsics are for its capture size, its video is recorded smaller: the same picture, so camera.json
    is scaled to the images (with a warning); another shape is still refused when a frame is read."""
    big = Camera(128, 96, 100, 101, 63.5, 47.5, (0.1, 0, 0, 0, 0))
    w = SequenceWriter(tmp_path / "seq", CAM)
    for s, img in zip(["1.0", "1.033333"], _frames(2)):
        w.add(s, img)
    w.close()
    big.save(tmp_path / "seq" / "camera.json")
    with caplog.at_level("WARNING"):
        seq = open_sequence(tmp_path / "seq")
    assert seq.camera == big.scaled(0.5) and (seq.camera.fx, seq.camera.cx) == (50.0, 31.5)
    assert seq.read(1).image.shape == (48, 64, 3) and "scaled" in caplog.text
    Camera(96, 96, 100, 100, 47.5, 47.5).save(tmp_path / "seq" / "camera.json")  # square: not the same picture
    with pytest.raises(SequenceError, match="camera.json says 96x96"):
        open_sequence(tmp_path / "seq").read(0)


def test_frames_out_of_time_order_are_warned_about(tmp_path, caplog):
    w = SequenceWriter(tmp_path / "seq", CAM)
    for s, img in zip(["1.000000", "1.066667", "1.033333"], _frames(3)):
        w.add(s, img)
    w.close()
    with caplog.at_level("WARNING"):
        seq = open_sequence(tmp_path / "seq")
    assert len(seq) == 3 and "do not increase" in caplog.text and "line" in caplog.text
