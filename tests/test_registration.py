"""``cristal scan check``: how well a scan's stations agree (services/io/registration.py), against stations moved by
a known amount; which points each station has, through E57, PLY and subsets."""

import json

import numpy as np
import pytest

from services.geometry.se3 import Pose
from services.io.registration import station_agreement
from services.io.scan import Scan
from services.io.scans import load_scan, save_ply, station_points


def _room(rng, n=300_000, noise=0.001):
    """Points on a 6 x 4 x 3 m room's floor, ceiling and walls (equal shares of x, y and z normals), ``noise`` along
    each normal, as a scanner sees them."""
    face = rng.integers(0, 6, n)
    p = rng.uniform([0, 0, 0], [6, 4, 3], (n, 3))
    axis, side = face // 2, face % 2
    p[np.arange(n), axis] = np.array([6.0, 4.0, 3.0])[axis] * side + rng.normal(0, noise, n)
    return p


def _stations(offset_m, rng):
    """Two stations scanning the same room, the second registered ``offset_m`` off."""
    a, b = _room(rng), _room(rng) + np.asarray(offset_m)
    xyz = np.concatenate([a, b]).astype(np.float32)
    st = [Pose.from_rotvec_t([0, 0, 0], [2, 2, 1.5]), Pose.from_rotvec_t([0, 0, 0], [4, 2, 1.5])]
    return Scan(xyz, np.full(xyz.shape, 128, np.uint8), np.zeros(3), st, meta={"station_points": [len(a), len(b)]})


def test_stations_registered_apart_are_measured_apart_and_agreeing_ones_agree():
    rng = np.random.default_rng(0)
    same = station_agreement(_stations([0, 0, 0], rng))
    assert same.registration_m < 0.0005 and 0.0007 < same.noise_m < 0.0015, (same.registration_m, same.noise_m)
    off = station_agreement(_stations([0.004, -0.003, 0.002], rng))
    # along the floor's, walls' and ceiling's normals in equal shares: RMS of 4, 3 and 2 mm
    expected = np.sqrt((0.004 ** 2 + 0.003 ** 2 + 0.002 ** 2) / 3)
    assert off.registration_m == pytest.approx(expected, rel=0.15), (off.registration_m, expected)
    assert {(p.a, p.b) for p in off.pairs} == {(0, 1), (1, 0)}
    one = _stations([0, 0, 0], rng)
    one.meta["station_points"] = None
    assert station_agreement(one) is None  # cannot tell: which points are whose is unknown


def test_the_one_station_registered_off_is_told_from_the_ones_that_agree():
    rng = np.random.default_rng(2)
    offsets = [[0, 0, 0], [0, 0, 0], [0.006, 0.0, 0.0], [0, 0, 0]]  # the third registered 6 mm off along x
    parts = [_room(rng, n=150_000) + np.asarray(o) for o in offsets]
    xyz = np.concatenate(parts).astype(np.float32)
    st = [Pose.from_rotvec_t([0, 0, 0], c) for c in ([1.5, 1, 1.5], [4.5, 1, 1.5], [1.5, 3, 1.5], [4.5, 3, 1.5])]
    scan = Scan(xyz, np.full(xyz.shape, 128, np.uint8), np.zeros(3), st, meta={"station_points": [len(p) for p in parts]})
    a = station_agreement(scan)
    sig = a.station_sigmas_m()
    # along the floor's, walls' and ceiling's normals in equal shares: 6 mm along x is an RMS of 6 / sqrt(3) mm
    assert sig[2] == pytest.approx(0.006 / np.sqrt(3), rel=0.2), sig
    assert np.delete(sig, 2).max() < 0.2 * sig[2], sig
    # two stations alone cannot say whose error it is: they split it
    two = station_agreement(_stations([0.004, 0, 0], rng)).station_sigmas_m()
    assert two[0] == pytest.approx(two[1], rel=0.05) and np.hypot(*two) == pytest.approx(0.004 / np.sqrt(3), rel=0.2), two


def test_which_points_each_station_has_survives_ply_and_ordered_subsets(tmp_path):
    scan = _stations([0.004, 0, 0], np.random.default_rng(1))
    n0 = scan.meta["station_points"][0]
    save_ply(scan, tmp_path / "s.ply")
    back = load_scan(tmp_path / "s.ply")
    assert station_points(back) == scan.meta["station_points"]
    keep = np.zeros(len(scan), bool)
    keep[::3] = True
    assert station_points(scan.subset(keep)) == [len(range(0, n0, 3)), int(keep[n0:].sum())]
    assert station_points(scan.subset(np.array([0, 1, n0 + 5]))) == [2, 1]
    assert station_points(scan.subset(np.array([n0 + 5, 0]))) is None  # reordered: no longer known
    from services.io.decimate import random_decimate, voxel_decimate

    half = random_decimate(scan, 0.5)
    assert sum(station_points(half)) == len(half) and min(station_points(half)) > 0.4 * n0
    assert "station_points" not in voxel_decimate(scan, 0.05).meta  # a voxel mixes the stations' points


def test_scan_check_prints_the_registration_error_and_its_number_for_localize(tmp_path, capsys):
    from services.cli import main

    save_ply(_stations([0.006, 0.006, 0.006], np.random.default_rng(2)), tmp_path / "s.ply")
    assert main(["scan", "check", str(tmp_path / "s.ply"), "--plot", str(tmp_path / "check.png")]) == 0
    out = capsys.readouterr().out
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["registration_mm"] == pytest.approx(6.0, rel=0.15) and summary["stations"] == 2
    assert f"pass {summary['registration_mm']:.1f}" in out
    # the picture: the one pair's line, in the colour of 6 mm on the 0-10 mm scale (between green and red)
    import cv2
    from matplotlib import colormaps

    assert summary["picture"] == str(tmp_path / "check.png")
    img = cv2.imread(summary["picture"])[:, :, ::-1].astype(int)
    want = np.array(colormaps["RdYlGn_r"](summary["registration_mm"] / 10.0)[:3]) * 255
    plot_area = img[:, :int(0.75 * img.shape[1])]  # (the colour bar on the right holds every colour)
    assert np.sum(np.abs(plot_area - want).sum(axis=2) < 30) > 300
    scan = load_scan(tmp_path / "s.ply")
    scan.meta.pop("station_points")
    save_ply(scan, tmp_path / "merged.ply")
    assert main(["scan", "check", str(tmp_path / "merged.ply")]) == 0
    out = capsys.readouterr().out
    assert "cannot tell" in out and json.loads(out.strip().splitlines()[-1])["registration_mm"] is None
