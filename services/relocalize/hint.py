"""A caller's hint of where a camera is, roughly (``near``: a dock, an entrance, a robot's own estimate), checked once
for both localizers: relocalization then searches only where the camera can be."""

from __future__ import annotations

import numpy as np


def near_hint(near) -> tuple[np.ndarray, float]:
    """``near`` = (world position (3,), radius m) as (float64 position, radius); ValueError unless both are finite and
    the radius is positive."""
    pos, radius = np.asarray(near[0], np.float64).reshape(3), float(near[1])
    if not (np.all(np.isfinite(pos)) and 0 < radius < float("inf")):
        raise ValueError(f"near: a finite position and a positive radius, not {near!r}")
    return pos, radius
