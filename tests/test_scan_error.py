"""The scan's own error in the reported 1-sigma (``--scan-sigma-mm``, services/localize/scan_error.py); the trackers'
use of it is tested with them (test_render_match, test_pnl)."""

import math

import pytest

from services.localize.scan_error import median_depth, scan_floor, with_scan_error


def test_a_perfect_scan_adds_nothing_and_a_flawed_one_adds_more_the_closer_the_camera_sees():
    assert scan_floor(0.0, 2.0) == (0.0, 0.0)
    assert with_scan_error(0.003, 0.04, 0.0, 2.0) == (0.003, 0.04)
    m, deg = scan_floor(0.008, 2.0)
    assert m == pytest.approx(0.016) and deg == pytest.approx(math.degrees(0.004))
    assert scan_floor(0.008, 1.0)[1] == pytest.approx(2 * deg)  # a close-up turns twice as far
    assert scan_floor(0.008, 0.01) == scan_floor(0.008, 0.3)  # no infinite turn at a lens cap
    assert scan_floor(0.008, float("nan")) == scan_floor(0.008, 3.0)  # nothing seen: a room's depth
    sm, sd = with_scan_error(0.006, 0.05, 0.008, 2.0)
    assert sm == pytest.approx(math.hypot(0.006, 0.016)) and sd == pytest.approx(math.hypot(0.05, deg))  # in quadrature


def test_median_depth_counts_what_lies_in_front():
    assert median_depth([[0, 0, 1.0], [0, 0, 2.0], [0, 0, 3.0], [0, 0, -5.0]]) == 2.0
    assert math.isnan(median_depth([[0, 0, -1.0]]))


@pytest.mark.parametrize("command", ["localize", "serve", "stream"])
def test_a_negative_scan_error_is_refused_before_anything_runs(command, tmp_path, capsys):
    from services.cli import main

    with pytest.raises(SystemExit) as e:
        main([command, "--scan-sigma-mm", "-3"])
    assert e.value.code == 2
    assert "--scan-sigma-mm: must be between 0 and 1000 millimetres, got -3" in capsys.readouterr().err


def test_auto_takes_what_build_db_or_prebuild_recorded_and_a_number_as_given(tmp_path):
    from argparse import Namespace

    from services.localize.cli import resolve_scan_sigma, scan_sigma_m
    from services.localize.scan_error import read_accuracy, write_accuracy

    def resolved(value, **where):
        args = Namespace(scan_sigma_mm=value)
        resolve_scan_sigma(args, **where)
        return scan_sigma_m(args)

    assert resolved(4.0, db_meta={"scan_sigma_mm": 9.0}) == pytest.approx(0.004)  # a number is the user's word
    assert resolved("auto", db_meta={"scan_sigma_mm": 9.0}) == pytest.approx(0.009)
    assert resolved("auto", db_meta={"scan_sigma_mm": None}, scan=object()) == 0.0  # build-db could not tell: no retry
    assert resolved("auto", map_dir=tmp_path) == 0.0  # nothing recorded
    write_accuracy(tmp_path, {"format_version": 1, "scan_sigma_mm": 6.5, "noise_mm": 1.2, "pairs": 4, "stations": 3})
    assert read_accuracy(tmp_path)["scan_sigma_mm"] == 6.5 and resolved("auto", map_dir=tmp_path) == pytest.approx(0.0065)
    (tmp_path / "scan_accuracy.json").write_text("{broken")
    assert read_accuracy(tmp_path) is None and resolved("auto", map_dir=tmp_path) == 0.0


def _two_rooms():
    """Two rooms 7 m apart: stations 0 and 1 scan the first (half its points each), station 2 the second."""
    import numpy as np

    from services.geometry.se3 import Pose
    from services.io.scan import Scan

    rng = np.random.default_rng(0)

    def room(x0, n):
        p = rng.uniform([x0, 0, 0], [x0 + 6, 4, 3], (n, 3))
        p[:, 2] = rng.choice([0.0, 3.0], n)  # floor and ceiling
        return p

    parts = [room(0, 40_000), room(0, 40_000), room(7, 40_000)]
    xyz = np.concatenate(parts).astype(np.float32)
    st = [Pose.from_rotvec_t([0, 0, 0], c) for c in ([2, 2, 1.5], [4, 2, 1.5], [10, 2, 1.5])]
    return Scan(xyz, np.full(xyz.shape, 128, np.uint8), np.zeros(3), st, meta={"station_points": [len(p) for p in parts]})


def test_the_scans_error_is_told_where_it_lies():
    """A loose station's error is where its points are: the grid of the stations' disagreement (what build-db and
    prebuild record) says so per place, and a camera looking elsewhere gets the error of what it sees."""
    import numpy as np

    from services.localize.scan_error import DisagreementGrid, grid_arg, local_scan_sigma

    scan = _two_rooms()
    grid = DisagreementGrid.from_scan(scan, np.array([0.010, 0.0, 0.0]), 0.012)
    first, second = np.asarray(scan.xyz[:80_000], float), np.asarray(scan.xyz[80_000:], float)
    # half the first room's points are the loose station's: sqrt(2 x (10² + 0²) / 2) = 10 mm; none of the second's
    assert grid.at(first, 0.012) == pytest.approx(0.010, rel=0.05)
    assert grid.at(second, 0.012) < 1e-6
    assert grid.at(np.array([[50.0, 50.0, 50.0]]), 0.012) == 0.012  # no scan there: the pooled error
    assert local_scan_sigma(0.012, None, second) == 0.012  # no grid: the pooled error everywhere
    assert local_scan_sigma(0.012, grid, second) < 1e-6
    back = grid_arg({"grid": grid.to_record()})
    assert back.at(first, 0.012) == pytest.approx(grid.at(first, 0.012), abs=1e-6)
    assert grid_arg({"grid": {"keys": [3, 1], "s_um": [1, 2]}}) is None and grid_arg({"stations": 3}) is None
    # unknown station errors count as the pooled error's share
    unknown = DisagreementGrid.from_scan(scan, np.array([np.nan, np.nan, np.nan]), 0.012)
    assert unknown.at(second, 0.0) == pytest.approx(0.012, rel=1e-6)


def test_auto_finds_where_the_error_lies_in_the_database_or_beside_the_map(tmp_path):
    from argparse import Namespace

    import numpy as np

    from services.localize.cli import resolve_scan_sigma, scan_grid
    from services.localize.scan_error import DisagreementGrid, read_accuracy, write_accuracy

    rec = DisagreementGrid.from_scan(_two_rooms(), np.array([0.010, 0.0, 0.0]), 0.012).to_record()
    args = Namespace(scan_sigma_mm="auto")
    resolve_scan_sigma(args, db_meta={"scan_sigma_mm": 12.0, "scan_grid": rec})
    assert scan_grid(args) is not None and args.scan_sigma_mm == 12.0
    args = Namespace(scan_sigma_mm=5.0)  # a number given: that number everywhere
    resolve_scan_sigma(args, db_meta={"scan_sigma_mm": 12.0, "scan_grid": rec})
    assert scan_grid(args) is None
    write_accuracy(tmp_path, {"format_version": 2, "scan_sigma_mm": 12.0, "noise_mm": 1.0, "pairs": 2, "grid": rec})
    assert read_accuracy(tmp_path)["grid"] == rec
    args = Namespace(scan_sigma_mm="auto")
    resolve_scan_sigma(args, map_dir=tmp_path)
    assert scan_grid(args).at(np.array([[9.0, 2.0, 0.0]]), 1.0) < 1e-6
