"""The per-frame record ``cristal localize`` writes beside its trajectory: ``TRAJ.frames.csv``.

One row per frame, in the sequence's order, LOST frames included (the TUM file has only the frames with a pose)::

    stamp,status,inliers,rmse_px,sigma_cm,sigma_deg,source,reason
    1.033333,TRACKING,118,0.91,0.32,0.071,direct,
    1.066667,LOST,0,,,,,no place in the map fits the frame: ...

``sigma_cm`` / ``sigma_deg``: the pose's predicted 1-sigma camera-centre and orientation uncertainty, what the
reporting gates judge and what a filter fusing these poses should weigh them by (empty where unknown). ``status``:
TRACKING, RELOCALIZED, LOST, or BACKFILLED (a pose the offline backward pass found: no uncertainty recorded).
``source``: what solved the pose (also a LOST frame's, where one was found and refused): ``features`` (matched
keypoints, PnP), ``direct`` (image patches aligned to the render or map, photometrically) or ``fused`` (both, weighed
by their covariances); empty where none. ``cristal eval`` breaks the errors down by it. Logs written before the
column existed (no ``source``) are still read.
``cristal eval`` reads it to draw the errors against the predicted uncertainty. Written atomically. No heavy deps.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

from services.io.atomic import atomic_write_text

__all__ = ["FrameRecord", "frame_log_path", "write_frame_log", "read_frame_log", "FrameLogError", "SOURCES"]

COLUMNS = ("stamp", "status", "inliers", "rmse_px", "sigma_cm", "sigma_deg", "source", "reason")
_COLUMNS_V1 = tuple(c for c in COLUMNS if c != "source")  # logs written before the source column
SOURCES = ("features", "direct", "fused")


class FrameLogError(ValueError):
    """A frame log that cannot be read."""


@dataclass(frozen=True)
class FrameRecord:
    stamp: str
    status: str
    inliers: int = 0
    rmse_px: float = float("nan")
    sigma_m: float = float("nan")
    sigma_deg: float = float("nan")
    reason: str = ""
    source: str = ""  # what solved the pose: one of SOURCES, or "" where none (or unknown)


def frame_log_path(traj_path: str | Path) -> Path:
    """``run/traj.txt`` -> ``run/traj.frames.csv``."""
    p = Path(traj_path)
    return p.with_name(p.stem + ".frames.csv")


def _num(x: float, scale: float = 1.0, digits: int = 4) -> str:
    return "" if x is None or not math.isfinite(x) else f"{x * scale:.{digits}g}"


def write_frame_log(path: str | Path, records: list[FrameRecord]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    for r in records:
        w.writerow([r.stamp, r.status, r.inliers, _num(r.rmse_px, digits=3), _num(r.sigma_m, 100.0),
                    _num(r.sigma_deg), r.source or "", r.reason or ""])
    atomic_write_text(path, buf.getvalue())


def read_frame_log(path: str | Path) -> dict[str, FrameRecord]:
    """The records by timestamp text; FrameLogError on a file that is not a frame log."""
    path = Path(path)
    try:
        rows = list(csv.reader(path.read_text().splitlines()))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise FrameLogError(f"{path}: cannot read a frame log: {e}") from None
    if not rows or tuple(rows[0]) not in (COLUMNS, _COLUMNS_V1):
        raise FrameLogError(f"{path}: not a frame log (its first line must be {','.join(COLUMNS)})")
    columns = tuple(rows[0])

    def f(s: str) -> float:
        return float(s) if s else float("nan")

    out: dict[str, FrameRecord] = {}
    for n, row in enumerate(rows[1:], start=2):
        try:
            if len(row) != len(columns):
                raise ValueError
            v = dict(zip(columns, row))
            out[v["stamp"]] = FrameRecord(v["stamp"], v["status"], int(v["inliers"]), f(v["rmse_px"]),
                                          f(v["sigma_cm"]) / 100.0, f(v["sigma_deg"]), v["reason"], v.get("source", ""))
        except ValueError:
            raise FrameLogError(f"{path}:{n}: expected {len(columns)} fields ({','.join(columns)}), got {row!r}") from None
    return out
