"""What a picture the product wrote shows, for the tests that check one."""

import cv2
import numpy as np


def red_pixels(png) -> int:
    """How many pixels of a PNG are the estimate's red (services.eval.plots.EST_COLOR, #d62728): what a top view
    draws the reported poses and the sampled positions in."""
    img = cv2.imread(str(png))
    assert img is not None, f"{png} is no image"
    return int((np.abs(img.astype(int) - (40, 39, 214)).sum(axis=2) < 40).sum())
