"""Shared by the trackers' tests of the scan's own error in the reported 1-sigma (test_render_match, test_pnl)."""

import numpy as np


def reported_alike(own: list, other: list) -> list[tuple[int, object, object]]:
    """(frame, own result, other result) of the frames with a pose, after checking that both runs reported the same
    frames with the same poses: the scan's error widens what is reported, never which frames or where."""
    out = []
    for i, (a, b) in enumerate(zip(own, other, strict=True)):
        assert a.status == b.status and (a.T_wc is None) == (b.T_wc is None)
        if a.T_wc is not None:
            assert np.allclose(a.T_wc.matrix(), b.T_wc.matrix(), atol=1e-9)
            out.append((i, a, b))
    return out


def added_m(a, b) -> float:
    """The centre 1-sigma ``b`` reports beyond ``a``'s (in quadrature)."""
    return float(np.sqrt(b.sigma_m ** 2 - a.sigma_m ** 2))


def uniform_grid(scan_path, s_m: float):
    """A grid of the stations' disagreement (services.localize.scan_error) saying ``s_m`` wherever the scan has points."""
    from services.io.scans import load_scan
    from services.localize.scan_error import DisagreementGrid

    scan = load_scan(scan_path)
    return DisagreementGrid.from_scan(scan, np.full(len(scan.stations), s_m / np.sqrt(2)), 1.0)
