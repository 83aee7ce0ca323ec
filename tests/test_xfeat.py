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


def test_mutual_nearest_neighbours_are_each_other_s_argmax_duplicates_included():
    """mutual_nn's numpy path takes a row's best column and checks it against the column's maximum (faster than a
    column argmax): the pairs must be exactly those of the definition, each row's argmax whose own argmax it is,
    also where duplicated descriptors tie (the first row or column of a tie, as argmax gives it)."""
    from services.features.matching import mutual_nn

    rng = np.random.default_rng(7)
    for n0, n1 in ((300, 500), (500, 200), (1, 40), (40, 1)):
        d0 = rng.standard_normal((n0, 64)).astype(np.float32)
        d1 = np.concatenate([d0[: n1 // 3] + 0.3 * rng.standard_normal((n1 // 3, 64)).astype(np.float32),
                             rng.standard_normal((n1 - n1 // 3, 64)).astype(np.float32)])
        d0[n0 // 2:n0 // 2 + 5] = d0[:5]  # duplicated rows and columns: ties in both directions
        d1[-3:] = d1[:3]
        d0 /= np.linalg.norm(d0, axis=1, keepdims=True)
        d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
        sim = d0 @ d1.T
        j, i = sim.argmax(axis=1), sim.argmax(axis=0)
        a = np.arange(n0)
        keep = (i[j] == a) & (sim[a, j] >= 0.5)
        ref = np.stack([a[keep], j[keep]], axis=1)
        got = mutual_nn(d0, d1, 0.5)
        assert got.dtype == ref.dtype and len(ref) > 0 or n0 == 1 or n1 == 1, (n0, n1)
        np.testing.assert_array_equal(got, ref)


def test_descriptors_matched_on_a_torch_device_pair_as_numpy_does(small_site):
    """The GPU server matches on the extractor's device (services.features.matching): the same mutual pairs as numpy,
    on real XFeat descriptors of two frames of a walk (torch's CPU here; CUDA too where there is one)."""
    from services.features.matching import mutual_nn
    from services.features.xfeat import XFeatExtractor
    from services.io.sequence import open_sequence

    torch.set_num_threads(1)
    out, _, _ = small_site
    seq = open_sequence(out / "seq_00")
    ext = XFeatExtractor(device="cpu", top_k=512)
    a, b = (ext.extract(seq.read(i).image).desc for i in (2, 5))
    ref = mutual_nn(a, b, 0.82)
    assert len(ref) > 50
    for dev in ["cpu"] + (["cuda"] if torch.cuda.is_available() else []):
        got = mutual_nn(a, b, 0.82, device=dev)
        assert got.dtype == np.int64 and got.shape == ref.shape, dev
        np.testing.assert_array_equal(got, ref)
    assert mutual_nn(a[:0], b, device="cpu").shape == (0, 2)
