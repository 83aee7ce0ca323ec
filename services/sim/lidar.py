"""A static terrestrial LiDAR scan, simulated: stations with a spherical ray grid, first returns.

Models what matters for localization: a regular angular grid (so density falls with
range and surfaces seen at grazing angles get sparse), Gaussian range noise (~2 mm),
random and grazing-angle dropouts, a minimum and maximum range, and colours taken by the
scanner's camera under the lighting of scan day (not the lighting the cameras see later).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from services.sim.materials import linear_to_srgb
from services.sim.scenes import Lighting
from services.sim.shading import SceneRenderer

__all__ = ["LidarConfig", "simulate_station", "scan_exposure"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LidarConfig:
    step_deg: float = 0.2  # angular step in azimuth and elevation
    elev_min_deg: float = -60.0  # below this the tripod blocks the view
    elev_max_deg: float = 90.0
    range_noise_m: float = 0.002  # 1-sigma, along the ray
    dropout: float = 0.005  # fraction of returns lost at random
    grazing_cos: float = 0.12  # below this incidence cosine most returns are lost
    min_range_m: float = 0.4
    max_range_m: float = 80.0
    colour_noise: float = 1.5  # 1-sigma in 8-bit levels


def station_directions(cfg: LidarConfig) -> np.ndarray:
    """Unit ray directions (N,3) of one station's grid, world axes (z up)."""
    az = np.deg2rad(np.arange(0.0, 360.0, cfg.step_deg))
    el = np.deg2rad(np.arange(cfg.elev_min_deg, cfg.elev_max_deg + 1e-9, cfg.step_deg))
    A, E = np.meshgrid(az, el)
    ce = np.cos(E)
    return np.stack([ce * np.cos(A), ce * np.sin(A), np.sin(E)], -1).reshape(-1, 3)


def scan_exposure(renderer: SceneRenderer, stations: np.ndarray, lighting: Lighting, seed: int = 0) -> float:
    """The scanner's global exposure: maps the median radiance seen from the stations to 18 % grey."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    meds = []
    for s in stations:
        rad, t, _ = renderer.cast(s, d, lighting)
        lum = rad[np.isfinite(t)] @ np.array([0.2126, 0.7152, 0.0722])
        if len(lum):
            meds.append(np.median(lum))
    return float(0.18 / max(np.median(meds), 1e-6)) if meds else 1.0


def simulate_station(renderer: SceneRenderer, centre: np.ndarray, lighting: Lighting, exposure: float,
                     cfg: LidarConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Returns (xyz float64 (N,3) world, rgb uint8 (N,3)) of one station's first returns."""
    dirs = station_directions(cfg)
    rad, t, tri = renderer.cast(centre, dirs, lighting, spread=np.deg2rad(cfg.step_deg), tmax=cfg.max_range_m)
    hit = np.isfinite(t) & (t >= cfg.min_range_m)
    n = renderer.normals[np.maximum(tri, 0)]
    cosi = np.abs(np.einsum("ij,ij->i", n, dirs))
    keep = hit & (rng.random(len(t)) >= cfg.dropout)
    grazing = cosi < cfg.grazing_cos
    keep &= ~(grazing & (rng.random(len(t)) < 0.8 * (1 - cosi / cfg.grazing_cos)))
    r = t[keep] + rng.normal(0.0, cfg.range_noise_m, keep.sum())
    xyz = centre + dirs[keep] * r[:, None]
    srgb = linear_to_srgb(rad[keep] * exposure) * 255.0
    srgb += rng.normal(0.0, cfg.colour_noise, srgb.shape)
    rgb = np.clip(np.round(srgb), 0, 255).astype(np.uint8)
    log.debug("station %s: %d rays, %d returns", centre, len(t), keep.sum())
    return xyz, rgb
