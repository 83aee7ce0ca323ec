"""`cristal density`: how many camera pixels apart a scan's samples are (services.render.density)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from services.geometry.camera import Camera


@pytest.fixture(scope="module")
def site_scan(small_site):
    from services.io.scans import load_scan
    from services.io.sequence import open_sequence

    torch.set_num_threads(1)
    root = small_site[0]
    seq = open_sequence(root / "seq_00")
    f = seq.read(0)
    return load_scan(root / "scan.ply"), seq.groundtruth.as_dict()[f.stamp], root


def test_spacing_doubles_with_twice_the_pixels_and_a_quarter_of_the_points(site_scan):
    from services.io.decimate import random_decimate
    from services.render.density import spacing_map
    from services.render.renderer import Renderer

    scan, T, _ = site_scan
    cam = Camera.from_fov(200, 150, 70)
    full = Renderer(scan, device="cpu", holefill=False)
    base = spacing_map(full, T, cam)
    assert base.surface > 0.8 and 0.3 < base.median < 3.0
    # the same view at twice the resolution: samples twice as many pixels apart
    assert spacing_map(full, T, cam.scaled(2.0)).median == pytest.approx(2 * base.median, rel=0.12)
    # a quarter of the points: twice the spacing (the scan's random quarter, not a coarser scanner grid: within 20 %)
    quarter = Renderer(random_decimate(scan, 0.25, seed=1), device="cpu", holefill=False)
    assert spacing_map(quarter, T, cam).median == pytest.approx(2 * base.median, rel=0.2)
    assert base.share_above(0.0) == 1.0 and base.share_above(1e6) == 0.0


def test_survey_poses_look_out_level_at_every_heading():
    from services.render.density import survey_poses

    poses = survey_poses(np.array([[1.0, 2.0, 1.5]]), yaws=4)
    forward = np.array([T.R[:, 2] for T in poses])  # camera z in the world
    down = np.array([T.R[:, 1] for T in poses])
    assert np.allclose(forward, [[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], atol=1e-9)
    assert np.allclose(down, [[0, 0, -1]] * 4, atol=1e-9)  # world z is up
    assert all(np.allclose(T.R.T @ T.R, np.eye(3)) and np.linalg.det(T.R) > 0 for T in poses)
    assert all(np.allclose(T.t, [1.0, 2.0, 1.5]) for T in poses)


def test_density_cli_writes_a_floor_plan_and_every_views_spacing(site_scan, tmp_path, capsys):
    from services.cli import main

    _, _, root = site_scan
    Camera.from_fov(320, 240, 70).save(tmp_path / "cam.json")
    rc = main(["density", str(root / "scan.ply"), "--camera", str(tmp_path / "cam.json"), "--out", str(tmp_path / "d"),
               "--spacing", "1.5", "--yaws", "4", "--max-side", "160"])
    assert rc == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rec = json.loads((tmp_path / "d" / "density.json").read_text())
    assert rec["keyframe_size"] == [160, 120] and s["views"] == 4 * s["positions"] > 0
    sp = np.array(rec["median_spacing_px"], float)
    assert sp.shape == (s["positions"], 4) and np.isfinite(sp).mean() > 0.9
    assert s["median_px"] == pytest.approx(float(np.nanmedian(sp)), abs=1e-3) and 0 <= s["share_above_1px"] <= 1
    img = cv2.imread(str(tmp_path / "d" / "density.png"))
    assert img is not None and img.shape[1] == 1100
    # at full resolution the same views are twice as coarse as at 160 px
    rc = main(["density", str(root / "scan.ply"), "--camera", str(tmp_path / "cam.json"), "--out", str(tmp_path / "e"),
               "--spacing", "1.5", "--yaws", "4", "--max-side", "0"])
    s2 = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rc == 0 and s2["median_px"] == pytest.approx(2 * s["median_px"], rel=0.15)
    # bad input is an error exit, not a traceback
    assert main(["density", str(root / "scan.ply"), "--camera", str(tmp_path / "cam.json"), "--out",
                 str(tmp_path / "f"), "--yaws", "0"]) == 2
