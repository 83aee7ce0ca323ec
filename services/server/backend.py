"""What a server runs per client: a localization backend and its per-client trackers.

A backend holds the heavy shared state (scan, renderer, feature extractor, relocalization
database) once; ``new_tracker()`` makes the cheap per-client state. Two backends:

- ``rm``  — Render & Match (:mod:`services.localize.render_match`): the GPU server's job, also runs on a CPU.
- ``pnl`` — the light Prebuild & Localize localizer on the server's CPU (no torch, no GPU), for
  sites served without a GPU; it needs only the P&L map directory.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.geometry.camera import Camera
from services.geometry.se3 import Pose

__all__ = ["TrackResult", "RMBackend", "PnlBackend", "load_backend"]

log = logging.getLogger(__name__)


@dataclass
class TrackResult:
    status: str  # "tracking" | "relocalized" | "lost"
    T_wc: Pose | None
    inliers: int = 0
    rmse_px: float = float("nan")
    sigma_m: float = float("nan")
    sigma_deg: float = float("nan")
    timings: dict[str, float] = field(default_factory=dict)
    reason: str | None = None  # why a LOST frame has no pose
    source: str | None = None  # what solved the pose: "features", "direct", "fused" (the frame log's column)


def _status(s) -> str:
    return str(getattr(s, "value", s))


class _RMTracker:
    def __init__(self, backend: "RMBackend"):
        from services.localize.render_match import RenderMatchTracker

        self.t = RenderMatchTracker(backend.renderer, backend.extractor, backend.db, backend.cfg, plan=backend.plan)

    def reset(self) -> None:
        self.t.reset()

    def process(self, image: np.ndarray, camera: Camera, prior: Pose | None, motion: Pose | None,
                stamp: float | None = None, exposure_s: float | None = None, readout_s: float | None = None,
                near=None) -> TrackResult:
        # stamps give the tracker its constant-velocity prediction and motion-blur model; odometry replaces the former
        r = self.t.process(image, camera, prior, stamp=stamp, motion=motion, exposure_s=exposure_s, readout_s=readout_s,
                           near=near)
        return TrackResult(_status(r.status), r.T_wc, int(r.inliers), float(r.rmse_px), float(r.sigma_m),
                           float(r.sigma_deg), dict(r.timings), getattr(r, "reason", None), r.source)


class RMBackend:
    name = "rm"

    def __init__(self, scan, renderer, extractor, db, cfg=None):
        from services.localize.render_match import RMConfig

        self.scan, self.renderer, self.extractor, self.db = scan, renderer, extractor, db
        self.cfg = cfg or RMConfig()
        self.plan = None  # the scan's floor plan, one for every client's tracker (built in warm_up)

    @classmethod
    def load(cls, scan_path: str | Path, db_path: str | Path, device: str = "auto", max_side: int | None = None,
             cfg=None) -> "RMBackend":
        from services.io.scans import load_scan
        from services.relocalize.database import RelocDB
        from services.render.renderer import Renderer

        db = RelocDB.load(db_path)
        scan = load_scan(scan_path)
        return cls.from_loaded(scan, Renderer(scan, device=device), db, max_side, cfg)

    @classmethod
    def from_loaded(cls, scan, renderer, db, max_side: int | None = None, cfg=None) -> "RMBackend":
        """Over a scan, renderer and database already in memory (``cristal demo`` shares them with its build steps)."""
        from services.features.xfeat import XFeatExtractor

        if max_side is None:
            max_side = None if renderer.device.type == "cuda" else 480
        ext = XFeatExtractor(device=str(renderer.device), top_k=1024, max_side=max_side)
        backend = cls(scan, renderer, ext, db, cfg)
        backend.warm_up()
        return backend

    def warm_up(self) -> None:
        """The scan's floor plan, and one tracked and one cold (relocalized) frame before serving: the first client's first
        frame must not pay for JIT compilation, kernel selection and lazy imports (measured: > 1 s, a missed deadline,
        in a fresh process), nor a client's relocalization for the plan (1.3 s for 6 M points)."""
        import time

        from services.geometry.camera import Camera
        from services.localize.render_match import floor_plan

        t0 = time.perf_counter()
        if self.plan is None:  # where a camera can have walked: once per map, not on a client's relocalization
            self.plan = floor_plan(self.renderer)
        T = self.db.view_pose(0) if self.db is not None and self.db.n_views else Pose.identity()
        cam = Camera.from_fov(320, 240, 60.0)
        tr = _RMTracker(self)
        r = self.renderer.render(T, cam)
        tr.t.process(r.rgb, cam, prior=T, stamp=0.0)
        tr.t.reset()
        tr.t.process(r.rgb, cam, prior=None, stamp=0.0)  # and the cold path a client's first frame takes (retrieval)
        log.info("backend warm in %.2f s", time.perf_counter() - t0)

    def new_tracker(self) -> _RMTracker:
        return _RMTracker(self)

    def site_meta(self) -> dict:
        lo, hi = self.scan.bounds()
        return {"origin": [float(x) for x in self.scan.origin], "bounds_min": [float(x) for x in lo],
                "bounds_max": [float(x) for x in hi]}


class _PnlTracker:
    def __init__(self, backend: "PnlBackend"):
        self.loc = backend.make()

    def reset(self) -> None:
        self.loc.reset()

    def process(self, image: np.ndarray, camera: Camera, prior: Pose | None, motion: Pose | None,
                stamp: float | None = None, exposure_s: float | None = None, readout_s: float | None = None,
                near=None) -> TrackResult:
        # odometry: predicts, carries through LOST
        r = self.loc.process(image, camera, prior, motion=motion, stamp=stamp, readout_s=readout_s, near=near)
        return TrackResult(_status(r.status), r.T_wc, int(r.inliers), float(r.rmse_px), float(r.sigma_m),
                           float(r.sigma_deg), dict(r.timings or {}), r.reason, r.source)


class PnlBackend:
    """The P&L localizer per client (each client gets its own localizer over one shared, loaded map)."""

    name = "pnl"

    def __init__(self, map_dir: str | Path, cfg=None):
        from services.localize.pnl import PnlConfig, PnlLocalizer  # issue 5

        self.map_dir = Path(map_dir)
        self._cls, self._cfg = PnlLocalizer, cfg or PnlConfig()
        self._proto = PnlLocalizer.load(self.map_dir, self._cfg)

    def make(self):
        import copy

        loc = copy.copy(self._proto)  # shares the (read-only) map, own tracking state
        loc.reset()
        return loc

    def new_tracker(self) -> _PnlTracker:
        return _PnlTracker(self)

    def site_meta(self) -> dict:
        return {}


def load_backend(kind: str, scan: str | None, db: str | None, map_dir: str | None, device: str = "auto",
                 rm_cfg=None, pnl_cfg=None):
    """A backend by name; ``rm_cfg`` (RMConfig) / ``pnl_cfg`` (PnlConfig): its trackers' settings, else the defaults."""
    if kind == "rm":
        if not scan or not db:
            raise ValueError("the rm backend needs a scan and --db")
        return RMBackend.load(scan, db, device=device, cfg=rm_cfg)
    if kind == "pnl":
        if not map_dir:
            raise ValueError("the pnl backend needs --map")
        return PnlBackend(map_dir, pnl_cfg)
    raise ValueError(f"unknown backend {kind!r} (rm or pnl)")
