"""ORB with stella_vslam's settings: selection rules, orientation and descriptors as stella computes them."""

import cv2
import numpy as np
import pytest

from services.features.orb import OrbExtractor, OrbSettings, hamming, ic_angles, level_centres


@pytest.fixture(scope="module")
def gray(small_site):
    from services.io.sequence import open_sequence

    img = open_sequence(small_site[0] / "seq_00").read(0).image
    return cv2.resize(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), (640, 480), interpolation=cv2.INTER_CUBIC)


def test_stella_selection_rules(gray):
    s = OrbSettings(max_keypoints=1500)
    f = OrbExtractor(s).extract(gray)
    assert 200 < len(f) <= 1500
    assert f.desc.shape == (len(f), 32) and f.desc.dtype == np.uint8
    assert f.octaves.min() >= 0 and f.octaves.max() < s.num_levels
    assert (f.responses >= s.min_fast_threshold).all()
    sc = s.scale_factor ** f.octaves
    lx, ly = f.kpts[:, 0] / sc, f.kpts[:, 1] / sc
    H, W = gray.shape
    assert (lx >= s.edge - 1e-3).all() and (ly >= s.edge - 1e-3).all()
    assert (lx < W / sc - s.edge + 1).all() and (ly < H / sc - s.edge + 1).all()
    # at most one keypoint per distribution cell and level
    cells = set(zip(f.octaves.tolist(), (ly // (s.distribution_cell / sc)).astype(int).tolist(),
                    (lx // (s.distribution_cell / sc)).astype(int).tolist()))
    assert len(cells) == len(f)
    # level centres: level-L pixel centre in the full image
    c = level_centres(np.array([[10.0, 20.0]]), np.array([3]), 1.2)
    assert np.allclose(c, [[10 + 0.5 * (1.728 - 1), 20 + 0.5 * (1.728 - 1)]])


def test_orientation_and_descriptor_match_stella_formula(gray):
    ex = OrbExtractor(OrbSettings(max_keypoints=1500))
    a = ex.extract(gray)
    b = ex.extract_stella(gray)
    assert len(a) == len(b) and np.array_equal(a.kpts, b.kpts)
    lvl0 = a.octaves == 0
    # stella's ic_angle (re-implemented in numpy) gives OpenCV's orientation exactly
    assert np.abs((ic_angles(gray, a.kpts[lvl0].astype(np.float64)) - a.angles[lvl0] + 180) % 360 - 180).max() < 1e-3
    # level 0: the same image, pattern and blur -> bit-identical descriptors
    assert (hamming(a.desc[lvl0], b.desc[lvl0]) == 0).all()
    # higher levels: stella's INTER_LINEAR pyramid vs OpenCV's differ by a few bits of 256, never more than a near match
    h = hamming(a.desc[~lvl0], b.desc[~lvl0])
    assert h.mean() < 12 and np.percentile(h, 95) < 30
