"""What a picture the product wrote shows, for the tests that check one."""

import cv2
import numpy as np

from services.eval.plots import EST_COLOR


def pixels_of(png, colour: str) -> int:
    """How many pixels of a PNG are ``colour`` ('#rrggbb'), give or take a little antialiasing."""
    img = cv2.imread(str(png))
    assert img is not None, f"{png} is no image"
    bgr = [int(colour[i:i + 2], 16) for i in (5, 3, 1)]
    return int((np.abs(img.astype(int) - bgr).sum(axis=2) < 40).sum())


def red_pixels(png) -> int:
    """Pixels of the estimate's red (services.eval.plots.EST_COLOR): what a top view draws the reported poses and the
    sampled positions in."""
    return pixels_of(png, EST_COLOR)
