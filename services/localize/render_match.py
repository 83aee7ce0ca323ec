"""Render & Match: drift-free camera tracking against renders of the scan.

Per frame: XFeat on the live frame; match against the features of a *keyframe render* (the scan
rendered at a recent pose with this frame's own intrinsics and distortion); back-project the
render's matched pixels with its measured depth into world points; PnP-RANSAC with non-linear
refinement. Every measurement comes from the scan, so nothing drifts.

Work is reused: one render and its features serve several live frames while the camera stays
near the keyframe pose and matches stay plentiful; when the pose moves away (or matching
weakens) the scan is re-rendered at the new pose and the frame is matched once more, which also
refines its pose. Gates on inliers and reprojection error turn weak solutions into LOST, never a
guess. With no pose (first frame, after LOST) the relocalization database gives a coarse pose,
which a render at that pose refines before tracking starts.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from services.features.matching import mutual_nn
from services.features.xfeat import Features, XFeatExtractor
from services.geometry.camera import Camera
from services.geometry.pnp import PnpResult, solve_pnp
from services.geometry.se3 import Pose

__all__ = ["Status", "RMConfig", "FrameResult", "RenderMatchTracker"]

log = logging.getLogger(__name__)


class Status(str, Enum):
    TRACKING = "tracking"
    RELOCALIZED = "relocalized"
    LOST = "lost"


@dataclass(frozen=True)
class RMConfig:
    min_inliers: int = 40  # gate: fewer inliers -> LOST
    max_rmse_px: float = 1.5  # gate: inlier reprojection RMSE
    max_sigma_m: float = 0.02  # gate: predicted 1-sigma camera-centre uncertainty from the inlier geometry
    max_sigma_deg: float = 0.3  # gate: predicted 1-sigma orientation uncertainty
    ransac_px: float = 2.0  # RANSAC inlier threshold
    match_cos: float = 0.82  # mutual-NN cosine threshold (XFeat's default)
    rerender_m: float = 0.15  # re-render when the pose is this far from the keyframe ...
    rerender_deg: float = 6.0  # ... or turned this much
    rerender_inlier_ratio: float = 0.4  # ... or inliers fell below this fraction of the keyframe's first match
    render_scale: float = 0.75  # keyframe render resolution relative to the frame (features need less than the frame)
    reloc_candidates: int = 8
    reloc_refine_rounds: int = 2  # render-and-match rounds after a relocalization's coarse pose


@dataclass
class Keyframe:
    T_wc: Pose
    camera: Camera
    feats: Features  # only keypoints with measured depth
    xyz: np.ndarray  # (N, 3) world points of those keypoints
    ref_inliers: int = 0


@dataclass
class FrameResult:
    status: Status
    T_wc: Pose | None
    inliers: int = 0
    rmse_px: float = float("nan")
    rerendered: bool = False
    timings: dict[str, float] = field(default_factory=dict)  # ms
    sigma_m: float = float("nan")  # predicted 1-sigma camera-centre uncertainty
    sigma_deg: float = float("nan")  # predicted 1-sigma orientation uncertainty


class RenderMatchTracker:
    def __init__(self, renderer, extractor: XFeatExtractor, db=None, cfg: RMConfig = RMConfig()):
        self.renderer = renderer
        self.extractor = extractor
        self.db = db
        self.cfg = cfg
        self.kf: Keyframe | None = None
        self.T_last: Pose | None = None
        self.relocalizations = 0

    def reset(self) -> None:
        self.kf = None
        self.T_last = None

    # ---- pieces --------------------------------------------------------------
    def _keyframe(self, T_wc: Pose, camera: Camera, tm: dict) -> Keyframe:
        t0 = time.perf_counter()
        cam = camera.scaled(self.cfg.render_scale) if self.cfg.render_scale != 1.0 else camera
        r = self.renderer.render(T_wc, cam)
        t1 = time.perf_counter()
        f = self.extractor.extract(r.rgb)
        X, ok = r.backproject(f.kpts.astype(np.float64))
        tm["render_ms"] = tm.get("render_ms", 0.0) + 1e3 * (t1 - t0)
        tm["kf_features_ms"] = tm.get("kf_features_ms", 0.0) + 1e3 * (time.perf_counter() - t1)
        return Keyframe(T_wc, cam, f.subset(ok), X[ok])

    def _match(self, live: Features, kf: Keyframe, camera: Camera, initial: Pose | None, tm: dict) -> PnpResult | None:
        t0 = time.perf_counter()
        m = mutual_nn(live.desc, kf.feats.desc, self.cfg.match_cos)
        t1 = time.perf_counter()
        r = solve_pnp(live.kpts[m[:, 0]], kf.xyz[m[:, 1]], camera, self.cfg.ransac_px, initial=initial) if len(m) >= 6 else None
        tm["match_ms"] = tm.get("match_ms", 0.0) + 1e3 * (t1 - t0)
        tm["pose_ms"] = tm.get("pose_ms", 0.0) + 1e3 * (time.perf_counter() - t1)
        return r

    def _good(self, r: PnpResult | None) -> bool:
        return (r is not None and r.n_inliers >= self.cfg.min_inliers and r.reproj_rmse_px <= self.cfg.max_rmse_px
                and r.sigma_t_m <= self.cfg.max_sigma_m and r.sigma_r_deg <= self.cfg.max_sigma_deg)

    def _far(self, T: Pose, kf: Keyframe) -> bool:
        dt, dr = T.distance_to(kf.T_wc)
        return dt > self.cfg.rerender_m or dr > self.cfg.rerender_deg

    def _render_and_refine(self, live: Features, camera: Camera, T: Pose, tm: dict, rounds: int = 1) -> PnpResult | None:
        """Render at ``T`` and match, up to ``rounds`` times while the pose still moves; keeps the last keyframe."""
        r = None
        for _ in range(rounds):
            kf = self._keyframe(T, camera, tm)
            r = self._match(live, kf, camera, T, tm)
            if not self._good(r):
                return None
            kf.ref_inliers = r.n_inliers
            self.kf = kf
            if not self._far(r.T_wc, kf) and T.distance_to(r.T_wc)[0] < 0.02:
                break
            T = r.T_wc
        return r

    # ---- the frame loop --------------------------------------------------------
    def process(self, image: np.ndarray, camera: Camera, prior: Pose | None = None) -> FrameResult:
        """Localize one frame (``image`` uint8, any channel order). ``prior``: a pose hint (e.g. from odometry)."""
        tm: dict[str, float] = {}
        t_start = time.perf_counter()
        t0 = time.perf_counter()
        live = self.extractor.extract(image)
        tm["features_ms"] = 1e3 * (time.perf_counter() - t0)
        status = Status.TRACKING
        r: PnpResult | None = None
        rerendered = False
        if prior is not None and self.T_last is None:
            self.T_last = prior
        if self.T_last is not None:
            kf = self.kf
            if kf is None or kf.camera.width != round(camera.width * self.cfg.render_scale) or self._far(self.T_last, kf):
                r = self._render_and_refine(live, camera, self.T_last, tm)
                rerendered = True
            else:
                r = self._match(live, kf, camera, self.T_last, tm)
                if log.isEnabledFor(logging.DEBUG):
                    log.debug("keyframe match: good=%s far=%s inliers=%s ref=%d", self._good(r), r is not None and self._far(r.T_wc, kf),
                              None if r is None else r.n_inliers, kf.ref_inliers)
                if not self._good(r) or self._far(r.T_wc, kf) or r.n_inliers < self.cfg.rerender_inlier_ratio * kf.ref_inliers:
                    r = self._render_and_refine(live, camera, r.T_wc if self._good(r) else self.T_last, tm)
                    rerendered = True
        if not self._good(r) and self.db is not None:
            t0 = time.perf_counter()
            coarse, _ = self.db.localize(live, camera, k=self.cfg.reloc_candidates, min_inliers=max(15, self.cfg.min_inliers // 2))
            tm["relocalize_ms"] = 1e3 * (time.perf_counter() - t0)
            r = self._render_and_refine(live, camera, coarse.T_wc, tm, self.cfg.reloc_refine_rounds) if coarse is not None else None
            if self._good(r):
                status = Status.RELOCALIZED
                self.relocalizations += 1
                rerendered = True
        tm["total_ms"] = 1e3 * (time.perf_counter() - t_start)
        if not self._good(r):
            self.T_last = None
            self.kf = None
            return FrameResult(Status.LOST, None, 0 if r is None else r.n_inliers,
                               float("nan") if r is None else r.reproj_rmse_px, rerendered, tm)
        self.T_last = r.T_wc
        return FrameResult(status, r.T_wc, r.n_inliers, r.reproj_rmse_px, rerendered, tm, r.sigma_t_m, r.sigma_r_deg)
