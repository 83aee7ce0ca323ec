"""The camera that films a simulated site: exposure, motion blur, vignetting, noise, white balance, JPEG.

A frame is developed from linear radiance the way a phone or headset camera would:
auto-exposure that lags behind the scene, a white balance unlike the scanner's, cos^4-like
vignetting, shot + read noise, the sRGB curve, 8-bit quantisation and JPEG compression.
Motion blur averages the sharp frame warped to sub-exposure poses (using its depth), which is
exact for rotation and close for the small translations within one exposure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.geometry.blur import blur_length_px
from services.geometry.camera import Camera
from services.geometry.se3 import Pose
from services.sim.materials import linear_to_srgb

__all__ = ["SensorModel", "AutoExposure", "motion_blur", "develop"]


@dataclass(frozen=True)
class SensorModel:
    exposure_time_s: float = 0.012
    ae_target: float = 0.16  # mean linear luminance the auto-exposure aims for
    ae_rate: float = 0.12  # fraction of the log-exposure error corrected per frame (lag)
    vignetting: float = 0.35  # relative darkening in the corners
    shot_noise: float = 0.010  # relative to signal at unit linear level (sqrt law)
    read_noise: float = 0.003
    white_balance: tuple[float, float, float] = (1.06, 1.0, 0.92)
    jpeg_quality: int = 88
    max_blur_samples: int = 8
    readout_s: float = 0.0  # rolling shutter: rows are read top to bottom over this long (phones 10-30 ms; 0 = global
    #                         shutter). The frame's stamp and ground-truth pose are those of its middle row


class AutoExposure:
    """Exposure gain that follows the scene's brightness with a lag, as real cameras do."""

    def __init__(self, model: SensorModel):
        self.model = model
        self.log_gain: float | None = None

    def update(self, radiance: np.ndarray) -> float:
        lum = float(np.mean(radiance @ np.array([0.2126, 0.7152, 0.0722], np.float32)))
        want = np.log(self.model.ae_target / max(lum, 1e-6))
        if self.log_gain is None:
            self.log_gain = want
        else:
            self.log_gain += self.model.ae_rate * (want - self.log_gain)
        return float(np.exp(self.log_gain))


def blur_samples(camera: Camera, T_a: Pose, T_b: Pose, max_samples: int) -> int:
    """Sub-exposure samples needed so the ghosts of a blur are about a pixel apart."""
    return int(np.clip(np.ceil(blur_length_px(camera, T_a, T_b)), 1, max_samples))


def develop(radiance: np.ndarray, gain: float, model: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """Linear radiance (H,W,3) -> 8-bit sRGB (H,W,3), before compression."""
    H, W = radiance.shape[:2]
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    r2 = ((xx - W / 2) / (W / 2)) ** 2 + ((yy - H / 2) / (H / 2)) ** 2
    vig = 1.0 - model.vignetting * np.clip(r2 / 2.0, 0, 1) ** 1.5  # 1 in the centre, 1 - v in the corners
    x = radiance * (gain * vig)[..., None] * np.asarray(model.white_balance, np.float32)
    x = x + rng.normal(0, 1, x.shape).astype(np.float32) * np.sqrt(model.shot_noise ** 2 * np.clip(x, 0, None) + model.read_noise ** 2)
    return (linear_to_srgb(x) * 255.0 + 0.5).astype(np.uint8)
