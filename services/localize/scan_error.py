"""The scan's own error in a pose's reported 1-sigma (``--scan-sigma-mm``).

A pose's predicted 1-sigma comes from its matches: how well the frame fixes the camera *against the scan*. A
registered scan is itself off by a few millimetres where its stations meet (the registration report's cloud-to-cloud
or bundle error; ``cristal scan check`` measures it). A camera that sees surfaces from stations that disagree by ``s``
is placed between them, whatever its own matches say: it turns by up to ``s / d`` (``d`` the median distance to what it
sees) where the near surfaces come from one station and the far ones from another, and its centre moves by ``s`` and
by as much again, the turn traded for a shift at that depth: ``2 s``. Without that term the poses on such a scan err
beyond 3 x their 1-sigma. Simulated office walks, stations registered 3 mm / 0.01 deg off per axis
(``python benchmarks/scan_error.py``, benchmarks/RESULTS.md stop 62): seed 1, 7.2 mm measured, Render & Match 163 of
279 poses beyond 3 sigma (0.98 cm / 0.127 deg RMSE), P&L 206 of 272; seed 8, 4.4 mm, 131 of 246 and 175 of 213. With
it: 0, 0, 2, 0, error / 1-sigma a median 0.44-0.74. (``s / 2d`` left 49 beyond on seed 1, all in orientation; a
centre term of ``s`` left seed 8's centre errors a median 1.7 x their 1-sigma.)

The term widens only what is reported (``sigma_m``/``sigma_deg`` on the wire and in ``TRAJ.frames.csv``); the report
gates keep judging the frame's own uncertainty, since no frame can do better than the scan it is placed in.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["with_scan_error", "scan_floor", "median_depth"]


def scan_floor(scan_sigma_m: float, depth_m: float) -> tuple[float, float]:
    """(metres, degrees): the 1-sigma a scan whose stations disagree by ``scan_sigma_m`` leaves on a camera that sees
    it at ``depth_m`` (the median distance of what it sees; clamped to at least 0.3 m, 3 m when unknown)."""
    if not scan_sigma_m > 0:
        return 0.0, 0.0
    d = max(float(depth_m), 0.3) if math.isfinite(depth_m) else 3.0
    return 2.0 * scan_sigma_m, math.degrees(scan_sigma_m / d)


def with_scan_error(sigma_m: float, sigma_deg: float, scan_sigma_m: float, depth_m: float) -> tuple[float, float]:
    """The reported 1-sigma: the pose's own and :func:`scan_floor`'s, in quadrature."""
    fm, fd = scan_floor(scan_sigma_m, depth_m)
    return math.hypot(sigma_m, fm), math.hypot(sigma_deg, fd)


def median_depth(points_cam: np.ndarray) -> float:
    """The median depth (z, metres) of points in camera axes in front of it; NaN when none is."""
    z = np.asarray(points_cam, np.float64).reshape(-1, 3)[:, 2]
    z = z[z > 0]
    return float(np.median(z)) if len(z) else float("nan")


# ---- the scan's error, measured once where the scan is loaded (build-db, prebuild) and read where it is not ------

ACCURACY_FILE = "scan_accuracy.json"  # beside a P&L map (and in its bundle): what prebuild measured of the scan
ACCURACY_VERSION = 1


def measure_scan(scan) -> dict:
    """What :func:`services.io.registration.station_agreement` says of ``scan``, as recorded with a database or map:
    ``scan_sigma_mm`` is None when the scan cannot tell (one station, or its stations' points unknown)."""
    from services.io.registration import station_agreement

    a = station_agreement(scan)
    ok = a is not None and bool(a.pairs)
    return {"format_version": ACCURACY_VERSION, "stations": len(scan.stations),
            "scan_sigma_mm": round(1e3 * a.registration_m, 2) if ok else None,
            "noise_mm": round(1e3 * a.noise_m, 2) if ok else None, "pairs": len(a.pairs) if a is not None else 0}


def describe(record: dict) -> str:
    """A :func:`measure_scan` record in words, for a build's summary line."""
    mm = record["scan_sigma_mm"]
    if mm is None:
        return "the scan's registration error unknown (it does not say which points each station has, or has one)"
    return f"the scan's stations disagree by {mm:.1f} mm (range noise {record['noise_mm']:.1f} mm)"


def write_accuracy(map_dir, record: dict) -> None:
    """``record`` (:func:`measure_scan`) into ``map_dir/scan_accuracy.json``, atomically."""
    import json
    from pathlib import Path

    from services.io.atomic import atomic_write

    with atomic_write(Path(map_dir) / ACCURACY_FILE, "w") as f:
        json.dump(record, f, indent=1)


def read_accuracy_mm(map_dir) -> float | None:
    """The scan error recorded beside a map (mm), None when there is none or it could not be measured."""
    import json
    from pathlib import Path

    p = Path(map_dir) / ACCURACY_FILE
    try:
        v = json.loads(p.read_text()).get("scan_sigma_mm")
    except (OSError, ValueError, AttributeError):
        return None
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v <= 1000 else None
