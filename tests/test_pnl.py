"""Prebuild & Localize end to end on the small simulated site: build a map from the scan, check it, localize against it.

The fixture's own frames are 200x150, too small for ORB (a 31-pixel patch, 8 pyramid levels); the
sequence localized here (``site_480``, conftest) is rendered from the same simulated site at the fixture's
ground-truth poses with the same lens (distortion included) at 480x360, under camera-day lighting (not the
scan's), so the map (from the scan's points) and the frames come from different sources.
"""

import subprocess
import sys

import numpy as np
import pytest

from services.geometry.camera import Camera
from _pictures import red_pixels
from _scan_floor import added_m, reported_alike, uniform_grid


@pytest.fixture(scope="module")
def pnl_site(site_480):
    return site_480


def _cli(*args):
    code = "import sys; from services.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, "-q", *map(str, args)], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def pnl_map(pnl_site):
    import json

    root, out, cam, box = pnl_site
    mapdir = out / "map"
    r = _cli("prebuild", root / "scan.ply", "--camera", out / "seq" / "camera.json", "--out", mapdir,
             "--roi", *box, "--spacing", "0.75")
    assert r.returncode == 0, r.stdout + r.stderr
    return mapdir, json.loads(r.stdout.strip().splitlines()[-1])



def test_prebuild_refuses_a_bad_supersampling_factor(pnl_site, tmp_path):
    from services.cli import main

    root, out, _, _ = pnl_site
    assert main(["prebuild", str(root / "scan.ply"), "--camera", str(out / "seq" / "camera.json"), "--out",
                 str(tmp_path / "m"), "--supersample", "0"]) == 2
    assert not (tmp_path / "m").exists()
    assert main(["prebuild", str(root / "scan.ply"), "--camera", str(out / "seq" / "camera.json"), "--out",
                 str(tmp_path / "m"), "--roi-polygon", "0,0", "4"]) == 2  # an outline as build-db takes it, checked
    assert not (tmp_path / "m").exists()

def test_prebuild_check_and_localize(pnl_site, pnl_map, tmp_path):
    import json

    from services.eval.ape import compute_ape
    from services.io.sequence import open_sequence
    from services.io.trajectory import read_tum
    from services.prebuild.stella_map import check_map_dir, read_map

    root, out, cam, box = pnl_site
    mapdir, summary = pnl_map
    assert summary["keyframes"] > 10 and summary["landmarks"] > 500
    assert (mapdir / "map.msg").exists() and (mapdir / "config.yaml").exists()
    assert summary["picture"] == str(mapdir / "map.png") and red_pixels(mapdir / "map.png") > 60  # its 9 positions
    from services.prebuild.patches import LandmarkPatches

    patches = LandmarkPatches.load(mapdir / "patches.npz")  # the light localizer's landmark patches, beside the map
    assert len(patches.lm_ids) == summary["landmarks"] and patches.size == 23
    # and what the scan's stations disagree by, for the light localizer's --scan-sigma-mm auto (the client's too)
    from services.client.fallback import load_local

    recorded = json.loads((mapdir / "scan_accuracy.json").read_text())["scan_sigma_mm"]
    assert recorded == summary["scan_sigma_mm"] and 0.0 <= recorded < 2.0  # a perfect simulated scan
    assert load_local(mapdir).loc.cfg.scan_sigma_m == pytest.approx(recorded / 1000.0)
    assert load_local(mapdir, 0.005).loc.cfg.scan_sigma_m == 0.005
    problems, stats = check_map_dir(mapdir)
    assert problems == [] and stats["config"]
    m = read_map(mapdir)
    assert m.n_landmarks == summary["landmarks"]
    assert m.camera() == cam  # the map's camera is the target camera, distortion included
    r = _cli("map", "check", mapdir)
    assert r.returncode == 0, r.stdout + r.stderr

    traj_path = tmp_path / "traj.txt"
    r = _cli("localize", mapdir, out / "seq", "--method", "pnl", "--map", mapdir, "--out", traj_path)
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads(r.stdout.strip().splitlines()[-1])
    seq = open_sequence(out / "seq")
    est = read_tum(traj_path)
    assert len(est) >= 7 and s["localized"] == len(est)  # the first frame relocalizes with no prior
    assert s["picture"] == str(tmp_path / "traj.png") and red_pixels(tmp_path / "traj.png") > 100  # over the landmarks
    a = compute_ape(seq.groundtruth, est, "none")
    # patch alignment: 0.3-0.4 cm / 0.06-0.07 deg here (ORB keypoints alone: 2.9 cm / 0.38 deg)
    assert a.trans_rmse < 0.015 and a.rot_rmse_deg < 0.25, (a.trans_rmse, a.rot_rmse_deg)
    assert s.get("direct_ms", 0) > 0  # direct tracking by default; --no-direct: ORB on every frame
    _check_frame_log(traj_path, seq, est, tmp_path)
    r = _cli("localize", mapdir, out / "seq", "--method", "pnl", "--map", mapdir, "--out", traj_path, "--no-direct")
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert r.returncode == 0 and "direct_ms" not in s and s["localized"] >= 7, r.stdout + r.stderr


def _check_frame_log(traj_path, seq, est, tmp_path):
    """TRAJ.frames.csv has every frame in order; a pose exactly where the status is not LOST, each with the 1-sigma
    that passed the gates; and `cristal eval` weighs the errors against those 1-sigmas (uncertainty.png)."""
    import json

    from services.io.frame_log import frame_log_path, read_frame_log

    log = read_frame_log(frame_log_path(traj_path))
    assert list(log) == seq.stamps
    posed = set(est.stamps)
    assert {k for k, r in log.items() if r.status != "LOST"} == posed
    for k in posed:
        assert 0 < log[k].sigma_m <= 0.01 and 0 < log[k].sigma_deg <= 0.1 and log[k].inliers >= 30, log[k]
        assert log[k].source in ("features", "direct"), log[k]  # what solved it: ORB keypoints or aligned patches
    assert all(r.reason for r in log.values() if r.status == "LOST")
    r = _cli("eval", seq.root / "groundtruth.txt", traj_path, "--align", "none", "--plots", tmp_path / "plots")
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert s["uncertainty_n"] == len(posed) and 0 <= s["uncertainty_beyond_3sigma"] <= len(posed), s
    assert 0 < s["uncertainty_t_ratio_median"] < 10 and (tmp_path / "plots" / "uncertainty.png").stat().st_size > 10_000


def test_localize_goes_on_past_broken_frames(pnl_site, pnl_map, tmp_path):
    """A recording with a missing and a truncated image: `cristal localize` gives every other frame its pose, counts
    the two as LOST ("unreadable image") and writes the trajectory, also with the backward pass."""
    import json
    import shutil

    root, out, cam, box = pnl_site
    seq_dir = tmp_path / "seq"
    shutil.copytree(out / "seq", seq_dir)
    files = sorted((seq_dir / "rgb").iterdir())
    files[2].unlink()
    files[5].write_bytes(files[5].read_bytes()[:500])
    traj_path = tmp_path / "traj.txt"
    r = _cli("localize", pnl_map[0], seq_dir, "--method", "pnl", "--map", pnl_map[0], "--out", traj_path, "--backfill")
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads(r.stdout.strip().splitlines()[-1])
    assert s["frames"] == 8 and s["lost_reasons"].get("unreadable image") == 2, s
    assert s["localized"] == 6 and traj_path.read_text().count("\n") >= 6, s
    from services.io.frame_log import frame_log_path, read_frame_log

    log = list(read_frame_log(frame_log_path(traj_path)).values())
    assert len(log) == 8 and [r.status for r in log].count("LOST") == 2, log
    assert log[2].reason.startswith("unreadable image") and log[5].reason.startswith("unreadable image")


def test_ctrl_c_keeps_the_frames_localized_so_far(pnl_site, pnl_map, tmp_path, capsys):
    """Ctrl-C in a long `cristal localize`: the trajectory of the frames done is written, the summary says so, and the
    exit status is 130 (the interrupt arrives inside the localizer, as it would)."""
    import argparse
    import json

    from services.io.sequence import open_sequence
    from services.io.trajectory import read_tum
    from services.localize.pnl import PnlLocalizer
    from services.localize.runner import localize_and_report

    class CtrlCAt:
        def __init__(self, loc, k):
            self.loc, self.k, self.calls = loc, k, 0

        def process(self, *a, **kw):
            self.calls += 1
            if self.calls == self.k:
                raise KeyboardInterrupt
            return self.loc.process(*a, **kw)

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    traj_path = tmp_path / "t.txt"
    args = argparse.Namespace(frames=None, out=str(traj_path), backfill=True)
    code = localize_and_report(CtrlCAt(PnlLocalizer.load(pnl_map[0]), 6), seq, args, "pnl")
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 130 and s["interrupted"] and s["frames"] == 5, s
    got = read_tum(traj_path)
    assert 4 <= len(got) <= 5 and set(got.stamps) <= set(seq.stamps[:5])


def _live_camera(seq, frames: int, end: BaseException | type):
    """``seq``'s first ``frames`` frames as a live camera gives them (its length a bound, no files), then ``end`` raised:
    the user's Ctrl-C, a camera unplugged."""

    class Live:
        camera, stamps, groundtruth, files = seq.camera, seq.stamps, seq.groundtruth, None

        def __len__(self):
            return 10 ** 9

        def frames(self, tolerant=False):
            for i in range(frames):
                yield seq.read(i)
            raise end

    return Live()


def test_a_stream_ended_by_ctrl_c_writes_what_it_localized(pnl_site, pnl_map, tmp_path):
    """A live camera's stream ends with Ctrl-C: the frames localized so far (here by the on-device P&L fallback, no
    server) are written with their sources, and the stats say it was interrupted. Its length is a bound (10**9
    frames), and nothing is allocated per frame of it up front."""
    import tracemalloc

    from services.client.fallback import load_local
    from services.client.stream import sources_path, stream_sequence
    from services.io.sequence import open_sequence
    from services.io.trajectory import read_tum

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    traj_path = tmp_path / "live.txt"
    local = load_local(pnl_map[0])
    tracemalloc.start()
    try:
        traj, st = stream_sequence(_live_camera(seq, 5, KeyboardInterrupt), None, local, traj_path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 300e6, f"a live stream of unknown length took {peak / 1e6:.0f} MB"  # (a list per frame bound: 8 GB)
    assert st.interrupted and st.summary()["interrupted"] and st.frames == 5
    got = read_tum(traj_path)
    assert len(got) == len(traj) >= 4 and len(sources_path(traj_path).read_text().splitlines()) == 6
    for stamp, T in zip(got.stamps, got.poses):
        assert seq.groundtruth_pose(stamp).distance_to(T)[0] < 0.015


def test_a_stream_keeps_every_frame_on_disk_as_it_goes_and_only_the_last_ones_in_memory(pnl_site, pnl_map, tmp_path):
    """A robot streams a live camera for days: each frame's pose and source are on disk (``.part``, flushed) before the
    next frame is read, so a kill loses nothing; a source that fails mid-stream (a camera unplugged) still leaves the
    trajectory and sources of the frames done in place; and memory holds only the last frames."""
    from services.client.fallback import load_local
    from services.client.stream import sources_path, stream_sequence
    from services.io.sequence import open_sequence
    from services.io.trajectory import read_tum

    _, out, _, _ = pnl_site
    seq = open_sequence(out / "seq")
    path = tmp_path / "live.txt"
    part, tum_part = (p.with_name(p.name + ".part") for p in (sources_path(path), path))
    on_disk, posed = [], []

    def on_frame(i, frame, T, *_):  # what is on disk as each frame's pose comes back
        posed.append(T is not None)
        on_disk.append((len(part.read_text().splitlines()) - 1, len(tum_part.read_text().splitlines())))

    with pytest.raises(RuntimeError, match="unplugged"):
        stream_sequence(_live_camera(seq, 6, RuntimeError("camera unplugged")), None, load_local(pnl_map[0]), path,
                        on_frame=on_frame)
    assert on_disk == [(i + 1, sum(posed[:i + 1])) for i in range(6)]  # each frame written before the next is read
    rows = sources_path(path).read_text().splitlines()[1:]
    got = read_tum(path)
    assert len(rows) == 6 and len(got) == sum(r.split()[1] == "local" for r in rows) == sum(posed) >= 5
    assert not part.exists() and not tum_part.exists()
    for stamp, T in zip(got.stamps, got.poses):
        assert seq.groundtruth_pose(stamp).distance_to(T)[0] < 0.015

    traj, st = stream_sequence(seq, None, load_local(pnl_map[0]), path, memory_frames=2)
    assert st.frames == 8 and st.server + st.local >= 7 and len(read_tum(path)) == st.server + st.local
    assert len(st.rows) <= 4 and len(traj) <= 4 and st.forgotten == 8 - len(st.rows)
    assert st.rows[-1][0] == seq.stamps[7] and st.summary()["frames_in_memory"] == len(st.rows)


def test_the_server_s_p_and_l_backend_replies_with_poses_their_1_sigma_and_what_solved_them(pnl_site, pnl_map):
    """`cristal serve --backend pnl` as a client sees it over a real Zenoh session on loopback: the walk's frames (real
    JPEGs) sent one by one get poses near the truth, each with the 1-sigma the gates judged and what solved it."""
    from _zenoh import config, endpoint, free_port

    from protocol.messages import Status
    from services.client.client import LocalizationClient, reply_pose
    from services.io.frame_log import SOURCES
    from services.io.sequence import open_sequence
    from services.server.backend import load_backend
    from services.server.service import LocalizationServer, ServerConfig

    _, out, _, _ = pnl_site
    seq = open_sequence(out / "seq")
    port = free_port()
    srv = LocalizationServer(load_backend("pnl", None, None, str(pnl_map[0])),
                             ServerConfig(site="lab", map_id="office", server_id="p0", idle_s=30),
                             config(listen=[endpoint(port)])).start()
    cl = LocalizationClient(config(connect=[endpoint(port)]), client_id="hmd", site="lab", map_id="office",
                            deadline_ms=20000)
    try:
        assert cl.wait_for_server(10)
        replies = [cl.localize(f.read_bytes(), seq.camera, stamp=seq.seconds(s), stamp_text=s)
                   for f, s in zip(seq.files, seq.stamps)]
    finally:
        cl.close()
        srv.close()
    posed = [(i, r) for i, r in enumerate(replies) if r is not None and r.status.has_pose]
    assert replies[0].status is Status.RELOCALIZED and len(posed) >= 6, replies
    for i, r in posed:
        dt, dr = seq.groundtruth.poses[i].distance_to(reply_pose(r))
        assert dt < 0.05 and dr < 1.0, (i, dt, dr)
        assert 0 < r.sigma_m <= 0.01 and 0 < r.sigma_deg <= 0.1 and r.source in SOURCES, r


def test_localize_pnl_without_map_is_a_clear_error(tmp_path):
    r = _cli("localize", tmp_path, tmp_path, "--method", "pnl", "--out", tmp_path / "t.txt")
    assert r.returncode == 2 and "--map" in r.stdout + r.stderr
    r = _cli("localize", tmp_path, tmp_path, "--method", "rm", "--out", tmp_path / "t.txt")
    assert r.returncode == 2 and "--db" in r.stdout + r.stderr
    r = _cli("localize", tmp_path, tmp_path, "--method", "pnl", "--map", tmp_path, "--near", "1", "2", "nan", "3",
             "--out", tmp_path / "t.txt")
    assert r.returncode == 2 and "--near X Y Z R" in r.stdout + r.stderr  # before the missing map is even looked at


def test_localizer_api_seed_and_lost_on_blank_frame(pnl_site, pnl_map):
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    root, out, cam, box = pnl_site
    loc = PnlLocalizer.load(pnl_map[0], PnlConfig())
    blank = np.full((cam.height, cam.width), 128, np.uint8)
    r = loc.process(blank, cam)
    assert r.status == Status.LOST and r.T_wc is None and "total_ms" in r.timings and r.reason
    # seeded with a pose 3 cm / ~1 degree off, the next frame tracks (no relocalization) and lands near the truth
    seq = open_sequence(out / "seq")
    f = seq.read(3)
    gt = seq.groundtruth_pose(f.stamp)
    from services.geometry.se3 import Pose

    loc.seed(gt @ Pose.from_rotvec_t([0.01, -0.01, 0.005], [0.03, -0.02, 0.01]))
    r = loc.process(f.image, cam)
    assert r.status == Status.TRACKING and r.inliers >= PnlConfig().min_inliers
    dt, dr = gt.distance_to(r.T_wc)
    assert dt < 0.05 and dr < 1.0
    # a frame full of keypoints that match nothing, at a good prior: LOST, no exception
    noise = np.random.default_rng(0).integers(0, 256, (cam.height, cam.width), dtype=np.uint8)
    loc.reset()
    r = loc.process(noise, cam, prior=gt)
    assert r.status == Status.LOST and r.T_wc is None
    loc.reset()
    assert loc.T_last is None
    import copy

    other = copy.copy(loc)  # the server shares one loaded map between clients
    assert other.idx is loc.idx and other._extractors is not loc._extractors and other.T_last is None
    assert other.carry is not loc.carry and other.odometry is not loc.odometry  # per-client tracking state


def _six_frames(pnl_site):
    """The camera, the walk's first six frames, their true poses and a blank frame (a hand over the lens)."""
    from services.io.sequence import open_sequence

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    frames = [seq.read(i) for i in range(6)]
    return cam, frames, [seq.groundtruth_pose(f.stamp) for f in frames], np.full((cam.height, cam.width), 128, np.uint8)


def test_odometry_carries_the_pose_through_lost_frames(pnl_site, pnl_map):
    """As in Render & Match: with the device's odometry a LOST stretch keeps the pose (carried on by the odometry,
    not reported) and the next good frame tracks from it; without odometry, or once the carry ran out, it cannot
    (relocalization switched off, so only the carried pose can bring the frame back)."""
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    cam, frames, gt, blank = _six_frames(pnl_site)

    def run(cfg: PnlConfig, odometry: bool):
        loc = PnlLocalizer.load(pnl_map[0], cfg)
        loc.seed(gt[0])
        res = [loc.process(frames[0].image, cam, stamp=float(frames[0].stamp))]
        for i in range(1, 6):  # frames 1-4 blank (a hand over the lens), frame 5 the camera's own
            motion = gt[i - 1].inverse() @ gt[i] if odometry else None
            res.append(loc.process(blank if i < 5 else frames[i].image, cam, motion=motion, stamp=float(frames[i].stamp)))
        return res, loc

    no_reloc = PnlConfig(reloc_min_inliers=10 ** 6)
    res, loc = run(no_reloc, odometry=True)
    assert res[0].T_wc is not None and all(r.status == Status.LOST and r.T_wc is None for r in res[1:5])
    assert res[5].status == Status.RELOCALIZED and loc.carry.seconds == 0.0, res[5]
    dt, dr = gt[5].distance_to(res[5].T_wc)
    assert dt < 0.05 and dr < 1.0, (dt, dr)
    no_coast = PnlConfig(reloc_min_inliers=10 ** 6, velocity_carry_s=0.0)  # (4 frames are within the velocity's coast)
    assert run(no_coast, odometry=False)[0][5].status == Status.LOST
    expired, loc = run(PnlConfig(reloc_min_inliers=10 ** 6, odometry_carry_s=0.05), odometry=True)
    assert expired[5].status == Status.LOST and loc.T_last is None


def test_the_last_velocity_carries_the_pose_through_a_few_lost_frames(pnl_site, pnl_map):
    """Without odometry, a frame or two no pose fits do not cost the track: the pose coasts on at the last tracked
    velocity (not reported) for velocity_carry_s and the next frame tracks from it; a longer gap is LOST
    (relocalization switched off, so only the coasted pose can bring the frame back)."""
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    cam, frames, gt, blank = _six_frames(pnl_site)

    def run(cfg: PnlConfig):
        loc = PnlLocalizer.load(pnl_map[0], cfg)
        loc.seed(gt[0])
        res = [loc.process(frames[i].image if i not in (3, 4) else blank, cam, stamp=float(frames[i].stamp))
               for i in range(6)]  # frames 3-4 blank (a hand over the lens)
        return res, loc

    res, loc = run(PnlConfig(reloc_min_inliers=10 ** 6))
    assert all(r.T_wc is not None for r in res[:3]) and all(r.status == Status.LOST for r in res[3:5])
    assert res[5].status == Status.RELOCALIZED and loc.carry.seconds == 0.0, res[5]
    dt, dr = gt[5].distance_to(res[5].T_wc)
    assert dt < 0.02 and dr < 0.3, (dt, dr)
    for limit in (0.0, 0.05):  # no coast, or one that two frames at 30 fps outlast
        assert run(PnlConfig(reloc_min_inliers=10 ** 6, velocity_carry_s=limit))[0][5].status == Status.LOST


def test_patches_of_another_map_are_refused(pnl_map, tmp_path):
    import shutil

    from services.localize.pnl import PnlConfig, PnlLocalizer
    from services.prebuild.patches import LandmarkPatches

    mapdir = tmp_path / "map"
    shutil.copytree(pnl_map[0], mapdir)
    assert PnlLocalizer.load(mapdir, PnlConfig()).patches is not None
    lp = LandmarkPatches.load(mapdir / "patches.npz")
    lp.map_fp = "0123456789abcdef"  # as if left over from an earlier build of the map
    lp.save(mapdir / "patches.npz")
    assert PnlLocalizer.load(mapdir, PnlConfig()).patches is None  # ignored, not used against the wrong landmarks
    r = _cli("map", "check", mapdir)
    assert r.returncode == 1 and "another map" in r.stdout


@pytest.mark.parametrize("mode", ["direct", "direct, retried", "keypoints+alignment", "keypoints"])
def test_tracking_modes_against_ground_truth(pnl_site, pnl_map, mode):
    """The default tracks straight from the prediction by patch alignment (no ORB after the first two frames: the one
    after a relocalization has no velocity to predict it, and its patch pose is checked by keypoints); with
    direct tracking off, keypoints then alignment; with no alignment (a map without patches, e.g. one
    saved by stella_vslam), keypoints alone under their own looser gates. "direct, retried": 20 patches cannot
    reach the 30-inlier gate, so direct tracking holds only by its retry with twice the patches (a fast turn's
    blurred frame, where about a quarter converge)."""
    from services.eval.ape import compute_ape
    from services.io.sequence import open_sequence
    from services.io.trajectory import Trajectory
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    root, out, cam, box = pnl_site
    cfg = {"direct": PnlConfig(), "direct, retried": PnlConfig(direct_landmarks=20),
           "keypoints+alignment": PnlConfig(direct_landmarks=0), "keypoints": PnlConfig(align=False)}[mode]
    assert mode != "direct, retried" or cfg.min_inliers > cfg.direct_landmarks
    loc = PnlLocalizer.load(pnl_map[0], cfg)
    seq = open_sequence(out / "seq")
    traj, used_orb = Trajectory(), []
    for f in seq:
        r = loc.process(f.image, cam)
        if r.T_wc is not None:
            traj.append(f.stamp, r.T_wc)
            if r.status == Status.TRACKING:
                used_orb.append("features_ms" in r.timings)
    assert len(traj) >= 7 and len(used_orb) >= 6
    a = compute_ape(seq.groundtruth, traj, "none")
    limit = (0.015, 0.25) if cfg.align else (0.05, 0.6)  # measured: 0.3-0.4 cm / 0.07 deg aligned, 2.9 cm / 0.38 deg keypoints
    assert a.trans_rmse < limit[0] and a.rot_rmse_deg < limit[1], (mode, a.trans_rmse, a.rot_rmse_deg)
    assert not any(used_orb[1:]) if mode.startswith("direct") else all(used_orb)


def test_backfill_tracks_back_from_a_later_pose_with_the_light_localizer(pnl_site, pnl_map):
    """``--backfill`` drives P&L the same way as Render & Match: frames without a forward pose are tracked back from the
    first pose after them, each within a few centimetres of the ground truth."""
    from services.io.sequence import open_sequence
    from services.localize.backfill import backfill
    from services.localize.pnl import PnlConfig, PnlLocalizer

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    gt = seq.groundtruth.poses
    poses = [None] * 5 + list(gt[5:])
    st = backfill(PnlLocalizer.load(pnl_map[0], PnlConfig()), lambda i: seq.read(i).image, cam, poses,
                  [float(s) for s in seq.stamps])
    assert st.stretches == 1 and st.filled >= 4 and st.rejected == 0
    err = np.array([gt[i].distance_to(poses[i]) for i in range(5) if poses[i] is not None])
    assert err[:, 0].max() < 0.03 and err[:, 1].max() < 0.5, err


def test_a_prediction_too_far_off_for_the_windows_is_found_by_searching_the_patches(pnl_site, pnl_map):
    """Direct tracking's windows converge from a few pixels; a turn that changed speed or direction puts the frame
    further off. Then 60 landmarks' templates are searched for around their predicted projections and PnP on those
    found gives the pose to align from, and the pose lands on the truth (checked by keypoints here: a prior is not a
    tracked frame's prediction). Without the search the frame goes the keypoint way."""
    from services.geometry.se3 import Pose
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    f = seq.read(4)
    gt = seq.groundtruth_pose(f.stamp)
    off = gt @ Pose.from_rotvec_t(np.radians([0.8, -2.2, 0.3]), [0.02, 0.0, -0.02])  # ~15 px away in the frame
    for search in (60, 0):
        loc = PnlLocalizer.load(pnl_map[0], PnlConfig(search_landmarks=search))
        r = loc.process(f.image, cam, prior=off)
        if search:
            assert r.status == Status.TRACKING and "search_ms" in r.timings, r
            dt, dr = gt.distance_to(r.T_wc)
            assert dt < 0.01 and dr < 0.1, (dt, dr)
        else:
            assert "search_ms" not in r.timings and "features_ms" in r.timings  # the keypoint way


def test_a_relocalization_the_keypoints_cannot_hold_is_aligned_from_the_landmark_patches(pnl_site, pnl_map):
    """A cold frame's coarse pose (PnP on a few dozen descriptor matches) is refined by tracking its keypoints from
    it; where they do not hold it (few ORB matches: a 90-degree lens), the landmarks' patches
    are searched around the coarse pose and aligned, as for a tracking prediction that is off. Here the keypoint step
    matches nothing (a window match must have Hamming distance 0): the frame still relocalizes within 1 cm, and
    without the patch step it is LOST."""
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    f = seq.read(2)
    gt = seq.groundtruth_pose(f.stamp)
    for search in (60, 0):
        loc = PnlLocalizer.load(pnl_map[0], PnlConfig(max_hamming=0, search_landmarks=search))
        r = loc.process(f.image, cam)
        if search:
            assert r.status == Status.RELOCALIZED and "search_ms" in r.timings, r
            dt, dr = gt.distance_to(r.T_wc)
            assert dt < 0.01 and dr < 0.1, (dt, dr)
        else:
            assert r.status == Status.LOST and r.T_wc is None, r
            assert r.reason.startswith("no place in the map was confirmed: the best ("), r.reason  # says why


def test_a_relocalization_aligns_only_from_a_keypoint_pose_within_the_windows_reach(pnl_site, pnl_map):
    """A cold frame's keypoint pose that is plausible but not sure is refined by direct alignment, as a tracking
    prediction is: but only from within ``align_sigma_factor`` x the gates. From further the windows settle on
    self-consistent wrong poses (office seed 5 frame 112, a brick wall seen through a doorway: reported 19 cm /
    1.4 deg off at a predicted 0.5 cm), so the patches are searched around it first. Here every keypoint pose
    counts as too uncertain (factor ~0): the frame still relocalizes within 1 cm, through the search."""
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    f = seq.read(2)
    gt = seq.groundtruth_pose(f.stamp)
    loc = PnlLocalizer.load(pnl_map[0], PnlConfig(align_sigma_factor=1e-6))
    r = loc.process(f.image, cam)
    assert r.status == Status.RELOCALIZED and "search_ms" in r.timings, r
    dt, dr = gt.distance_to(r.T_wc)
    assert dt < 0.01 and dr < 0.1, (dt, dr)


def test_a_pose_too_uncertain_to_report_is_tracked_on_from_its_most_certain_solution(pnl_site, pnl_map):
    """A frame with no pose to report still leaves a pose to track the next frame from. Where the keypoint solution is
    weaker than the landmark patches' aligned one (960x540 walk after a whip pan: keypoints 2-9 cm off, aligned ~1 cm),
    tracking goes on from the aligned one. Here the reporting gates are out of reach, so no solution is good: the
    frame is LOST, and the pose kept is the aligned one, more certain than the keypoints' and within 1 cm / 0.1 deg."""
    from services.geometry.se3 import Pose
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    f = seq.read(4)
    gt = seq.groundtruth_pose(f.stamp)
    prior = gt @ Pose.from_rotvec_t(np.radians([0.1, -0.2, 0.05]), [0.005, 0.0, -0.005])
    unreachable = dict(max_sigma_m=1e-6, max_sigma_deg=1e-6, kp_max_sigma_m=1e-6, kp_max_sigma_deg=1e-6)
    kp = PnlLocalizer.load(pnl_map[0], PnlConfig(align=False, **unreachable)).process(f.image, cam, prior=prior)
    loc = PnlLocalizer.load(pnl_map[0], PnlConfig(**unreachable))
    r = loc.process(f.image, cam, prior=prior)
    assert r.status == kp.status == Status.LOST and r.T_wc is None and r.reason.startswith("pose too uncertain"), r
    assert r.sigma_m < kp.sigma_m and r.sigma_deg < kp.sigma_deg, (r, kp)
    dt, dr = gt.distance_to(loc.T_last)
    assert dt < 0.01 and dr < 0.1, (dt, dr)


def test_a_report_after_a_run_of_uncertain_frames_is_confirmed_by_a_relocalization(pnl_site, pnl_map):
    """A track that went ``confirm_after`` frames without a pose to report has nothing anchoring it: office seed 8's
    slid along a wall through 7 such frames after a turn and reported frame 282 55 cm / 11 deg off at a 1-sigma of
    0.7 cm. Its next report must agree with a relocalization of the frame; with none, or one elsewhere, the frame is not
    reported and tracking goes on. Here the reporting gates are out of reach for 4 frames, then restored."""
    import dataclasses

    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    frames = [seq.read(i) for i in range(5)]
    truth = [seq.groundtruth_pose(f.stamp) for f in frames]
    gates = ("max_sigma_m", "max_sigma_deg", "kp_max_sigma_m", "kp_max_sigma_deg")

    def after_uncertain_run(**kw):
        loc = PnlLocalizer.load(pnl_map[0], PnlConfig(**{g: 1e-6 for g in gates}, confirm_after=3))
        loc.seed(truth[0])
        for f in frames[:4]:
            r = loc.process(f.image, cam)
            assert r.T_wc is None and r.reason.startswith("pose too uncertain"), r.reason
        loc.cfg = dataclasses.replace(loc.cfg, **{g: getattr(PnlConfig(), g) for g in gates}, **kw)
        return loc, loc.process(frames[4].image, cam)

    for kw in ({}, {"confirm_after": 0}):  # a relocalization agrees; no confirmation asked for
        loc, r = after_uncertain_run(**kw)
        assert r.status == Status.TRACKING and truth[4].distance_to(r.T_wc)[0] < 0.01, (kw, r)
        assert ("confirm_ms" in r.timings) == (not kw)
    for kw, why in (({"reloc_min_inliers": 10**6}, "(relocalization: "), ({"confirm_m": 0.0}, "(a relocalization is ")):
        loc, r = after_uncertain_run(**kw)  # no relocalization to agree, or one that disagrees: not reported ...
        assert r.T_wc is None and r.reason.startswith("pose not confirmed after 4 uncertain frames " + why), r.reason
        assert truth[4].distance_to(loc.T_last)[0] < 0.01  # ... but tracked on from


def _after_one_uncertain(pnl_site, pnl_map, shrink: float, frames: int = 3, **kw):
    """A localizer seeded at frame 0's truth whose frame 1 was tracked at ``shrink`` x the gates' 1-sigma (the gates
    shrunk for that frame alone); then frames 2.. (``frames`` in all) processed as usual: (localizer, their results,
    their truths)."""
    import dataclasses

    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    images = [seq.read(i) for i in range(frames)]
    truth = [seq.groundtruth_pose(f.stamp) for f in images]
    gates = ("max_sigma_m", "max_sigma_deg", "kp_max_sigma_m", "kp_max_sigma_deg")
    loc = PnlLocalizer.load(pnl_map[0], PnlConfig(confirm_after=5, **kw))
    loc.seed(truth[0])
    assert loc.process(images[0].image, cam).T_wc is not None
    sigma = loc.process(images[1].image, cam)  # (tracked: its 1-sigma decides the gates below)
    loc = PnlLocalizer.load(pnl_map[0], PnlConfig(confirm_after=5, **kw))
    loc.seed(truth[0])
    loc.process(images[0].image, cam)
    loc.cfg = dataclasses.replace(loc.cfg, max_sigma_m=sigma.sigma_m / shrink, max_sigma_deg=sigma.sigma_deg / shrink,
                                  kp_max_sigma_m=sigma.sigma_m / shrink, kp_max_sigma_deg=sigma.sigma_deg / shrink)
    r = loc.process(images[1].image, cam)
    assert r.T_wc is None and r.reason.startswith("pose too uncertain"), r.reason
    loc.cfg = dataclasses.replace(loc.cfg, **{g: getattr(PnlConfig(), g) for g in gates})
    return loc, [loc.process(f.image, cam) for f in images[2:]], truth[2:]


def test_a_report_after_one_frame_far_beyond_the_gates_is_confirmed_by_a_relocalization(pnl_site, pnl_map):
    """One tracked frame ``confirm_beyond`` x the gates' 1-sigma means the track slipped: office seed 2's frame 269 (1.8 cm
    / 0.22 deg, an accelerating pan) was followed by frames 270-272 aligned at 0.4-0.6 cm 1-sigma, 2.5-5.4 cm off. The
    next report waits for a relocalization to agree, as after ``confirm_after`` uncertain frames; a frame just over the
    gates (office seed 13's frame 6 at 0.105 deg) asks for none. Here the gates are out of reach for one frame."""
    from services.localize.pnl import Status

    loc, (r,), (truth,) = _after_one_uncertain(pnl_site, pnl_map, 3.0)  # far beyond: a relocalization agrees, reported
    assert r.status == Status.TRACKING and "confirm_ms" in r.timings and truth.distance_to(r.T_wc)[0] < 0.01, r
    loc, (r,), _ = _after_one_uncertain(pnl_site, pnl_map, 1.5)  # just over the gates: no confirmation asked for
    assert r.status == Status.TRACKING and "confirm_ms" not in r.timings, r
    # far beyond, nothing to agree: not reported, tracked on
    loc, (r,), (truth,) = _after_one_uncertain(pnl_site, pnl_map, 3.0, reloc_min_inliers=10**6)
    assert r.T_wc is None and r.reason.startswith("pose not confirmed after 1 uncertain frame (relocalization: "), r.reason
    assert truth.distance_to(loc.T_last)[0] < 0.01


def test_a_track_no_relocalization_can_check_is_reported_after_a_run_of_good_frames(pnl_site, pnl_map):
    """Where relocalization finds no place at all, frame after frame (a map from a scan in laser intensity: its ORB
    descriptors seldom match a photograph; office seed 8 in intensity tracked frames 2-60 within 0.1-1.3 cm, 1-sigma
    within the gates, and reported none), a track that stays good for ``confirm_unopposed`` frames in a row is
    reported: nothing says otherwise. A relocalization that disagrees, or rival places, start the count again."""
    from services.localize.pnl import Status

    loc, results, truths = _after_one_uncertain(pnl_site, pnl_map, 3.0, frames=6, reloc_min_inliers=10**6,
                                                confirm_unopposed=3)
    assert [r.T_wc is None for r in results] == [True, True, False, False], [r.reason for r in results]
    assert results[1].reason.startswith("pose not confirmed after 2 uncertain frames"), results[1].reason
    assert results[2].status == Status.TRACKING and all(t.distance_to(r.T_wc)[0] < 0.01 for r, t in zip(results[2:], truths[2:]))
    loc, results, _ = _after_one_uncertain(pnl_site, pnl_map, 3.0, frames=6, reloc_min_inliers=10**6, confirm_unopposed=0)
    assert all(r.T_wc is None for r in results)  # (0: off, as before)


def _text_strip(img: np.ndarray, seed: int, share: float = 0.15) -> np.ndarray:
    """``img`` with a strip of printed text over its left ``share`` (something in front of the scene: a sign, people)."""
    import cv2

    rng = np.random.default_rng(seed)
    img = img.copy()
    sign = np.full((img.shape[0], int(share * img.shape[1]), 3), 230, np.uint8)
    for y in range(12, sign.shape[0], 14):
        text = "".join(rng.choice(list("ABCDEFGHKMNPRSTWXYZ0123456789#%&"), 30))
        cv2.putText(sign, text, (2, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (20, 20, 20), 1, cv2.LINE_AA)
    img[:, :sign.shape[1]] = sign
    return img


def test_a_crowded_cold_frame_is_matched_with_more_keypoints(pnl_site, pnl_map):
    """Something in front of the scene (people, signs) takes many of ORB's strongest keypoints: a cold frame that no
    place fits with the ``reloc_keypoints`` strongest is matched with up to ``reloc_keypoints_crowded``. A strip of
    printed text over 15 % of each test frame: no place with 600 on any of the 8 (9-30 descriptor matches, mostly not
    held by one group of keyframes); with 1000, 7 of the 8 relocalize within 0.4 cm / 0.08 deg. (benchmarks/occluders.py:
    the office walk with passers-by over 28 % of the frame, 236 -> 260 of 300 frames; clean walks never pay.)"""
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer, Status

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    found = 0
    for idx in range(len(seq)):
        f = seq.read(idx)
        img = _text_strip(f.image, idx)
        few = PnlLocalizer.load(pnl_map[0], PnlConfig(reloc_keypoints_crowded=600)).process(img, cam)
        assert few.status == Status.LOST and few.reason.startswith("no place in the map fits"), (idx, few.reason)
        r = PnlLocalizer.load(pnl_map[0]).process(img, cam)
        if r.T_wc is not None:
            dt, dr = seq.groundtruth_pose(f.stamp).distance_to(r.T_wc)
            assert dt < 0.01 and dr < 0.2, (idx, dt, dr)  # never a wrong pose (today's environment: 0.43 cm / 0.106 deg)
            found += 1
    assert found >= 6, found


def _with_look_alike(m, shift: np.ndarray, unique: set[int]):
    """The map ``m`` and a copy of it ``shift`` away (a look-alike place: identical racks, a second floor), where the
    landmarks ``unique`` are seen at the copy only (the original's keyframes lose those observations)."""
    import copy

    from services.geometry.se3 import Pose

    lm_off, kf_off = int(m.lm_ids.max()) + 1, max(m.keyframes) + 1
    kfs = {}
    for k, kf in m.keyframes.items():
        a = copy.copy(kf)
        a.lm_ids = np.where(np.isin(kf.lm_ids, list(unique)), -1, kf.lm_ids)
        kfs[k] = a
        b = copy.copy(kf)
        b.id, b.T_wc = k + kf_off, Pose(kf.T_wc.R, kf.T_wc.t + shift)
        b.lm_ids = np.where(kf.lm_ids >= 0, kf.lm_ids + lm_off, -1)
        b.span_parent = kf.span_parent + kf_off if kf.span_parent >= 0 else -1
        b.span_children, b.loop_edges = [c + kf_off for c in kf.span_children], []
        kfs[b.id] = b
    twin = copy.copy(m)
    twin.keyframes = kfs
    twin.lm_ids = np.concatenate([m.lm_ids, m.lm_ids + lm_off])
    twin.lm_pos = np.concatenate([m.lm_pos, m.lm_pos + shift])
    for name in ("lm_first_kf", "lm_ref_kf"):
        setattr(twin, name, np.concatenate([getattr(m, name), getattr(m, name) + kf_off]))
    for name in ("lm_n_vis", "lm_n_fnd"):
        setattr(twin, name, np.concatenate([getattr(m, name), getattr(m, name)]))
    return twin, lm_off


def _patches_with_look_alike(p, shift: np.ndarray, lm_off: int):
    """The landmark patches of :func:`_with_look_alike`'s map: the copy's are the original's, seen from shifted keyframes."""
    from services.prebuild.patches import LandmarkPatches

    T = p.src_T_cw.copy()
    T[:, :, 3] -= np.einsum("vij,j->vi", p.src_T_cw[:, :, :3], shift)  # world-to-camera of a keyframe moved by shift
    return LandmarkPatches(np.concatenate([p.lm_ids, p.lm_ids + lm_off]), np.concatenate([p.patches, p.patches]),
                           np.concatenate([p.normals, p.normals]), np.concatenate([p.src, p.src + len(p.src_T_cw)]),
                           np.concatenate([p.src_T_cw, T]), p.K)


def test_a_crowded_frame_is_not_relocalized_at_a_look_alike_place(pnl_site, pnl_map):
    """The crowded retry matches its extra keypoints only around the places the first matches voted for; distinct
    there is not distinct in the map when a look-alike place lies elsewhere (the survey-density warehouse's frame 313
    was relocalized in a bay 28.6 m off and tracked there for 38 frames). Here the test map gets a copy of itself 30 m
    away, and the landmarks the first 600 keypoints of each crowded frame match are seen at the copy only, so the
    first matches vote for the copy alone. Matched around it, the extra keypoints put 7 of the 8 frames there; each
    must also pass the ratio test against every landmark, which the original's twins fail: no frame gets a pose."""
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlLocalizer

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    plain = PnlLocalizer.load(pnl_map[0])
    m, shift = plain.idx.map, np.array([30.0, 0.0, 0.0])
    assert plain.patches is not None
    for idx in range(len(seq)):
        f = seq.read(idx)
        img = _text_strip(f.image, idx)
        fr = plain._features(plain._frame(img, cam), {})
        first = np.argsort(-fr.feats.responses)[:plain.cfg.reloc_keypoints]
        _, rows = plain._ratio_matches(fr.feats.desc, first, plain.idx._reloc_rows)
        twin, lm_off = _with_look_alike(m, shift, {int(i) for i in m.lm_ids[rows]})
        r = PnlLocalizer(twin, patches=_patches_with_look_alike(plain.patches, shift, lm_off)).process(img, cam)
        assert r.T_wc is None, (idx, seq.groundtruth_pose(f.stamp).distance_to(r.T_wc))


def test_a_hint_of_where_the_camera_starts_resolves_a_twin_place(pnl_site, pnl_map):
    """``process(near=(position, radius))``: the test map plus an identical copy 30 m away. Cold, no frame can tell the
    two apart (ambiguous or a ratio test failed by the twins); told the camera starts within 3 m of a point 1.5 m from
    the truth, the first frame relocalizes at the true place and the walk tracks on from it."""
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlLocalizer

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    plain = PnlLocalizer.load(pnl_map[0])
    shift = np.array([30.0, 0.0, 0.0])
    twin, lm_off = _with_look_alike(plain.idx.map, shift, set())
    patches = _patches_with_look_alike(plain.patches, shift, lm_off)
    f0, G0 = seq.read(0), seq.groundtruth.poses[0]
    assert PnlLocalizer(twin, patches=patches).process(f0.image, cam).T_wc is None
    loc = PnlLocalizer(twin, patches=patches)
    for i in range(len(seq)):
        f = seq.read(i)
        r = loc.process(f.image, cam, near=(G0.t + [1.5, 0, 0], 3.0))  # (sent with every frame: kept, then ignored)
        assert r.T_wc is not None, (i, r.reason)
        dt, dr = seq.groundtruth_pose(f.stamp).distance_to(r.T_wc)
        assert dt < 0.015 and dr < 0.2, (i, dt, dr)


def test_places_about_as_good_are_told_apart_by_tracking_from_each(pnl_site, pnl_map):
    """A cold frame's descriptor matches can fit a wrong place about as well as the right one (office cold frames 71
    and 77: 27 and 33 coarse inliers at a place 4.3 m / 100 deg away, against 28 and 37). Tracked from each, only the
    right place holds its landmarks: its pose wins, within the tracking accuracy. A look-alike place that tracks as well
    (the map's copy 30 m away) leaves the frame unreported, as before."""
    from services.geometry.se3 import Pose
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlLocalizer

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    plain = PnlLocalizer.load(pnl_map[0])
    shift = np.array([30.0, 0.0, 0.0])
    twin_map, lm_off = _with_look_alike(plain.idx.map, shift, set())
    twin = PnlLocalizer(twin_map, patches=_patches_with_look_alike(plain.patches, shift, lm_off))
    won = 0
    for i in range(0, len(seq), 3):
        f, G = seq.read(i), seq.groundtruth.poses[i]
        coarse = Pose(G.R, G.t + [0.03, -0.02, 0.02])  # a coarse PnP pose of the right place
        turned = Pose(G.R @ np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]), G.t + [1.5, 0, 0.5])  # another place
        fr = plain._frame(f.image, cam)
        r = plain._contest(fr, [(33, turned), (30, coarse)], {})  # (the wrong place first)
        if r is not None:
            won += 1
            dt, dr = G.distance_to(Pose(r[0].T, -r[0].T @ r[1]))
            assert dt < 0.015 and dr < 0.2, (i, dt, dr)
        far = Pose(coarse.R, coarse.t + shift)
        assert twin._contest(twin._frame(f.image, cam), [(31, coarse), (30, far)], {}) is None, i
    assert won >= len(range(0, len(seq), 3)) - 1, won


def test_relocalization_matching_scales_past_opencv_s_knn_limit(kernels):
    """OpenCV's brute-force kNN takes at most 2^18 train rows at once; the survey-density warehouse map has 327,379
    landmarks and its relocalization raised cv2.error. The nearest two are now taken over chunks and merged: the same
    answer as one kNN where one kNN works, and an answer past the limit. Compiled (numba) or with OpenCV alike."""
    import cv2

    from services.localize.pnl import knn2_hamming

    rng = np.random.default_rng(0)
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    q = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    train = rng.integers(0, 256, (300_000, 32), dtype=np.uint8)
    train[123_456] = q[0]  # an exact match beyond the first chunk
    best, d1, d2 = knn2_hamming(bf, q, train)
    assert best[0] == 123_456 and d1[0] == 0 and d2[0] > 0
    small = train[:5000]
    one = bf.knnMatch(q, small, k=2)
    b, e1, e2 = knn2_hamming(bf, q, small, chunk=777)
    assert [m[0].distance for m in one] == list(e1) and [m[1].distance for m in one] == list(e2)
    distinct = e1 < e2  # where the nearest is nearer than the second, it is the same row
    assert [m[0].trainIdx for m, k in zip(one, distinct) if k] == list(b[distinct])
    b, e1, e2 = knn2_hamming(bf, q, small[:1])  # one landmark: no second nearest
    assert (b == 0).all() and np.isfinite(e1).all() and np.isinf(e2).all()


def _rolling_walk(pnl_site, readout_s: float, pan_deg: float):
    """``pnl_site``'s ground-truth walk turned by ``pan_deg`` more each frame (about the world's z, 30 frames a second),
    rendered row by row over ``readout_s`` (a rolling shutter, rows top to bottom; the pose of frame k is its middle
    row's). Returns the frames (BGR) and their poses."""
    import cv2

    from services.geometry.rolling_shutter import row_time
    from services.geometry.se3 import Pose, rotvec_to_rotmat
    from services.io.sequence import open_sequence
    from services.sim.materials import linear_to_srgb
    from services.sim.site import SimSite

    root, out, cam, box = pnl_site
    gt = [T for _, T in open_sequence(out / "seq").groundtruth]
    site = SimSite(root)

    def pose(s: float) -> Pose:  # s in frames
        i = int(np.clip(np.floor(s), 0, len(gt) - 2))
        T = gt[i].interpolate(gt[i + 1], s - i)
        return Pose(rotvec_to_rotmat([0.0, 0.0, np.radians(pan_deg) * s]) @ T.R, T.t)

    frames, poses = [], []
    for k in range(len(gt)):
        rows = [pose(k + 30.0 * tau) for tau in row_time(np.arange(cam.height), cam.height, readout_s)]
        rad, _ = site.renderer.render_rows(rows, cam, site.camera_lighting)
        rgb = (linear_to_srgb(rad * (0.16 / max(float(rad.mean()), 1e-6))) * 255.0 + 0.5).astype(np.uint8)
        frames.append(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        poses.append(pose(k))
    return frames, poses


def test_a_rolling_shutter_frame_is_unrolled_before_tracking(pnl_site, pnl_map):
    """A phone reads its rows one after another: turning at 90 deg/s while walking, with a 30 ms readout, the bottom
    row sees the scene 2.7 deg and 3.4 cm further on than the top one. Tracked as if taken at one instant, none of
    the 8 frames is certain enough to report. With ``readout_s`` declared, each frame with a motion to go by is first
    re-sampled into its middle row's view (services.geometry.rolling_shutter), and reported once the motion comes
    from frames unrolled too: frames 4-7, within 0.5-1.2 cm / 0.07-0.15 deg. Before, the cold first frame has no
    motion to undo (it relocalized 12.6 cm / 1.5 deg off) and the frames after it inherit its error (frame 2: 1.9 cm
    / 0.35 deg): not reported."""
    from services.localize.pnl import PnlConfig, PnlLocalizer

    root, out, cam, box = pnl_site
    frames, poses = _rolling_walk(pnl_site, 0.030, 3.0)
    got = {}
    for readout in (0.0, 0.030):
        loc = PnlLocalizer.load(pnl_map[0], PnlConfig(readout_s=readout))
        got[readout] = [(k, T.distance_to(r.T_wc)) for k, (T, r) in enumerate(zip(poses, (loc.process(f, cam) for f in frames)))
                        if r.T_wc is not None]
    print("rolling shutter: without", got[0.0], "with", got[0.030])
    assert [k for k, _ in got[0.030]] == [4, 5, 6, 7], got[0.030]
    settled = np.array([e for _, e in got[0.030]])
    rmse = np.sqrt((settled ** 2).mean(axis=0))
    assert rmse[0] < 0.015 and rmse[1] < 0.2, rmse
    # undeclared, the shutter's skew is reported as pose: the cold frame 12.6 cm / 1.5 deg off (no motion to undo, as
    # below) and, depending on the environment with P&L unchanged, one or two frames after it (2026-12-02: frame 1,
    # 3.9 cm / 0.71 deg; 2026-12-03 stop 36's venv, the same packages as stop 35's: frames 1 and 2, 12.9 cm / 1.5 deg
    # and 2.8 cm / 0.45 deg). Which frames come out is chaotic; that they are fewer and far worse is the point.
    undeclared = np.array([e for _, e in got[0.0]]).reshape(-1, 2)
    assert len(undeclared) < len(settled), got[0.0]
    assert len(undeclared) == 0 or np.sqrt((undeclared[:, 0] ** 2).mean()) > 2 * rmse[0], (got[0.0], rmse)


def test_a_hand_over_in_a_turn_is_predicted_from_the_seeds_motion(pnl_site, pnl_map):
    """The client seeds the local localizer with every server pose; when the server misses a frame in a fast turn,
    the first local frame was predicted with no motion at all (the seed's pose), and a 960x540 walk's frame in a
    1.8 deg-a-frame turn was tracked into a pose 2.9 cm / 1.8 deg off and reported. Seeds with capture times a
    frame apart now give the velocity: in this walk turned 4 deg a frame more, each frame handed over after two
    seeds that is reported is near the truth (frames 3-4 within 0.4 cm / 0.07 deg; the later ones tracked at
    0.8-1.8 cm / 0.13-0.31 deg 1-sigma and not reported); seeded once (no motion known), none is reported."""
    from services.localize.pnl import PnlConfig, PnlLocalizer

    root, out, cam, box = pnl_site
    frames, poses = _rolling_walk(pnl_site, 0.0, 4.0)
    loc = PnlLocalizer.load(pnl_map[0], PnlConfig(reloc_min_inliers=10 ** 6))  # (only the hand-over can place them)
    got = {}
    for seeds in (1, 2):
        got[seeds] = []
        for k in range(2, len(frames) - 1):
            loc.reset()
            for j in range(k - seeds + 1, k + 1):
                loc.seed(poses[j], stamp=j / 30.0)
            r = loc.process(frames[k + 1], cam, stamp=(k + 1) / 30.0)
            got[seeds].append(r.reason if r.T_wc is None else poses[k + 1].distance_to(r.T_wc))
    print("hand-over: one seed", got[1], "two seeds", got[2])
    reported = {n: [e for e in got[n] if isinstance(e, tuple)] for n in got}  # (else the reason it was not)
    assert len(reported[2]) >= 2 and all(dt < 0.01 and dr < 0.2 for dt, dr in reported[2]), got[2]
    assert len(reported[1]) < len(reported[2]) and all(dt < 0.05 and dr < 1.0 for dt, dr in reported[1]), got[1]
    loc.reset()  # seeds further apart than seed_velocity_gap_s give no velocity
    loc.seed(poses[2], stamp=0.0)
    loc.seed(poses[3], stamp=1.0)
    assert loc._vel is None


def _dim(image: np.ndarray, seed: int) -> np.ndarray:
    """A dim room at a fixed short exposure (benchmarks/photometric.py's "dark"): a third of the light, gamma 1.3, read
    noise, JPEG."""
    import cv2

    x = 0.3 * (image.astype(np.float32) / 255.0) ** 1.3 + np.random.default_rng(seed).normal(0, 0.015, image.shape)
    ok, jpg = cv2.imencode(".jpg", np.clip(255 * x, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 90])
    return cv2.imdecode(jpg, cv2.IMREAD_COLOR)


def test_dim_frames_are_tracked_and_relocalized(pnl_site, pnl_map):
    """A dark frame's corners fall under ORB's grey-level thresholds, and its noise and JPEG blocks pull the alignment's
    windows: a cold frame no place fits is relocalized again with its grey levels stretched, and a frame this noisy
    for its contrast is smoothed before patches are aligned to it (``PnlConfig.reloc_stretch_*``, ``denoise_above``).
    On the 8 test frames made dim: 8 with both (5 without either until stop 28's environment; 8 in 2026-12-02's).
    (benchmarks/photometric.py: the office walk at a third of the light, 84 -> 150 of 150 frames.)"""
    import cv2

    from services.io.sequence import open_sequence
    from services.localize.direct import noise_ratio
    from services.localize.pnl import PnlConfig, PnlLocalizer

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    clean = [seq.read(i).image for i in range(len(seq))]
    frames = [(_dim(im, i), seq.groundtruth_pose(seq.read(i).stamp)) for i, im in enumerate(clean)]
    cfg = PnlConfig()
    assert all(noise_ratio(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY)) < cfg.denoise_above for im in clean)
    assert all(noise_ratio(cv2.cvtColor(im, cv2.COLOR_BGR2GRAY)) > cfg.denoise_above for im, _ in frames)

    def cold(cfg: PnlConfig) -> list:
        loc = PnlLocalizer.load(pnl_map[0], cfg)
        errors = []
        for im, g in frames:
            loc.reset()
            r = loc.process(im, cam)
            if r.T_wc is not None:
                errors.append(g.distance_to(r.T_wc))
        return errors

    found = cold(cfg)
    assert len(found) == len(frames) and all(dt < 0.015 and dr < 0.2 for dt, dr in found), found
    # (the ablation, without either: 5 of 8 until stop 28; in the 2026-12-02 environment all 8, with P&L unchanged, so
    # this site no longer shows what they add: benchmarks/photometric.py does)
    loc = PnlLocalizer.load(pnl_map[0], cfg)
    for i, (im, g) in enumerate(frames):
        r = loc.process(im, cam, prior=g if i == 0 else None)
        assert r.T_wc is not None, (i, r.reason)
        dt, dr = g.distance_to(r.T_wc)
        assert dt < 0.01 and dr < 0.15, (i, dt, dr)


def test_a_patch_pose_from_an_untracked_prediction_is_checked_by_keypoints(pnl_site, pnl_map, caplog):
    """From a prediction 5-20 cm off that no tracked frame made (a caller's prior here; a pose carried or relocalized,
    a seed with no velocity), the patches of a few near landmarks can lock onto the wrong edge while the far ones leave
    the translation-rotation valley open: before the check, this site reported 2 of these 144 frames 14-15 cm off
    (0.9-1.7 deg). Now each is kept where the keypoints agree, else a relocalization decides: none far off. A frame
    the relocalization decided is reported as relocalized (it was reported as tracked)."""
    import logging

    from services.geometry.se3 import Pose, rotvec_to_rotmat
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer
    from services.localize.status import Status

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    loc = PnlLocalizer.load(pnl_map[0], PnlConfig())
    rng = np.random.default_rng(0)
    reported, off, decided = 0, [], []
    for dist in (0.05, 0.1, 0.2):
        for i in range(len(seq)):
            f = seq.read(i)
            gt = seq.groundtruth_pose(f.stamp)
            for _ in range(6):
                d, a = rng.standard_normal(3), rng.standard_normal(3)
                prior = Pose(rotvec_to_rotmat(a / np.linalg.norm(a) * np.radians(10 * dist)) @ gt.R,
                             gt.t + dist * d / np.linalg.norm(d))
                loc.reset()
                caplog.clear()
                with caplog.at_level(logging.DEBUG, logger="services.localize.pnl"):
                    r = loc.process(f.image, cam, prior=prior, stamp=float(f.stamp))
                if "disagrees with a relocalization" in caplog.text:
                    decided.append(r.status)
                if r.T_wc is not None:
                    reported += 1
                    dt, dr = gt.distance_to(r.T_wc)
                    if dt > 0.03 or dr > 0.5:
                        off.append((dist, i, round(100 * dt, 1), round(dr, 2)))
    print(f"{reported} of {3 * 6 * len(seq)} reported, off: {off}; decided by a relocalization: {decided}")
    assert reported >= 0.9 * 3 * 6 * len(seq) and not off, (reported, off)
    assert decided and all(s == Status.RELOCALIZED for s in decided), decided


def test_a_velocity_made_of_a_correction_is_not_carried(pnl_site, pnl_map, caplog):
    """A pose handed over (or tracked) off the truth, then a frame whose patches pull it back: the motion between the two
    holds the correction, and the next frame predicted with it starts off by as much, where patches can settle in a wrong
    basin at a small 1-sigma (the narrow-lens walk reported frames 162-166 8-14 cm off at 0.3-0.5 cm). A pose further
    from its constant-velocity prediction than the motion allows is now checked by keypoints and its motion is not
    carried: the next frame is predicted from it with no motion, and checked too. Seeded on the truth, the motion is
    carried as before. None is reported far off, and most are reported."""
    import logging

    from services.geometry.se3 import Pose, rotvec_to_rotmat
    from services.io.sequence import open_sequence
    from services.localize.pnl import PnlConfig, PnlLocalizer

    root, out, cam, box = pnl_site
    seq = open_sequence(out / "seq")
    loc = PnlLocalizer.load(pnl_map[0], PnlConfig())
    gts = [seq.groundtruth_pose(seq.read(i).stamp) for i in range(len(seq))]
    stamps = [float(seq.read(i).stamp) for i in range(len(seq))]
    rng = np.random.default_rng(1)
    trials, reported, off, carried = 0, 0, [], {}
    for dist in (0.0, 0.02, 0.03):
        for i in range(2, len(seq) - 1):
            for _ in range(1 if dist == 0 else 3):
                d, a = rng.standard_normal(3), rng.standard_normal(3)
                wrong = Pose(rotvec_to_rotmat(a / np.linalg.norm(a) * np.radians(5 * dist)) @ gts[i - 1].R,
                             gts[i - 1].t + dist * d / np.linalg.norm(d))
                loc.reset()
                loc.seed(gts[i - 2], stamp=stamps[i - 2])
                loc.seed(wrong, stamp=stamps[i - 1])  # the velocity holds the error: frame i is predicted twice as far off
                for j in (i, i + 1):
                    caplog.clear()
                    with caplog.at_level(logging.DEBUG, logger="services.localize.pnl"):
                        r = loc.process(seq.read(j).image, cam, stamp=stamps[j])
                    if j == i and r.T_wc is not None:  # (jumped: whether the pose was checked for being off the prediction)
                        carried.setdefault(dist, []).append(("from the prediction" in caplog.text, loc._vel is not None))
                    trials += 1
                    if r.T_wc is not None:
                        reported += 1
                        dt, dr = gts[j].distance_to(r.T_wc)
                        if dt > 0.03 or dr > 0.5:
                            off.append((dist, j, round(100 * dt, 1), round(dr, 2)))
    print(f"{reported} of {trials} reported, off: {off}; (jumped, motion carried) after frame i: {carried}")
    assert all(c == (False, True) for c in carried[0.0]), carried[0.0]
    jumped = [c for k in (0.02, 0.03) for c in carried[k] if c[0]]
    assert len(jumped) >= 10 and not any(v for _, v in jumped), carried
    assert not off and reported >= 0.8 * trials, (reported, trials, off)


def test_the_report_gates_given_on_the_command_line_reach_the_light_localizer():
    from services.cli import build_parser
    from services.localize.pnl import PnlConfig
    from services.localize.pnl_cli import pnl_config

    base = ["localize", "map", "seq", "--method", "pnl", "--map", "map", "--out", "t.txt"]
    d, cfg = PnlConfig(), pnl_config(build_parser().parse_args(base))
    assert (cfg.max_sigma_m, cfg.max_sigma_deg, cfg.kp_max_sigma_deg) == (d.max_sigma_m, d.max_sigma_deg, d.kp_max_sigma_deg)
    cfg = pnl_config(build_parser().parse_args(base + ["--max-sigma-deg", "0.2", "--max-sigma-cm", "3"]))
    assert cfg.max_sigma_deg == 0.2 and abs(cfg.max_sigma_m - 0.03) < 1e-12
    assert abs(cfg.kp_max_sigma_deg - 2 * d.kp_max_sigma_deg) < 1e-12 and abs(cfg.kp_max_sigma_m - 3 * d.kp_max_sigma_m) < 1e-12


def test_the_report_gates_given_to_cristal_serve_reach_every_client_s_tracker(pnl_map):
    """`cristal serve --max-sigma-cm/--max-sigma-deg/--min-agreement` set the gates of the trackers the server makes
    per client (before, the server always ran the defaults): the P&L backend loaded from a real map, the R&M
    backend's configuration as the command builds it."""
    from services.cli import build_parser
    from services.localize.render_match import RMConfig
    from services.server.backend import load_backend
    from services.server.cli import backend_configs

    mapdir, _ = pnl_map
    gates = ["--max-sigma-deg", "0.2", "--max-sigma-cm", "3", "--min-agreement", "0.45"]
    args = build_parser().parse_args(["serve", "--backend", "pnl", "--map", str(mapdir), *gates])
    backend = load_backend(args.backend, args.scan, args.db, args.map_dir, "cpu", *backend_configs(args))
    cfg = backend.make().cfg
    assert cfg.max_sigma_deg == 0.2 and abs(cfg.max_sigma_m - 0.03) < 1e-12
    rm, pnl = backend_configs(build_parser().parse_args(["serve", "scan.ply", "--db", "db.npz", *gates]))
    assert pnl is None and (rm.max_sigma_deg, rm.reloc_min_agreement) == (0.2, 0.45) and abs(rm.max_sigma_m - 0.03) < 1e-12
    d, _ = backend_configs(build_parser().parse_args(["serve", "scan.ply", "--db", "db.npz"]))
    assert (d.max_sigma_m, d.max_sigma_deg, d.reloc_min_agreement) == (RMConfig().max_sigma_m, RMConfig().max_sigma_deg,
                                                                         RMConfig().reloc_min_agreement)


def test_a_sequence_without_camera_json_is_localized_with_camera(pnl_site, pnl_map, tmp_path):
    """A TUM RGB-D download has rgb.txt and images but no camera.json: the error says what to write or pass, and
    --camera supplies it."""
    import json
    import shutil

    root, out, _, _ = pnl_site
    mapdir, _ = pnl_map
    seq = tmp_path / "tum"
    shutil.copytree(out / "seq", seq)
    (seq / "camera.json").rename(tmp_path / "camera.json")
    r = _cli("localize", mapdir, seq, "--method", "pnl", "--map", mapdir, "--out", tmp_path / "t.txt")
    assert r.returncode != 0 and "no camera.json found" in r.stderr and "--camera" in r.stderr, r.stderr
    r = _cli("localize", mapdir, seq, "--method", "pnl", "--map", mapdir, "--out", tmp_path / "t.txt",
             "--camera", tmp_path / "camera.json")
    assert r.returncode == 0, r.stdout + r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1])["localized"] >= 7


def test_the_scans_own_error_widens_the_reported_sigma_and_nothing_else(pnl_site, pnl_map):
    """As Render & Match's (test_render_match): the light localizer counts ``--scan-sigma-mm`` in each reported
    1-sigma, at the depth of its map's keyframe nearest the pose, and reports the same poses."""
    from services.localize.pnl import PnlConfig, PnlLocalizer
    from services.localize.scan_error import scan_floor

    cam, frames, _, _ = _six_frames(pnl_site)

    def run(cfg):
        loc = PnlLocalizer.load(pnl_map[0], cfg)
        return [loc.process(f.image, cam, stamp=float(f.stamp)) for f in frames]

    own, widened = run(PnlConfig()), run(PnlConfig(scan_sigma_m=0.008))
    assert sum(r.T_wc is not None for r in own) >= 4
    for _, a, b in reported_alike(own, widened):
        assert added_m(a, b) == pytest.approx(0.016, rel=1e-6)
        floor_deg = np.sqrt(b.sigma_deg ** 2 - a.sigma_deg ** 2)
        # a room a few metres across: seen from 1-5 m
        assert scan_floor(0.008, 5.0)[1] < floor_deg < scan_floor(0.008, 1.0)[1], floor_deg
    # where on the site the error lies, as prebuild records it beside the map: 2 mm wherever the scan has points
    local = run(PnlConfig(scan_sigma_m=0.008, scan_grid=uniform_grid(pnl_site[0] / "scan.ply", 0.002)))
    for _, a, c in reported_alike(own, local):
        assert added_m(a, c) == pytest.approx(0.004, rel=0.1)
