"""Shared fixtures: one small simulated site per test session (ground truth for every accuracy test)."""

import os

import pytest

os.environ.setdefault("CRISTAL_PROGRESS", "0")


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
