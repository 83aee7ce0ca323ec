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

The error is not the same all over a site: one loose station (a setup few targets held) puts its error where its
points are, and the pooled number would tell it everywhere. ``build-db`` and ``prebuild`` record each station's own
share (``StationAgreement.station_sigmas_m``) as a grid of the stations' disagreement per place
(:class:`DisagreementGrid`), and each pose counts the disagreement where its keyframe's points lie. Office walk,
one station 1 cm / 0.03 deg off and the others 1 mm (``--scan-flaws loose``, benchmarks/RESULTS.md stop 63): the
room with it 1.8 cm / 0.21 deg off at a reported 2.9 cm / 0.29 deg, the other room 0.20 cm / 0.032 deg at 0.31 cm /
0.028 deg where the pooled 12.4 mm reported 2.5 cm / 0.17 deg there; none beyond 3 sigma either way.

The term widens only what is reported (``sigma_m``/``sigma_deg`` on the wire and in ``TRAJ.frames.csv``); the report
gates keep judging the frame's own uncertainty, since no frame can do better than the scan it is placed in.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["with_scan_error", "scan_floor", "median_depth", "DisagreementGrid", "local_scan_sigma", "grid_arg",
           "measure_scan", "describe", "write_accuracy", "read_accuracy"]


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


class DisagreementGrid:
    """How far the stations disagree where each part of the scan lies: the scan's error per place, not pooled.

    A voxel's points come from the stations that saw it, in their shares; its disagreement is ``sqrt(2 x the mean
    of their own errors squared)`` (``StationAgreement.station_sigmas_m``: two stations' disagreement is both their
    errors), which is the pooled scan error where every station is alike, more where a loose station's points lie, less
    away from them. A camera is placed between the stations of what it sees: :meth:`at` its points. Compared by identity
    (it rides in frozen configs)."""

    def __init__(self, origin, cell_m: float, dims, keys: np.ndarray, s_m: np.ndarray):
        self.origin = np.asarray(origin, np.float64).reshape(3)
        self.cell_m = float(cell_m)
        self.dims = np.asarray(dims, np.int64).reshape(3)
        self.keys = np.asarray(keys, np.int64)  # sorted linear voxel indices
        self.s_m = np.asarray(s_m, np.float64)

    @classmethod
    def from_scan(cls, scan, station_sigma_m: np.ndarray, default_m: float, cell_m: float = 1.0,
                  max_points: int = 4_000_000, seed: int = 0) -> "DisagreementGrid | None":
        """From ``scan``'s points and which station each is (``station_points``); stations of unknown error
        (NaN) count as ``default_m`` / sqrt(2). At most ``max_points`` points are read (a random subset). Metre cells:
        a registration's error varies from station to station, metres apart (a 6 M-point warehouse: 17 k cells,
        0.2 MB recorded; half-metre cells 68 k, 0.8 MB)."""
        from services.io.scans import station_points

        counts = station_points(scan)
        if counts is None or len(counts) != len(station_sigma_m):
            return None
        n = len(scan)
        idx = (np.arange(n) if n <= max_points else
               np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False)))
        label = np.searchsorted(np.cumsum(counts), idx, side="right")
        own = np.where(np.isfinite(station_sigma_m), station_sigma_m, default_m / math.sqrt(2.0))
        P = np.asarray(scan.xyz[idx], np.float64) + scan.origin
        lo = np.floor(P.min(axis=0) / cell_m) * cell_m
        ijk = np.floor((P - lo) / cell_m).astype(np.int64)
        dims = ijk.max(axis=0) + 1
        keys, inv = np.unique((ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2], return_inverse=True)
        var = np.bincount(inv, own[label] ** 2, len(keys)) / np.bincount(inv, None, len(keys))
        return cls(lo, cell_m, dims, keys, np.sqrt(2.0 * var))

    def at(self, points_world: np.ndarray, default_m: float) -> float:
        """The disagreement over ``points_world`` (RMS of their voxels'; ``default_m`` for points in no voxel)."""
        P = np.asarray(points_world, np.float64).reshape(-1, 3)
        P = P[np.isfinite(P).all(axis=1)]
        if not len(P):
            return default_m
        ijk = np.floor((P - self.origin) / self.cell_m).astype(np.int64)
        inside = ((ijk >= 0) & (ijk < self.dims)).all(axis=1)
        key = (ijk[:, 0] * self.dims[1] + ijk[:, 1]) * self.dims[2] + ijk[:, 2]
        pos = np.clip(np.searchsorted(self.keys, key), 0, len(self.keys) - 1)
        hit = inside & (self.keys[pos] == key)
        s = np.where(hit, self.s_m[pos], default_m)
        return float(np.sqrt(np.mean(s ** 2)))

    def to_record(self) -> dict:
        return {"origin": [round(float(v), 4) for v in self.origin], "cell_m": self.cell_m,
                "dims": [int(v) for v in self.dims], "keys": self.keys.tolist(),
                "s_um": np.round(1e6 * self.s_m).astype(int).tolist()}

    @classmethod
    def from_record(cls, r) -> "DisagreementGrid | None":
        """From :meth:`to_record`'s dict; None when there is none or it is malformed."""
        try:
            keys, s = np.asarray(r["keys"], np.int64), np.asarray(r["s_um"], np.float64) / 1e6
            if keys.shape != s.shape or keys.ndim != 1 or not len(keys) or np.any(np.diff(keys) <= 0):
                return None
            return cls(r["origin"], float(r["cell_m"]), r["dims"], keys, s)
        except (KeyError, TypeError, ValueError):
            return None


def local_scan_sigma(scan_sigma_m: float, grid: DisagreementGrid | None, points_world: np.ndarray | None,
                     max_points: int = 400) -> float:
    """The stations' disagreement where a camera sees ``points_world`` (at most ``max_points`` of them read), what
    :func:`scan_floor` takes per view: ``grid``'s (:class:`DisagreementGrid`), or ``scan_sigma_m`` without one."""
    if grid is None or points_world is None or not len(points_world) or not scan_sigma_m > 0:
        return scan_sigma_m
    P = np.asarray(points_world).reshape(-1, 3)
    return grid.at(P[:: max(1, len(P) // max_points)], scan_sigma_m)


def grid_arg(record: dict | None) -> DisagreementGrid | None:
    """The :class:`DisagreementGrid` of a :func:`measure_scan` record (None in records before format 2)."""
    g = (record or {}).get("grid")
    return DisagreementGrid.from_record(g) if isinstance(g, dict) else None


def median_depth(points_cam: np.ndarray) -> float:
    """The median depth (z, metres) of points in camera axes in front of it; NaN when none is."""
    z = np.asarray(points_cam, np.float64).reshape(-1, 3)[:, 2]
    z = z[z > 0]
    return float(np.median(z)) if len(z) else float("nan")


# ---- the scan's error, measured once where the scan is loaded (build-db, prebuild) and read where it is not ------

ACCURACY_FILE = "scan_accuracy.json"  # beside a P&L map (and in its bundle): what prebuild measured of the scan
ACCURACY_VERSION = 2  # 2: each station's own error and centre (``stations``), the disagreement per place (``grid``)


def measure_scan(scan) -> dict:
    """What :func:`services.io.registration.station_agreement` says of ``scan``, as recorded with a database or map:
    ``scan_sigma_mm`` is None when the scan cannot tell (one station, or its stations' points unknown)."""
    from services.io.registration import station_agreement

    a = station_agreement(scan)
    ok = a is not None and bool(a.pairs)
    stations, grid = [], None
    if ok:
        own = a.station_sigmas_m()
        stations = [[round(float(v), 4) for v in p.t] + [None if not np.isfinite(e) else round(1e3 * float(e), 2)]
                    for p, e in zip(scan.stations, own)]
        grid = DisagreementGrid.from_scan(scan, own, a.registration_m)
    return {"format_version": ACCURACY_VERSION, "n_stations": len(scan.stations),
            "scan_sigma_mm": round(1e3 * a.registration_m, 2) if ok else None,
            "noise_mm": round(1e3 * a.noise_m, 2) if ok else None, "pairs": len(a.pairs) if a is not None else 0,
            "stations": stations, "loose_stations": a.loose_stations(own) if ok else [],
            "grid": None if grid is None else grid.to_record()}


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

    with atomic_write(Path(map_dir) / ACCURACY_FILE, "w") as f:  # a key a line, each value on one (the grid is long)
        f.write("{\n" + ",\n".join(f" {json.dumps(k)}: {json.dumps(v)}" for k, v in record.items()) + "\n}\n")


def read_accuracy(map_dir) -> dict | None:
    """The :func:`measure_scan` record beside a map, None when there is none or its scan error could not be measured
    (``scan_sigma_mm`` a float in millimetres; :func:`grid_arg` reads its ``grid``, absent before format 2)."""
    import json
    from pathlib import Path

    p = Path(map_dir) / ACCURACY_FILE
    try:
        record = json.loads(p.read_text())
        v = record.get("scan_sigma_mm")
    except (OSError, ValueError, AttributeError):
        return None
    if not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v <= 1000):
        return None
    return {**record, "scan_sigma_mm": float(v)}
