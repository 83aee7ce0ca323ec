"""Prebuild & Localize: the light on-device localizer against a prebuilt stella_vslam map.

No torch, no scipy: numpy + OpenCV + msgpack, so a headset or robot client imports it. Where numba is installed, the
patch alignment, the pose solve (below) and the relocalization's descriptor kNN run as compiled kernels
(:mod:`services.kernels`; a tracked frame's CPU halves); without numba, the same arithmetic runs in numpy / OpenCV.
Public API (used by the Zenoh client's local fallback)::

    from services.localize.pnl import PnlLocalizer, PnlConfig
    loc = PnlLocalizer.load(map_dir, PnlConfig())
    res = loc.process(image, camera, prior=None)   # res.status, res.T_wc, res.inliers, res.rmse_px, res.timings
    res = loc.process(image, camera, motion=D, stamp=t)   # with the device's odometry D = T_prev^-1 @ T_now
    loc.reset(); loc.seed(T_wc, stamp=t)   # a server's pose for the frame captured at t

Per frame, with a pose to start from (the previous pose moved by the device's odometry or else the
constant-velocity model, a client prior, or a seed), the landmarks of nearby keyframes that the predicted
camera can see (distance inside the landmark's scale range, viewing angle within 60 degrees of its mean) are
the local map. With odometry, a LOST frame's pose is carried on by it (up to ``odometry_carry_s``, not
reported), so the next frame tracks from there rather than relocalizing; without, by the last velocity for
a few frames (``velocity_carry_s``).

Keypoint tracking: stella_vslam-style ORB on the frame, keypoints undistorted with the frame's own
intrinsics; each projected landmark looks for the best keypoint within a small window at a compatible
pyramid level (Hamming distance, ratio test, orientation histogram), and a motion-only Gauss-Newton with
Huber weights and chi-square outlier rounds optimises the pose. Done twice: a wide window from the
prediction, then a narrow one from the first estimate. The pose passes a gate (inliers, inlier
reprojection RMSE, predicted uncertainty) or the frame is LOST and gives no pose.

Patch alignment, when the map folder has landmark patches (``patches.npz``, written by ``cristal prebuild``
beside ``map.msg``): ORB's corners shift with the viewpoint (1.5-2 px from where the landmarks project at
the true pose, even on a noise-free image), so the pose is measured again by aligning the live frame to
each landmark's patch warped into the live view (:mod:`services.prebuild.patches`, 0.2-0.3 px at the true
pose). Each alignment weighs by its patch's gradient structure (an edge-like patch constrains only across
its edge); alignment and pose solve alternate until the pose stops moving (one that does not converge is
at least as uncertain as its last step). The reported pose and its uncertainty (the gate: 1 cm / 0.1 deg,
as Render & Match) come from this solution.

- Direct tracking (the default while tracking): the frame is aligned to 240 visible landmarks with
  corner-like patches, spread over the image, straight from the prediction; no ORB is extracted at all.
  The windows converge from ~4 px, so this holds while the motion model predicts well. When it does not
  (a turn that changed speed or direction), 60 landmarks' templates are searched for within 32 px by
  normalised cross-correlation, PnP-RANSAC on those found gives a pose to align from, and the motion to it
  predicts the blur. When that pose is not good either, the frame goes the keypoint way. When the velocity
  predicts 6 px of blur or more (over an assumed 0.3 of the frame interval: P&L gets no timestamps), the
  templates are smeared with the same motion (the mean of the patch seen from 5 poses across the exposure).
- After keypoint tracking, the keypoint inliers and up to 60 landmarks no keypoint matched are aligned,
  from keypoint solutions within 3x the gates (from further, the windows settle on self-consistent wrong
  poses).

Office walk, one core: 253-264/300 frames at 0.60 cm / 0.06 deg in ~9 ms per tracked frame; keypoints alone
gave 1.7 cm / 0.23 deg over 197 frames in ~18 ms.

With no pose (first frame, after LOST) the frame relocalizes against the map itself: each keypoint's
descriptor is matched against every landmark's representative descriptor (ratio test), the
matches vote for the keyframes observing those landmarks, and PnP-RANSAC on the matches around the
best-voted keyframes gives a coarse pose which the tracking step refines and gates (when its keypoints do not
hold the coarse pose, the patch search and direct step above start from it instead). No external vocabulary is
needed.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from services.features.orb import OrbExtractor, OrbFeatures, OrbSettings, hamming, level_centres
from services.geometry.blur import blur_length_px
from services.geometry.camera import Camera
from services.geometry.rolling_shutter import NOT_UNDONE, ShutterTrack, depth_field, rate_changed, unroll_moving
from services.geometry.se3 import Pose
from services.kernels import optional_kernels
from services.localize.carry import OdometryCarry
from services.localize.innovation import within_motion
from services.localize.odometry_check import OdometryCheck
from services.localize.scan_error import local_scan_sigma, median_depth, with_scan_error
from services.localize.status import Status
from services.localize.direct import (DirectConfig, align_and_solve, cov_sigmas, pose_covariance, solve_motion_only,
                                     undistorted_gray)
from services.prebuild.patches import (PATCH_FILE, LandmarkPatches, alignment_backend, corner_scores, map_fingerprint,
                                      search_patches)
from services.prebuild.stella_map import StellaMap, read_map
from services.relocalize.ambiguity import distinct, rival
from services.relocalize.hint import near_hint

__all__ = ["PnlConfig", "PnlResult", "PnlLocalizer", "Status"]

log = logging.getLogger(__name__)

_DESC_PER_LANDMARK = 4


@dataclass(frozen=True)
class PnlConfig:
    max_keypoints: int = 1000  # ORB keypoints per frame
    distribution_cell: int | None = None  # px; None: 12 at 640 px width, scaled with the frame width
    min_inliers: int = 30  # gate: fewer -> LOST
    max_rmse_px: float = 1.5  # gate: inlier reprojection RMSE (pixels, each divided by its pyramid scale)
    max_sigma_m: float = 0.01  # gate: predicted 1-sigma camera-centre uncertainty of the reported solution ...
    max_sigma_deg: float = 0.1  # ... and orientation: a pose less certain than the accuracy we promise is LOST (as Render & Match)
    kp_max_sigma_m: float = 0.02  # the same gates for a keypoint-only pose (a map without landmark patches, e.g. one
    kp_max_sigma_deg: float = 0.3  # saved by stella_vslam): ORB corners cannot do better than ~1.5 cm / 0.2 deg here
    sigma_ref_px_deg: float = 0.12  # ... for cameras whose pixels subtend up to this (VGA); coarser ones scale both
    scan_sigma_m: float = 0.0  # the scan's registration error (1-sigma), counted in the reported 1-sigma (scan_error.py)
    scan_grid: object = None  # ... and where on the site it lies (scan_error.DisagreementGrid): the error where it looks
    coarse_radius_px: float = 16.0  # window around the predicted projection (x scale^octave, capped by the grid)
    fine_radius_px: float = 4.0  # window after the first pose estimate
    max_hamming: int = 80
    ratio: float = 0.9  # best / second best distance
    local_radius_m: float = 4.0  # keyframes within this distance of the predicted camera give the local landmarks
    reloc_ratio: float = 0.8
    reloc_keypoints: int = 600  # strongest keypoints matched against every landmark first ...
    reloc_keypoints_crowded: int = 1000  # ... and this many when no place fits them (matched around the places their
    #                                      matches voted for, then checked against every landmark): people in front of
    #                                      the camera may hold the strongest
    reloc_max_hamming: int = 64
    reloc_stretch_below: float = 133.0  # a frame no place fits whose grey levels span less than this (0.5-99.5 %) is
    reloc_stretch_range: float = 200.0  # ... tried again with them stretched to span this (at most 4x): FAST's thresholds
    #                                     and the descriptors' smoothing count grey levels, and a dark frame's corners fall
    #                                     under them (office walk at a third of the light, benchmarks/photometric.py: tracking
    #                                     slipped at frame 88 and no place fitted again, 88/150; stretched, 149/150). Clean walks' frames span 130-250
    reloc_keyframes: int = 4  # best-voted keyframes tried
    reloc_ransac_px: float = 4.0
    reloc_min_inliers: int = 11  # coarse PnP inliers a place needs before it is tracked from (_settle), which decides:
    #                              15 -> 11 relocalized 11 more of 320 cold frames on eight office sites and 2 more of 100
    #                              in the warehouse, none off; office seed 2's walk 197 -> 221 frames (stop 64)
    confirm_after: int = 5  # a tracked pose after this many tracked frames in a row too uncertain to report is reported
    #                         only if a relocalization of the frame agrees (within confirm_m / confirm_deg): office seed
    #                         8's track slid along a wall through 7 such frames after a turn and reported frame 282 55 cm
    #                         / 11 deg off at a 1-sigma of 0.7 cm (0 = never)
    confirm_beyond: float = 2.0  # ... and so is one after a single tracked frame this many times the gates' 1-sigma: its
    #                              track had slipped (office seed 2: frame 269 at 1.8 cm / 0.22 deg in an accelerating
    #                              pan, then 270-272 aligned at 0.4-0.6 cm 1-sigma, 2.5-5.4 cm off)
    confirm_unopposed: int = 30  # ... or, with no relocalization to agree, once this many good tracked frames in a row
    #                              went unopposed (no place found: neither a pose elsewhere nor rival places; 0 = never):
    #                              a map whose descriptors seldom match the frames (an intensity scan's, office seed 8:
    #                              frames 2-60 tracked 0.1-1.3 cm off, 1-sigma within the gates, none reported;
    #                              73 -> 126/300 frames, none off; no colour walk nor the warehouse ever gets there)
    confirm_m: float = 0.03
    confirm_deg: float = 0.5
    reloc_ambiguity: float = 0.8  # another place with this share of the best's inliers makes a relocalization ambiguous,
    reloc_cold_ambiguity: float = 0.5  # ... and so do two places over 2 m away with this share (services.relocalize.ambiguity)
    reloc_contest: int = 3  # ambiguous places tracked from to tell them apart (_contest): at most this many, else refused
    reloc_contest_share: float = 0.5  # ... the one good pose wins when every other tracked holds under this share of its inliers
    use_velocity: bool = True
    max_speed_mps: float = 3.0  # a caller's hint of where the camera is (``near``) widens by this much a second until a pose
    readout_s: float = 0.0  # rolling shutter: rows read top to bottom over this long (0 = global shutter); a frame with a
    #                         motion to predict it is re-sampled as if read at its middle row's time (as Render & Match)
    odometry_carry_s: float = 5.0  # with the device's odometry (``motion``), a LOST frame's pose is carried on by it for
    #                                up to this long and the next frame tracks from it (as Render & Match does)
    velocity_carry_s: float = 0.3  # without odometry, at the last velocity for up to this long (it drifts much faster)
    seed_velocity_gap_s: float = 0.15  # a seed (a server's pose) this soon after the last known pose gives the velocity
    #                                    between them (seed(): consecutive frames up to ~7 fps)
    cell_px: int = 24  # keypoint grid for window search
    cell_capacity: int = 8
    coarse_subsample: int = 2  # the wide-window pass searches every n-th visible landmark
    align: bool = True  # with the map's landmark patches: re-measure inlier matches by patch alignment, solve again
    align_max: int = 60  # at most this many keypoint inliers aligned per frame ...
    align_extra: int = 60  # ... and this many visible landmarks no keypoint matched (alignment needs no keypoint)
    align_min_corner: float = 0.2  # those extra patches' corner score (0 edge or flat .. 0.5 isotropic corner)
    align_sigma_factor: float = 3.0  # align only from keypoint solutions within this many times the gates ...
    align_min_inlier_frac: float = 0.5  # ... and keep the aligned solution only when this share of the alignments agree
    exposure_s: float = 0.01  # exposure time assumed for motion blur (indoor video: ~10 ms); with no capture times the
    #                           frames are taken 1/30 s apart (then 0.3 of the interval). A 10 fps camera's frames are
    #                           smeared over a tenth of their motion, not 0.3 of it (office walk at 10 fps: 84 -> 86/100)
    blur_min_px: float = 6.0  # direct tracking smears its templates with the predicted motion from this blur on (px at
    #                           640 wide: a sharper camera's pixels are finer, not its blur longer)
    blur_sigma_px: float = 5.0  # ... and a direct pose's covariance grows by blur / this (px at 640 wide) beyond it, as in
    #                             Render & Match: smeared templates align less surely than their gradients say
    direct_landmarks: int = 240  # tracking first aligns this many visible landmarks from the prediction, no ORB; 0: off
    #                              (240, not 120: office seeds 1-3 gained 1-4 frames each and 0.02-0.12 cm, at 9.0
    #                              instead of 6.6 ms a tracked frame on one core)
    search_landmarks: int = 60  # when the direct step fails from the prediction: this many landmarks' templates are
    search_radius_px: float = 32.0  # ... searched this far (px at 640 wide) and a pose solved from those found, when
    search_min_found: int = 12  # ... at least this many are found and agree (services.prebuild.patches.search_patches);
    #                             the direct step then starts from it. 0 landmarks: off. Office walks seeds 2/3/5:
    #                             195 -> 198, 223 -> 228, 241 -> 257 frames; a 90-degree lens 245 -> 261; none worse
    align_passes: int = 3  # alignment and pose solve alternate until the pose moves less than half its sigma, at most this often
    align_sigma_px: float = 0.5  # a corner patch's alignment noise (1 sigma, px; measured 0.2-0.3 px at the true pose)
    align_rmse_floor: float = 1.0  # the aligned solution's covariance assumes at least align_sigma_px of noise (whitened RMSE floor)
    warp_noise_ref: float = 0.0  # > 0: a patch's alignment noise is align_sigma_px x its warp's noise factor / this
    #                              (services.prebuild.patches.warp_noise_factor: a patch seen stretched from nearer than
    #                              its keyframe, or shrunk from much further, aligns worse). Off: at 1.6 (the population's
    #                              spread kept) the P&L walks gained 15 frames (960x540 79 -> 84, survey-density warehouse
    #                              177 -> 188) but the test site's rolling-shutter and crowded-frame poses lost accuracy
    #                              (benchmarks/RESULTS.md, Prebuild & Localize, stop 28)
    innovation_sigmas: float = 4.0  # a pose aligned from the constant-velocity prediction further from it than this many
    innovation_accel_mps2: float = 20.0  # sigmas plus this acceleration's a dt^2 / 2 is checked as an untracked prediction's
    #                                      is (_checked), and its velocity is not carried to the next frame, which is checked
    #                                      too: a velocity made of a correction predicted the narrow-lens walk's frames
    #                                      161-166 5-15 cm off, and the patches aligned there (8-14 cm off at 0.3-0.5 cm 1-sigma)
    align_probe_sigmas: float = 10.0  # the aligned pose's basin is tested from this many sigmas off (direct._probed;
    #                                   0: off, 20-30 % more FPS; benchmarks/RESULTS.md stop 51)
    denoise_above: float = 0.06  # a frame noisier than this (noise / grey-level spread, direct.noise_ratio) is smoothed
    #                              before patches are aligned to it: dark or high-ISO frames (inf: never)


@dataclass
class PnlResult:
    status: Status
    T_wc: Pose | None
    inliers: int = 0
    rmse_px: float = float("nan")
    timings: dict[str, float] = field(default_factory=dict)  # ms
    sigma_m: float = float("nan")  # predicted 1-sigma camera-centre uncertainty
    sigma_deg: float = float("nan")  # predicted 1-sigma orientation uncertainty
    reason: str | None = None  # why a LOST frame has no pose
    source: str | None = None  # what solved the pose: "features" (ORB keypoints) or "direct" (patches); None: no pose


def _source(r) -> str | None:
    """The ``source`` of a pose tuple (R, t, inliers, rmse, sigma_m, sigma_deg, direct)."""
    return None if r is None else "direct" if r[6] else "features"


class _MapIndex:
    """Landmark arrays the localizer needs, derived once from the map (as stella_vslam derives them at load)."""

    def __init__(self, m: StellaMap):
        self.map = m
        orb = next(iter(m.orb_params.values()))
        self.scale_factor = float(orb.scale_factor)
        self.num_levels = int(orb.num_levels)
        row = {int(i): r for r, i in enumerate(m.lm_ids.tolist())}
        self.pos = np.ascontiguousarray(m.lm_pos, np.float64)
        M = len(self.pos)
        kf_ids = sorted(m.keyframes)
        self.kf_ids = np.array(kf_ids, np.int64)
        self.kf_center = np.array([m.keyframes[k].T_wc.t for k in kf_ids]).reshape(-1, 3)
        self.kf_axis = np.array([m.keyframes[k].T_wc.R[:, 2] for k in kf_ids]).reshape(-1, 3)
        obs_lm, obs_kf, obs_desc, obs_ang, obs_oct = [], [], [], [], []
        self.kf_lms: list[np.ndarray] = []
        for ki, k in enumerate(kf_ids):
            kf = m.keyframes[k]
            sel = np.flatnonzero(kf.lm_ids >= 0)
            rows = np.array([row.get(int(x), -1) for x in kf.lm_ids[sel].tolist()], np.int64)
            ok = rows >= 0
            sel, rows = sel[ok], rows[ok]
            self.kf_lms.append(rows)
            obs_lm.append(rows)
            obs_kf.append(np.full(len(rows), ki, np.int64))
            obs_desc.append(kf.desc[sel])
            obs_ang.append(kf.angles[sel])
            obs_oct.append(kf.octaves[sel])
        cat = (lambda a, dt, shape=(0,): np.concatenate(a) if a else np.zeros(shape, dt))
        obs_lm, obs_kf = cat(obs_lm, np.int64), cat(obs_kf, np.int64)
        obs_desc = cat(obs_desc, np.uint8, (0, 32))
        obs_ang, obs_oct = cat(obs_ang, np.float32), cat(obs_oct, np.int32)
        self.obs_lm, self.obs_kf = obs_lm, obs_kf
        # representative descriptor: the Hamming medoid of each landmark's observations (as stella does)
        order = np.argsort(obs_lm, kind="stable")
        lm_s = obs_lm[order]
        start = np.searchsorted(lm_s, np.arange(M))
        count = np.bincount(obs_lm, minlength=M)
        rep = np.full(M, -1, np.int64)
        for n in np.unique(count):
            if n == 0:
                continue
            L = np.flatnonzero(count == n)
            idx = order[start[L][:, None] + np.arange(n)[None, :]]  # (L, n) observation indices
            if n <= 2:
                rep[L] = idx[:, 0]
                continue
            d = obs_desc[idx]  # (L, n, 32)
            dist = hamming(d[:, :, None, :], d[:, None, :, :]).sum(axis=2)
            rep[L] = idx[np.arange(len(L)), np.argmin(dist, axis=1)]
        has = rep >= 0
        self.valid = has
        rep = np.where(has, rep, 0)
        self.desc = obs_desc[rep] if len(obs_desc) else np.zeros((M, 32), np.uint8)
        # up to K observation descriptors per landmark (the medoid first): tracking takes the closest, which
        # keeps matching across the viewpoint and scale changes between the keyframes and the live camera
        K = _DESC_PER_LANDMARK
        self.descs = np.repeat(self.desc[:, None, :], K, axis=1)
        if len(obs_desc):
            for k in range(1, K):
                j = np.minimum(k - 1, np.maximum(count - 1, 0))  # the k-th other observation (repeats when fewer)
                o = order[np.minimum(start + j, len(order) - 1)]
                ok = (count > k - 1) & has
                self.descs[ok, k] = obs_desc[o[ok]]
        self.angle = obs_ang[rep] if len(obs_ang) else np.zeros(M, np.float32)
        # scale range and mean viewing direction (stella: from the reference keyframe's observation)
        ref_kf_row = {int(k): i for i, k in enumerate(kf_ids)}
        ref = np.array([ref_kf_row.get(int(k), -1) for k in m.lm_ref_kf.tolist()], np.int64)
        ref_oct = np.zeros(M, np.int32)
        # octave of the observation in the reference keyframe
        is_ref = obs_kf == ref[obs_lm] if len(obs_lm) else np.zeros(0, bool)
        ref_oct[obs_lm[is_ref]] = obs_oct[is_ref]
        ref_center = self.kf_center[np.where(ref >= 0, ref, 0)] if len(kf_ids) else np.zeros((M, 3))
        dist = np.linalg.norm(self.pos - ref_center, axis=1)
        self.max_dist = dist * self.scale_factor ** ref_oct
        self.min_dist = self.max_dist / self.scale_factor ** (self.num_levels - 1)
        nrm = np.zeros((M, 3))
        if len(obs_lm):
            v = self.pos[obs_lm] - self.kf_center[obs_kf]
            v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
            np.add.at(nrm, obs_lm, v)
        self.normal = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-9)
        self.log_sf = math.log(self.scale_factor)
        self._bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._reloc_rows = np.flatnonzero(self.valid)


KNN_CHUNK = 1 << 17  # OpenCV's brute-force kNN takes at most 2^18 train rows at once (a 60 x 40 m site's map has more)


def knn2_hamming(matcher, query: np.ndarray, train: np.ndarray, chunk: int = KNN_CHUNK
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each binary descriptor of ``query``, its nearest in ``train`` (index, -1 when none) and the Hamming
    distances to the nearest and the second nearest (inf when missing), ``train`` taken in chunks of ``chunk`` rows
    (the survey-density warehouse map has 327,379 landmarks: one kNN over all of them raised cv2.error). Where numba
    is installed, a compiled loop does it instead (:mod:`services.features.hamming_kernels`: 6x faster; ``matcher``
    and ``chunk`` unused): the same distances, and the same nearest wherever it is nearer than the second."""
    kern = optional_kernels("services.features.hamming_kernels")
    if kern is not None and query.dtype == np.uint8 and train.dtype == np.uint8 and query.shape[1] % 8 == 0 \
            and query.shape[1:] == train.shape[1:]:
        n = len(query)
        best, e1, e2 = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.int64)
        kern.knn2(np.ascontiguousarray(query).view(np.uint64), np.ascontiguousarray(train).view(np.uint64), best, e1, e2)
        d = np.column_stack([e1, e2]).astype(np.float64)
        d[d >= kern.NONE] = np.inf
        return best, d[:, 0], d[:, 1]
    n = len(query)
    best = np.full(n, -1, np.int64)
    d = np.full((n, 2), np.inf)
    for start in range(0, len(train), chunk):
        for mm in matcher.knnMatch(query, train[start:start + chunk], k=2):
            if not mm:
                continue
            i = mm[0].queryIdx
            for m in mm:  # merge this chunk's two nearest into the running two
                if m.distance < d[i, 0]:
                    d[i, 1], d[i, 0], best[i] = d[i, 0], m.distance, start + m.trainIdx
                elif m.distance < d[i, 1]:
                    d[i, 1] = m.distance
    return best, d[:, 0], d[:, 1]


def _warm_kernels(align: bool) -> None:
    """Compile (or load from numba's cache) the kernels a first frame needs — the relocalization's kNN, the pose solve
    and, with ``align``, the patch alignment — at map load, not in the first frame (a few seconds on a first run, under
    a second from the cache); log which path tracking takes."""
    t0 = time.perf_counter()
    backend = alignment_backend(warm=align)
    if backend == "numba":
        d = np.zeros((3, 32), np.uint8)
        knn2_hamming(cv2.BFMatcher(cv2.NORM_HAMMING), d, d)
        P = np.array([[0.0, 0, 2], [1, 0, 2], [0, 1, 2], [1, 1, 3], [-1, 0, 3], [0, -1, 2]])
        solve_motion_only(P, P[:, :2] / P[:, 2:] * 100 + 50, np.tile(np.eye(2), (6, 1, 1)),
                          np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]), np.eye(3), np.zeros(3), rounds=(1,))
    log.info("P&L kernels: %s (ready in %.2f s)", "compiled (numba)" if backend == "numba" else
             "numpy (numba not installed, or CRISTAL_KERNELS=numpy: tracking takes about twice the CPU)",
             time.perf_counter() - t0)


def _pnp_ransac(obj: np.ndarray, img: np.ndarray, K: np.ndarray, px: float, iterations: int) -> tuple[Pose | None, int]:
    """Camera-to-world pose from world points ``obj`` seen at undistorted pixels ``img`` (SQPnP in RANSAC, ``px``
    threshold) and its inlier count; (None, 0) when there is none, or when the solver refuses a degenerate sample
    (OpenCV's SQPnP asserts on some)."""
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj.astype(np.float64), img.astype(np.float64), K, None,
                                                 iterationsCount=iterations, reprojectionError=px, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_SQPNP)
        if not ok or inl is None:
            return None, 0
        return Pose(cv2.Rodrigues(rvec)[0], tvec.reshape(3)).inverse(), len(inl)
    except (cv2.error, ValueError):
        return None, 0


@dataclass
class _Frame:
    K: np.ndarray
    width: int
    height: int
    image: np.ndarray | None = None  # the frame as given (for patch alignment)
    camera: Camera | None = None
    coarse: float = 1.0  # the gates' scale for this camera: its pixel angle / sigma_ref_px_deg, at least 1
    # ORB, extracted only when the frame needs keypoints (see PnlLocalizer._features)
    feats: OrbFeatures | None = None
    uv: np.ndarray | None = None  # (N, 2) undistorted pixels (float64)
    grid: np.ndarray | None = None  # (n_cells, capacity) keypoint indices or -1
    gw: int = 0
    gh: int = 0
    inv_sigma2: np.ndarray | None = None  # (N,) 1 / scale^(2 octave)
    gray: np.ndarray | None = None  # undistorted grey float32, for patch alignment (see PnlLocalizer._gray)
    reason: str | None = None  # why this frame has no pose, when it has none
    rivals: bool = False  # its relocalization found places about as good as each other (a repetitive site)
    spare: tuple | None = None  # the most certain aligned solution tracking found that was not good (PnlLocalizer._spare)
    unchecked: bool = False  # its pose came from an untracked prediction and nothing could check it (PnlLocalizer._checked)
    relocalized: bool = False  # ... or a relocalization replaced that pose (PnlLocalizer._checked)
    jumped: bool = False  # its pose is further from the constant-velocity prediction than the motion allows (PnlLocalizer._consistent)
    exposure_fraction: float = 0.3  # the exposure over the interval since the last frame (motion blur from the velocity)
    near_rows: np.ndarray | None = None  # relocalization rows of the landmarks within a caller's hint (None: no hint)
    near: tuple[np.ndarray, float] | None = None  # that hint now: (position, how far the camera can be from it)


def _iso(w: np.ndarray) -> np.ndarray:
    """Isotropic information matrices (M, 2, 2) from weights (M,)."""
    return w[:, None, None] * np.eye(2)


class PnlLocalizer:
    """Tracks a camera in a prebuilt map; see the module docstring."""

    def __init__(self, stella_map: StellaMap, cfg: PnlConfig = PnlConfig(), patches: LandmarkPatches | None = None):
        self.cfg = cfg
        t0 = time.perf_counter()
        self.idx = _MapIndex(stella_map)
        self._kf_floor: dict[int, tuple[float, float]] = {}  # keyframe row -> (local scan error, median depth): _view_floor
        self.patches = patches
        self._patch_of_row = np.full(len(self.idx.pos), -1, np.int64)  # landmark row -> patch index
        if patches is not None:
            row = {int(i): r for r, i in enumerate(stella_map.lm_ids.tolist())}
            for j, lid in enumerate(patches.lm_ids.tolist()):
                r = row.get(int(lid))
                if r is not None:
                    self._patch_of_row[r] = j
        self._corner = corner_scores(patches.patches) if patches is not None else np.zeros(0)
        # where patch alignment places each landmark: the patch file's refitted position where it has one, else the
        # map's (ORB keypoint measurements keep the map's positions, which is where the corners were detected)
        self._apos = self.idx.pos.copy()
        if patches is not None and patches.pos is not None:
            has = self._patch_of_row >= 0
            self._apos[has] = patches.pos[self._patch_of_row[has]]
        self._undistort: dict = {}
        orb = next(iter(stella_map.orb_params.values()))
        self._orb = orb
        self._extractors: dict[int, OrbExtractor] = {}
        self._inv_s2 = 1.0 / (orb.scale_factor ** (2 * np.arange(orb.num_levels)))
        self.T_last: Pose | None = None  # camera-to-world of the last localized frame
        self._vel: Pose | None = None  # T_cw(t) @ T_wc(t-1): the last frame-to-frame motion
        self.carry = OdometryCarry(self.cfg.odometry_carry_s)  # ``T_last`` carried on through LOST frames by the odometry
        self.odometry = OdometryCheck()  # whether the device's odometry agrees with the tracked motion (else unused)
        self._stamp: float | None = None  # the last frame's capture time
        self._local_key: tuple | None = None
        self._local_rows = np.zeros(0, np.int64)
        self._local_P = np.zeros((0, 3))
        self.relocalizations = 0
        self._sigma_last = 0.0  # the last tracked pose's position 1-sigma (m)
        self._unsure = 0  # tracked frames in a row since the last reported pose that were too uncertain to report
        self._slipped = False  # ... one of them far beyond the gates, or tracked from an unchecked prediction: confirm
        self._unopposed = 0  # good tracked frames in a row awaiting confirmation that no relocalization opposed
        self.shutter = ShutterTrack()  # whether a rolling shutter's frames may be reported yet
        self._near: tuple[np.ndarray, float, float | None, int] | None = None  # hint: position, radius, stamp, frames since
        self._tracked = False  # whether ``T_last`` is a tracked frame's pose or a seed (not a carried or a relocalized one)
        log.info("P&L localizer: %d keyframes, %d landmarks indexed in %.2f s", stella_map.n_keyframes,
                 stella_map.n_landmarks, time.perf_counter() - t0)

    @classmethod
    def load(cls, map_dir: str | Path, cfg: PnlConfig = PnlConfig()) -> "PnlLocalizer":
        """The map of ``map_dir`` (``map.msg``, or the file itself), with its landmark patches when present."""
        p = Path(map_dir)
        m = read_map(map_dir)
        patches = None
        if p.is_dir() and (p / PATCH_FILE).is_file():
            patches = LandmarkPatches.load(p / PATCH_FILE)
            if patches.map_fp != map_fingerprint(m.lm_ids, m.lm_pos):  # a stale sidecar must not move poses
                log.warning("%s belongs to another map (fingerprint %s): patch alignment off", p / PATCH_FILE, patches.map_fp)
                patches = None
        _warm_kernels(patches is not None)
        return cls(m, cfg, patches)

    def __copy__(self) -> "PnlLocalizer":
        """A localizer over the same (read-only) map index with its own tracking state and extractors (one per client/thread)."""
        new = object.__new__(PnlLocalizer)
        new.__dict__.update(self.__dict__)
        new._extractors = {}
        new._undistort = {}
        new._local_key = None
        new._local_rows = np.zeros(0, np.int64)
        new._local_P = np.zeros((0, 3))
        new.relocalizations = 0
        new.odometry = OdometryCheck()
        new.carry = OdometryCarry(self.cfg.odometry_carry_s)  # its own: reset() only clears it
        new.shutter = ShutterTrack()
        new._stamp = None
        new.reset()
        return new

    # ---- state ----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the pose: the next frame relocalizes."""
        self.T_last = None
        self._vel = None
        self._tracked = False
        self._near = None
        self._trusted()
        self._sigma_last = 0.0
        self.shutter.reset()
        self.carry.reset()

    def _trusted(self) -> None:
        """No doubt carried over (a pose reported or given, or none left to doubt): an uncertain run counts anew."""
        self._unsure, self._slipped, self._unopposed = 0, False, 0

    def seed(self, T_wc: Pose, stamp: float | None = None) -> None:
        """Start tracking from an external pose (e.g. a server answer) for the frame captured at ``stamp`` (seconds).
        With capture times, a seed within ``seed_velocity_gap_s`` of the last pose this localizer knew (a seed, or a
        frame it tracked) also gives the velocity, so the next frame it is asked for is predicted where the motion
        leads, as a tracked frame's is; without, none is assumed. (Handed over in a 1.8 deg-a-frame turn with no
        velocity, a 960x540 frame was tracked into a pose 2.9 cm / 1.8 deg off on 35 inliers and reported:
        benchmarks/RESULTS.md, stop 36.)"""
        gap = None if stamp is None or self._stamp is None else stamp - self._stamp
        known = self.T_last is not None and self.carry.seconds == 0.0  # (not a pose carried through LOST frames)
        self._vel = self.T_last.inverse() @ T_wc if known and gap is not None and 0 < gap <= self.cfg.seed_velocity_gap_s else None
        self.T_last = T_wc
        self._tracked = True  # (a server's pose: as good as a tracked one; with no velocity the next frame is checked)
        self._stamp = stamp
        self._trusted()
        self._sigma_last = 0.0  # (the server's pose: its own 1-sigma is not handed over)
        self.carry.reset()

    def _direct_retry(self, fr: _Frame, pred: Pose, tm: dict, spare: bool = False):
        """The direct step from ``pred``; when it fails, once more with twice the patches: on a fast turn's blurred
        frame only about a quarter of them converge (from the true pose, office frames 95-98: 27-29 of 120, 50-54 of
        240, all within 0.5 cm / 0.07 deg). None unless the pose is good. ``spare``: keep the most certain plausible
        solution that is not good in ``fr.spare`` (a pose to track on from, see :meth:`_spare`)."""
        for n in (self.cfg.direct_landmarks, 2 * self.cfg.direct_landmarks):
            r = self._direct(fr, pred, tm, n)
            if self._good(r, fr):
                return r
            if spare and self._plausible(r) and (fr.spare is None or (r[4], r[5]) < (fr.spare[4], fr.spare[5])):
                fr.spare = r
        return None

    def _checked(self, fr: _Frame, r, pred: Pose, tm: dict):
        """A pose aligned to the landmarks' patches (directly, or from where searching them put the camera) from a
        prediction that is not a tracked frame's or a seed's with its velocity (a caller's prior, a pose carried or
        relocalized, a seed with no velocity), checked: kept where the keypoints tracked from that prediction agree
        (within ``confirm_m`` / ``confirm_deg``), else decided by a relocalization (its pose where it disagrees: tracked
        from a prediction 20 cm off, keypoints too can hold a pose 22 cm off, office seed 8 frame 295); where neither
        gives a pose, kept but ``fr.unchecked`` (not reported: :meth:`process`). A relocalization's pose sets
        ``fr.relocalized``: the frame is then reported as relocalized, and no velocity is taken from the jump to it.
        A pose aligned from a tracked frame's prediction but further from it than the motion allows (``fr.jumped``,
        :meth:`_consistent`) is checked so too.

        From a prediction 3-20 cm off, the patches of a few near landmarks can lock onto the wrong edge while the far
        ones fit a pose anywhere along the translation-rotation valley they leave open, and a search can find a wrong
        place: the tests' site reported poses 11-31 cm off at 0.6-0.8 cm 1-sigma where the keypoints came within 0.5 cm,
        the office walk one 72 cm off (benchmarks/off_prediction.py, RESULTS stop 43)."""
        T = Pose(r[0].T, -r[0].T @ r[1])

        def agrees(c) -> bool:
            dt, dr = T.distance_to(Pose(c[0].T, -c[0].T @ c[1]))
            return dt <= self.cfg.confirm_m and dr <= self.cfg.confirm_deg

        k = self._track(fr, pred, self.cfg.coarse_radius_px, tm)  # (from that prediction too: it can lock on wrong)
        if self._good(k, fr) and agrees(k):
            return r
        c = self._relocalize(fr, tm)  # no prediction at all decides
        if self._good(c, fr):
            if agrees(c):
                return r
            log.debug("a patch pose from an untracked prediction disagrees with a relocalization: not kept")
            # after a jump from a tracked prediction, the tracked poses, the patches and the relocalization disagree
            # three ways: the view is ambiguous here, so the relocalization is tracked on from, not reported (narrow-lens
            # walk frame 160: patches 4.8 cm off, keypoints 4.4, the relocalization 6.6 at 0.4 cm 1-sigma)
            fr.relocalized, fr.unchecked = True, fr.jumped
            return c
        fr.reason, fr.unchecked = None, True  # (the relocalization's reason: the frame keeps its pose, unreported)
        return r

    def _consistent(self, r, pred: Pose, dt: float) -> bool:
        """Whether a pose aligned from the constant-velocity prediction ``pred`` is where the motion could have taken the
        camera (services.localize.innovation), as Render & Match's tracked poses must be. Further off, the pose
        corrected the track or slid off it."""
        ok, off, bound = within_motion(-r[0].T @ r[1], pred.t, r[4], self._sigma_last, dt, self.cfg.innovation_sigmas,
                                       self.cfg.innovation_accel_mps2)
        if not ok:
            log.debug("aligned pose %.1f cm from the prediction (bound %.1f cm): checked", 100 * off, 100 * bound)
        return ok

    def _spare(self, fr: _Frame, r):
        """The frame's tracking result, or its spare aligned solution (``fr.spare``) where that is more certain than a
        result that is not good either: still not reported, but tracked on from. After a whip pan the 960x540 walk's
        keypoint poses were 2-9 cm / 0.6-2.7 deg off (a poster and a plain box: 1-sigma 2-4 cm), while patches aligned
        from them came within ~1 cm / 0.25 deg at a 1-sigma just over the gates; tracking on from the keypoint pose,
        with a velocity made of its errors, lost frames 67-90."""
        s = fr.spare
        if s is None or self._good(r, fr):
            return r
        return s if not self._plausible(r) or (s[4] <= r[4] and s[5] <= r[5]) else r

    # ---- frame preparation -------------------------------------------------------------
    def _extractor(self, width: int) -> OrbExtractor:
        ex = self._extractors.get(width)
        if ex is None:
            o, cfg = self._orb, self.cfg
            cell = cfg.distribution_cell or max(3, round(12 * width / 640))
            ex = OrbExtractor(OrbSettings(scale_factor=o.scale_factor, num_levels=o.num_levels, ini_fast_threshold=o.ini_fast_threshold,
                                          min_fast_threshold=o.min_fast_threshold, max_keypoints=cfg.max_keypoints,
                                          distribution_cell=cell))
            self._extractors[width] = ex
        return ex

    def _frame(self, image: np.ndarray, camera: Camera) -> _Frame:
        if image.shape[0] != camera.height or image.shape[1] != camera.width:
            raise ValueError(f"image is {image.shape[1]}x{image.shape[0]} but the camera says {camera.width}x{camera.height}")
        coarse = max(1.0, math.degrees(1.0 / max(camera.fx, camera.fy)) / self.cfg.sigma_ref_px_deg)
        return _Frame(camera.K, camera.width, camera.height, image, camera, coarse)

    def _features(self, fr: _Frame, tm: dict) -> _Frame:
        """The frame's ORB keypoints (undistorted) and their search grid, extracted once."""
        if fr.feats is not None:
            return fr
        t0 = time.perf_counter()
        f = self._extractor(fr.width).extract(fr.image)
        pts = level_centres(f.kpts, f.octaves, self._orb.scale_factor)
        cam = fr.camera
        if cam.is_distorted and len(pts):
            uv = cv2.undistortPoints(pts.reshape(-1, 1, 2), fr.K, cam.dist, P=fr.K).reshape(-1, 2)
        else:
            uv = pts
        c, cap = self.cfg.cell_px, self.cfg.cell_capacity
        gw, gh = fr.width // c + 2, fr.height // c + 2
        # undistorted points may leave the image a little: shift by one cell
        cx = np.clip((uv[:, 0] // c).astype(np.int64) + 1, 0, gw - 1)
        cy = np.clip((uv[:, 1] // c).astype(np.int64) + 1, 0, gh - 1)
        cell = cy * gw + cx
        order = np.lexsort((-f.responses, cell))
        cs = cell[order]
        start = np.searchsorted(cs, cs, side="left")
        rank = np.arange(len(cs)) - start
        keep = rank < cap
        grid = -np.ones((gw * gh, cap), np.int64)
        grid[cs[keep], rank[keep]] = order[keep]
        fr.feats, fr.uv, fr.grid, fr.gw, fr.gh, fr.inv_sigma2 = f, uv, grid, gw, gh, self._inv_s2[f.octaves]
        tm["features_ms"] = tm.get("features_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        return fr

    # ---- local map -----------------------------------------------------------------------
    def _local(self, T_wc: Pose) -> np.ndarray:
        c = T_wc.t
        key = self._local_key
        if key is not None and np.linalg.norm(key[0] - c) < 0.25 and float(key[1] @ T_wc.R[:, 2]) > math.cos(math.radians(10)):
            return self._local_rows
        idx = self.idx
        d = np.linalg.norm(idx.kf_center - c, axis=1)
        near = np.flatnonzero((d < self.cfg.local_radius_m) & (idx.kf_axis @ T_wc.R[:, 2] > -0.2))
        if len(near) == 0:
            near = np.argsort(d)[:20]
        seen = np.zeros(len(idx.pos), bool)  # the union, sorted (np.unique hashes: 6 ms against 0.1 here)
        for i in near:
            seen[idx.kf_lms[i]] = True
        rows = np.flatnonzero(seen)
        self._local_key = (c.copy(), T_wc.R[:, 2].copy())
        self._local_rows = rows
        self._local_P = np.ascontiguousarray(idx.pos[rows])
        return rows

    def _visible(self, fr: _Frame, R: np.ndarray, t: np.ndarray, rows: np.ndarray, margin: float = -8.0):
        """The landmarks of ``rows`` the camera (R, t) sees: in front, projecting inside the image (``margin`` px in
        from its border; negative: outside), inside their scale range and within 60 degrees of their mean viewing
        direction. Returns those rows, their pixels (u, v) and distances."""
        idx = self.idx
        P = self._local_P if rows is self._local_rows else idx.pos[rows]
        # in front and inside the image first (cheap, removes most), then scale range and viewing angle
        z = P @ R[2] + t[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = np.where(z > 0.05, 1.0 / z, -1.0)
            u = fr.K[0, 0] * (P @ R[0] + t[0]) * iz + fr.K[0, 2]
            v = fr.K[1, 1] * (P @ R[1] + t[1]) * iz + fr.K[1, 2]
        m = margin
        sel = np.flatnonzero((iz > 0) & (u >= m) & (u < fr.width - m) & (v >= m) & (v < fr.height - m))
        PO = P[sel] - (-R.T @ t)
        rs = rows[sel]
        dist = np.sqrt(np.einsum("ij,ij->i", PO, PO))
        ok = (dist >= 0.7 * idx.min_dist[rs]) & (dist <= 1.3 * idx.max_dist[rs])
        ok &= np.einsum("ij,ij->i", PO, idx.normal[rs]) >= 0.5 * dist
        return rs[ok], u[sel][ok], v[sel][ok], dist[ok]

    # ---- projection matching ----------------------------------------------------------------
    def _match(self, fr: _Frame, R: np.ndarray, t: np.ndarray, rows: np.ndarray, radius: float,
               subsample: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Landmark rows and keypoint indices matched by projecting ``rows`` with world-to-camera (R, t); and the visible rows.

        ``subsample``: search only every n-th visible landmark (the first, wide-window pass needs a pose, not every match).
        """
        idx, cfg = self.idx, self.cfg
        visible, u, v, dist = self._visible(fr, R, t, rows)
        if len(visible) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), visible
        sel = np.arange(len(visible))[::subsample]
        rows, u, v, dist = visible[sel], u[sel], v[sel], dist[sel]
        pred_oct = np.clip(np.ceil(np.log(np.maximum(idx.max_dist[rows] / dist, 1e-9)) / idx.log_sf), 0, idx.num_levels - 1).astype(np.int64)
        r = np.minimum(radius * idx.scale_factor ** pred_oct, cfg.cell_px)
        c = cfg.cell_px
        cx = np.clip((u // c).astype(np.int64) + 1, 1, fr.gw - 2)
        cy = np.clip((v // c).astype(np.int64) + 1, 1, fr.gh - 2)
        cells = (cy[:, None] + np.array([-1, -1, -1, 0, 0, 0, 1, 1, 1])) * fr.gw + cx[:, None] + np.array([-1, 0, 1] * 3)
        cand = fr.grid[cells].reshape(len(rows), -1)  # (M, 9 * capacity)
        li, ci = np.nonzero(cand >= 0)
        kp = cand[li, ci]
        du = fr.uv[kp, 0] - u[li]
        dv = fr.uv[kp, 1] - v[li]
        ko = fr.feats.octaves[kp]
        m = (np.abs(du) <= r[li]) & (np.abs(dv) <= r[li]) & (ko >= pred_oct[li] - 1) & (ko <= pred_oct[li] + 1)
        li, kp = li[m], kp[m]
        if len(li) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), visible
        hd = hamming(idx.descs[rows[li]], fr.feats.desc[kp][:, None, :]).min(axis=1)
        order = np.lexsort((hd, li))
        li, kp, hd = li[order], kp[order], hd[order]
        first = np.r_[True, li[1:] != li[:-1]]
        fi = np.flatnonzero(first)
        best_hd = hd[fi]
        second = np.full(len(fi), 1 << 20)
        has2 = (fi + 1 < len(li))
        has2[has2] = ~first[fi[has2] + 1]
        second[has2] = hd[fi[has2] + 1]
        good = (best_hd <= cfg.max_hamming) & (best_hd < cfg.ratio * second)
        fi = fi[good]
        if len(fi) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), visible
        lm_i, kp_i, d_i = li[fi], kp[fi], hd[fi]
        # one landmark per keypoint: the closest descriptor
        o = np.lexsort((d_i, kp_i))
        lm_i, kp_i, d_i = lm_i[o], kp_i[o], d_i[o]
        u1 = np.r_[True, kp_i[1:] != kp_i[:-1]]
        lm_i, kp_i = lm_i[u1], kp_i[u1]
        # orientation consistency: the three strongest bins of the angle-difference histogram (as ORB-SLAM / stella)
        if len(kp_i) >= 10:
            da = (fr.feats.angles[kp_i] - idx.angle[rows[lm_i]]) % 360.0
            b = (da * (30 / 360.0)).astype(np.int64) % 30
            cnt = np.bincount(b, minlength=30)
            top = np.argsort(-cnt)[:3]
            keep = np.isin(b, top[cnt[top] >= 0.1 * cnt[top[0]]])
            lm_i, kp_i = lm_i[keep], kp_i[keep]
        return rows[lm_i], kp_i, visible

    # ---- pose optimisation ------------------------------------------------------------------
    def _optimize(self, fr: _Frame, R: np.ndarray, t: np.ndarray, rows: np.ndarray, kp: np.ndarray, rounds=(4, 3, 2)):
        """Motion-only Gauss-Newton on the keypoint matches (information 1 / scale^(2 octave) each), Huber
        weights, chi-square outlier rounds. Returns (R, t, inlier mask, rmse in level-0 pixels with each
        residual divided by its keypoint's pyramid scale)."""
        return solve_motion_only(self.idx.pos[rows], fr.uv[kp], _iso(fr.inv_sigma2[kp]), fr.K, R, t, rounds)

    @staticmethod
    def _covariance(fr: _Frame, R: np.ndarray, t: np.ndarray, P: np.ndarray, w: np.ndarray, rmse: float) -> tuple[float, float]:
        """Predicted 1-sigma camera-centre (m) and orientation (deg) uncertainty of a keypoint solution."""
        return cov_sigmas(pose_covariance(P, _iso(w), fr.K, R, t, rmse))

    def _track(self, fr: _Frame, T_wc_pred: Pose, coarse_radius: float, tm: dict) -> tuple[np.ndarray, np.ndarray, int, float] | None:
        self._features(fr, tm)
        t0 = time.perf_counter()
        rows = self._local(T_wc_pred)
        T_cw = T_wc_pred.inverse()
        R, t = T_cw.R.copy(), T_cw.t.copy()
        lm, kp, visible = self._match(fr, R, t, rows, coarse_radius, self.cfg.coarse_subsample)
        t1 = time.perf_counter()
        tm["match_ms"] = tm.get("match_ms", 0.0) + 1e3 * (t1 - t0)
        if len(lm) < 10:
            return None
        R, t, inl, _ = self._optimize(fr, R, t, lm, kp, rounds=(4, 2))
        t2 = time.perf_counter()
        tm["pose_ms"] = tm.get("pose_ms", 0.0) + 1e3 * (t2 - t1)
        if inl.sum() < 10:
            return None
        lm, kp, _ = self._match(fr, R, t, visible, self.cfg.fine_radius_px)
        t3 = time.perf_counter()
        tm["match_ms"] += 1e3 * (t3 - t2)
        if len(lm) < 10:
            return None
        R, t, inl, rmse = self._optimize(fr, R, t, lm, kp)
        sigma = self._covariance(fr, R, t, self.idx.pos[lm[inl]], fr.inv_sigma2[kp[inl]], rmse) if inl.sum() >= 6 \
            else (float("inf"), float("inf"))
        tm["pose_ms"] += 1e3 * (time.perf_counter() - t3)
        r = (R, t, int(inl.sum()), rmse, *sigma, False)
        k = self.cfg.align_sigma_factor
        if self.patches is not None and self.cfg.align and self._within(r, fr, k * self.cfg.max_sigma_m, k * self.cfg.max_sigma_deg):
            # the reported pose and its uncertainty come from the patch alignment; the keypoint solution's
            # inliers and RMSE still decide whether there is a pose to refine at all
            t4 = time.perf_counter()
            ra = self._aligned(fr, R, t, self._align_rows(fr, R, t, lm, kp, inl, visible))
            tm["align_ms"] = 1e3 * (time.perf_counter() - t4)
            if ra is not None:
                r = (ra[0], ra[1], *r[2:4], *ra[4:])  # aligned: judged by the aligned gates
        return r

    def _aligned(self, fr: _Frame, R: np.ndarray, t: np.ndarray, rows: np.ndarray, max_moved_px: float | None = 2.0,
                 blur: list | None = None) -> tuple | None:
        """The pose solved from landmarks ``rows`` (with patches) measured by aligning the live frame to their
        patches (:func:`services.localize.direct.align_and_solve`), as (R, t, inliers, whitened rmse, sigma_m,
        sigma_deg, True); None when that does not hold up. ``max_moved_px``: from a keypoint pose, the
        landmarks' projections may move at most this far (median; a larger move is a degenerate set)."""
        cfg = self.cfg
        dc = DirectConfig(passes=cfg.align_passes, sigma_px=cfg.align_sigma_px, rmse_floor=cfg.align_rmse_floor,
                          min_inliers=cfg.min_inliers // 2, min_inlier_frac=cfg.align_min_inlier_frac, max_moved_px=max_moved_px,
                          warp_noise_ref=cfg.warp_noise_ref, probe_sigmas=cfg.align_probe_sigmas)
        d = align_and_solve(self.patches, self._patch_of_row[rows], self._apos[rows], R, t, fr.K, self._gray(fr), dc, blur)
        return None if d is None else (d.R, d.t, d.inliers, d.rmse, d.sigma_m, d.sigma_deg, True)

    def _align_rows(self, fr: _Frame, R: np.ndarray, t: np.ndarray, lm: np.ndarray, kp: np.ndarray, inl: np.ndarray,
                    visible: np.ndarray) -> np.ndarray:
        """The landmarks to align: the keypoint inliers with patches (finest octaves first, at most ``align_max``),
        then up to ``align_extra`` more visible landmarks no keypoint matched (alignment needs no keypoint, so it
        measures landmarks ORB did not find again)."""
        pidx = self._patch_of_row[lm]
        sel = np.flatnonzero(inl & (pidx >= 0))
        sel = sel[np.argsort(fr.feats.octaves[kp[sel]], kind="stable")[: self.cfg.align_max]]
        rows = lm[sel]
        if self.cfg.align_extra <= 0 or len(visible) == 0:
            return rows
        return np.concatenate([rows, self._corners(fr, R, t, visible[~np.isin(visible, lm[inl])], self.cfg.align_extra)])

    def _blur_deltas(self, fr: _Frame, blur_px: float) -> list | None:
        """The camera's motion over the exposure as camera-frame deltas around the frame's pose, from the velocity
        (``exposure_s`` over the frame interval), when its blur ``blur_px``
        (:meth:`_blur_px`) smears ``blur_min_px`` or more."""
        if blur_px < self.cfg.blur_min_px * fr.width / 640:  # (0 without a velocity)
            return None
        ident = Pose.identity()
        e = fr.exposure_fraction
        n = 7  # odd: the frame's own pose is one of the samples
        out = []
        for f in np.linspace(-e / 2, e / 2, n):
            if abs(f) < 1e-9:
                continue
            D = ident.interpolate(self._vel, float(f)).inverse()  # T_cw(t + f) = exp(-f xi) T_cw(t)
            out.append((D.R, D.t))
        return out

    def _corners(self, fr: _Frame, R: np.ndarray, t: np.ndarray, rows: np.ndarray, n: int) -> np.ndarray:
        """Up to ``n`` of the landmarks ``rows`` to align: those with corner-like patches projecting 12 px inside the
        image, spread over it (the best patch of each 40 px cell first, then the second best of each, ...)."""
        pidx = self._patch_of_row[rows]
        rows = rows[pidx >= 0]
        rows = rows[self._corner[self._patch_of_row[rows]] >= self.cfg.align_min_corner]
        if len(rows) == 0 or n <= 0:
            return rows[:0]
        X = self._apos[rows] @ R.T + t
        z = np.maximum(X[:, 2], 1e-6)
        u = fr.K[0, 0] * X[:, 0] / z + fr.K[0, 2]
        v = fr.K[1, 1] * X[:, 1] / z + fr.K[1, 2]
        m = 12
        inside = (X[:, 2] > 0.1) & (u >= m) & (u < fr.width - m) & (v >= m) & (v < fr.height - m)
        rows, u, v = rows[inside], u[inside], v[inside]
        cell = (v // 40).astype(np.int64) * 1000 + (u // 40).astype(np.int64)
        score = self._corner[self._patch_of_row[rows]]
        o = np.lexsort((-score, cell))
        cs = cell[o]
        rank = np.arange(len(cs)) - np.searchsorted(cs, cs, side="left")
        o = o[np.argsort(rank, kind="stable")]
        return rows[o[:n]]

    def _corners_seen(self, fr: _Frame, T_wc: Pose, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The world-to-camera (R, t) of ``T_wc`` and up to ``n`` of the local landmarks it sees to align
        (:meth:`_corners`)."""
        T_cw = T_wc.inverse()
        R, t = T_cw.R.copy(), T_cw.t.copy()
        visible, _, _, _ = self._visible(fr, R, t, self._local(T_wc))
        return R, t, self._corners(fr, R, t, visible, n)

    def _direct(self, fr: _Frame, T_wc_pred: Pose, tm: dict, n: int | None = None):
        """Track without keypoints: align the frame to the patches of up to ``n`` (default ``direct_landmarks``)
        visible landmarks from the predicted pose and solve. Returns the aligned solution (as ``_aligned``) or None."""
        t0 = time.perf_counter()
        R, t, sel = self._corners_seen(fr, T_wc_pred, n or self.cfg.direct_landmarks)
        blur = self._blur_px(fr)
        r = self._aligned(fr, R, t, sel, max_moved_px=None, blur=self._blur_deltas(fr, blur))
        tm["direct_ms"] = tm.get("direct_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        b = blur / (self.cfg.blur_sigma_px * fr.width / 640)
        if r is not None and b > 1:
            r = (*r[:4], r[4] * b ** 0.5, r[5] * b ** 0.5, r[6])
        return r

    def _recentred(self, fr: _Frame, pred: Pose, tm: dict) -> Pose | None:
        """A pose to align from when the prediction is too far off for the windows (a turn that changed speed or
        direction since the last frame): landmarks' templates searched around their predicted projections
        (:func:`search_patches`), and PnP-RANSAC on what was found. None when too few are found or agree."""
        t0 = time.perf_counter()
        R, t, sel = self._corners_seen(fr, pred, self.cfg.search_landmarks)
        deltas = self._blur_deltas(fr, self._blur_px(fr))
        uv, found = search_patches(self.patches, self._patch_of_row[sel], self._apos[sel], R, t, fr.K, self._gray(fr),
                                   radius=int(round(self.cfg.search_radius_px * fr.width / 640)),
                                   blur=[(Rd @ R, Rd @ t + td) for Rd, td in deltas] if deltas else None)
        out = None
        if found.sum() >= self.cfg.search_min_found:
            T, n = _pnp_ransac(self._apos[sel[found]], uv[found], fr.K, 2.0, 200)
            out = T if n >= self.cfg.search_min_found else None
        tm["search_ms"] = 1e3 * (time.perf_counter() - t0)
        return out

    def _aligned_from(self, fr: _Frame, T_wc: Pose, near: bool, tm: dict):
        """The direct step (:meth:`_direct_retry`) from ``T_wc`` when it is ``near`` enough for the windows, else from
        where the patches searched around it (:meth:`_recentred`) put the camera; None when neither gives a good pose."""
        start = T_wc if near else (self._recentred(fr, T_wc, tm) if self.cfg.search_landmarks > 0 else None)
        return self._direct_retry(fr, start, tm) if start is not None else None

    def _blur_px(self, fr: _Frame) -> float:
        """The frame's predicted motion blur (frame pixels) from the velocity over the assumed exposure."""
        if self._vel is None or fr.exposure_fraction <= 0:
            return 0.0
        ident = Pose.identity()
        return blur_length_px(fr.camera, ident, ident.interpolate(self._vel, fr.exposure_fraction))

    def _scene_depth(self, T_wc: Pose, camera: Camera) -> np.ndarray | None:
        """How far the scene is over the frame of a camera at ``T_wc`` (rolling_shutter.depth_field of the local
        landmarks), for the share of a rolling shutter's skew that the camera's travel makes."""
        self._local(T_wc)
        return depth_field((self._local_P - T_wc.t) @ T_wc.R, camera)

    def _unrolled_again(self, image: np.ndarray, camera: Camera, fr: _Frame, r, move: Pose, dt: float, readout: float,
                        depth: np.ndarray | None, tm: dict):
        """A rolling-shutter frame unrolled with the motion model's last motion, tracked to ``r``: when the motion
        from the last pose to ``r`` turns at a rate that would move the frame's edge rows by over half a pixel more,
        it is unrolled again with that motion and aligned from ``r``. The motion model lags a pan that speeds up:
        office walk at 20 ms, frames 263-268 0.4-0.8 deg off; unrolled again, 270 -> 268 frames, 0.76 -> 0.70 cm,
        0.119 -> 0.092 deg. Returns (result, frame), the second round's when it holds."""
        T_wc = Pose(r[0].T, -r[0].T @ r[1])
        D = self.T_last.inverse() @ T_wc
        if not rate_changed(move, dt, D, dt, camera, readout):
            return r, fr
        fr2 = self._frame(image, camera)
        fr2.image = unroll_moving(image, camera, D, dt, readout, depth)
        r2 = self._direct_retry(fr2, T_wc, tm)
        return (r2, fr2) if self._plausible(r2) else (r, fr)

    def _gray(self, fr: _Frame) -> np.ndarray:
        """The frame in grey (float32), undistorted like its keypoints; computed once per frame."""
        if fr.gray is None:
            fr.gray = undistorted_gray(fr.image, fr.camera, self._undistort, self.cfg.denoise_above)
        return fr.gray

    def _plausible(self, r) -> bool:
        """Enough inliers with a small reprojection error: a pose to keep tracking from."""
        return r is not None and r[2] >= self.cfg.min_inliers and r[3] <= self.cfg.max_rmse_px

    def _good(self, r, fr: _Frame) -> bool:
        """Plausible and well constrained: a pose to report. An aligned solution answers to the gates we promise
        (``max_sigma_*``); a keypoint-only one only where alignment is off or impossible (a map without patches),
        to the looser ``kp_max_sigma_*``."""
        if r is not None and r[6]:
            return self._within(r, fr, self.cfg.max_sigma_m, self.cfg.max_sigma_deg)
        if self.patches is not None and self.cfg.align:  # alignment was possible but did not hold: only tracked from
            return False
        return self._within(r, fr, self.cfg.kp_max_sigma_m, self.cfg.kp_max_sigma_deg)

    def _within(self, r, fr: _Frame, sigma_m: float, sigma_deg: float) -> bool:
        """Plausible, with a predicted uncertainty within (``sigma_m``, ``sigma_deg``) x the camera's scale."""
        c = fr.coarse
        return self._plausible(r) and r[4] <= sigma_m * c and r[5] <= sigma_deg * c

    # ---- relocalization ------------------------------------------------------------------------
    def _votes(self, lm: np.ndarray) -> np.ndarray:
        """Per keyframe, how many of the landmarks ``lm`` it observes."""
        return np.bincount(self.idx.obs_kf[np.isin(self.idx.obs_lm, lm)], minlength=len(self.idx.kf_ids))

    def _places(self, fr: _Frame, q: np.ndarray, lm: np.ndarray, votes: np.ndarray) -> list[tuple[int, Pose]]:
        """Coarse poses from descriptor matches (frame keypoints ``q`` to landmarks ``lm``): the keyframes that observe
        most of the matched landmarks vote (``votes``, :meth:`_votes`), and each of the best-voted places (keyframes
        within 2 m) is solved by PnP-RANSAC from the matches to its landmarks. Returns (inliers, camera-to-world) per
        place tried."""
        idx, cfg = self.idx, self.cfg
        results: list[tuple[int, Pose]] = []
        tried_centers: list[np.ndarray] = []
        for k in np.argsort(-votes)[: 3 * cfg.reloc_keyframes]:
            if votes[k] < 5 or len(tried_centers) >= cfg.reloc_keyframes:
                break
            c = idx.kf_center[k]
            if any(np.linalg.norm(c - tc) < 0.5 for tc in tried_centers):
                continue
            tried_centers.append(c)
            near_kf = np.flatnonzero(np.linalg.norm(idx.kf_center - c, axis=1) < 2.0)
            near_lm = np.unique(np.concatenate([idx.kf_lms[i] for i in near_kf]))
            sel = np.isin(lm, near_lm)
            if sel.sum() < cfg.reloc_min_inliers:
                continue
            obj = idx.pos[lm[sel]].astype(np.float64)
            img = fr.uv[q[sel]].astype(np.float64)
            T, n = _pnp_ransac(obj, img, fr.K, cfg.reloc_ransac_px, 300)
            if n >= 6:
                results.append((n, T))
        return results

    def _voted_rows(self, votes: np.ndarray) -> np.ndarray:
        """The relocalization rows of the landmarks seen from within 2 m of the best-voted keyframes (``votes`` of a
        frame's first descriptor matches): where a second, cheaper kNN looks."""
        idx, cfg = self.idx, self.cfg
        top = [k for k in np.argsort(-votes)[: 3 * cfg.reloc_keyframes] if votes[k] >= 2]
        if not top:
            return idx._reloc_rows[:0]
        d = np.linalg.norm(idx.kf_center[:, None] - idx.kf_center[top][None], axis=2).min(1)
        near = np.unique(np.concatenate([idx.kf_lms[i] for i in np.flatnonzero(d < 2.0)]))
        return idx._reloc_rows[np.isin(idx._reloc_rows, near)]

    def _ratio_matches(self, desc: np.ndarray, q: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The frame's keypoints ``q`` whose nearest landmark among ``rows`` passes the relocalization's distance and
        ratio tests against the second nearest there: (keypoints, landmark rows)."""
        cfg = self.cfg
        best, d1, d2 = knn2_hamming(self.idx._bf, desc[q], self.idx.desc[rows])
        keep = (best >= 0) & (d1 <= cfg.reloc_max_hamming) & (d1 < cfg.reloc_ratio * d2)
        return q[keep], rows[best[keep]]

    def _relocalize(self, fr: _Frame, tm: dict):
        """A pose with no prior: descriptor matches to the map's landmarks, coarse poses of the places they vote for
        (:meth:`_places`), refused when two places fit about as well, then tracked from the best and aligned to its
        landmarks' patches. The result as :meth:`_track` gives it, or None with ``fr.reason`` saying why."""
        self._features(fr, tm)
        t0 = time.perf_counter()
        idx, cfg = self.idx, self.cfg
        fr.reason = f"no place in the map fits the frame: {len(fr.feats)} keypoints on the frame"
        everywhere = idx._reloc_rows if fr.near_rows is None else fr.near_rows  # (a hint: only the landmarks near it)
        if len(fr.feats) < 10 or len(everywhere) < 10:
            if fr.near_rows is not None:
                fr.reason = f"no place in the map near the given position: {len(everywhere)} landmarks within reach"
            return None
        # the strongest keypoints first: the kNN against every landmark is the cost of a relocalization. A frame no
        # place fits with them is matched with more, against the landmarks around the keyframes its matches voted for,
        # and those matches then against every landmark: people in front of the camera take many of the strongest
        # (benchmarks/occluders.py, two passers-by over 28 % of the frame: 236 -> 260 of 300 frames; all 1000 against
        # every landmark made a LOST frame on the 327 k-landmark warehouse map take 1.1 s instead of 0.6; this way 0.6)
        order = np.argsort(-fr.feats.responses)
        q, lm, done = np.zeros(0, np.int64), np.zeros(0, np.int64), 0
        rows, votes = everywhere, None
        for budget in (cfg.reloc_keypoints, cfg.reloc_keypoints_crowded):
            budget = min(budget, len(order))
            if budget <= done:
                break
            crowded = done > 0
            if crowded:
                rows = self._voted_rows(self._votes(lm) if votes is None else votes)
            qsel = order[done:budget]
            done = budget
            t1 = time.perf_counter()
            qsel, lsel = self._ratio_matches(fr.feats.desc, qsel, rows)
            if crowded and len(qsel):
                # distinct only among the voted places' landmarks is not distinct: a look-alike bay elsewhere holds the
                # same corners (survey-density warehouse: frame 313 matched a bay 28.6 m off this way and was tracked
                # there for 38 frames). Those matches face every landmark's ratio test too, as the first pass's did.
                qsel, lsel = self._ratio_matches(fr.feats.desc, qsel, everywhere)
            q, lm = np.concatenate([q, qsel]), np.concatenate([lm, lsel])
            tm["reloc_match_ms"] = tm.get("reloc_match_ms", 0.0) + 1e3 * (time.perf_counter() - t1)
            results, votes = [], None
            if len(q) >= cfg.reloc_min_inliers:
                votes = self._votes(lm)
                results = self._places(fr, q, lm, votes)
                if fr.near is not None:  # a caller's hint: no place where the camera cannot be (coarse: + 0.5 m)
                    results = [(n, T) for n, T in results if np.linalg.norm(T.t - fr.near[0]) <= fr.near[1] + 0.5]
            if results and max(n for n, _ in results) >= cfg.reloc_min_inliers:
                break
        tm["relocalize_ms"] = tm.get("relocalize_ms", 0.0) + 1e3 * (time.perf_counter() - t0)  # (twice when stretched)
        if len(q) < cfg.reloc_min_inliers:
            fr.reason = (f"no place in the map fits the frame: {len(q)} descriptor matches pass the ratio test, "
                         f"a place needs {cfg.reloc_min_inliers}")
            return None
        if not results or max(n for n, _ in results) < cfg.reloc_min_inliers:
            fr.reason = (f"too few inliers in the map: the best place has {max(n for n, _ in results)}, a pose needs "
                         f"{cfg.reloc_min_inliers}" if results else
                         f"no place in the map fits the frame: {len(q)} descriptor matches, but no group of "
                         f"keyframes holds {cfg.reloc_min_inliers} of them")
            return None
        n_best, T_wc = max(results, key=lambda nr: nr[0])
        # another place about as good, or several look-alikes far away: a repetitive site (services.relocalize.ambiguity)
        why = rival(T_wc, n_best, [(T, n, None) for n, T in results if T is not T_wc], cfg.reloc_ambiguity,
                    cfg.reloc_cold_ambiguity)
        if not why:
            return self._settle(fr, T_wc, n_best, tm)
        r = self._contest(fr, results, tm)
        if r is None:
            fr.reason = f"ambiguous place: {why}"
            fr.rivals = True
            log.info("relocalization %s", fr.reason)
        return r

    def _contest(self, fr: _Frame, results: list[tuple[int, Pose]], tm: dict):
        """Places whose descriptor matches fit the frame about as well (``results``: coarse PnP inliers, pose), told
        apart by tracking from each (:meth:`_settle`): the place whose pose is good to report, while every other's
        tracked pose is not plausible or holds under ``reloc_contest_share`` of its inliers. Every distinct place with
        ``reloc_cold_ambiguity`` x the best's coarse inliers is tracked from, at most ``reloc_contest`` of them; None
        when there are more, or when no place wins so (identical rack bays track alike: refused as before). Office cold
        frames 71 and 77: the right place had 28 and 37 coarse inliers, a place 4.3 m / 100 deg away 27 and 33."""
        cfg = self.cfg
        places: list[tuple[int, Pose]] = []
        n_best = max(n for n, _ in results)
        for n, T in sorted(results, key=lambda nr: -nr[0]):  # every place that made it ambiguous, or none
            if n >= cfg.reloc_cold_ambiguity * n_best and all(distinct(T, P) for _, P in places):
                places.append((n, T))
        if len(places) > cfg.reloc_contest:  # more look-alikes than are worth tracking from: a repetitive site
            return None
        tracked = [self._settle(fr, T, n, tm) for n, T in places]
        self._local_key = None
        good = [r for r in tracked if self._good(r, fr)]
        if len(good) != 1:
            return None
        win = good[0]
        if any(r is not win and self._plausible(r) and r[2] >= cfg.reloc_contest_share * win[2] for r in tracked):
            return None
        return win

    def _settle(self, fr: _Frame, T_wc: Pose, n_best: int, tm: dict):
        """The pose tracked from a relocalization's coarse place ``T_wc`` (``n_best`` PnP inliers): the landmarks
        around it matched in windows and their patches aligned, as from a tracking prediction. The result as
        :meth:`_track` gives it, not plausible with ``fr.reason`` saying why."""
        self._local_key = None
        r = self._track(fr, T_wc, self.cfg.coarse_radius_px, tm)
        if self._plausible(r) and not r[6] and self.patches is not None and self.cfg.align:
            # PnP from a few hundred descriptor matches starts coarse: once more from the keypoint solution,
            # whose matches (and uncertainty) are then those of a tracked frame, which alignment may refine
            r2 = self._track(fr, Pose(r[0].T, -r[0].T @ r[1]), self.cfg.fine_radius_px, tm)
            if self._plausible(r2):
                r = r2
        can_align = self.patches is not None and self.cfg.align and self.cfg.direct_landmarks > 0
        if self._plausible(r) and not self._good(r, fr) and can_align:
            # the keypoint pose is close but not sure: the direct step from it, as from a tracking prediction (cold
            # frames of the office walk: 6 of 11 failures were plausible keypoint poses of 39-84 inliers). Only from
            # within align_sigma_factor x the gates, as in tracking: from further, the windows settle on a
            # self-consistent wrong pose (office seed 5 frame 112, a brick wall through a doorway: a keypoint pose
            # 21 cm off at 11.5 cm sigma was aligned to one 19 cm / 1.4 deg off at 0.5 cm sigma, and reported).
            # From further the patches are searched first, as for a prediction that is off.
            k = self.cfg.align_sigma_factor
            near = self._within(r, fr, k * self.cfg.max_sigma_m, k * self.cfg.max_sigma_deg)
            rd = self._aligned_from(fr, Pose(r[0].T, -r[0].T @ r[1]), near, tm)
            if rd is not None:
                r = rd
        if not self._plausible(r) and can_align:
            # the keypoints did not hold the coarse pose: its landmarks' patches searched around it and aligned, as
            # when a tracking prediction is off (cold frames of the 90-degree-lens walk: 22 -> 27 of 40 relocalized)
            rd = self._aligned_from(fr, T_wc, False, tm)
            if rd is not None:
                r = rd
        if not self._plausible(r):
            fr.reason = f"no place in the map was confirmed: the best ({n_best} PnP inliers) did not track from its coarse pose"
        return r

    def _hinted(self, fr: _Frame, stamp: float | None) -> None:
        """With a caller's hint: where the camera can be now (``fr.near``: its radius grown by ``max_speed_mps`` since it
        was given) and the relocalization rows of the landmarks seen from keyframes within it, or from the nearest
        keyframe position when none is (``fr.near_rows``). Not wider: in a site of identical rack bays every landmark
        more is a look-alike for the ratio test (survey-density warehouse, 24 frames hinted within 1 m of the truth:
        7 relocalized so, 5 and 4 with the keyframes 1-3 m further too)."""
        if self._near is None:
            return
        pos, radius, s0, frames = self._near
        dt = max(0.0, stamp - s0) if s0 is not None and stamp is not None else frames / 30.0
        fr.near = (pos, radius + self.cfg.max_speed_mps * dt)
        idx = self.idx
        d = np.linalg.norm(idx.kf_center - pos, axis=1)
        kf = np.flatnonzero(d <= max(fr.near[1], d.min() if len(d) else 0.0))
        if len(kf) == 0:
            fr.near_rows = idx._reloc_rows[:0]
            return
        lms = np.unique(np.concatenate([idx.kf_lms[i] for i in kf]))
        fr.near_rows = idx._reloc_rows[np.isin(idx._reloc_rows, lms)]

    def _stretched(self, fr: _Frame) -> _Frame | None:
        """The frame for a second relocalization with its grey levels stretched (``reloc_stretch_*``), or None when they
        already span enough. Only ORB sees it: patch alignment is normalised per window."""
        cfg = self.cfg
        g = fr.image if fr.image.ndim == 2 else cv2.cvtColor(fr.image, cv2.COLOR_BGR2GRAY)
        lo, hi = np.percentile(g, (0.5, 99.5))
        if hi - lo >= cfg.reloc_stretch_below:
            return None
        gain = min(4.0, cfg.reloc_stretch_range / max(float(hi - lo), 1.0))
        img = np.clip((g.astype(np.float32) - float(lo)) * gain + 0.5, 0, 255).astype(np.uint8)
        return replace(fr, image=img, feats=None, uv=None, grid=None, inv_sigma2=None, reason=None)

    # ---- the frame loop ---------------------------------------------------------------------------
    def process(self, image: np.ndarray, camera: Camera, prior: Pose | None = None, motion: Pose | None = None,
                stamp: float | None = None, readout_s: float | None = None,
                near: tuple[np.ndarray, float] | None = None) -> PnlResult:
        """Localize one frame (grey or BGR uint8). ``prior``: a camera-to-world hint (server) for this frame.
        ``motion``: the camera's motion since the previous frame from the device's odometry (``T_prev^-1 @ T_now``):
        it predicts the frame, and carries the pose on through LOST frames for up to ``odometry_carry_s``
        (``stamp``: capture time in seconds, for that clock; frames/30 without). ``near``: (world position, radius m) the
        camera is within at this frame, roughly (a dock, an entrance): until a pose is reported, relocalization matches
        only the landmarks of keyframes as far from it as the camera can have gone since (``max_speed_mps``), so a
        look-alike place elsewhere neither takes the descriptor matches nor makes it ambiguous. Ignored while tracking."""
        tm: dict[str, float] = {}
        t_start = time.perf_counter()
        c_start = time.thread_time()
        fr = self._frame(image, camera)
        status = Status.TRACKING
        r = None
        dt = stamp - self._stamp if stamp is not None and self._stamp is not None and stamp > self._stamp else 1.0 / 30.0
        fr.exposure_fraction = min(1.0, self.cfg.exposure_s / dt)
        odometry = motion  # the device's, checked against the tracked motion; used only while it agrees
        motion = self.odometry.use(motion)
        self._stamp = stamp
        move = motion if motion is not None else (self._vel if self.cfg.use_velocity else None)
        readout = self.cfg.readout_s if readout_s is None else float(readout_s)  # (per frame: the service's clients)
        unrolled = readout > 0 and prior is None and self.T_last is not None and move is not None
        depth = self._scene_depth(self.T_last @ move, camera) if unrolled else None  # (where the motion leads)
        if unrolled:  # rows read while the camera moved: re-sampled into the middle row's view first
            fr.image = unroll_moving(fr.image, camera, move, dt, readout, depth)
        rs_settled = self.shutter.step(readout, unrolled, motion is not None)
        pred = prior
        if pred is None and self.T_last is not None:
            pred = self.T_last
            if motion is not None:  # the device's odometry: this frame's own motion (blur too)
                self._vel = motion
                pred = self.T_last @ motion
            elif self.cfg.use_velocity and self._vel is not None:
                pred = self.T_last @ self._vel  # T_wc(t) = T_wc(t-1) @ (T_c(t-2)c(t-1))
        if pred is not None:
            if self.patches is not None and self.cfg.align and self.cfg.direct_landmarks > 0:
                r = self._direct_retry(fr, pred, tm, spare=True)  # no ORB at all when the prediction is inside the windows' reach
                velocity = self._tracked and self._vel is not None and prior is None and motion is None
                fr.jumped = r is not None and velocity and not self._consistent(r, pred, dt)
                if r is None and self.cfg.search_landmarks > 0:  # too far off for the windows (a turn that changed)
                    found = self._recentred(fr, pred, tm)
                    if found is not None:
                        # the motion to the pose found predicts the frame's blur (with the last frame's, office seed
                        # 3 frames 213-214 were aligned 1.7-3.1 cm off at a predicted 0.4-0.5 cm)
                        if self.T_last is not None:
                            self._vel = self.T_last.inverse() @ found
                        r = self._direct_retry(fr, found, tm, spare=True)
                if r is not None and (fr.jumped or not (self._tracked and self._vel is not None and prior is None)):
                    r = self._checked(fr, r, pred, tm)
                    if fr.relocalized:
                        status = Status.RELOCALIZED
                        self.relocalizations += int(not fr.unchecked)  # (one not reported is no relocalization)
            if r is None:
                r = self._track(fr, pred, self.cfg.coarse_radius_px, tm)
            if prior is None and not self._plausible(r) and self._vel is not None:  # velocity model failed: from the last pose, wider
                r = self._track(fr, self.T_last, 2 * self.cfg.coarse_radius_px, tm)
            if self._plausible(r):  # (else relocalization first: it may find a pose to report)
                r = self._spare(fr, r)
        if unrolled and motion is None and self._plausible(r) and self.patches is not None:
            r, fr = self._unrolled_again(image, camera, fr, r, move, dt, readout, depth, tm)
        if near is not None and self.T_last is None:
            pos, radius = near_hint(near)
            if self._near is None or self._near[1] != radius or not np.array_equal(self._near[0], pos):
                self._near = (pos, radius, stamp, -1)  # (the same hint again keeps its clock)
        if self._near is not None:
            self._near = (*self._near[:3], self._near[3] + 1)  # frames since the hint (its clock without stamps)
        if not self._plausible(r):
            self._hinted(fr, stamp)
            r = self._relocalize(fr, tm)
            if not self._plausible(r) and (dim := self._stretched(fr)) is not None:
                r = self._relocalize(dim, tm)
                fr.reason = dim.reason and f"{dim.reason} (grey levels stretched)"
            if self._good(r, fr):
                status = Status.RELOCALIZED
                self.relocalizations += 1
            else:
                r = self._spare(fr, r)
        tm["total_ms"] = 1e3 * (time.perf_counter() - t_start)
        tm["cpu_ms"] = 1e3 * (time.thread_time() - c_start)  # this thread's CPU time: one core's cost on a busy machine
        if not self._plausible(r):
            # carried on by the odometry or, briefly, the last velocity (not reported), or dropped
            coast = motion is None and prior is None and self.cfg.use_velocity and self._vel is not None
            self._tracked = False
            self.T_last = self.carry.lost(pred if prior is None and (motion is not None or coast) else None, dt,
                                          self.cfg.velocity_carry_s if coast else None)
            if not coast or self.T_last is None:
                self._vel = None
            self._trusted()
            return PnlResult(Status.LOST, None, 0 if r is None else r[2], float("nan") if r is None else r[3], tm,
                             reason=fr.reason or "no pose", source=_source(r))
        R, t, n, rmse, sig_m, sig_deg, _ = r
        T_wc = Pose(R.T, -R.T @ t)
        self._sigma_last = sig_m
        if self.carry.tracked() and status == Status.TRACKING:  # tracked from a pose the odometry carried: re-acquired
            status = Status.RELOCALIZED
            self.relocalizations += int(self._good(r, fr))
        if self.T_last is not None and status == Status.TRACKING and not fr.jumped:  # (also weakly constrained: a fast pan keeps it)
            self._vel = self.T_last.inverse() @ T_wc
            if odometry is not None and self._good(r, fr):
                self.odometry.update(self._vel, odometry)
        else:
            self._vel = None
        unconfirmed = None
        if (self._good(r, fr) and rs_settled and status == Status.TRACKING and prior is None
                and 0 < self.cfg.confirm_after and (self.cfg.confirm_after <= self._unsure or self._slipped)):
            t0 = time.perf_counter()
            unconfirmed, unopposed = self._confirm(fr, T_wc)
            tm["confirm_ms"] = 1e3 * (time.perf_counter() - t0)
            self._unopposed = self._unopposed + 1 if unopposed else 0
            if unconfirmed is not None and 0 < self.cfg.confirm_unopposed <= self._unopposed:
                log.debug("a pose good for %d frames that no relocalization opposes: reported", self._unopposed)
                unconfirmed = None
        if fr.unchecked and self._good(r, fr):  # tracked on from, reported once a relocalization agrees with a later frame
            unconfirmed = ("pose away from where the motion leads, and a relocalization disagrees with it (tracked on "
                           "from the relocalization)" if fr.relocalized else
                           "pose tracked from an untracked prediction not confirmed (neither keypoints nor a relocalization give a pose)")
        self._tracked = status == Status.TRACKING and prior is None
        if unconfirmed is not None or not self._good(r, fr) or not rs_settled:  # not reported, but tracked from
            self.T_last = T_wc
            self._unsure += 1
            if not self._good(r, fr):  # (unopposed only while good in a row)
                self._unopposed = 0
            self._slipped |= fr.unchecked or not self._within(r, fr, self.cfg.confirm_beyond * self.cfg.max_sigma_m,
                                                               self.cfg.confirm_beyond * self.cfg.max_sigma_deg)
            if unconfirmed is not None:
                return PnlResult(Status.LOST, None, n, rmse, tm, sig_m, sig_deg, unconfirmed, _source(r))
            return PnlResult(Status.LOST, None, n, rmse, tm, sig_m, sig_deg,
                             f"pose too uncertain to report ({100 * sig_m:.1f} cm / {sig_deg:.2f} deg 1-sigma)"
                             if not self._good(r, fr) else NOT_UNDONE, _source(r))
        self.T_last, self._near = T_wc, None
        self._trusted()
        if self.cfg.scan_sigma_m:
            sig_m, sig_deg = with_scan_error(sig_m, sig_deg, *self._view_floor(T_wc))
        return PnlResult(status, T_wc, n, rmse, tm, sig_m, sig_deg, source=_source(r))

    def _view_floor(self, T_wc: Pose) -> tuple[float, float]:
        """(the stations' disagreement where its landmarks lie, their median depth) for the map's keyframe nearest
        ``T_wc`` among those looking its way: what :func:`with_scan_error` takes."""
        idx = self.idx
        if not len(idx.kf_center):
            return self.cfg.scan_sigma_m, float("nan")
        d = np.linalg.norm(idx.kf_center - T_wc.t, axis=1)
        d[idx.kf_axis @ T_wc.R[:, 2] < 0.7] += 1e3  # (any keyframe when none looks its way)
        k = int(np.argmin(d))
        if k not in self._kf_floor:
            kf = self.idx.map.keyframes[int(idx.kf_ids[k])].T_wc
            P = idx.pos[idx.kf_lms[k]]
            self._kf_floor[k] = (local_scan_sigma(self.cfg.scan_sigma_m, self.cfg.scan_grid, P),
                                 median_depth((P - kf.t) @ kf.R))
        return self._kf_floor[k]

    def _confirm(self, fr: _Frame, T_wc: Pose) -> tuple[str | None, bool]:
        """Whether a tracked pose ``T_wc`` after a run of poses too uncertain to report (``_unsure``) agrees with a
        relocalization of the frame: (None when it does, else why not; whether nothing opposes it: the relocalization
        found no place, neither rival places nor a pose elsewhere). Either can be the wrong one (a turn along a plain
        wall fits poses sliding along it: office seed 8 frame 282 tracked 55 cm off, frame 187 relocalized 18 cm off),
        so a disagreement, or no relocalization to agree, leaves the frame unreported, tracked on from its tracked
        pose, until ``confirm_unopposed`` good frames in a row went unopposed."""
        c = self._relocalize(fr, {})
        dt, dr = T_wc.distance_to(Pose(c[0].T, -c[0].T @ c[1])) if self._plausible(c) else (np.inf, np.inf)
        agrees = dt <= self.cfg.confirm_m and dr <= self.cfg.confirm_deg
        why = f"pose not confirmed after {self._unsure} uncertain frame{'s' * (self._unsure != 1)}"
        if not self._good(c, fr):  # unopposed: no place found at all, or one that agrees but too uncertain to report
            return (f"{why} (relocalization: {fr.reason or 'no pose to report'})",
                    not fr.rivals and (agrees or not self._plausible(c)))
        if agrees:
            return None, False
        return f"{why} (a relocalization is {100 * dt:.0f} cm / {dr:.1f} deg away)", False
