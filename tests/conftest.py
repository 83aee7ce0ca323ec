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
