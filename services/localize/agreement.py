"""Does a render agree with the frame, as a picture? A check on a relocalized pose that keypoints cannot make.

Keypoint matches count what repeats: in a hall of identical racks on a floor of repeating texture, a frame looking
down an aisle matched the next aisle over, 6.3 m off, with 103-174 PnP inliers after rendering there (the true pose
gives 40-72), so every check on inlier counts confirmed it (warehouse seed 3, frames 318-365). The picture as a whole
disagrees: the render there has a brick wall where the frame has racks. :func:`structure_agreement` scores that: the
zero-mean normalised cross-correlation of the two images' gradient magnitudes at low resolution, over the pixels the
scan covers. Gradient magnitude, not intensity: render and frame differ in exposure, white balance and shading;
low resolution: a verified pose a few pixels off, motion blur and sensor noise barely change it.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["structure_agreement"]


def _gradient(gray: np.ndarray, blur: float) -> np.ndarray:
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), blur)
    return cv2.magnitude(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))


def structure_agreement(frame_gray: np.ndarray, render_gray: np.ndarray, covered: np.ndarray,
                        side: int = 160, blur: float = 1.0, min_covered: float = 0.1) -> float:
    """ZNCC (-1..1) of the gradient magnitudes of ``frame_gray`` and ``render_gray`` (any sizes of one aspect), both
    resized to ``side`` px across and blurred by ``blur`` px, over the pixels where ``covered`` (the render's
    bool mask of scan-backed pixels) holds; NaN when under ``min_covered`` of them do (nothing to judge by)."""
    h, w = render_gray.shape[:2]
    size = (side, max(8, round(side * h / w))) if w >= h else (max(8, round(side * w / h)), side)
    a = _gradient(cv2.resize(frame_gray, size, interpolation=cv2.INTER_AREA), blur)
    b = _gradient(cv2.resize(render_gray, size, interpolation=cv2.INTER_AREA), blur)
    # a cell counts when scan points land in it (a sparse scan's measured pixels are scattered between hole-filled
    # ones), its neighbours too (no gradient across the coverage's edge)
    m = cv2.resize(covered.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.05
    m = cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    if m.mean() < min_covered:
        return float("nan")
    a, b = a[m] - a[m].mean(), b[m] - b[m].mean()
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else float("nan")
