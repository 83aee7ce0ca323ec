"""APE (against evo on the same files), plots and ``cristal eval``."""

import json

import numpy as np
import pytest

from services.eval.ape import DegenerateAlignment, associate, compute_ape, evaluate, umeyama
from services.eval.plots import RELOC_COLOR
from services.geometry.se3 import Pose, rotvec_to_rotmat
from services.io.scan import Scan
from services.io.trajectory import Trajectory, write_tum

from _pictures import pixels_of, red_pixels


def walk(n=60, seed=0) -> Trajectory:
    """A hand-held-like walk: a curving 3D path, the camera turning as it goes; stamps like rgb.txt's."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 2 * np.pi, n)
    pos = np.stack([3 * np.cos(s) + 4, 2 * np.sin(2 * s) + 1, 1.5 + 0.2 * np.sin(3 * s)], axis=1)
    traj = Trajectory()
    for i in range(n):
        rv = np.array([0.1 * np.sin(s[i]), 0.2 * np.cos(2 * s[i]), s[i]]) + rng.normal(0, 0.02, 3)
        traj.append(f"{1700000000 + i / 30:.6f}", Pose.from_rotvec_t(rv, pos[i]))
    return traj


def perturb(traj: Trajectory, T: Pose = Pose.identity(), scale=1.0, trans_sigma=0.0, rot_sigma_deg=0.0,
            drop=(), seed=1) -> Trajectory:
    """est = T applied to traj with scaled translations, plus noise, minus the frames in ``drop``."""
    rng = np.random.default_rng(seed)
    out = Trajectory()
    for i, (stamp, p) in enumerate(traj):
        noise = Pose.from_rotvec_t(np.radians(rng.normal(0, rot_sigma_deg, 3)), rng.normal(0, trans_sigma, 3))
        q = T @ Pose(p.R, scale * p.t) @ noise
        if i not in drop:
            out.append(stamp, q)
    return out


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(20, 3))
    R = rotvec_to_rotmat([0.3, -0.5, 1.2])
    dst = 2.5 * src @ R.T + [1, 2, 3]
    R_, t_, s_ = umeyama(src, dst, with_scale=True)
    assert np.allclose(R_, R) and np.allclose(t_, [1, 2, 3]) and s_ == pytest.approx(2.5)
    assert umeyama(src, dst)[2] == 1.0
    with pytest.raises(DegenerateAlignment):
        umeyama(np.outer(np.arange(5.0), [1, 2, 3]), np.outer(np.arange(5.0), [3, 2, 1]))


def test_perfect_estimate():
    gt = walk()
    for name, r in evaluate(gt, gt).items():
        assert r.fraction == 1.0 and r.n_matched == r.n_gt == len(gt), name
        assert r.trans_max < 1e-9 and r.rot_max_deg < 1e-6, name
        assert r.scale == pytest.approx(1.0)


def test_constant_offset_exact_without_alignment_and_zero_after_se3():
    gt = walk()
    est = perturb(gt, Pose(np.eye(3), [0.3, -0.4, 0.0]))  # 0.5 m everywhere
    r = compute_ape(gt, est, "none")
    assert r.trans_rmse == pytest.approx(0.5, abs=1e-12)
    assert r.trans_median == pytest.approx(0.5) and r.trans_max == pytest.approx(0.5)
    assert r.rot_max_deg < 1e-6
    se3 = compute_ape(gt, est, "se3")
    assert se3.trans_max < 1e-9 and se3.rot_max_deg < 1e-6
    assert np.allclose(se3.alignment.t, [-0.3, 0.4, 0.0])

    est_rot = perturb(gt, Pose.from_rotvec_t([0, 0, np.radians(5)], [0, 0, 0]))
    assert compute_ape(gt, est_rot, "none").rot_rmse_deg == pytest.approx(5.0, abs=1e-9)


def test_similarity_copy_vanishes_after_sim3_only():
    gt = walk()
    est = perturb(gt, Pose.from_rotvec_t([0.4, -0.2, 1.0], [10, -5, 2]), scale=0.6)
    res = evaluate(gt, est)
    assert res["sim3"].trans_max < 1e-9 and res["sim3"].rot_max_deg < 1e-6
    assert res["sim3"].scale == pytest.approx(1 / 0.6)
    assert res["se3"].trans_rmse > 0.1 and res["se3"].rot_max_deg < 1e-6  # rotation is right, scale is not
    assert res["none"].trans_rmse > 1.0


def test_timestamps_match_as_exact_text():
    p = Pose.identity()
    gt = Trajectory(["1.50", "2.00", "2.50"], [p, p, p])
    est = Trajectory(["1.5", "2.00"], [p, p])
    with pytest.raises(ValueError, match="'1.5'"):
        compute_ape(gt, est)
    r = compute_ape(gt, est, strict=False)
    assert r.stamps == ("2.00",) and r.n_matched == 1 and r.n_est == 2
    assert r.lost_stamps == ("1.50", "2.50") and r.fraction == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="no estimated pose matches"):
        compute_ape(gt, Trajectory(["1.5"], [p]), strict=False)
    g, e = associate(gt, Trajectory(["2.50", "1.50"], [p, p]))
    assert g.stamps == e.stamps == ["1.50", "2.50"]  # ground-truth order


def test_missing_frames_lower_the_fraction_and_skip_degenerate_alignments():
    gt = walk(40)
    r = compute_ape(gt, perturb(gt, drop=set(range(10, 20))), "se3")
    assert r.n_matched == 30 and r.fraction == pytest.approx(0.75) and len(r.lost_times) == 10
    assert r.trans_max < 1e-9
    two = Trajectory(gt.stamps[:2], gt.poses[:2])
    res = evaluate(gt, two)
    assert list(res) == ["none"] and res["none"].fraction == pytest.approx(2 / 40)


@pytest.mark.parametrize("align", ["none", "se3", "sim3"])
def test_numbers_equal_evo(tmp_path, align):
    from evo.core import metrics, sync
    from evo.tools import file_interface

    gt = walk(80)
    est = perturb(gt, Pose.from_rotvec_t([0.05, -0.1, 0.3], [0.5, -0.2, 0.1]), scale=0.9, trans_sigma=0.03,
                  rot_sigma_deg=1.5, drop={0, 7, 8, 9, 40, 79})
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)

    from services.io.trajectory import read_tum

    ours = compute_ape(read_tum(tmp_path / "gt.txt"), read_tum(tmp_path / "est.txt"), align)
    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.txt"))
    e = file_interface.read_tum_trajectory_file(str(tmp_path / "est.txt"))
    ref, e = sync.associate_trajectories(ref, e)
    assert ours.n_matched == ref.num_poses == len(gt) - 6
    if align != "none":
        r_a, t_a, s = e.align(ref, correct_scale=align == "sim3")
        assert np.allclose(ours.alignment.R, r_a) and np.allclose(ours.alignment.t, t_a)
        assert ours.scale == pytest.approx(s, rel=1e-9)
    for relation, prefix in ((metrics.PoseRelation.translation_part, "trans_"),
                             (metrics.PoseRelation.rotation_angle_deg, "rot_")):
        ape = metrics.APE(relation)
        ape.process_data((ref, e))
        stats = ape.get_all_statistics()
        unit = "_deg" if prefix == "rot_" else ""
        for k in ("rmse", "mean", "median", "max"):
            assert getattr(ours, f"{prefix}{k}{unit}") == pytest.approx(stats[k], rel=1e-6), (relation, k)
        assert np.allclose(ours.trans_err if prefix == "trans_" else ours.rot_err_deg, ape.error, rtol=1e-6, atol=1e-9)


def _scan(n=20000, seed=0) -> Scan:
    """Floor, walls and a ceiling around the walk, coloured; stored relative to a non-zero origin."""
    rng = np.random.default_rng(seed)
    origin = np.array([2.0, -1.0, 0.5])
    pts = rng.uniform([0, -2, 0], [8, 4, 2.8], size=(n, 3))
    k = rng.integers(0, 4, n)
    pts[k == 0, 2] = 0.0  # floor
    pts[k == 1, 2] = 2.8  # ceiling (cut from the top view)
    pts[k == 2, 0] = rng.choice([0.0, 8.0], (k == 2).sum())
    pts[k == 3, 1] = rng.choice([-2.0, 4.0], (k == 3).sum())
    rgb = np.stack([k * 60, 200 - k * 40, 80 + k * 30], axis=1)
    return Scan(pts - origin, rgb, origin)


def test_plots_write_pngs(tmp_path):
    from services.eval.plots import plot_errors, plot_trajectory_topdown

    gt = walk(120)
    est = perturb(gt, Pose(np.eye(3), [0.05, 0.02, 0]), trans_sigma=0.02, rot_sigma_deg=0.5,
                  drop=set(range(30, 45)) | {90})
    scan = Scan(np.zeros((0, 3)), np.zeros((0, 3)))
    for name, s in (("topdown.png", _scan()), ("topdown_noscan.png", None), ("topdown_emptyscan.png", scan)):
        out = plot_trajectory_topdown(gt, est, tmp_path / "sub" / name, scan=s)
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and red_pixels(out) > 500  # the estimate is drawn
    out = plot_errors(compute_ape(gt, est, "se3"), tmp_path / "errors.png")
    assert out.read_bytes()[:4] == b"\x89PNG" and out.stat().st_size > 10000
    assert not list(tmp_path.rglob("*.tmp"))


def test_a_localization_is_drawn_from_above_with_its_lost_stretches(tmp_path):
    """The run's picture (cristal localize writes it beside TRAJ.txt): the poses reported, broken at LOST frames, with
    the relocalizations, the LOST stretch after the last pose, over the scan or a map's landmarks; no poses at all
    still gives a picture (of the ground truth), and an estimate drawn adds red that the ground truth alone lacks."""
    from services.eval.plots import picture_path, plot_localization_topdown, plot_positions_topdown
    from services.io.frame_log import FrameRecord

    gt = walk(120)
    lost = set(range(30, 45)) | set(range(110, 120))
    est = perturb(gt, trans_sigma=0.01, drop=lost)
    status = ["LOST" if i in lost else "RELOCALIZED" if i in (0, 45) else "TRACKING" for i in range(120)]
    records = [FrameRecord(stamp, st) for (stamp, _), st in zip(gt, status)]
    assert picture_path(tmp_path / "run" / "traj.txt") == tmp_path / "run" / "traj.png"
    with_poses = plot_localization_topdown(est, records, tmp_path / "a.png", scan=_scan(), gt=gt)
    landmarks = plot_localization_topdown(est, records, tmp_path / "b.png", landmarks=_scan().xyz)
    none = plot_localization_topdown(Trajectory(), [FrameRecord(r.stamp, "LOST") for r in records], tmp_path / "c.png",
                                     gt=gt)
    for out in (with_poses, landmarks, none):
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert red_pixels(with_poses) > 500 and red_pixels(landmarks) > 500 and red_pixels(none) < 50
    pos = plot_positions_topdown(gt.positions(), tmp_path / "pos.png", scan=_scan(), label="database positions")
    assert red_pixels(pos) > 200 and not list(tmp_path.rglob("*.tmp"))


@pytest.fixture
def main():
    import services.cli

    return services.cli.main


def test_cli_eval(tmp_path, capsys, main):
    gt = walk(50)
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", perturb(gt, Pose(np.eye(3), [0.1, 0, 0]), drop={3, 4}))
    rc = main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--plots", str(tmp_path / "plots"),
               "--json", str(tmp_path / "ape.json")])
    out = capsys.readouterr().out
    assert rc == 0
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["n_gt"] == 50 and summary["n_matched"] == 48 and summary["fraction"] == pytest.approx(0.96)
    assert summary["ape_none_trans_rmse_m"] == pytest.approx(0.1)
    assert summary["ape_se3_trans_rmse_m"] < 1e-6 and "ape_sim3_rot_rmse_deg" in summary
    assert "trans RMSE cm" in out and "48/50" in out
    for f in ("trajectory.png", "errors_none.png", "errors_se3.png", "errors_sim3.png"):
        assert (tmp_path / "plots" / f).stat().st_size > 0
    assert json.loads((tmp_path / "ape.json").read_text())["se3"]["n_matched"] == 48

    rc = main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--align", "none"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == 0 and summary["aligns"] == ["none"] and "ape_se3_trans_rmse_m" not in summary


def test_cli_errors_exit_2(tmp_path, main):
    write_tum(tmp_path / "gt.txt", walk(10))
    (tmp_path / "bad.txt").write_text("0.0 1 2 3 0 0 0\n")  # 7 fields
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "bad.txt")]) == 2
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "missing.txt")]) == 2
    (tmp_path / "other.txt").write_text("5.0 1 2 3 0 0 0 1\n")  # stamp not in the ground truth
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "other.txt")]) == 2
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "other.txt"), "--lenient"]) == 2  # no match
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "gt.txt"), "--scan", "x.ply"]) == 2  # no --plots


def test_cli_eval_weighs_errors_against_the_predicted_uncertainty(tmp_path, capsys, main):
    """With est.frames.csv beside the estimate (what `cristal localize` writes), eval counts the poses whose error
    exceeds 3 times the 1-sigma they were reported with: here every pose is 10 cm off, 40 claimed 5 cm (within 3
    sigma) and 8 claimed 1 cm (beyond), and 2 LOST frames have none."""
    from services.io.frame_log import FrameRecord, frame_log_path, write_frame_log

    gt = walk(50)
    est = perturb(gt, Pose(np.eye(3), [0.1, 0, 0]), drop={3, 4})
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", est)
    recs = [FrameRecord(s, "LOST", reason="no place") if i in (3, 4) else
            FrameRecord(s, "RELOCALIZED" if i == 0 else "TRACKING", 100, 0.8, 0.01 if i >= 42 else 0.05, 1.0,
                        source="features" if i >= 42 else "direct")
            for i, s in enumerate(gt.stamps)]
    write_frame_log(frame_log_path(tmp_path / "est.txt"), recs)
    rc = main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--align", "se3", "--plots",
               str(tmp_path / "plots")])
    out = capsys.readouterr().out
    s = json.loads(out.strip().splitlines()[-1])
    assert rc == 0 and s["uncertainty_n"] == 48 and s["uncertainty_beyond_3sigma"] == 8, s  # (in the scan frame)
    assert s["uncertainty_t_ratio_median"] == pytest.approx(2.0) and "8 beyond 3 sigma" in out
    # the error by what solved each pose (the log's source column): 40 aligned directly, 8 by keypoints
    assert {k: v["n"] for k, v in s["by_source"].items()} == {"direct": 40, "features": 8}, s["by_source"]
    assert s["by_source"]["features"]["trans_rmse_m"] == pytest.approx(0.1) and "direct 40 poses, 10.00 cm" in out
    assert (tmp_path / "plots" / "uncertainty.png").stat().st_size > 10_000
    assert pixels_of(tmp_path / "plots" / "trajectory.png", RELOC_COLOR) > 20  # the log's relocalization marked
    # a log that is not one: a clear error, exit 2
    (tmp_path / "x.csv").write_text("stamp,pose\n1,2\n")
    assert main(["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--frame-log", str(tmp_path / "x.csv")]) == 2
    assert "not a frame log" in capsys.readouterr().err


def test_the_frame_log_round_trips_and_reads_logs_written_before_its_source_column(tmp_path):
    """Every field survives a write and a read (a reason with commas and quotes included); a log from before the
    source column (seven columns) is still read, its sources empty; a row with a field missing is a clear error."""
    from services.io.frame_log import FrameLogError, FrameRecord, read_frame_log, write_frame_log

    recs = [FrameRecord("1.000000", "RELOCALIZED", 120, 0.9, 0.004, 0.05, source="fused"),
            FrameRecord("1.033333", "TRACKING", 118, 0.91, 0.0032, 0.071, source="direct"),
            FrameRecord("1.066667", "LOST", 12, 2.5, reason='ambiguous place: 2 places, "far" apart', source="features"),
            FrameRecord("1.100000", "LOST", reason="unreadable image: truncated")]
    write_frame_log(tmp_path / "t.frames.csv", recs)
    back = read_frame_log(tmp_path / "t.frames.csv")
    assert list(back) == [r.stamp for r in recs]
    for r, b in zip(recs, back.values()):
        assert (b.status, b.inliers, b.reason, b.source) == (r.status, r.inliers, r.reason, r.source)
        assert np.allclose([b.rmse_px, b.sigma_m, b.sigma_deg], [r.rmse_px, r.sigma_m, r.sigma_deg], equal_nan=True)
    (tmp_path / "old.csv").write_text("stamp,status,inliers,rmse_px,sigma_cm,sigma_deg,reason\n"
                                      "1.0,TRACKING,118,0.91,0.32,0.071,\n1.1,LOST,0,,,,no pose\n")
    old = read_frame_log(tmp_path / "old.csv")
    assert old["1.0"].sigma_m == pytest.approx(0.0032) and old["1.0"].source == "" and old["1.1"].reason == "no pose"
    (tmp_path / "bad.csv").write_text("stamp,status,inliers,rmse_px,sigma_cm,sigma_deg,source,reason\n1.0,TRACKING,1\n")
    with pytest.raises(FrameLogError, match="bad.csv:2: expected 8 fields"):
        read_frame_log(tmp_path / "bad.csv")


def test_a_picture_that_cannot_be_drawn_costs_a_warning_not_the_run(tmp_path, caplog):
    """Every command draws its picture through ``drawn`` after writing its outputs: a failure there is logged."""
    from services.eval.plots import drawn, plot_positions_topdown

    (tmp_path / "f").write_text("")  # a file where the picture's folder should be
    with caplog.at_level("WARNING", logger="services.eval.plots"):
        assert drawn("the positions", plot_positions_topdown, np.zeros((3, 3)), tmp_path / "f" / "x.png") is None
    assert "no picture of the positions" in caplog.text
    assert drawn("the positions", plot_positions_topdown, np.zeros((3, 3)), tmp_path / "x.png") == tmp_path / "x.png"
