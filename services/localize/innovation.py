"""Whether a tracked pose is where the motion model could have taken the camera (numpy only; Render & Match and
P&L share it).

A pose whose own uncertainty looks fine can still be wrong (matches that agree on the wrong place, patches that
settled where a bad prediction put them). Its innovation, the distance from the constant-velocity prediction, is
judged against ``sigmas`` x the combined 1-sigma of the pose and the prediction (about sqrt(3) x the last pose's, as
it extrapolates from two of them), plus a hard acceleration's ``a dt^2 / 2``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["within_motion"]


def within_motion(position: np.ndarray, predicted: np.ndarray, sigma_m: float, sigma_last_m: float, dt: float,
                  sigmas: float, accel_mps2: float) -> tuple[bool, float, float]:
    """(whether ``position`` is within the bound of ``predicted``, the distance, the bound), in metres."""
    sigma = float(np.sqrt(sigma_m ** 2 + 3.0 * sigma_last_m ** 2))
    bound = sigmas * sigma + 0.5 * accel_mps2 * dt * dt
    off = float(np.linalg.norm(np.asarray(position) - np.asarray(predicted)))
    return off <= bound, off, bound
