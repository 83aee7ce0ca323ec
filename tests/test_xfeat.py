"""XFeat extraction on the CPU: our faster detection path gives XFeat's own keypoints and descriptors."""

import numpy as np
import torch


def test_fast_nms_matches_xfeats_own_detection(small_site):
    from services.features import xfeat as X
    from services.io.sequence import open_sequence

    torch.set_num_threads(1)
    out, _, _ = small_site
    img = open_sequence(out / "seq_00").read(3).image
    img = np.ascontiguousarray(np.tile(img, (2, 2, 1)))  # 400x300: more keypoints than the 200x150 frame
    ext = X.XFeatExtractor(device="cpu", top_k=512)
    ours = ext.extract(img)
    fast = X._nms_cpu
    try:
        X._nms_cpu = lambda heat, thr, k: ext.model.NMS(heat, threshold=thr, kernel_size=k)
        theirs = ext.extract(img)
    finally:
        X._nms_cpu = fast
    assert len(ours.kpts) > 100
    np.testing.assert_array_equal(ours.kpts, theirs.kpts)
    np.testing.assert_array_equal(ours.desc, theirs.desc)
    # a flat image has no keypoints: an empty result, not an error
    assert len(ext.extract(np.full((96, 128), 90, np.uint8)).kpts) == 0
