"""Timestamp units: the seconds a sequence's timestamp text counts in.

``docs/CONVENTIONS.md`` and the TUM format count seconds, but recorders do not all agree: a ROS 2 bag exported
frame by frame names its images by nanoseconds, some phone apps by milliseconds. Read as seconds, a 30 fps
camera's frames would then lie 33 333 333 "seconds" apart, and every consumer of the capture time (constant
velocity, motion blur, the odometry's clock, a start hint's widening) would take each frame as the first after a
long gap: it tracks on, but without motion. The unit is recognised from the frame interval, which for any camera
is between a millisecond and a few seconds, and the text itself is never changed: trajectories still copy it
exactly. Frames numbered instead of timed (``000001.png``, as KITTI names them) are taken at a video rate.
"""

from __future__ import annotations

import logging

import numpy as np

__all__ = ["UNITS", "seconds_per_unit"]

log = logging.getLogger(__name__)

UNITS = ((1.0, "seconds"), (1e-3, "milliseconds"), (1e-6, "microseconds"), (1e-9, "nanoseconds"))
MAX_INTERVAL_S = 10.0  # a median frame interval longer than this is taken as a finer unit's (a timelapse would not track)
FRAME_NUMBER_FPS = 30.0  # frames numbered 0, 1, 2... (KITTI-style names) instead of timed: taken this many a second


def seconds_per_unit(stamps: list[str] | np.ndarray, source: str | None = None) -> tuple[float, str]:
    """(seconds per unit, the unit's name) of timestamps: the coarsest of seconds, milli-, micro- and nanoseconds in
    which their median interval is at most ``MAX_INTERVAL_S``; for whole numbers a step of 1 apart (frames numbered,
    not timed), 1 / ``FRAME_NUMBER_FPS`` ("frames"). Seconds when there are fewer than two increasing
    numeric stamps. ``source``: where they come from, for a warning when a unit other than seconds is recognised
    (None: no warning)."""
    try:
        t = np.array([float(s) for s in stamps], np.float64)
    except ValueError:
        return 1.0, "seconds"
    steps = np.diff(t)
    steps = steps[np.isfinite(steps) & (steps > 0)]
    if len(steps) == 0:
        return 1.0, "seconds"
    median = float(np.median(steps))
    if median == 1.0 and all(str(x).strip().isdigit() for x in stamps) and t.max() < 1e7:
        # numbered, not timed: one frame a second would leave tracking without its motion model, so a video rate
        # is assumed (the motion model and the blur use ratios of intervals; the rate only sets how far a LOST
        # camera can have walked)
        if source:
            log.warning("%s are frame numbers (0, 1, 2...), not times: taken %g frames a second; write capture times "
                        "in seconds for another rate", source, FRAME_NUMBER_FPS)
        return 1.0 / FRAME_NUMBER_FPS, "frames"
    for scale, name in UNITS:
        if median * scale <= MAX_INTERVAL_S:
            if scale != 1.0 and source:
                log.warning("%s count %s, not seconds: their median interval, %g %s, is %.4g ms", source, name,
                            median, name, 1e3 * median * scale)
            return scale, name
    return UNITS[-1]
