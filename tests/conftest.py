"""Shared fixtures: one small simulated site per test session (ground truth for every accuracy test)."""

import os

import numpy as np
import pytest

os.environ.setdefault("CRISTAL_PROGRESS", "0")


@pytest.fixture
def use_kernels(monkeypatch):
    """``use_kernels("numba")`` runs the rest of the test on the compiled kernels (skipped where numba is missing),
    ``use_kernels("numpy")`` on the numpy path a light client without numba takes (services.kernels)."""
    from services.kernels import ENV

    def use(name: str) -> None:
        if name == "numba":
            pytest.importorskip("numba")
            monkeypatch.delenv(ENV, raising=False)
        else:
            monkeypatch.setenv(ENV, "numpy")
    return use


@pytest.fixture(params=["numpy", "numba"])
def kernels(request, use_kernels):
    """The test once on each path of the optional kernels: both must hold."""
    use_kernels(request.param)
    return request.param


@pytest.fixture(scope="session")
def small_site(tmp_path_factory):
    """Office preset, seed 3: ~0.4 M points (0.6 degree scanner step), 12 frames 200x150 with lens distortion."""
    from services.sim.site import config_for, generate_site

    out = tmp_path_factory.mktemp("site")
    cfg = config_for("office", seed=3, frames=12, width=200, height=150, lidar_step_deg=0.6,
                     distortion=(-0.1, 0.02, 0.0, 0.0, 0.0))
    summary = generate_site(cfg, out)
    return out, cfg, summary


@pytest.fixture(scope="session")
def small_site_db(small_site, tmp_path_factory):
    """A Render & Match relocalization database of ``small_site`` saved to disk (service tests, server processes)."""
    import torch

    from services.features.xfeat import XFeatExtractor
    from services.io.scans import load_scan
    from services.relocalize.database import DBConfig, build_database
    from services.relocalize.roi import RoiConfig, sample_positions
    from services.render.renderer import Renderer

    torch.set_num_threads(1)
    scan = load_scan(small_site[0] / "scan.ply")
    renderer = Renderer(scan)
    ext = XFeatExtractor(device="cpu", top_k=1024)
    db = build_database(renderer, sample_positions(scan, RoiConfig(spacing=1.5)), ext, DBConfig(face_size=192, top_k=512))
    path = tmp_path_factory.mktemp("db") / "reloc.npz"
    db.save(path)
    return path


@pytest.fixture(scope="session")
def site_480(small_site, tmp_path_factory):
    """``small_site``'s first 8 ground-truth poses rendered at 480x360 (same field of view and distortion) under
    camera-day lighting (not the scan's): frames large enough for ORB and for direct tracking.
    Returns (site root, folder with ``seq``, camera, a box around the walk)."""
    import cv2

    from services.io.sequence import SequenceWriter, open_sequence
    from services.sim.site import SimSite

    root, cfg, _ = small_site
    seq = open_sequence(root / "seq_00")
    cam = seq.camera.scaled(2.4)  # 480x360, same field of view and distortion
    out = tmp_path_factory.mktemp("pnl")
    site = SimSite(root)
    with SequenceWriter(out / "seq", cam) as w:
        for stamp, T_wc in list(seq.groundtruth)[:8]:
            rgb, _ = site.render(T_wc, cam, lighting="camera")
            w.add(stamp, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), T_wc)
    gt = np.array([T.t for _, T in seq.groundtruth])
    box = [*(gt.min(0) - [1.5, 1.5, 0.3]), *(gt.max(0) + [1.5, 1.5, 0.3])]
    return root, out, cam, box
