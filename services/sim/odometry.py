"""A device's own odometry (VIO on a headset, wheel + IMU on a robot), simulated from a walk's ground truth.

Real odometry is smooth and locally accurate but drifts: each frame-to-frame motion is the true one with
a small rotation error, a translation error proportional to the step, and a scale bias; chained, the
errors grow with time and distance. The trajectory starts at an arbitrary pose in its own world frame, as
a device's does, so only its relative motions carry information (what ``cristal localize --odometry`` and
the wire's ``FrameRequest.motion`` use).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.se3 import Pose
from services.io.trajectory import Trajectory

__all__ = ["OdometryNoise", "simulate_odometry"]


@dataclass(frozen=True)
class OdometryNoise:
    rot_deg: float = 0.03  # per frame, each axis, 1 sigma (at 30 fps: ~0.16 deg random walk per second)
    trans_frac: float = 0.01  # translation error per frame, each axis, as a fraction of the step (1 sigma)
    trans_floor_m: float = 3e-4  # ... plus this much (1 sigma)
    scale: float = 1.01  # scale bias (monocular VIO: about 1 %)


def simulate_odometry(gt: Trajectory, noise: OdometryNoise = OdometryNoise(), seed: int = 0) -> Trajectory:
    """Odometry poses for the stamps of ``gt``, in a world frame of their own, drifting as ``noise`` says."""
    rng = np.random.default_rng(seed)
    out = Trajectory()
    if not len(gt):
        return out
    T = Pose.from_rotvec_t(rng.normal(0, 1, 3), rng.normal(0, 10, 3))  # the device's own world: unrelated to the scan's
    out.append(gt.stamps[0], T)
    for i in range(1, len(gt)):
        D = gt.poses[i - 1].inverse() @ gt.poses[i]
        step = float(np.linalg.norm(D.t))
        t = D.t * noise.scale + rng.normal(0, noise.trans_frac * step + noise.trans_floor_m, 3)
        R = Pose.from_rotvec_t(np.radians(rng.normal(0, noise.rot_deg, 3)), np.zeros(3)).R @ D.R
        T = T @ Pose(R, t)
        out.append(gt.stamps[i], T)
    return out
