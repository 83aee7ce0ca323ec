"""Hand-held camera walks: a person carries the camera along a route and looks at things.

Position: a Catmull-Rom spline through the scene's route, walked at a varying speed,
with step bobbing. Orientation: the operator looks at points of interest that are in
sight, switching between them smoothly or, now and then, with a fast turn (up to
several hundred degrees per second), plus hand shake in yaw, pitch and roll.
``Walk.pose(t)`` is continuous in time, so motion blur can sample within an exposure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.se3 import Pose, rotvec_to_rotmat
from services.sim.raytrace import trace
from services.sim.scenes import Scene
from services.sim.shading import SceneRenderer

__all__ = ["Walk", "make_walk"]

_RATE = 200.0  # internal sampling rate (Hz) of the continuous trajectory


def _catmull_rom(points: np.ndarray, samples_per_seg: int = 60) -> np.ndarray:
    P = np.vstack([points[0], points, points[-1]])
    out = []
    for i in range(1, len(P) - 2):
        p0, p1, p2, p3 = P[i - 1], P[i], P[i + 1], P[i + 2]
        s = np.linspace(0, 1, samples_per_seg, endpoint=False)[:, None]
        out.append(0.5 * ((2 * p1) + (-p0 + p2) * s + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s ** 2 + (-p0 + 3 * p1 - 3 * p2 + p3) * s ** 3))
    out.append(points[-1:])
    return np.vstack(out)


def _smooth_noise(rng: np.random.Generator, n: int, sigma: float, corr_samples: float) -> np.ndarray:
    """Band-limited noise with standard deviation ``sigma`` and correlation length ``corr_samples``."""
    k = max(1, int(corr_samples))
    x = rng.normal(size=n + 6 * k)
    w = np.exp(-0.5 * (np.arange(-3 * k, 3 * k + 1) / k) ** 2)
    y = np.convolve(x, w / np.sqrt((w ** 2).sum()), mode="valid")[:n]
    return y * sigma


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0, 1)
    return x * x * (3 - 2 * x)


@dataclass
class Walk:
    times: np.ndarray  # (K,) seconds from the start, at _RATE
    positions: np.ndarray  # (K, 3)
    rotations: np.ndarray  # (K, 3, 3) R_wc

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def pose(self, t: float) -> Pose:
        """Camera-to-world pose at time ``t`` (seconds), interpolated."""
        x = np.clip(t * _RATE, 0, len(self.times) - 1)
        i = int(min(np.floor(x), len(self.times) - 2))
        a = x - i
        P0 = Pose(self.rotations[i], self.positions[i])
        P1 = Pose(self.rotations[i + 1], self.positions[i + 1])
        return P0.interpolate(P1, a)


def make_walk(scene: Scene, renderer: SceneRenderer, duration: float, rng: np.random.Generator,
              speed: float = 0.9, fast_turn_prob: float = 0.3) -> Walk:
    n = int(np.ceil(duration * _RATE)) + 2
    times = np.arange(n) / _RATE
    # --- path -------------------------------------------------------------
    way = np.array([p + rng.uniform(-0.1, 0.1, 2) for p in scene.route])
    curve = _catmull_rom(way)
    seg = np.linalg.norm(np.diff(curve, axis=0), axis=1)
    arc = np.concatenate([[0], np.cumsum(seg)])
    v = speed * (1 + 0.3 * _smooth_noise(rng, n, 1.0, 1.5 * _RATE))  # walking speed varies
    v = np.clip(v, 0.15, 1.6)
    s = np.concatenate([[0], np.cumsum(v[:-1] / _RATE)])
    if s[-1] > arc[-1]:  # route shorter than the walk: slow down to end at the last waypoint
        s *= arc[-1] / s[-1]
    xy = np.stack([np.interp(s, arc, curve[:, 0]), np.interp(s, arc, curve[:, 1])], 1)
    h0 = rng.uniform(*scene.height_range)
    z = h0 + _smooth_noise(rng, n, 0.05, 2 * _RATE) + 0.015 * np.sin(2 * np.pi * 1.8 * times + rng.uniform(0, 6))
    z = np.clip(z, scene.height_range[0] - 0.1, scene.height_range[1] + 0.1)
    pos = np.column_stack([xy, z])
    # heading of travel, smoothed (for the fallback look direction)
    vel = np.gradient(xy, axis=0)
    travel = np.unwrap(np.arctan2(vel[:, 1], vel[:, 0]))
    # --- gaze: a sequence of points of interest -----------------------------
    t_key = 0.0
    prev_target = pos[0] + 3 * np.array([np.cos(travel[0]), np.sin(travel[0]), 0.0])
    keys = []  # (t_start, t_end, target)
    while t_key < duration + 1:
        i = min(int(t_key * _RATE), n - 1)
        target = _pick_target(scene, renderer, pos[i], travel[i], rng)
        trans = rng.uniform(0.25, 0.4) if rng.random() < fast_turn_prob else rng.uniform(0.6, 1.2)
        keys.append((t_key, t_key + trans, target))
        t_key += trans + rng.uniform(0.8, 2.0)
    yaw = np.empty(n)
    pitch = np.empty(n)
    cur_from = prev_target
    k = 0
    for j in range(n):
        t = times[j]
        while k + 1 < len(keys) and t >= keys[k + 1][0]:
            cur_from = keys[k][2]
            k += 1
        t0, t1, tgt = keys[k]
        a = _smoothstep((t - t0) / (t1 - t0))
        d_from = cur_from - pos[j]
        d_to = tgt - pos[j]
        y0 = np.arctan2(d_from[1], d_from[0])
        y1 = np.arctan2(d_to[1], d_to[0])
        dy = (y1 - y0 + np.pi) % (2 * np.pi) - np.pi
        yaw[j] = y0 + a * dy
        p0 = np.arctan2(d_from[2], np.linalg.norm(d_from[:2]))
        p1 = np.arctan2(d_to[2], np.linalg.norm(d_to[:2]))
        pitch[j] = p0 + a * (p1 - p0)
    yaw = np.unwrap(yaw) + _smooth_noise(rng, n, np.deg2rad(0.8), 0.25 * _RATE)
    pitch = np.clip(pitch + _smooth_noise(rng, n, np.deg2rad(0.8), 0.25 * _RATE), np.deg2rad(-35), np.deg2rad(25))
    roll = _smooth_noise(rng, n, np.deg2rad(2.5), 0.6 * _RATE)
    # --- rotations: OpenCV camera (x right, y down, z forward) ----------------
    R = np.empty((n, 3, 3))
    for j in range(n):
        fwd = np.array([np.cos(pitch[j]) * np.cos(yaw[j]), np.cos(pitch[j]) * np.sin(yaw[j]), np.sin(pitch[j])])
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        Rj = np.stack([right, down, fwd], 1)
        R[j] = Rj @ rotvec_to_rotmat([0.0, 0.0, roll[j]])
    return Walk(times, pos, R)


def _pick_target(scene: Scene, renderer: SceneRenderer, p: np.ndarray, heading: float, rng) -> np.ndarray:
    """A point of interest in sight and not behind the walker, else a point 3 m ahead."""
    d = scene.pois - p
    dist = np.linalg.norm(d, axis=1)
    ang = np.abs((np.arctan2(d[:, 1], d[:, 0]) - heading + np.pi) % (2 * np.pi) - np.pi)
    ok = (dist > 1.5) & (dist < 20.0) & (ang < np.deg2rad(110))
    cand = np.flatnonzero(ok)
    if len(cand):
        t, _, _, _ = trace(renderer.bvh, p, d[cand])  # t in units of the full distance
        cand = cand[t > 0.9]
    if len(cand) == 0:
        return p + 3 * np.array([np.cos(heading), np.sin(heading), -0.3])
    return scene.pois[rng.choice(cand)] + rng.uniform(-0.3, 0.3, 3)
