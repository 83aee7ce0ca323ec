"""Offline second pass (``cristal localize --backfill``): track backwards in time from the first pose after each
LOST stretch, so frames recorded before the camera saw anything distinctive get poses too.

A live localizer must wait for a place it can tell apart (the aisle of identical bays at the start of the warehouse
walk cannot be relocalized); once it has one, the frames before it can be tracked back from it. Every frame goes
through the localizer's own gates, and a stretch between two forward poses is kept only if the backward track lands
on the earlier one (``meet_m``, ``meet_deg``). Nothing here runs in the live server. No torch."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from services.geometry.se3 import Pose

__all__ = ["BackfillStats", "backfill"]


@dataclass
class BackfillStats:
    filled: int = 0  # frames that got a pose from the backward pass
    stretches: int = 0  # LOST stretches tracked into
    rejected: int = 0  # frames dropped because their stretch's backward track missed the forward pose before it


def backfill(loc, frame: Callable[[int], np.ndarray | None], camera, poses: list[Pose | None], stamps: list[float | None],
             motions: list[Pose | None] | None = None, give_up_s: float = 1.0, meet_m: float = 0.03,
             meet_deg: float = 0.3, progress: Callable[[int], None] | None = None,
             stats: BackfillStats | None = None) -> BackfillStats:
    """Fill ``poses`` (one per frame, None where the forward pass reported none) in place.

    ``loc``: a localizer with ``reset()`` and ``process(image, camera, prior=, stamp=, motion=)`` (Render & Match or
    P&L); ``frame(i)``: frame i's image; ``stamps``: capture times in seconds (None: unknown; frames are then taken
    1/30 s apart), fed negated so that time runs forward for the localizer; ``motions``: the device's odometry,
    ``T_{i-1}^-1 @ T_i`` per frame, inverted for the backward step. A backward track stops at a frame with a forward
    pose or after ``give_up_s`` of LOST frames; a frame whose image is None (unreadable) counts as LOST.
    ``progress(k)``: called with the number of frames processed. ``stats``: counted into (returned either way)."""
    st = stats if stats is not None else BackfillStats()
    n = len(poses)
    times = [s if s is not None else i / 30.0 for i, s in enumerate(stamps)]
    b = n - 1
    while b > 0:
        if poses[b] is None or poses[b - 1] is not None:
            b -= 1
            continue
        a = b - 1  # poses[a] is None: track back from b
        while a > 0 and poses[a - 1] is None:
            a -= 1
        st.stretches += 1
        loc.reset()
        loc.process(frame(b), camera, prior=poses[b], stamp=-times[b])
        got: dict[int, Pose] = {}
        lost_since = None
        meets = None  # the backward pose of the forward-posed frame before the stretch (a - 1)
        for j in range(b - 1, a - 2, -1):
            if j < 0:
                break
            motion = motions[j + 1].inverse() if motions is not None and motions[j + 1] is not None else None
            img = frame(j)
            T = None if img is None else loc.process(img, camera, stamp=-times[j], motion=motion).T_wc
            if progress is not None:
                progress(1)
            if j == a - 1:
                meets = T
                break
            if T is not None:
                got[j], lost_since = T, None
            elif lost_since is None:
                lost_since = times[j]
            elif lost_since - times[j] > give_up_s:
                break
        if a > 0 and meets is not None:
            dm, dd = meets.distance_to(poses[a - 1])
            if dm > meet_m or dd > meet_deg:
                st.rejected += len(got)
                got = {}
        for j, T in got.items():
            poses[j] = T
        st.filled += len(got)
        b = a - 1
    loc.reset()
    return st
