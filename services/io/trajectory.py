"""TUM trajectories: ``timestamp tx ty tz qx qy qz qw`` per line, camera-to-world, '#' comments.

Timestamps are kept as the exact text of the file (``rgb.txt`` and our outputs must
match character for character), never reformatted through a float.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from services.geometry.se3 import Pose
from services.io.atomic import atomic_write_text
from services.io.stamps import seconds_per_unit

__all__ = ["Trajectory", "TrajectoryError", "read_tum", "write_tum", "format_tum_line", "relative_motions", "read_odometry",
           "ODOMETRY_AXES"]


class TrajectoryError(ValueError):
    """A trajectory file that cannot be read; the message names the file and line."""


@dataclass
class Trajectory:
    """Camera-to-world poses ``T_wc`` keyed by their timestamp text, in file order."""

    stamps: list[str] = field(default_factory=list)
    poses: list[Pose] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.stamps)

    def __iter__(self) -> Iterator[tuple[str, Pose]]:
        return iter(zip(self.stamps, self.poses))

    def append(self, stamp: str, T_wc: Pose) -> None:
        self.stamps.append(stamp)
        self.poses.append(T_wc)

    def as_dict(self) -> dict[str, Pose]:
        return dict(zip(self.stamps, self.poses))

    def positions(self) -> np.ndarray:
        return np.array([p.t for p in self.poses]).reshape(-1, 3)

    def times(self) -> np.ndarray:
        return np.array([float(s) for s in self.stamps])


def format_tum_line(stamp: str, T_wc: Pose) -> str:
    v = T_wc.to_tum()
    return stamp + " " + " ".join(f"{x:.9f}" for x in v)


def read_tum(path: str | Path) -> Trajectory:
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise TrajectoryError(f"{path}: no such trajectory file") from None
    except UnicodeDecodeError:
        raise TrajectoryError(f"{path}: not a text file") from None
    traj = Trajectory()
    seen: set[str] = set()
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise TrajectoryError(f"{path}:{n}: expected 8 fields 'timestamp tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            float(parts[0])
            vals = [float(x) for x in parts[1:]]
        except ValueError:
            raise TrajectoryError(f"{path}:{n}: fields are not numbers: {line!r}") from None
        if not np.all(np.isfinite(vals)):
            raise TrajectoryError(f"{path}:{n}: non-finite value")
        if np.linalg.norm(vals[3:7]) < 1e-6:
            raise TrajectoryError(f"{path}:{n}: zero quaternion")
        if parts[0] in seen:
            raise TrajectoryError(f"{path}:{n}: duplicate timestamp {parts[0]}")
        seen.add(parts[0])
        traj.append(parts[0], Pose.from_tum(vals))
    return traj


def write_tum(path: str | Path, traj: Trajectory | Iterable[tuple[str, Pose]], header: str | None = None) -> None:
    """Write atomically. ``header`` lines are written as '#' comments."""
    lines = []
    if header:
        lines += [f"# {h}" for h in header.splitlines()]
    lines += [format_tum_line(s, p) for s, p in traj]
    atomic_write_text(path, "\n".join(lines) + "\n")


def relative_motions(traj: Trajectory, stamps: Iterable[str]) -> list[Pose | None]:
    """For each of ``stamps`` (frames in order), the camera's motion since the previous one, ``T_prev^-1 @ T_now``,
    from ``traj`` (a device's odometry, in any world frame of its own); None where either has no pose."""
    poses = traj.as_dict()
    out: list[Pose | None] = []
    prev = None
    for s in stamps:
        now = poses.get(s)
        out.append(prev.inverse() @ now if prev is not None and now is not None else None)
        prev = now
    return out


ODOMETRY_AXES = {  # the odometry's camera axes -> OpenCV's (x right, y down, z forward)
    "opencv": np.eye(3),
    "opengl": np.diag([1.0, -1.0, -1.0]),  # x right, y up, z backward (ARKit, ARCore, most game engines' cameras)
}


def read_odometry(path: str | Path, stamps: list[str], max_gap_s: float = 0.2, axes: str = "opencv") -> Trajectory:
    """A device's odometry for a sequence (``--odometry``): a TUM trajectory in any frame of its own, returned at the
    sequence's frame stamps. A frame whose stamp the file has (character for character) takes that pose; any other
    takes the pose interpolated between the samples around its time (a VIO logs at its own rate), when they are at
    most ``max_gap_s`` apart; frames outside the odometry's time span, or in a gap, get none. ``axes``: the camera
    axes its poses use (``ODOMETRY_AXES``); returned in OpenCV's, as every pose here."""
    if axes not in ODOMETRY_AXES:
        raise TrajectoryError(f"odometry axes must be one of {', '.join(ODOMETRY_AXES)}, got {axes!r}")
    odo = read_tum(path)
    flip = Pose(ODOMETRY_AXES[axes], np.zeros(3))
    odo = Trajectory(odo.stamps, [T @ flip for T in odo.poses])
    exact = odo.as_dict()
    t = np.array([float(s) for s in odo.stamps])  # read_tum checked they are numbers
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        raise TrajectoryError(f"{path}: timestamps must increase (line order), as a device logs them")
    scale, _ = seconds_per_unit(stamps)  # the frames' clock's unit (services.io.stamps): max_gap_s is in seconds
    out = Trajectory()
    for s in stamps:
        if s in exact:
            out.append(s, exact[s])
            continue
        try:
            f = float(s)
        except ValueError:
            continue
        k = int(np.searchsorted(t, f))
        if 0 < k < len(t) and (t[k] - t[k - 1]) * scale <= max_gap_s:
            out.append(s, odo.poses[k - 1].interpolate(odo.poses[k], (f - t[k - 1]) / (t[k] - t[k - 1])))
    if not len(out):
        span = f"{odo.stamps[0]}..{odo.stamps[-1]}" if len(odo) else "no poses"
        raise TrajectoryError(f"{path}: its {len(odo)} poses ({span}) cover none of the sequence's frames "
                              f"({stamps[0] if stamps else '?'}..{stamps[-1] if stamps else '?'}): stamps in seconds, "
                              f"on the frames' clock")
    return out
