"""The simulator: layout, determinism, and that frames, depth and scan agree with the ground-truth poses."""

import json

import cv2
import numpy as np
import pytest

from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.io.sequence import open_sequence
from services.sim.site import SimSite, generate_site


def test_layout_follows_conventions(small_site):
    out, cfg, summary = small_site
    for f in ["scan.ply", "site.json", "mesh.npz", "seq_00/rgb.txt", "seq_00/camera.json", "seq_00/groundtruth.txt"]:
        assert (out / f).exists(), f
    seq = open_sequence(out / "seq_00")
    assert len(seq) == 12 and seq.groundtruth.stamps == seq.stamps
    assert seq.camera.distortion == pytest.approx((-0.1, 0.02, 0.0, 0.0, 0.0))
    assert all(f.name.endswith(".jpg") for f in seq.files)
    assert summary["points"] > 100_000 and json.loads((out / "site.json").read_text())["seed"] == 3


def test_scan_points_agree_with_ground_truth_depth(small_site):
    """Project the scan with a ground-truth pose: the nearest points sit on the ray-traced depth (2 mm noise)."""
    from services.io.scans import load_scan

    out, cfg, _ = small_site
    scan = load_scan(out / "scan.ply")
    seq = open_sequence(out / "seq_00")
    site = SimSite(out)
    cam = seq.camera
    for i in (0, 6, 11):
        T_wc = seq.groundtruth.poses[i]
        _, depth = site.render(T_wc, cam)
        Xc = T_wc.inverse().transform(scan.world_xyz())
        Xc = Xc[Xc[:, 2] > 0.2]
        uv, z = cam.project(Xc)
        px = np.round(uv).astype(int)
        ok = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        px, z = px[ok], z[ok]
        zbuf = np.full((cam.height, cam.width), np.inf)
        np.minimum.at(zbuf, (px[:, 1], px[:, 0]), z)
        both = np.isfinite(zbuf) & (depth > 0)
        rel = np.abs(zbuf[both] - depth[both]) / depth[both]
        assert both.mean() > 0.3
        assert np.median(rel) < 0.01, f"frame {i}: scan and ground-truth depth disagree"


def _ncc(a, b):
    a = a.astype(np.float64) - a.mean()
    b = b.astype(np.float64) - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def test_frames_match_renders_at_their_ground_truth_pose(small_site):
    out, _, _ = small_site
    seq = open_sequence(out / "seq_00")
    site = SimSite(out)
    for i in (2, 9):
        frame = cv2.cvtColor(seq.read(i).image, cv2.COLOR_BGR2GRAY)
        T_wc = seq.groundtruth.poses[i]
        rgb, _ = site.render(T_wc, seq.camera, lighting="camera")
        good = _ncc(frame, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
        off = T_wc @ Pose.from_rotvec_t(np.deg2rad([0, 4, 0]), [0, 0, 0])
        rgb_off, _ = site.render(off, seq.camera, lighting="camera")
        bad = _ncc(frame, cv2.cvtColor(rgb_off, cv2.COLOR_RGB2GRAY))
        assert good > 0.8 and good > bad + 0.1, (good, bad)


def test_same_seed_same_site(small_site, tmp_path):
    out, cfg, _ = small_site
    generate_site(cfg, tmp_path)
    assert (out / "seq_00" / "groundtruth.txt").read_text() == (tmp_path / "seq_00" / "groundtruth.txt").read_text()
    assert (out / "scan.ply").read_bytes() == (tmp_path / "scan.ply").read_bytes()
    assert (out / "seq_00" / "rgb.txt").read_text() == (tmp_path / "seq_00" / "rgb.txt").read_text()


def test_sim_cli_and_view(tmp_path, capsys, small_site):
    from services.cli import main

    out, _, _ = small_site
    cam = Camera.from_fov(120, 90, 60)
    cam.save(tmp_path / "cam.json")
    rc = main(["sim-view", str(out), "--pose", "3 2.5 1.5 -0.5 0.5 -0.5 0.5", "--camera", str(tmp_path / "cam.json"),
               "--out", str(tmp_path / "v.png"), "--depth", str(tmp_path / "d.npy")])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["hit_fraction"] == 1.0  # indoors every ray hits something
    assert cv2.imread(str(tmp_path / "v.png")).shape == (90, 120, 3)
    assert np.load(tmp_path / "d.npy").max() < 15
    assert main(["sim-view", str(tmp_path), "--pose", "0 0 0 0 0 0 1", "--camera", str(tmp_path / "cam.json"),
                 "--out", str(tmp_path / "x.png")]) == 2
    assert main(["sim-view", str(out), "--pose", "1 2 3", "--camera", str(tmp_path / "cam.json"),
                 "--out", str(tmp_path / "x.png")]) == 2


def test_a_loose_station_is_the_one_scan_check_names(tmp_path):
    """``--scan-flaws loose``: a millimetre registration but for one station (the one nearest the stations' middle),
    which ``cristal scan check`` names (services/io/registration.py) and the scan's record locates."""
    from services.io.registration import station_agreement
    from services.io.scans import load_scan
    from services.localize.scan_error import grid_arg, measure_scan
    from services.sim.lidar import loose_station
    from services.sim.scenes import make_scene
    from services.sim.site import config_for

    from services.sim.cli import FLAW_NAMES
    from services.sim.lidar import FLAWS

    assert set(FLAW_NAMES) == set(FLAWS)  # every flaw preset can be named to cristal sim
    cfg = config_for("office", seed=1, frames=2, width=160, height=120, lidar_step_deg=0.4, scan_flaws="loose")
    generate_site(cfg, tmp_path / "s")
    scan = load_scan(tmp_path / "s" / "scan.ply")
    k = loose_station(make_scene("office", 1).stations)
    a = station_agreement(scan)
    own = a.station_sigmas_m()
    assert a.loose_stations() == [k], own
    record = measure_scan(scan)
    assert record["loose_stations"] == [k]
    grid = grid_arg(record)
    near = np.asarray(scan.xyz[:], float)
    d = np.linalg.norm(near - scan.stations[k].t, axis=1)
    far = near[d > np.percentile(d, 90)]
    assert grid.at(near[d < 1.5], 1.0) > 2 * grid.at(far, 1.0), (grid.at(near[d < 1.5], 1.0), grid.at(far, 1.0))


def test_a_scan_with_a_real_registrations_flaws_has_them(tmp_path):
    """``--scan-flaws``: each station is registered a little off (its points moved rigidly with it, and the station
    pose written is the registered one), its panorama exposed apart, and returns on range edges float between the two
    surfaces (mixed pixels). Without flaws the scan is the perfect one, draw for draw (test_same_seed_same_site)."""
    from services.io.scans import load_scan
    from services.sim.lidar import FLAWS, LidarConfig, ScanFlaws, simulate_station
    from services.sim.scenes import make_scene
    from services.sim.shading import SceneRenderer
    from services.sim.site import config_for

    perfect = config_for("office", seed=3, frames=2, width=160, height=120, lidar_step_deg=0.8)
    flawed = config_for("office", seed=3, frames=2, width=160, height=120, lidar_step_deg=0.8, scan_flaws="poor")
    assert flawed.flaws == FLAWS["poor"] and not perfect.flaws.any
    generate_site(perfect, tmp_path / "a")
    generate_site(flawed, tmp_path / "b")
    a, b = load_scan(tmp_path / "a" / "scan.ply"), load_scan(tmp_path / "b" / "scan.ply")
    from services.io.registration import station_agreement

    # each station's points are known (scan check): the perfect stations agree, the flawed ones by centimetres
    perfect_mm, flawed_mm = (1e3 * station_agreement(s).registration_m for s in (a, b))
    assert perfect_mm < 2.0 and flawed_mm > 2 * perfect_mm + 3.0, (perfect_mm, flawed_mm)
    for sa, sb in zip(a.stations, b.stations, strict=True):
        dt, dr = sa.distance_to(sb)
        assert 1e-4 < dt < 0.06 and 1e-4 < dr < 0.2, (dt, dr)  # 1 cm / 0.03 deg 1-sigma per axis

    # one station, the same rays: only the flaws differ
    scene = make_scene("office", 3)
    renderer = SceneRenderer(scene.mesh, texture_seed=3)
    cfg = LidarConfig(step_deg=0.8, dropout=0.0, grazing_cos=1e-9, range_noise_m=0.0, colour_noise=0.0)
    centre = scene.stations[0]

    def station(flaws):
        return simulate_station(renderer, centre, scene.scan_lighting, 1.0, cfg, np.random.default_rng(0), flaws,
                                np.random.default_rng(1))

    xyz0, rgb0 = station(None)
    xyz1, rgb1 = station(ScanFlaws(mixed_pixels=1.0))
    assert len(xyz0) == len(xyz1) and np.array_equal(rgb0, rgb1)
    moved = np.linalg.norm(xyz1 - xyz0, axis=1)
    assert 0.002 < np.mean(moved > 0.02) < 0.2  # the silhouettes' returns, not the surfaces'
    _, rgb2 = station(ScanFlaws(gain=0.5))
    ratio = rgb2[rgb0 > 30].astype(float) / rgb0[rgb0 > 30]
    assert np.std(ratio) < 0.2 and abs(np.median(ratio) - 1.0) > 0.02  # one exposure for the whole panorama


def test_a_scanner_without_pictures_writes_intensity_that_loads_as_grey(tmp_path):
    """``--scan-colour intensity``: each point has the laser's return strength instead of a colour; it follows the
    surface's visible brightness only loosely (each material its own near-infrared gain), carries none of the room's
    shading, and loads as grey levels spread over the range."""
    from plyfile import PlyData

    from services.io.scans import load_scan
    from services.sim.lidar import LidarConfig, simulate_station
    from services.sim.scenes import make_scene
    from services.sim.shading import SceneRenderer
    from services.sim.site import config_for

    cfg = config_for("office", seed=3, frames=2, width=160, height=120, lidar_step_deg=0.8, scan_intensity=True)
    assert cfg.lidar.intensity_only
    generate_site(cfg, tmp_path / "nir")
    names = PlyData.read(str(tmp_path / "nir" / "scan.ply"))["vertex"].data.dtype.names
    assert "intensity" in names and "red" not in names
    scan = load_scan(tmp_path / "nir" / "scan.ply")
    assert scan.meta["has_color"] is False and scan.meta["intensity_grey"] == len(scan)
    grey = scan.rgb[:, 0].astype(float)
    assert np.all(scan.rgb[:, :1] == scan.rgb) and np.percentile(grey, 99) - np.percentile(grey, 1) > 150

    # one station, the same rays, in colour and in intensity: the same points, brightness related but not the same
    scene = make_scene("office", 3)
    renderer = SceneRenderer(scene.mesh, texture_seed=3)
    lidar = LidarConfig(step_deg=0.8, dropout=0.0, grazing_cos=1e-9, range_noise_m=0.0, colour_noise=0.0)

    def station(seed):
        return simulate_station(renderer, scene.stations[0], scene.scan_lighting, 1.0, lidar, np.random.default_rng(0),
                                intensity_seed=seed)

    xyz0, rgb = station(None)
    xyz1, intensity = station(3)
    assert np.array_equal(xyz0, xyz1) and intensity.shape == (len(xyz0),) and intensity.dtype == np.float32
    assert 0.0 <= intensity.min() and intensity.max() <= 1.0
    rank = lambda v: np.argsort(np.argsort(v))  # noqa: E731
    rho = np.corrcoef(rank(rgb.astype(float) @ [0.2126, 0.7152, 0.0722]), rank(intensity))[0, 1]
    assert 0.2 < rho < 0.95, rho
