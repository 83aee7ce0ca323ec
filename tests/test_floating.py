"""Floating points (mixed pixels) found and dropped, against the simulator's truth: the same scan simulated with and
without mixed pixels draws the same rays, so the points a flaw moved off their surface are known."""

import json

import numpy as np
import pytest

from services.io.scans import load_scan


@pytest.fixture(scope="module")
def twin_scans(tmp_path_factory):
    """(perfect, flawed) scan files of one small site; in the flawed one 30 % of the returns on range edges are mixed."""
    from dataclasses import replace

    from services.sim.lidar import ScanFlaws
    from services.sim.site import config_for, generate_site

    root = tmp_path_factory.mktemp("twins")
    cfg = config_for("office", seed=3, frames=2, width=160, height=120, lidar_step_deg=0.4)
    generate_site(cfg, root / "perfect")
    generate_site(replace(cfg, flaws=ScanFlaws(mixed_pixels=0.3)), root / "flawed")
    return root / "perfect" / "scan.ply", root / "flawed" / "scan.ply"


def test_floating_points_are_the_mixed_pixels(twin_scans):
    from services.io.floating import floating_points

    perfect, flawed = (load_scan(p) for p in twin_scans)
    moved = np.linalg.norm(flawed.xyz.astype(np.float64) - perfect.xyz, axis=1)
    assert len(perfect) == len(flawed) and 0.002 < np.mean(moved > 0.05) < 0.05
    f = floating_points(flawed)
    assert np.mean(f[moved > 0.2]) > 0.8, "points floating 20 cm or more off their surface are found"
    assert np.mean(f[moved > 0.1]) > 0.6  # (nearer a surface a point can be one of its neighbours)
    assert np.mean(f[moved < 0.001]) < 0.005, "points on surfaces stay"
    assert np.mean(floating_points(perfect)) < 0.005  # a scan without mixed pixels loses next to nothing


def test_scan_convert_drops_floating_points(twin_scans, tmp_path, capsys):
    from services.cli import main

    _, flawed = twin_scans
    out = tmp_path / "clean.ply"
    assert main(["scan", "convert", str(flawed), str(out), "--drop-floating"]) == 0
    s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    clean, raw = load_scan(out), load_scan(flawed)
    assert s["floating_dropped"] > 0 and len(clean) == len(raw) - s["floating_dropped"] == s["points_out"]
    assert len(clean.stations) == len(raw.stations)
