"""A static terrestrial LiDAR scan, simulated: stations with a spherical ray grid, first returns.

Models what matters for localization: a regular angular grid (so density falls with
range and surfaces seen at grazing angles get sparse), Gaussian range noise (~2 mm),
random and grazing-angle dropouts, a minimum and maximum range, and colours taken by the
scanner's camera under the lighting of scan day (not the lighting the cameras see later).

A real registered scan has flaws a perfect simulation lacks (``ScanFlaws``, off by default): each station registered
a few millimetres and hundredths of a degree off, each station's panorama exposed and white-balanced a little
differently, and *mixed pixels*, returns whose beam straddled a range edge and came back from between the two
surfaces (points floating in the air along every silhouette, where a scanner's own filter left them).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from services.sim.materials import linear_to_srgb
from services.sim.scenes import Lighting
from services.sim.shading import SceneRenderer

__all__ = ["LidarConfig", "ScanFlaws", "FLAWS", "simulate_station", "scan_exposure", "misregister", "loose_station",
           "laser_intensity"]

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
    intensity_only: bool = False  # a scanner that took no pictures: each point has the laser's intensity, no colour


@dataclass(frozen=True)
class ScanFlaws:
    """What a registered survey scan gets wrong, per station (1-sigma values; zeros: a perfect scan)."""

    registration_m: float = 0.0  # the station's position error, per axis
    registration_deg: float = 0.0  # ... and its orientation error, per axis
    gain: float = 0.0  # its panorama's exposure error (log gain)
    tint: float = 0.0  # ... and white balance error (log gain per channel)
    mixed_pixels: float = 0.0  # share of the returns on a range edge that come back from between the two surfaces
    edge_m: float = 0.05  # a range edge: a neighbouring ray's range differs by more than this
    loose_m: float = 0.0  # one station (the one nearest the stations' middle) registered this far off instead ...
    loose_deg: float = 0.0  # ... and turned this much: a setup the registration held weakly (few targets, a corridor)

    @property
    def any(self) -> bool:
        return any((self.registration_m, self.registration_deg, self.gain, self.tint, self.mixed_pixels, self.loose_m,
                    self.loose_deg))

    @property
    def misregistered(self) -> bool:
        return any((self.registration_m, self.registration_deg, self.loose_m, self.loose_deg))


FLAWS = {  # ``cristal sim --scan-flaws NAME``
    "none": ScanFlaws(),
    # a good registration (2-4 mm between setups), HDR panoramas a little apart, the scanner's mixed-pixel filter on
    "survey": ScanFlaws(registration_m=0.003, registration_deg=0.01, gain=0.1, tint=0.03, mixed_pixels=0.3),
    # only the survey's registration (3 mm / 0.01 deg per station): what it alone costs a camera (scan_error.py)
    "registration": ScanFlaws(registration_m=0.003, registration_deg=0.01),
    # a hurried one: centimetre registration, panoramas visibly apart, no mixed-pixel filter
    "poor": ScanFlaws(registration_m=0.01, registration_deg=0.03, gain=0.3, tint=0.08, mixed_pixels=1.0),
    # a millimetre registration but for one loose setup, 1 cm / 0.03 deg off: where on the site the scan's error lies
    "loose": ScanFlaws(registration_m=0.001, registration_deg=0.003, loose_m=0.01, loose_deg=0.03),
}


def loose_station(centres: np.ndarray) -> int:
    """The station ``ScanFlaws.loose_m`` moves: the one nearest the stations' middle (a setup most others lean on)."""
    c = np.asarray(centres, float).reshape(-1, 3)
    return int(np.argmin(np.linalg.norm(c - c.mean(axis=0), axis=1)))


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


def laser_intensity(renderer: SceneRenderer, centre: np.ndarray, dirs: np.ndarray, tri: np.ndarray, cosi: np.ndarray,
                    seed: int, rng: np.random.Generator) -> np.ndarray:
    """The return strength (0..1) of rays ``dirs`` from ``centre`` hitting triangles ``tri`` at incidence cosines
    ``cosi``: the surface's reflectance at the laser's near-infrared wavelength, which follows its visible albedo
    only loosely (each material's luminance bent by its own gain and gamma, drawn from ``seed``: paint, wood and
    fabric that look alike can return apart, and the reverse), times a Lambertian falloff with incidence, with 5 %
    speckle. Unlit: the laser is its own light, so none of the room's shading is in it."""
    albedo, _, _ = renderer.cast(centre, dirs, Lighting(np.zeros((0, 7)), np.ones(3)))
    lum = albedo @ np.array([0.2126, 0.7152, 0.0722])
    mats = renderer.mat[np.maximum(tri, 0)]
    n_mat = int(renderer.mat.max()) + 1
    mrng = np.random.default_rng([seed, 57])
    gain, gamma = np.exp(mrng.normal(0.0, 0.35, n_mat)), np.exp(mrng.normal(0.0, 0.25, n_mat))
    rho = np.clip(gain[mats] * np.maximum(lum, 1e-4) ** gamma[mats], 0.0, 1.0)
    i = rho * (0.3 + 0.7 * cosi) * np.exp(rng.normal(0.0, 0.05, len(rho)))
    return np.clip(i, 0.0, 1.0).astype(np.float32)


def _mixed_ranges(t: np.ndarray, shape: tuple[int, int], flaws: ScanFlaws, rng: np.random.Generator) -> np.ndarray:
    """Ranges ``t`` (one per ray of the (elevation, azimuth) grid ``shape``; inf where nothing was hit) with
    ``flaws.mixed_pixels`` of the rays on a range edge returning from a random point between their own surface and
    the farther or nearer one their neighbour saw."""
    T = t.reshape(shape)
    best = np.zeros(shape)  # the largest range step to a neighbour, signed
    for axis in (0, 1):
        for step in (-1, 1):
            nb = np.roll(T, step, axis=axis)
            if axis == 0:  # no wrap over the poles
                (nb[0] if step == 1 else nb[-1])[:] = np.inf
            both = np.isfinite(T) & np.isfinite(nb)
            d = np.zeros(shape)
            d[both] = nb[both] - T[both]
            best = np.where(np.abs(d) > np.abs(best), d, best)
    edge = (np.abs(best) > flaws.edge_m) & (rng.random(shape) < flaws.mixed_pixels)
    out = T.copy()
    out[edge] += rng.random(int(edge.sum())) * best[edge]
    return out.reshape(-1)


def misregister(xyz: np.ndarray, centre: np.ndarray, flaws: ScanFlaws, rng: np.random.Generator, loose: bool = False):
    """One station's points placed by a registration ``flaws`` off: (xyz, the station's registered rotation, centre).
    ``loose``: the station is the loose one (``flaws.loose_m``, ``flaws.loose_deg``)."""
    from services.geometry.se3 import rotvec_to_rotmat

    sigma_deg, sigma_m = (flaws.loose_deg, flaws.loose_m) if loose else (flaws.registration_deg, flaws.registration_m)
    R = rotvec_to_rotmat(np.deg2rad(rng.normal(0.0, sigma_deg, 3)))
    c = centre + rng.normal(0.0, sigma_m, 3)
    return (xyz - centre) @ R.T + c, R, c


def simulate_station(renderer: SceneRenderer, centre: np.ndarray, lighting: Lighting, exposure: float,
                     cfg: LidarConfig, rng: np.random.Generator, flaws: ScanFlaws | None = None,
                     flaws_rng: np.random.Generator | None = None,
                     intensity_seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Returns (xyz float64 (N,3) world, rgb uint8 (N,3)) of one station's first returns. With ``flaws``: its mixed
    pixels and its panorama's exposure and white balance (drawn from ``flaws_rng``; the registration error is
    :func:`misregister`'s). With ``intensity_seed``: a scanner that took no pictures, (xyz, intensity float32 (N,)
    in 0..1) instead (:func:`laser_intensity`)."""
    dirs = station_directions(cfg)
    rad, t, tri = renderer.cast(centre, dirs, lighting, spread=np.deg2rad(cfg.step_deg), tmax=cfg.max_range_m)
    if flaws is not None and flaws.mixed_pixels > 0:
        n_el = len(np.arange(cfg.elev_min_deg, cfg.elev_max_deg + 1e-9, cfg.step_deg))
        t = _mixed_ranges(np.where(np.isfinite(t), t, np.inf), (n_el, len(dirs) // n_el), flaws, flaws_rng)
    hit = np.isfinite(t) & (t >= cfg.min_range_m)
    n = renderer.normals[np.maximum(tri, 0)]
    cosi = np.abs(np.einsum("ij,ij->i", n, dirs))
    keep = hit & (rng.random(len(t)) >= cfg.dropout)
    grazing = cosi < cfg.grazing_cos
    keep &= ~(grazing & (rng.random(len(t)) < 0.8 * (1 - cosi / cfg.grazing_cos)))
    r = t[keep] + rng.normal(0.0, cfg.range_noise_m, keep.sum())
    xyz = centre + dirs[keep] * r[:, None]
    if intensity_seed is not None:
        return xyz, laser_intensity(renderer, centre, dirs[keep], tri[keep], cosi[keep], intensity_seed, rng)
    gain = np.ones(3)
    if flaws is not None and (flaws.gain or flaws.tint):
        gain = np.exp(flaws_rng.normal(0.0, flaws.gain) + flaws_rng.normal(0.0, flaws.tint, 3))
    srgb = linear_to_srgb(rad[keep] * exposure * gain) * 255.0
    srgb += rng.normal(0.0, cfg.colour_noise, srgb.shape)
    rgb = np.clip(np.round(srgb), 0, 255).astype(np.uint8)
    log.debug("station %s: %d rays, %d returns", centre, len(t), keep.sum())
    return xyz, rgb
