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
    from services.localize.scan_error import read_accuracy_mm, write_accuracy

    def resolved(value, **where):
        args = Namespace(scan_sigma_mm=value)
        resolve_scan_sigma(args, **where)
        return scan_sigma_m(args)

    assert resolved(4.0, db_meta={"scan_sigma_mm": 9.0}) == pytest.approx(0.004)  # a number is the user's word
    assert resolved("auto", db_meta={"scan_sigma_mm": 9.0}) == pytest.approx(0.009)
    assert resolved("auto", db_meta={"scan_sigma_mm": None}, scan=object()) == 0.0  # build-db could not tell: no retry
    assert resolved("auto", map_dir=tmp_path) == 0.0  # nothing recorded
    write_accuracy(tmp_path, {"format_version": 1, "scan_sigma_mm": 6.5, "noise_mm": 1.2, "pairs": 4, "stations": 3})
    assert read_accuracy_mm(tmp_path) == 6.5 and resolved("auto", map_dir=tmp_path) == pytest.approx(0.0065)
    (tmp_path / "scan_accuracy.json").write_text("{broken")
    assert read_accuracy_mm(tmp_path) is None and resolved("auto", map_dir=tmp_path) == 0.0
