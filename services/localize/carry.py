"""A LOST track's pose carried on by the device's odometry (numpy only; Render & Match and P&L share it).

A headset's VIO or a robot's wheels know how the camera moved while the images could not say where it is (a whip
pan's blur, a blank wall). Rather than drop the pose and wait for relocalization, the tracker keeps the pose the
odometry leads to, unreported, and the next frame tracks from it. Odometry drifts, so only for ``limit_s``
seconds; after that the database decides. Without odometry, the last tracked velocity can carry a pose the same
way for a much shorter time (P&L: a frame or two with nothing to match). A frame tracked from a carried pose is
reported as re-acquired (RELOCALIZED), not as continuous tracking.
"""

from __future__ import annotations

from services.geometry.se3 import Pose

__all__ = ["OdometryCarry"]


class OdometryCarry:
    def __init__(self, limit_s: float):
        self.limit_s = limit_s
        self.seconds = 0.0  # how long the pose has been carried through LOST frames (0: tracked)

    def lost(self, T: Pose | None, dt: float, limit_s: float | None = None) -> Pose | None:
        """After a LOST frame: ``T`` (where the odometry puts this frame), the pose the next frame tracks from, while
        the carry stays within ``limit_s`` (``dt``: seconds since the previous frame; a frame at 30 Hz if unknown;
        ``limit_s``: a shorter limit for this carry, e.g. one by constant velocity, which drifts faster);
        None when there is none or the carry has gone on too long."""
        dt = dt if dt > 0 else 1.0 / 30.0
        limit = self.limit_s if limit_s is None else min(limit_s, self.limit_s)
        if T is None or self.seconds + dt > limit:
            self.reset()
            return None
        self.seconds += dt
        return T

    def reset(self) -> None:
        """No pose is carried (the track was dropped or seeded)."""
        self.seconds = 0.0

    def tracked(self) -> bool:
        """A frame got a pose: whether it was tracked from a carried one (a re-acquisition). Ends the carry."""
        carried = self.seconds > 0
        self.reset()
        return carried
