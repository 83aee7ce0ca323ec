"""Render & Match: drift-free camera tracking against renders of the scan.

Per frame: XFeat on the live frame; match against the features of a *keyframe render* (the scan
rendered at a recent pose with this frame's own intrinsics and distortion); back-project the
render's matched pixels into world points with the depth of the scan points around them (a plane
fitted within a few pixels, so keypoints between the points of a sparse render count; none on a
depth edge); PnP-RANSAC with non-linear refinement. Every measurement comes from the scan, so nothing drifts.

Work is reused: one render and its features serve several live frames while the camera stays
near the keyframe pose and matches stay plentiful; when the pose moves away (or matching
weakens) the scan is re-rendered at the new pose and the frame is matched once more, which also
refines its pose. Gates on inliers, reprojection error and the pose's predicted uncertainty turn weak
solutions into LOST, never a guess; a pose that is plausible (enough inliers, small error) but less
certain than promised is not reported, yet tracking continues from it, so a few weak frames in a fast
turn do not cost a relocalization. With no pose (first frame, after LOST) the relocalization database gives a coarse pose,
which a render at that pose refines before tracking starts; soon after a reported pose, where no database view places
the frame (a close-up that views a metre off barely share), views rendered on demand where the camera was heading
do. With the device's own odometry (``motion``) a LOST
frame's pose is carried on by it for a few seconds instead, unreported, and the next frame tracks from there.

Three things keep it accurate where a plain render-and-match is not:
- **Motion blur.** In a fast turn the live frame is blurred and its features move (measured: a
  2-3 px systematic shift, a third of the matches lost). With frame timestamps the tracker knows
  the camera's motion (constant velocity from the last two poses), so it blurs the keyframe render
  with that motion over the exposure time before extracting features. The exposure time comes
  from the caller (``exposure_s``), the config, or is calibrated on the first frames that move at
  least 20 px per frame interval (slower ones barely blur, so every candidate matches alike): each
  candidate exposure's share of the inliers is summed over 8 such frames and the peak refined by a
  parabola (office walks: 10.8-12.0 ms for the simulator's 12). Until then, 0.3 of the frame interval.
  Blurred matches still err more than their scatter says (measured on the office walks: the pose
  error is ~2x the predicted 1-sigma below 10 px of blur, 5-15x at 15-30 px), so the predicted
  uncertainty is scaled by blur / 5 px (of a 640-wide frame, i.e. 3.75 px at the 480 px XFeat sees)
  before the gate and on the wire. One reason: on a blurred frame XFeat's keypoints lie on its feature
  grid along the blur, so the pose stays where the render was. A frame blurred over ``blur_min_px`` is
  therefore matched against a render turned to where phase correlation with the blurred keyframe puts
  it (``_centered``), and its uncertainty scaled by the square root of that factor instead.
- **Keypoint bias between viewpoints.** XFeat places a keypoint by its network's 8-pixel cells, so
  the same corner seen from two poses a few pixels apart comes out shifted differently (measured:
  0.03 deg at a render from the very pose, 0.12-0.2 deg from any other, even with the simulator's
  perfect image and depth). Each match is therefore re-aligned by Lucas-Kanade: the render's patch
  around its keypoint is tracked into the live frame, starting at the matched live keypoint, and
  the pose is solved from where it lands (median 0.10 -> 0.05 deg over random offsets).
- **Feature poses err more than they say.** Against ground truth, poses solved from XFeat matches are 1.7-4.9 sigma
  off (office walks), direct ones (corner patches of the render aligned into the frame) 0.9-1.5 sigma. So a
  pose found by XFeat is aligned once more directly, starting from it: a direct pose that passes the gate
  replaces it; one that is only plausible is combined with it by their covariances (while tracking), the
  disagreement of the two added when it exceeds them (:func:`_fuse`).
- **Sparse scans.** Keypoints between the points of a sparse render get their depth from a plane
  fitted to the points around them (services/render/depth_sampling.py). Where most of a render is
  too far from any point even for that (far or grazing surfaces, views through a window) the keyframe
  is re-rendered at half resolution, where the same points cover the image, and the live frame is
  matched at that resolution too.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from services.features.matching import mutual_nn
from services.features.xfeat import Features, XFeatExtractor
from services.geometry.blur import blur_length_px, motion_blur_linear
from services.geometry.camera import Camera
from services.geometry.pnp import PnpResult, solve_pnp
from services.geometry.rolling_shutter import NOT_UNDONE, ShutterTrack, depth_field, rate_changed, unroll_moving
from services.geometry.se3 import Pose, yaw_sweep
from services.localize.agreement import structure_agreement
from services.localize.carry import OdometryCarry
from services.localize.innovation import within_motion
from services.localize.direct import DirectConfig, align_and_solve, undistorted_gray
from services.localize.odometry_check import OdometryCheck
from services.localize.scan_error import local_scan_sigma, with_scan_error
from services.localize.status import Status
from services.prebuild.patches import LandmarkPatches, corner_scores, sample_patches
from services.relocalize.ambiguity import FAR_M
from services.relocalize.database import DBConfig, RelocDB, view_features
from services.relocalize.hint import near_hint
from services.relocalize.reach import FloorPlan
from services.render.depth_sampling import invented_near, plane_normals, support_fraction

__all__ = ["Status", "RMConfig", "FrameResult", "RenderMatchTracker", "floor_plan", "normalised_gray", "phase_turn",
           "refine_matches_lk"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RMConfig:
    min_inliers: int = 40  # gate: fewer inliers -> LOST
    max_rmse_px: float = 1.5  # gate: inlier reprojection RMSE
    max_sigma_m: float = 0.01  # gate: predicted 1-sigma camera-centre uncertainty from the inlier geometry ...
    max_sigma_deg: float = 0.1  # ... and orientation: a pose less certain than the accuracy we promise is LOST ...
    sigma_ref_px_deg: float = 0.12  # ... for cameras whose pixels subtend up to this (VGA, 65 deg wide); coarser ones scale both
    scan_sigma_m: float = 0.0  # the scan's registration error (1-sigma), counted in the reported 1-sigma (scan_error.py)
    scan_grid: object = None  # ... and where on the site it lies (scan_error.DisagreementGrid): the error where it looks
    ransac_px: float = 2.0  # RANSAC inlier threshold
    match_cos: float = 0.82  # mutual-NN cosine threshold (XFeat's default)
    rerender_m: float = 0.15  # re-render when the pose is this far from the keyframe ...
    rerender_deg: float = 6.0  # ... or turned this much
    rerender_inlier_ratio: float = 0.4  # ... or inliers fell below this fraction of the keyframe's first match
    keyframe_supersample: int = 2  # keyframes are rendered at this many times their resolution and pooled
    #                               (Renderer.render's supersample): points land within half a pixel of this, not of a
    #                               pixel, and direct alignment from the render lands closer (office, at the truth:
    #                               0.25 -> 0.15 cm median; the sweep's office walk 0.28 -> 0.22 cm); 1 = off
    max_holes: float = 0.35  # a keyframe render with more pixels than this beyond depth_radius of any point is redone at half resolution ...
    coarse_levels: int = 2  # ... at most this many times (sparse scans, far surfaces, views through windows)
    reloc_candidates: int = 8  # database views (by global descriptor) solved for a coarse pose ...
    reloc_widen: int = 32  # ... or this many when none of those reaches the inliers a pose needs: the place's best view
    #                        may rank lower (office frame 143: 26 inliers in the top 8, 62 from a view ranked below)
    reloc_px_ratio: float = 2.5  # a relocalizing frame is matched to the database at most this many times the faces'
    #                              pixels per radian (XFeat matches poorly across larger scale changes: a 1280x720
    #                              frame matched at full size, 6x the 320 px faces, relocalized nowhere for 70 frames;
    #                              a VGA frame at the CPU's 480 px is 2.3x); 0 = the tracking scale
    reloc_top_k: int = 2048  # a cold relocalizing frame that no place fits with the extractor's keypoints (1024) is
    #                          searched and verified again with this many: people in front of the camera take many of
    #                          the strongest (benchmarks/occluders.py: two passers-by over 28 % of the frame; cold frame
    #                          0 had 18 inliers with its best view, not 177, and 31 with 2048)
    reloc_min_inliers: int = 30  # a database view's coarse pose needs this many inliers to be verified (rendered at and
    #                              matched again; false poses from a wrong view reach 10-40) ...
    reloc_weak_inliers: int = 12  # ... or this many while the camera cannot be further than reloc_weak_reach_m from where
    reloc_weak_reach_m: float = 1.0  # its last velocity leads (a close-up after a whip pan shares 12-25 with a view 1 m off;
    #                                  a weak pose elsewhere was an identical rack bay 2-4 m on, which verification confirms)
    reloc_verify: int = 2  # verify at most this many places per frame (the best-matching first) ...
    reloc_rival_verify: float = 0.5  # ... and, once one passed, the next when it has this fraction of its coarse inliers:
    #                                  two verified places are a repetitive site (identical rack bays 2 m apart)
    reloc_ambiguity: float = 0.8  # another place with this fraction of the best's inliers makes a relocalization ambiguous ...
    reloc_cold_ambiguity: float = 0.5  # ... or, when nothing says where the camera is (no recent pose), two places over
    #                                    2 m away with this fraction: a repetitive site (a cold warehouse frame matched a
    #                                    wrong aisle 12.8 m off with 39 inliers against six places' 20-23, verified it, 89
    #                                    inliers to the true place's 78, then searched near it for 30 s). One such place
    #                                    can be a chance solution (a small office: 28 against 55, turned 180 deg)
    max_speed_mps: float = 3.0  # a relocalization within anchor_s of the last reported pose searches only views this
    anchor_s: float = 30.0  # ... fast a camera could have got to (+1 m): no jumping to an identical aisle 40 m away
    max_accel_mps2: float = 3.0  # ... and, when its velocity then is known, accepts only a pose this close to where that
    reach_m: float = 0.3  # ... velocity leads (+ this): not the identical rack bay 2 m on (0.6 m after 0.4 s, 1.5 m after 0.9 s)
    hint_view_reach_m: float = 3.0  # with a caller's hint (process(near=...)): database views this much beyond where
    #                                 the camera can be are searched too (a view of the frame's wall may stand further off)
    reloc_check: int = 32  # a relocalization is refused when views ranked up to this hold a rival place ...
    reloc_check_fraction: float = 0.02  # ... or up to this fraction of the database, if more (warehouse at 1 m, 6180
    #                                     views: the top 32 held no rival of a pose 40 m off, the top 128 four) ...
    reloc_cold_check_fraction: float = 0.05  # ... or this fraction when nothing says where the camera is (no recent
    #                                          pose): survey-density warehouse, 480 px faces, cold frame 325 fitted an
    #                                          aisle 38 m off with 111 inliers; the top 33 views held one place with half
    #                                          that, the top 83 three (a periodic site), and the true place none
    reloc_refine_rounds: int = 2  # render-and-match rounds after a relocalization's coarse pose
    verify_renders_kept: int = 6  # renders of recent verifications kept while LOST, for the next frame's (_reusable);
    #                               ~2.5 MB each at 640x480 (a LOST server client holds up to ~15 MB more); 0 = none
    reloc_xfeat_sigma_t: float = 2.0  # a relocalized or re-acquired pose that no direct alignment replaced (XFeat's own) has its
    #                                  position 1-sigma taken this many times larger: XFeat poses err 1.7-4.9x their
    #                                  scatter, most along the view in far scenes (warehouse seed 3, aisles ~10 m deep:
    #                                  frames 370-371 relocalized 5.1-5.3 cm off at 0.5-0.7 cm 1-sigma; a render at the
    #                                  truth gave 0.8 cm, one 5 cm to the side 2.9 cm along the view). 1 = as solved
    reloc_min_agreement: float = 0.6  # a verified place over 2 m from the last known position (or found cold) whose
    #                                   render agrees with the frame less than this as a picture (services.localize.
    #                                   agreement: gradient correlation at 160 px) is refused, and is no rival either:
    #                                   the next aisle over on a floor of repeating texture gave 103-174 inliers, more
    #                                   than the true place, at 0.08-0.51; right poses score 0.76-1.0 on clean frames
    #                                   (office walks, dark and high-ISO copies, the warehouse), 0.28-0.59 with people
    #                                   over 28 % of the frame, 0.41 with a sign over half of it
    intensity_agreement: float = 0.75  # ... times this for a scan grey from the laser's intensity (no colour): its
    #                                    renders agree less with a photograph at the true pose (every 10th frame at
    #                                    the truth: office median 0.75 against 0.97 in colour, 10th percentile 0.58
    #                                    against 0.82; seed 8 0.80 against 0.93, 0.65 against 0.89; at a pose from the
    #                                    walk's other half 0.00 in all four, at most 0.14). Office cold 31 -> 36/40
    look_around_s: float = 2.0  # a LOST frame this soon after the last reported pose that no database view places is
    #                             matched to views rendered on demand where its last velocity leads, every way round
    #                             with its own camera (0 = off): the database's 90-degree faces at 1 m spacing and set
    #                             heights share 10-24 inliers with a close-up 0.5 m from a rack after a whip pan (office
    #                             walk frames 285-299), views with the frame's camera at its own height 40-70
    look_around_overlap: float = 0.7  # ... their yaw step, as a fraction of the frame's horizontal field of view
    look_around_step_m: float = 0.3  # ... rendered again once the camera is expected this far from where they were
    look_around_repeat: tuple[int, float, float] = (20, 0.1, 5.0)  # ... and a coarse pose among them with fewer inliers
    #                                 than reloc_min_inliers, but at least the first of these, is verified when the
    #                                 previous frame's best coarse pose among them lies within the second (metres) and
    #                                 third (degrees) of it: chance fits do not repeat from frame to frame, the right
    #                                 place does (office walk, the rack close-up after the whip pan, frames 286-295:
    #                                 25-29 inliers a frame, every one 1-3.5 cm / 0.7-1.9 deg from the truth)
    velocity_window_s: float = 0.3  # the velocity a LOST frame's search follows: the mean over the poses reported this
    #                                 long before (s), not the last step alone (two poses 33 ms apart, each 0.3 cm
    #                                 off, give a velocity 0.1-0.3 m/s off, carried for up to look_around_s)
    gap_motion_s: float = 0.5  # after a relocalization this soon after the last good pose, assume the motion between them
    recover_s: float = 1.5  # after LOST, first try to re-acquire at the last good pose for this long (s; frames/30 without stamps)
    odometry_carry_s: float = 5.0  # with the device's odometry (``motion``), a LOST frame's pose is carried on by it for up to
    #                                this long and the next frame tracks from it (a whip pan does not cost the track)
    depth_radius: int = 4  # render pixels: a keypoint's depth is a plane fitted to the scan points this close ...
    depth_max_residual: float = 0.01  # ... all within this fraction of their depth of it (a depth edge is refused)
    exposure_s: float | None = None  # camera exposure time; None: per frame from the caller, else calibrated
    blur_min_px: float = 8.0  # blur the keyframe render when the frame's predicted blur exceeds this (frame pixels)
    blur_center: bool = True  # a frame blurred that much is matched against a render turned to where phase correlation
    #                           puts it: XFeat's keypoints on a blurred image lie on the feature grid along the blur, so
    #                           the pose stays where the render was (benchmarks/blur_bias.py: a render 0.3 deg off the
    #                           truth gave poses 0.2-0.5 deg off along the turn; phase correlation read the 0.3 to 0.04)
    center_min_response: float = 0.5  # ... when its peak is this clear (0.87-0.92 at 10-17 px of blur, 0.39 at 37 px
    #                                   where its reading was 0.26 deg off) ...
    center_max_deg: float = 3.0  # ... and the turn it reads is at most this (more is a wrong peak or a wild prediction)
    centred_blur_power: float = 1.0  # a centred frame's XFeat covariance grows as (blur / blur_sigma_px)^this, not ^2:
    #                                  centred, frames blurred 10-17 px erred 0.03-0.08 deg where ^2 said 0.12-0.23 (one
    #                                  step from the true poses before); ^1 without centring let seed 8's walk report
    #                                  frames 0.3-0.7 deg off (0.45 cm / 0.107 deg RMSE)
    exposure_prior: float = 0.3  # exposure / frame interval assumed until calibrated (indoor video: ~10 ms at 30 fps)
    calib_min_px: float = 20.0  # frames moving at least this much per frame interval calibrate the exposure ...
    calib_frames: int = 8  # ... until this many have
    calib_min_frames: int = 3  # the calibrated exposure replaces exposure_prior once this many frames have scored: one or
    #                            two fast frames alone pick 0 or the whole interval (office seed 61: 0 ms twice; with its
    #                            keyframes at another resolution, 33 ms, truly 12, and the 30 frames after it read 3x their
    #                            blur and were too uncertain to report). The sweep: +22 frames over 10 walks (stop 58)
    calib_fractions: tuple[float, ...] = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0)  # exposure candidates, x frame interval
    blur_sigma_px: float = 3.75  # a frame blurred more than this (pixels as XFeat sees them: 5 px of a 640-wide frame) has its uncertainty scaled by blur / this
    track_sigma_factor: float = 3.0  # a pose up to this many times less certain than the gate is not reported but tracked from
    innovation_sigmas: float = 4.0  # a tracked pose further from the constant-velocity prediction than this many sigmas
    innovation_accel_mps2: float = 20.0  # ... plus this acceleration's a*dt^2/2 is not reported (tracked from, as above):
    #                                      a wrong XFeat pose, office seed 2 frame 138, 61 inliers, was 5 cm off at a
    #                                      predicted 0.5 cm, and 5 cm from where the last two tracked frames led
    ransac_min_iterations: int = 100  # while tracking (relocalization keeps poselib's 1000)
    lk_window: int = 15  # patch (pixels at the render's resolution) re-aligning each match by Lucas-Kanade; 0 = off
    lk_max_px: float = 2.0  # a match whose patch lands further than this from its keypoint keeps the keypoint ...
    lk_motion_px: float = 4.0  # ... plus, while tracking, as far as the predicted motion since the keyframe moves the
    #                           image, up to this (_image_motion_px): on weak texture (carpet, plaster) XFeat keypoints
    #                           keep to their 8x8 cells in render and frame alike, so a reused keyframe's matches say the
    #                           camera has not moved since it, and the true place lies beyond 2 px (office seed 8 after
    #                           its desk was taken away: poses stuck to a keyframe 5 frames old, 5-7 cm / 0.84 deg off)
    direct_points: int = 300  # tracking first aligns the frame to this many corner patches of the keyframe render
    #                           from the prediction (no XFeat on the frame); 0 = off (see _direct). 300, not 150: in
    #                           a fast turn's blur only some converge (whip pan with odometry: 20 of 30 frames
    #                           reported instead of 11), and the walks gained 1-19 frames on 7 of 10 benchmark runs
    direct_min_inliers: int = 60  # a direct pose needs this many aligned patches, else features decide (with 40-45 of
    #                              150 it slid 1-5 cm over 4 frames at a predicted 0.6 cm, office seed 2)
    match_sigma_scale: float = 1.0  # XFeat poses' covariance x this^2: against ground truth their errors run ~2 sigma (direct
    #                                 poses' ~1); 2 halves the RMSE on office seeds 2-3 but reports a quarter fewer frames
    denoise_above: float = float("inf")  # smooth a frame noisier than this (direct.noise_ratio) before the render's patches
    #                              are aligned to it, as P&L does at 0.06. Off: XFeat takes over where the alignment fails,
    #                              and at 0.06 six dark and high-ISO copies of the office walk gave 880 frames instead of
    #                              877 of 900 but the high-ISO ones 0.48-0.54 cm instead of 0.42-0.44 (benchmarks/photometric.py)
    direct_blur_power: float = 1.0  # a direct pose's covariance grows as (blur / blur_sigma_px)^this (XFeat's: ^2)
    direct_min_corner: float = 0.2  # those patches' corner score (0 edge or flat .. 0.5 isotropic corner)
    direct_hole_px: float = 2.0  # those patches only where no hole wider than twice this (px at 480 wide) lies within
    #                              8 px (services.render.depth_sampling.invented_near), unless that leaves too few:
    #                              hole filling's colours there are made up (warehouse seed 3, frames 496-515 aligned
    #                              at the truth: a rack's panel grown over the boxes behind it, which the scanner never
    #                              saw; 3.1 -> 1.1 cm median; 960x540 walk 0.35 -> 0.32, office 0.15 -> 0.15 cm)
    direct_check: float = 0.4  # a direct pose less certain than this fraction of the report gate is checked by XFeat
    direct_check_xfeat_scale: float = 2.0  # ... whose 1 sigma is taken this many times larger there
    direct_probe_sigmas: float = 10.0  # a direct pose's basin is tested from this many sigmas off (direct._probed)
    direct_corner_quality: tuple[float, ...] = (0.005, 0.002)  # corner strength, relative to the render's strongest, for
    #                                     those patches; the next only when the first leaves fewer than direct_min_inliers
    #                                     (a close-up render: a few strong label edges outshine the rest)
    reloc_sharp_px: float = 4.0  # a relocalizing frame whose blur reads under this (frame px, _reloc_blur) takes a good
    #                              direct pose from the pose found even where the two disagree: its patches, cut
    #                              sharp, model it (a blurred one's did not: stop 44), and XFeat's poses err 2-3x their
    #                              1-sigma where direct ones err ~1x. Else the two disagreeing hold the frame back
    #                              (_polish). Cold: seeds 8 / 90 23 -> 25, 22 -> 23 of 40; walks +5 frames (stop 68)
    direct_drop_missed: bool = True  # a keyframe patch whose alignment missed a sharp frame's good direct pose grossly
    #                                  (direct._gross) is not aligned again on that keyframe: what it shows moved or went
    #                                  since the scan (RenderMatchTracker._direct; changed seed 8's frame 5.2 cm off
    #                                  gone, three changed walks +12 frames, eight unchanged ones -2: stop 71)
    direct_edge_retry: bool = True  # and where the corners were enough to try but give no pose, the frame is aligned
    #                                 again with the edge-like patches too: a sparse scan's plain walls left 62-111
    #                                 corners that did not align, and XFeat's poses there (0.24 deg RMSE, ~2-3x their
    #                                 1-sigma) carried office seed 61 to 0.099 deg; twelve walks +38 frames, rotation
    #                                 RMSE down on nine (seed 61 0.087, changed seed 8 0.107 -> 0.084 deg: stop 68)
    reloc_track_unsure: bool = True  # a place a relocalization's render confirms, passing every check but too uncertain
    #                                  to report (a blurred frame, a plain view), is not reported but kept as a last good
    #                                  pose is: the next frame is rendered at it and matched again (re-acquired, polished
    #                                  and checked as a relocalization) before the database is searched once more (office
    #                                  seed 2 frames 251-259 were each found again at 0.11-0.20 deg 1-sigma and LOST).
    #                                  Tracking on from it instead reported frames 0.15-0.2 deg off at 0.06 (stop 69)
    direct_edge_corner: float = 0.1  # and when both leave too few, patches down to this corner score: edges count too
    #                                  (the alignment weighs each by its gradients, so an edge still fixes where it lies
    #                                  across itself). Only then: on every render they cost office frames 0.033 -> 0.042
    #                                  deg and put a warehouse pose 4.1 cm off at 0.7 cm 1-sigma (benchmarks/RESULTS.md
    #                                  stop 63); as a last level, the 0.3-deg scan's plain walls 250 -> 257 frames,
    #                                  0.119 -> 0.112 deg, seeds 2 / 8 +4 / -1 frames (seed 8's worst pose 3.9 -> 1.9
    #                                  cm), five more walks the same to the frame. 0 = off
    blur_probe_px: tuple[float, ...] = (0, 4, 8, 12, 16, 24, 32, 48)  # blur lengths (px at 640 wide) tried on the render
    #                                     at a relocalized pose to read the frame's blur from the image; () = off
    blur_probe_gain: float = 0.05  # ... the best length counts when it removes this share of the sharp render's misfit
    #                                (1 - correlation); a smaller gain is render noise smoothed away
    readout_s: float = 0.0  # rolling shutter: the camera reads its rows top to bottom over this long (phones 10-30 ms;
    #                         0 = global shutter). A frame with a motion to predict it is re-sampled as if read at its
    #                         middle row's time (services.geometry.rolling_shutter; office walk at 20 ms: see RESULTS)


@dataclass
class Keyframe:
    T_wc: Pose
    frame_camera: Camera  # the live camera this keyframe serves
    scale: float  # render resolution relative to the live frame (the live frame is matched at it)
    render: object  # services.render.renderer.Render
    feats: Features | None  # only keypoints with measured, smooth depth (None until first needed: see _sharp_points)
    xyz: np.ndarray | None  # (N, 3) world points of those keypoints
    gray: np.ndarray | None = None  # the render in normalised grey (Lucas-Kanade's template)
    ref_inliers: int = 0
    blurred_img: tuple | None = None  # (start pose, end pose, grey image) of the last blurred render
    blurred: tuple | None = None  # (features, world points, normalised grey) of that blurred render
    direct: dict = field(default_factory=dict)  # edges? -> (LandmarkPatches, world points, render pixels, edges taken):
    #                                             corner patches for direct tracking (edges: the edge-like ones too)
    direct_blurred: dict = field(default_factory=dict)  # edges? -> the same patches cut from the blurred render
    direct_missed: dict = field(default_factory=dict)  # edges? -> (N,) bool: patches a sharp frame's good pose found
    #                                                    aligned grossly off it, no longer aligned (direct_drop_missed)
    scene_points: np.ndarray | None = None  # world points of the render's measured depth (RenderMatchTracker._scene_depth)
    depth_m: float | None = None  # median measured depth of the render (the scan's error in the reported 1-sigma) ...
    scan_sigma_m: float | None = None  # ... and the stations' disagreement where it looks (scan_error.local_scan_sigma)


@dataclass
class _Anchor:
    """Where the camera was last known to be, for a relocalization that follows: the last reported pose (1 m) or a
    caller's hint (``process(near=...)``); it widens by ``max_speed_mps`` a second, for ``anchor_s``."""

    position: np.ndarray  # world (3,)
    stamp: float | None  # when (None: a hint given with no clock yet)
    velocity: np.ndarray | None  # world velocity then, when tracked (tightens the reach)
    radius: float
    hint: bool = False
    confirmed: bool = True  # False: a pose found with nothing to say where the camera was (a cold relocalization) that
    #                         no tracked frame has followed yet. A later relocalization searches the whole database
    #                         then, not near it: in a site of look-alike aisles a cold frame can fit the wrong one, and
    #                         searched near it, later frames found the look-alike again (warehouse seed 3: frame 17
    #                         relocalized 12.8 m off and LOST after it; frame 289, searched near it, 17.1 m off and
    #                         tracked there for 77 frames)


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
    blur_px: float = 0.0  # predicted motion blur of the frame (pixels) the render was blurred with
    reason: str | None = None  # why a LOST frame has no pose (an ambiguous place, too uncertain a pose, ...)
    source: str | None = None  # what solved the pose (PnpResult.source: "features", "direct", "fused"); None: no pose


def _parabolic_peak(x: np.ndarray, y: np.ndarray) -> float:
    """Where the parabola through the highest of the samples ``(x, y)`` and its two neighbours peaks
    (clipped to them); the best sample itself at either end."""
    i = int(np.argmax(y))
    if i == 0 or i == len(x) - 1:
        return float(x[i])
    (x0, x1, x2), (y0, y1, y2) = x[i - 1:i + 2], y[i - 1:i + 2]
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / den
    if a >= 0:
        return float(x1)
    return float(np.clip(-b / (2 * a), x0, x2))


def floor_plan(renderer) -> FloorPlan:
    """The floor plan of the renderer's scan (services.relocalize.reach): ~1.3 s for 6 M points, at most 4 M used."""
    t0 = time.perf_counter()
    cloud = renderer.cloud
    xyz = cloud.xyz
    if not isinstance(xyz, np.ndarray):  # on a torch device: every n-th point to the host
        xyz = xyz[::max(1, len(cloud) // 4_000_000)].cpu().numpy()
    plan = FloorPlan.from_points(xyz, cloud.origin)
    log.info("floor plan of the scan: %d x %d cells of %.1f m in %.2f s", *plan.blocked.shape[::-1], plan.cell,
             time.perf_counter() - t0)
    return plan


def normalised_gray(image: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
    """uint8 grey (the channel mean, as XFeat sees it: any channel order) with the image's mean and
    contrast normalised (render and live frame differ in exposure and white balance), resized to
    ``size`` = (width, height) when given."""
    if size is not None and (image.shape[1], image.shape[0]) != size:
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    g = image if image.ndim == 2 else cv2.transform(image, np.full((1, 3), 1 / 3))
    mean, std = cv2.meanStdDev(g)
    a = 50.0 / (float(std[0, 0]) + 1e-6)
    return cv2.addWeighted(g, a, g, 0.0, 128.0 - a * float(mean[0, 0]))  # saturates to uint8


def phase_turn(render_gray: np.ndarray, live_gray: np.ndarray, camera: Camera) -> tuple[np.ndarray, float]:
    """The turn (camera-frame rotation vector, radians, about x and y) from the view rendered as ``render_gray`` to the
    one ``live_gray`` shows (both grey, the same size; ``camera``: the render's), read from their global image shift by
    phase correlation, and the peak's response (near 1: one clean shift). A blurred frame's pose stays where its render
    was along the blur (see ``RenderMatchTracker._centered``); this reads where the frame is from the content."""
    h, w = render_gray.shape
    (dx, dy), response = cv2.phaseCorrelate(render_gray.astype(np.float32), live_gray.astype(np.float32),
                                            cv2.createHanningWindow((w, h), cv2.CV_32F))
    return np.array([np.arctan(dy / camera.fy), -np.arctan(dx / camera.fx), 0.0]), float(response)


def refine_matches_lk(template: np.ndarray, target: np.ndarray, uv_template: np.ndarray, uv_target: np.ndarray,
                      window: int, max_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Track each ``template`` patch at ``uv_template`` into ``target``, starting at ``uv_target``
    (both in their images' pixels, same size). Returns the refined target points and a mask of those
    that converged within ``max_px`` of where they started on a well-conditioned patch (not an edge,
    where Lucas-Kanade slides along it). One pyramid level and few iterations: the matches start
    within a pixel or two, and a longer search only finds a wrong texture."""
    if len(uv_template) == 0:
        return uv_target.astype(np.float64), np.zeros(0, bool)
    p0 = np.ascontiguousarray(uv_template, np.float32).reshape(-1, 1, 2)
    p1 = np.ascontiguousarray(uv_target, np.float32).reshape(-1, 1, 2)
    q, st, _ = cv2.calcOpticalFlowPyrLK(template, target, p0, p1.copy(), winSize=(window, window), maxLevel=0,
                                        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.01),
                                        flags=cv2.OPTFLOW_USE_INITIAL_FLOW, minEigThreshold=1e-3)
    q = q.reshape(-1, 2).astype(np.float64)
    ok = (st.ravel() == 1) & (np.linalg.norm(q - p1.reshape(-1, 2), axis=1) <= max_px)
    return q, ok


def _image_motion_px(camera: Camera, a: Pose, b: Pose, X: np.ndarray) -> float:
    """Median distance (frame pixels) the world points ``X`` move in the image between poses ``a`` and ``b``."""
    if len(X) == 0:
        return 0.0
    A, B = a.inverse(), b.inverse()
    pa, za = camera.project(X @ A.R.T + A.t)
    pb, zb = camera.project(X @ B.R.T + B.t)
    ok = (za > 0) & (zb > 0)
    return float(np.median(np.linalg.norm(pa[ok] - pb[ok], axis=1))) if ok.any() else 0.0


@dataclass
class _Frame:
    """What one ``process`` call knows about its frame."""

    image: np.ndarray
    camera: Camera
    tm: dict
    motion: tuple[Pose, float] | None  # camera motion (T_prev^-1 T_last) over dt seconds, for blur
    dt_next: float  # seconds since the last localized frame
    exposure_s: float | None
    live: dict = field(default_factory=dict)  # scale -> (keypoint budget, Features)
    top_k: int | None = None  # keypoints matched on this frame (None: the extractor's; more for a crowded cold frame)
    gray: dict = field(default_factory=dict)  # (width, height) -> the live frame in normalised grey at that size
    relocalizing: bool = False
    reason: str | None = None  # why this frame has no pose, when it has none
    stamp: float | None = None  # capture time (s), when the caller gives it
    centred: bool = False  # matched against a render turned to where phase correlation put the blurred frame
    best_coarse: PnpResult | None = None  # the best coarse pose of the last relocalization search
    blur_read_px: float | None = None  # a relocalizing frame's blur as read from the image (_reloc_blur), frame pixels


CHI2_6DOF_1PCT = 16.81  # two pose estimates disagree beyond this chi-square (6 dof, 1 %)


def _fuse(a: PnpResult, b: PnpResult, inflate: bool = True) -> PnpResult:
    """Two estimates of one pose combined by their information (covariances of right perturbations, as
    PnpResult keeps them), ``a``'s inliers and error kept. Where they disagree beyond their covariances
    (chi-square, 6 dof, 1 %), the disagreement is added to the result's covariance (``inflate``): one of them is
    wrong, and the gate should see it."""
    if a.cov is None or b.cov is None or not (np.all(np.isfinite(a.cov)) and np.all(np.isfinite(b.cov))):
        return a
    Ra = a.T_wc.R
    d = _difference(a, b)
    try:
        Ia, Ib = np.linalg.inv(a.cov), np.linalg.inv(b.cov)
        C = np.linalg.inv(Ia + Ib)
        chi2 = _chi2(a, b, d)
    except np.linalg.LinAlgError:
        return a
    x = C @ Ib @ d
    T = Pose(Ra @ Pose.from_rotvec_t(x[3:], np.zeros(3)).R, a.T_wc.t + Ra @ x[:3])
    if inflate and chi2 > CHI2_6DOF_1PCT:
        C = C + np.outer(d, d)
    return dataclasses.replace(a, T_wc=T, cov=C, source="fused")


def _difference(a: PnpResult, b: PnpResult) -> np.ndarray:
    """``b``'s pose as a right perturbation of ``a``'s (translation, rotation vector), as the covariances are."""
    Ra = a.T_wc.R
    return np.concatenate([Ra.T @ (b.T_wc.t - a.T_wc.t), Pose(Ra.T @ b.T_wc.R, np.zeros(3)).rotvec()])


def _chi2(a: PnpResult, b: PnpResult, d: np.ndarray) -> float:
    """Chi-square of the difference ``d`` (``_difference(a, b)``) under both covariances."""
    return float(d @ np.linalg.solve(a.cov + b.cov, d))


def _agree(a: PnpResult, b: PnpResult) -> bool:
    """Whether two estimates of one pose agree within their covariances (the test ``_fuse`` makes)."""
    if a.cov is None or b.cov is None:
        return True
    try:
        return _chi2(a, b, _difference(a, b)) <= CHI2_6DOF_1PCT
    except np.linalg.LinAlgError:
        return True


class RenderMatchTracker:
    def __init__(self, renderer, extractor: XFeatExtractor, db=None, cfg: RMConfig = RMConfig(),
                 plan: FloorPlan | None = None):
        self.renderer = renderer
        self.extractor = extractor
        self.db = db
        self.cfg = cfg
        dev = getattr(extractor, "device", None)  # descriptors are matched on the extractor's GPU, if it has one
        self.match_device = dev if str(dev).startswith("cuda") else None
        if db is not None:
            db.match_device = self.match_device
        self._plan = plan  # the scan's obstacles, for where a camera can have walked (shared by a server's trackers)
        # a far or cold relocalization's render must agree with the frame this well (less for a scan in intensity)
        self.min_agreement = cfg.reloc_min_agreement * (
            cfg.intensity_agreement if getattr(renderer, "intensity_share", 0.0) > 0.5 else 1.0)
        self.relocalizations = 0
        # exposure calibration: per candidate (fraction of the frame interval) the summed share of inliers it got
        self.calib_scores = np.zeros(len(cfg.calib_fractions))
        self.calib_intervals: list[float] = []
        self._undistort: dict = {}
        self.reset()

    def reset(self) -> None:
        """Forget the track (the next frame relocalizes from the database)."""
        self._lose()
        self.recent: tuple[Pose, float | None] | None = None  # last good pose and its stamp, kept while LOST
        self.anchor: _Anchor | None = None  # where the camera was last known to be (a reported pose or a caller's hint)
        self.trail: list[tuple[float, np.ndarray]] = []  # (stamp, position) of the poses reported within velocity_window_s
        self.recover_kf: Keyframe | None = None  # a render at ``recent`` (valid while its pose is recent's), reused while re-acquiring
        self.verify_kfs: list[Keyframe] = []  # renders made to verify relocalizations while LOST (newest last; _reusable)
        self.around: tuple[np.ndarray, Camera, RelocDB] | None = None  # views rendered by _look_around: (where, for which camera, them)
        self.around_best: tuple[float, Pose] | None = None  # the best coarse pose among them for this frame: (stamp, pose)
        self.around_prev: tuple[float, Pose] | None = None  # ... and for the frame before
        self.lost_frames = 0
        self.shutter = ShutterTrack()  # whether a rolling shutter's frames may be reported yet
        self.carry = OdometryCarry(self.cfg.odometry_carry_s)  # ``T_last`` carried through LOST frames by the odometry
        self.odometry = OdometryCheck()  # whether the device's odometry agrees with the tracked motion (else unused)

    def _scene_depth(self, T_wc: Pose | None, camera: Camera) -> np.ndarray | None:
        """How far the scene is over the frame of a camera at ``T_wc`` (rolling_shutter.depth_field of the points the
        current keyframe's render measured, every 8th pixel): for the share of a rolling shutter's skew that the
        camera's travel makes (it shrinks with distance)."""
        if self.kf is None or T_wc is None:
            return None
        if self.kf.scene_points is None:
            rnd = self.kf.render
            v, u = np.mgrid[4:rnd.camera.height:8, 4:rnd.camera.width:8]
            X, ok = rnd.backproject(np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64))
            self.kf.scene_points = X[ok]
        return depth_field((self.kf.scene_points - T_wc.t) @ T_wc.R, camera)

    def _lose(self) -> None:
        self.kf: Keyframe | None = None
        self.T_last: Pose | None = None
        self.stamp_last: float | None = None
        self.motion: tuple[Pose, float] | None = None
        self.sigma_last: float = 0.0  # the last pose's predicted 1-sigma position uncertainty (m)
        self.motion_tracked = False  # whether ``motion`` is between two tracked frames

    @property
    def exposure_s(self) -> float | None:
        """The exposure time in use: configured, else calibrated (once ``calib_min_frames`` have scored), else None
        (``exposure_prior`` of the frame interval is assumed).

        Calibrated: the peak of the candidates' scores, refined by a parabola through the best candidate
        and its neighbours, times the median frame interval."""
        if self.cfg.exposure_s is not None:
            return self.cfg.exposure_s
        if len(self.calib_intervals) < self.cfg.calib_min_frames:
            return None
        return self._calibrated_exposure()

    def _calibrated_exposure(self) -> float:
        return float(_parabolic_peak(np.asarray(self.cfg.calib_fractions), self.calib_scores) * np.median(self.calib_intervals))

    def _exposure(self, fr: "_Frame") -> float | None:
        """This frame's exposure time: from the caller, else configured or calibrated, else (before the
        calibration has seen a fast frame) ``exposure_prior`` of the frame interval."""
        e = fr.exposure_s or self.exposure_s
        if e is None and fr.motion is not None:
            e = self.cfg.exposure_prior * fr.motion[1]
        return e

    # ---- pieces --------------------------------------------------------------
    def _base_scale(self, camera: Camera) -> float:
        """The live frame's feature resolution (the extractor's ``max_side``); keyframes render at it."""
        side = self.extractor.max_side
        return min(1.0, side / max(camera.width, camera.height)) if side else 1.0

    def _reloc_scale(self, camera: Camera) -> float:
        """The live frame's feature resolution for a database query: the tracking one, capped at
        ``reloc_px_ratio`` x the database faces' focal length."""
        s = self._base_scale(camera)
        face = self.db.meta.get("face_size") if self.db is not None else None
        if face and self.cfg.reloc_px_ratio > 0:
            s = min(s, self.cfg.reloc_px_ratio * (face / 2) / max(camera.fx, camera.fy))
        return s

    def _live(self, fr: _Frame, scale: float) -> Features:
        """Live-frame features at ``scale`` of its resolution, the frame's ``top_k`` strongest; computed once per frame,
        scale and budget (XFeat's strongest k of a larger budget are exactly what it gives for k)."""
        k = fr.top_k or self.extractor.top_k
        if fr.live.get(scale, (0, None))[0] < k:
            t0 = time.perf_counter()
            fr.live[scale] = (k, self.extractor.extract(fr.image, top_k=k, max_side=max(32, round(scale * max(fr.image.shape[:2])))))
            fr.tm["features_ms"] = fr.tm.get("features_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        f = fr.live[scale][1]
        return f if len(f) <= k else f.subset(slice(0, k))

    def _points(self, render, rgb: np.ndarray, tm: dict) -> tuple[Features, np.ndarray]:
        """Features of a render image with the world points behind them (depth from the scan points around
        each keypoint, none on a depth edge)."""
        t0 = time.perf_counter()
        f = self.extractor.extract(rgb)
        X, ok, _ = render.surface_points(f.kpts, self.cfg.depth_radius, self.cfg.depth_max_residual)
        tm["kf_features_ms"] = tm.get("kf_features_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        return f.subset(ok), X[ok]

    def _keyframe(self, T_wc: Pose, fr: _Frame) -> Keyframe:
        """Render at ``T_wc``; coarser while most of the render is too far from any scan point for its
        depth to be interpolated (sparse scans, far surfaces)."""
        s = self._base_scale(fr.camera)
        for level in range(self.cfg.coarse_levels + 1):
            cam = fr.camera.scaled(s) if s != 1.0 else fr.camera
            t0 = time.perf_counter()
            r = self.renderer.render(T_wc, cam, supersample=self.cfg.keyframe_supersample)
            fr.tm["render_ms"] = fr.tm.get("render_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
            holes = 1.0 - support_fraction(r.measured, self.cfg.depth_radius)
            if holes <= self.cfg.max_holes or level == self.cfg.coarse_levels or min(cam.width, cam.height) < 128:
                break
            s /= 2
        gray = normalised_gray(r.rgb) if self.cfg.lk_window else None
        return Keyframe(T_wc, fr.camera, s, r, None, None, gray)

    def _sharp_points(self, kf: Keyframe, fr: _Frame) -> tuple:
        """The keyframe render's XFeat features, world points and grey image (features extracted on first use:
        a keyframe that direct tracking serves never needs them)."""
        if kf.feats is None:
            kf.feats, kf.xyz = self._points(kf.render, kf.render.rgb, fr.tm)
        return kf.feats, kf.xyz, kf.gray

    def _blur_px(self, fr: _Frame, exposure_s: float | None, motion: tuple[Pose, float] | None = None) -> float:
        """The frame's blur (frame pixels) had the camera kept ``motion`` (default: the frame's own) over the exposure."""
        motion = motion or fr.motion
        if motion is None or not exposure_s:
            return 0.0
        D, dt = motion
        return blur_length_px(fr.camera, Pose.identity(), Pose.identity().interpolate(D, exposure_s / dt))

    def _blurred_image(self, kf: Keyframe, fr: _Frame, exposure_s: float, reuse: bool = True) -> tuple[np.ndarray, bool]:
        """The keyframe render in grey blurred with the frame's motion over ``exposure_s``, and whether it is new.

        Consecutive frames move alike: the last blurred render is reused while its blur's end poses are
        within a tenth of the blur length (at least a pixel) of this frame's.
        """
        D, dt = fr.motion
        blur = self._blur_px(fr, exposure_s)
        n = int(np.clip(np.ceil(blur * kf.scale), 2, 10))
        half = 0.5 * (1 - 1 / n) * exposure_s / dt  # first and last of n samples spread over the exposure
        ident = Pose.identity()
        Ta, Tb = kf.T_wc @ ident.interpolate(D, -half), kf.T_wc @ ident.interpolate(D, half)
        if reuse and kf.blurred_img is not None:
            Ta0, Tb0, img = kf.blurred_img
            tol = max(1.0, 0.1 * blur)
            if blur_length_px(fr.camera, Ta, Ta0) <= tol and blur_length_px(fr.camera, Tb, Tb0) <= tol:
                return img, False
        img = self._blur_render(kf, fr, Ta, Tb, n)
        kf.blurred_img, kf.blurred, kf.direct_blurred = (Ta, Tb, img), None, {}
        return img, True

    def _blur_render(self, kf: Keyframe, fr: _Frame, Ta: Pose, Tb: Pose, n: int) -> np.ndarray:
        """The keyframe render in grey (uint8) as seen over an exposure from ``Ta`` to ``Tb`` (``n`` samples),
        warped by its depth: a blurred view from poses near the keyframe's without rendering again."""
        t0 = time.perf_counter()
        r = kf.render
        gray = cv2.cvtColor(r.rgb, cv2.COLOR_RGB2GRAY)  # XFeat sees grey anyway: a third of the warping
        if self.renderer.device.type == "cuda":  # one grid_sample on the GPU instead of numpy + OpenCV (0.2 s at 720p)
            from services.render.blur_torch import motion_blur_linear_torch

            img = motion_blur_linear_torch(gray, r.depth_filled, r.camera, kf.T_wc, Ta, Tb, n, self.renderer.device)
        else:
            img = motion_blur_linear(gray, r.depth_filled, r.camera, kf.T_wc, Ta, Tb, n)
        fr.tm["blur_ms"] = fr.tm.get("blur_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)

    def _centered(self, fr: _Frame, T_pred: Pose) -> Pose | None:
        """For a frame blurred at least ``blur_min_px``: the prediction turned by the global image shift between the frame
        and the current keyframe seen blurred from the prediction (phase correlation, ``blur_center``), or None (a sharp
        frame, no keyframe, an unclear peak). A pose solved from XFeat matches on a blurred frame stays where its render
        was along the blur, so the render must be where the frame is, and the features measure the rest."""
        kf = self.kf
        exposure = self._exposure(fr)
        if (not self.cfg.blur_center or kf is None or kf.frame_camera != fr.camera or fr.motion is None
                or self._far(T_pred, kf) or self._blur_px(fr, exposure) < self.cfg.blur_min_px):
            return None
        D, dt = fr.motion
        n = int(np.clip(np.ceil(self._blur_px(fr, exposure) * kf.scale), 2, 10))
        half = 0.5 * (1 - 1 / n) * exposure / dt
        ident = Pose.identity()
        img = self._blur_render(kf, fr, T_pred @ ident.interpolate(D, -half), T_pred @ ident.interpolate(D, half), n)
        size = (img.shape[1], img.shape[0])
        if size not in fr.gray:
            fr.gray[size] = normalised_gray(fr.image, size)
        turn, response = phase_turn(normalised_gray(img), fr.gray[size], kf.render.camera)
        if response < self.cfg.center_min_response or np.degrees(np.linalg.norm(turn)) > self.cfg.center_max_deg:
            log.debug("blur centring: no clear shift (%s deg, response %.2f)", np.round(np.degrees(turn), 3), response)
            return None
        log.debug("blur centring: prediction turned %s deg (response %.2f)", np.round(np.degrees(turn), 3), response)
        return T_pred @ Pose.from_rotvec_t(turn, np.zeros(3))

    def _blurred_points(self, kf: Keyframe, fr: _Frame, exposure_s: float, reuse: bool = True) -> tuple:
        """The keyframe's features, world points and grey image after blurring its render with the frame's
        motion over ``exposure_s`` (reused with the blurred render: a render XFeat pass saved)."""
        img, new = self._blurred_image(kf, fr, exposure_s, reuse)
        if new or kf.blurred is None:
            feats, xyz = self._points(kf.render, img, fr.tm)
            kf.blurred = (feats, xyz, normalised_gray(img) if self.cfg.lk_window else None)
        return kf.blurred

    def _solve(self, live: Features, feats: Features, xyz: np.ndarray, gray: np.ndarray | None, fr: _Frame,
               initial: Pose | None, px_factor: float = 1.0, kf_pose: Pose | None = None) -> PnpResult | None:
        """Match, re-align the matches by Lucas-Kanade against the keyframe image ``gray``, and solve.
        ``px_factor``: frame pixels per feature pixel relative to the base resolution (2 at half
        resolution): the RANSAC threshold and the reprojection gate scale with it. ``kf_pose``: where the keyframe
        was rendered; with ``initial`` it sets how far the re-alignment may move a match (:meth:`_lk_reach`)."""
        t0 = time.perf_counter()
        m = mutual_nn(live.desc, feats.desc, self.cfg.match_cos, self.match_device)
        uv, X = live.kpts[m[:, 0]].astype(np.float64), xyz[m[:, 1]]
        if gray is not None and len(m):
            reach = self._lk_reach(fr, X, gray.shape[1] / fr.camera.width, kf_pose, initial)
            uv, X = self._refine(fr, uv, X, feats.kpts[m[:, 1]], gray, reach)
        t1 = time.perf_counter()
        r = None
        if len(uv) >= 6:
            r = solve_pnp(uv, X, fr.camera, self.cfg.ransac_px * px_factor, initial=initial,
                          min_iterations=1000 if fr.relocalizing else self.cfg.ransac_min_iterations, soft=not fr.relocalizing)
            if r is not None:  # read by _good
                r.px_factor = px_factor
                r.px_deg = float(np.degrees(1.0 / max(fr.camera.fx, fr.camera.fy)))
                # the blur as the matched features see it (live frame at kf.scale = base scale / px_factor)
                r.cov = self._blur_scaled(r.cov, self._blur_px(fr, self._exposure(fr)) * self._base_scale(fr.camera) / px_factor,
                                          power=self.cfg.centred_blur_power if fr.centred else 2.0)
                if r.cov is not None:
                    r.cov = r.cov * self.cfg.match_sigma_scale ** 2
        fr.tm["match_ms"] = fr.tm.get("match_ms", 0.0) + 1e3 * (t1 - t0)
        fr.tm["pose_ms"] = fr.tm.get("pose_ms", 0.0) + 1e3 * (time.perf_counter() - t1)
        return r

    def _lk_reach(self, fr: _Frame, X: np.ndarray, scale: float, kf_pose: Pose | None, predicted: Pose | None) -> float:
        """How far (pixels of a keyframe image ``scale`` times the frame's size) a match may move when re-aligned:
        ``lk_max_px``, and while tracking against a keyframe rendered away from the frame's predicted pose, as far
        as that motion moves the matched points ``X`` in the image, up to ``lk_motion_px`` more."""
        if kf_pose is None or predicted is None or fr.relocalizing or self.cfg.lk_motion_px <= 0:
            return self.cfg.lk_max_px
        return self.cfg.lk_max_px + min(self.cfg.lk_motion_px, scale * _image_motion_px(fr.camera, kf_pose, predicted, X))

    def _refine(self, fr: _Frame, uv: np.ndarray, X: np.ndarray, uv_kf: np.ndarray, gray: np.ndarray, reach: float):
        """Live keypoints ``uv`` (frame pixels) moved to where the keyframe's patches around ``uv_kf``
        land in the live frame, within ``reach`` pixels of the keyframe image; a match whose patch does not converge
        keeps its keypoint."""
        size = (gray.shape[1], gray.shape[0])
        if size not in fr.gray:
            fr.gray[size] = normalised_gray(fr.image, size)
        sx, sy = size[0] / fr.camera.width, size[1] / fr.camera.height  # pixel centres at integers
        start = np.column_stack([(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5])
        q, ok = refine_matches_lk(gray, fr.gray[size], uv_kf, start, self.cfg.lk_window, reach)
        q = np.column_stack([(q[:, 0] + 0.5) / sx - 0.5, (q[:, 1] + 0.5) / sy - 0.5])
        return np.where(ok[:, None], q, uv), X

    def _match(self, kf: Keyframe, fr: _Frame, initial: Pose | None, fresh: bool = False) -> PnpResult | None:
        """Match the frame against a keyframe, blurred like the frame when it moves fast.

        ``fresh``: the keyframe was rendered for this frame, so blur, not viewpoint, dominates what the
        exposure candidates change: only such frames calibrate the exposure.
        """
        live = self._live(fr, kf.scale)
        px = self._base_scale(fr.camera) / kf.scale
        calibrate = (fresh and fr.exposure_s is None and self.cfg.exposure_s is None and fr.motion is not None
                     and len(self.calib_intervals) < self.cfg.calib_frames
                     and self._blur_px(fr, fr.motion[1]) >= self.cfg.calib_min_px)
        if calibrate:  # try every exposure candidate; the scores accumulate
            results, points = [], []
            for frac in self.cfg.calib_fractions:  # scored by the XFeat matches alone: patch alignment would blur the choice
                e = frac * fr.motion[1]
                points.append(self._blurred_points(kf, fr, e, reuse=False) if self._blur_px(fr, e) >= 1.0 else self._sharp_points(kf, fr))
                results.append(self._solve(live, *points[-1][:2], None, fr, initial, px))
            inl = np.array([0 if r is None else r.n_inliers for r in results], float)
            if self._plausible(results[int(np.argmax(inl))]):
                self.calib_scores += inl / inl.max()
                self.calib_intervals.append(fr.motion[1])
                log.info("exposure calibration %d/%d: best %.1f ms on this frame, %.1f ms over all", len(self.calib_intervals),
                         self.cfg.calib_frames, 1e3 * self.cfg.calib_fractions[int(np.argmax(inl))] * fr.motion[1], 1e3 * self._calibrated_exposure())
            # the frame's pose as any other frame's, with the exposure calibrated so far: one frame's own best
            # candidate is noisy, and these are the fastest, least forgiving frames
        return self._solve(live, *self._keyframe_points(kf, fr), fr, initial, px, kf.T_wc)

    def _keyframe_points(self, kf: Keyframe, fr: _Frame) -> tuple:
        """The keyframe's features, world points and grey image as this frame sees them (blurred when it moves fast)."""
        exposure = self._exposure(fr)
        if self._blur_px(fr, exposure) >= self.cfg.blur_min_px:
            return self._blurred_points(kf, fr, exposure)
        return self._sharp_points(kf, fr)

    def _direct_patches(self, kf: Keyframe, edges: bool = False) -> tuple[LandmarkPatches, np.ndarray, np.ndarray, bool]:
        """Corner patches of the keyframe render with the world points and surface normals behind them,
        spread over the image (built once per keyframe), and whether edge-like patches had to be taken too.
        ``edges``: corners and edges alike (``direct_edge_corner``), whatever the corners alone would give."""
        if edges not in kf.direct:
            r = kf.render
            gray = cv2.cvtColor(r.rgb, cv2.COLOR_RGB2GRAY)
            h, w = gray.shape
            m = 12 * w / 640  # a patch's margin from the image border
            levels = [(q, self.cfg.direct_min_corner) for q in self.cfg.direct_corner_quality]
            edge_level = (self.cfg.direct_corner_quality[-1], self.cfg.direct_edge_corner)
            if edges:
                levels = [edge_level]
            elif self.cfg.direct_edge_corner > 0:
                levels.append(edge_level)
            for quality, min_corner in levels:  # weaker corners, then edges, only where the stronger ones cannot do
                c = cv2.goodFeaturesToTrack(gray, maxCorners=8 * self.cfg.direct_points, qualityLevel=quality,
                                            minDistance=max(3.0, w / 80), blockSize=5)
                uv = np.zeros((0, 2)) if c is None else c.reshape(-1, 2).astype(np.float64)
                uv = uv[(uv[:, 0] >= m) & (uv[:, 0] < w - 1 - m) & (uv[:, 1] >= m) & (uv[:, 1] < h - 1 - m)]
                X, ok, planes = r.surface_points(uv, self.cfg.depth_radius, self.cfg.depth_max_residual)
                uv, X, planes = uv[ok], X[ok], planes[ok]
                patches = np.clip(sample_patches(gray, uv, 23) + 0.5, 0, 255).astype(np.uint8)
                keep = np.flatnonzero(corner_scores(patches) >= min_corner)
                gap = max(1.5, self.cfg.direct_hole_px * w / 480)  # (a 1-px gap between points is no hole)
                real = keep[~invented_near(r.measured, uv[keep], max(4, 8 * w // 480), gap)]
                keep = (real if len(real) >= self.cfg.direct_min_inliers else keep)[: self.cfg.direct_points]
                log.debug("direct patches at quality %g, corner score %g: %d corners, %d with depth, %d kept", quality,
                          min_corner, 0 if c is None else len(c), len(uv), len(keep))
                if len(keep) >= self.cfg.direct_min_inliers:
                    break
            cam = r.camera
            normals = plane_normals(uv[keep], planes[keep], cam.fx, cam.fy, cam.cx, cam.cy) @ kf.T_wc.R.T  # world axes
            T_cw = kf.T_wc.inverse()
            lp = LandmarkPatches(np.arange(len(keep)), patches[keep], normals, np.zeros(len(keep), np.int64),
                                 np.column_stack([T_cw.R, T_cw.t])[None], cam.K.copy())
            kf.direct[edges] = (lp, X[keep], uv[keep], (quality, min_corner) == edge_level)
        return kf.direct[edges]

    def _undistorted_gray(self, fr: _Frame) -> np.ndarray:
        """The frame in grey at full resolution, undistorted (float32), once per frame."""
        if "undistorted" not in fr.gray:
            fr.gray["undistorted"] = undistorted_gray(fr.image, fr.camera, self._undistort, self.cfg.denoise_above)
        return fr.gray["undistorted"]

    def _direct(self, kf: Keyframe, fr: _Frame, T_pred: Pose) -> PnpResult | None:
        """Track without features on the frame: align it to the keyframe render's corner patches warped into the
        predicted view (:mod:`services.localize.direct`) and solve. None when it does not converge.

        Patches whose alignments miss a sharp frame's good pose grossly are not aligned again on this keyframe
        (``direct_drop_missed``): in a site changed since its scan a render shows a desk that is gone, and the patches on
        its edges align onto the carpet beneath, each a few px off. Once most agree the pose holds, but frame after
        frame aligned to the same keyframe those few pull the same way: office seed 8 changed 30 %, frames 80-82 were
        reported 1.1, 2.8 and 5.2 cm off at 0.2-0.6 cm 1-sigma, each started from the last. Dropped as they miss,
        the same frames are 0.1 cm off, and eleven walks kept their frames (2674 -> 2684) with fewer poses beyond 3
        sigma (45 -> 33). Unchanged sites mark 0.1-0.4 patches a keyframe, that changed one 5.7 (benchmarks/RESULTS.md,
        stop 71)."""
        t0 = time.perf_counter()
        exposure = self._exposure(fr)
        blur = self._blur_px(fr, exposure)
        cam = fr.camera
        T_cw = T_pred.inverse()
        need = max(self.cfg.min_inliers, self.cfg.direct_min_inliers)
        d, dc = None, DirectConfig(min_inliers=need, probe_sigmas=self.cfg.direct_probe_sigmas)
        # a blurred frame aligns to the same corners cut from the render blurred with its motion
        img = self._blurred_image(kf, fr, exposure)[0] if blur >= self.cfg.blur_min_px else None
        for edges in (False, True):
            lp, P, uv, edged = self._direct_patches(kf, edges)
            if img is not None:
                if edges not in kf.direct_blurred:
                    kf.direct_blurred[edges] = dataclasses.replace(
                        lp, patches=np.clip(sample_patches(img, uv, lp.size) + 0.5, 0, 255).astype(np.uint8))
                lp = kf.direct_blurred[edges]
            Xc = P @ T_cw.R.T + T_cw.t
            z = np.maximum(Xc[:, 2], 1e-6)
            u, v = cam.fx * Xc[:, 0] / z + cam.cx, cam.fy * Xc[:, 1] / z + cam.cy
            m = 12 * cam.width / 640
            missed = kf.direct_missed.setdefault(edges, np.zeros(len(P), bool))
            vis = np.flatnonzero((Xc[:, 2] > 0.1) & (u >= m) & (u < cam.width - 1 - m) & (v >= m) & (v < cam.height - 1 - m)
                                & ~missed)
            if len(vis) >= need:
                d = align_and_solve(lp, vis, P[vis], T_cw.R, T_cw.t, cam.K, self._undistorted_gray(fr), dc)
            # corners that do not align (too few converge: a sparse scan's plain walls) are tried again with the
            # edge-like patches too (direct_edge_retry)
            if d is not None or edged or not self.cfg.direct_edge_retry or self.cfg.direct_edge_corner <= 0:
                break
        fr.tm["direct_ms"] = fr.tm.get("direct_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        if d is None:
            log.debug("direct: no pose (%d of %d patches in view, %d needed, blur %.0f px)", len(vis), len(P), need, blur)
            return None
        # blurred templates model the blur, so its cost grows slower than for XFeat's matches (_solve): sigma x
        # sqrt(blur / blur_sigma_px), not x blur / blur_sigma_px (against ground truth, linear: errors 0.2-0.4 sigma
        # at 16-24 px, none: 2 sigma)
        cov = self._blur_scaled(d.cov_right_wc(), blur * self._base_scale(cam), power=self.cfg.direct_blur_power)
        r = PnpResult(d.T_wc, np.ones(d.inliers, bool), d.rmse * dc.sigma_px, 0, cov, 1.0,
                      float(np.degrees(1.0 / max(cam.fx, cam.fy))), source="direct")
        if self.cfg.direct_drop_missed and blur < self.cfg.blur_min_px and self._good(r):
            missed[d.missed] = True  # (a blurred frame's alignments miss more, and say less about the scene)
        return r

    def _unrolled_again(self, image: np.ndarray, camera: Camera, fr: _Frame, r: PnpResult, readout: float) -> PnpResult:
        """A rolling-shutter frame unrolled with the motion model's last motion, tracked to ``r``: when the motion from
        the last pose to ``r`` turns at a rate that would move the frame's edge rows by over half a pixel more, the
        frame is unrolled again with it (``fr.image``) and aligned from ``r`` directly (as P&L does: the motion model
        lags a pan that speeds up). Returns that pose when it is good, else ``r``."""
        D = self.T_last.inverse() @ r.T_wc
        if not rate_changed(*fr.motion, D, fr.dt_next, camera, readout):
            return r
        redo = dataclasses.replace(fr, image=unroll_moving(image, camera, D, fr.dt_next, readout,
                                                           self._scene_depth(r.T_wc, camera)),
                                   live={}, gray={})
        r2 = self._direct(self.kf, redo, r.T_wc)
        if not self._good(r2) or self._far(r2.T_wc, self.kf):
            return r
        fr.image, fr.live, fr.gray = redo.image, redo.live, redo.gray
        return r2

    def _blur_scaled(self, cov: np.ndarray | None, blur_px: float, power: float = 2.0) -> np.ndarray | None:
        """A pose covariance scaled by (blur / blur_sigma_px)^power when the frame is blurred more than blur_sigma_px
        (``blur_px`` as the features see it: pixels at the base resolution)."""
        if cov is None or self.cfg.blur_sigma_px <= 0 or blur_px <= self.cfg.blur_sigma_px:
            return cov
        return cov * (blur_px / self.cfg.blur_sigma_px) ** power

    def _image_blur(self, fr: _Frame, kf: Keyframe) -> tuple[float, float]:
        """The frame's motion blur read from the image: the length (frame pixels) and direction (degrees from
        the image x axis) of the line kernel (over four directions) that, blurring the keyframe render,
        correlates best with the frame (both as the camera sees them, distortion included; at <= 320 px wide)."""
        t0 = time.perf_counter()
        ref = cv2.cvtColor(kf.render.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
        s = min(1.0, 320 / ref.shape[1])  # blur lengths are long, detail is not needed
        ref = cv2.resize(ref, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else ref
        h, w = ref.shape
        img = fr.image if fr.image.ndim == 2 else cv2.cvtColor(fr.image, cv2.COLOR_BGR2GRAY)
        live = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
        # compared band-passed: blur acts on edges, while the large flat areas that dominate a plain correlation
        # barely change with it (a frame blurred 17 px: 0.810 sharp, 0.819 at its blur; band-passed 0.67 -> 0.90)
        sigma = 3.0 * w / 320
        m = max(4, w // 16)

        def band(x: np.ndarray) -> np.ndarray:
            x = (x - cv2.GaussianBlur(x, (0, 0), sigma))[m:-m, m:-m]
            return (x - x.mean()) / (x.std() + 1e-6)

        def smeared(src: np.ndarray, fixed: np.ndarray, angles=(0.0, 45.0, 90.0, 135.0)) -> dict[tuple[float, float], float]:
            """(length in probe pixels, direction) -> correlation of ``src`` smeared so with ``fixed`` (band-passed)."""
            out = {}
            for length in self.cfg.blur_probe_px:
                k = 2 * int(round(length * w / 640 / 2)) + 1  # odd: the line's middle on the kernel's anchor (no shift)
                length = length * w / 640 if k > 1 else 0.0
                for ang in ([0.0] if k == 1 else angles):
                    ker = np.zeros((k, k), np.float32)
                    c = k // 2
                    for j in range(-c, c + 1):  # a line through the centre at this angle
                        ker[c + int(round(j * np.sin(np.radians(ang)))), c + int(round(j * np.cos(np.radians(ang))))] = 1.0
                    out[(length, ang)] = float((band(cv2.filter2D(src, -1, ker / ker.sum(), borderType=cv2.BORDER_REFLECT)) * fixed).mean())
            return out

        scores = smeared(ref, band(live))  # the render smeared: a blurred frame fits it better
        sharp = scores.get((0.0, 0.0), -1.0)
        (length, ang), best = max(scores.items(), key=lambda kv: kv[1])
        # Smoothing of any kind helps where the render is softer or noisier than the frame (a sparse scan seen close
        # up: leaks, U-Net fill). Then smearing the *frame* helps as much: a blur counts only for what the render's
        # smearing gains beyond that (office seed 2's rack close-up, 7-8 px of blur, read as 32-48 px without it, so
        # every relocalization there was too uncertain to report). And it has to explain a real share of what the
        # sharp render leaves unexplained, and be a blur: smearing along its direction must fit clearly better than across it.
        gain = along = best - sharp
        if length > 0 and gain >= self.cfg.blur_probe_gain * (1.0 - sharp):
            # along the same direction: a frame smeared by motion gains little from more of it, whatever the render
            back = smeared(live, band(ref), (ang,))
            gain -= max(0.0, max(v for (ln, _), v in back.items() if ln > 0) - sharp)
        fr.tm["blur_ms"] = fr.tm.get("blur_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        across = scores.get((length, (ang + 90.0) % 180.0), best)
        if length == 0 or gain < self.cfg.blur_probe_gain * (1.0 - sharp) or best - across < 0.5 * along:
            return 0.0, 0.0
        return length / (kf.scale * s), ang

    def _reloc_blur(self, r: PnpResult | None, fr: _Frame) -> PnpResult | None:
        """A relocalized pose's covariance scaled by the frame's blur read from the image against the render at
        that pose, as _solve scales a tracked frame's by its predicted blur. A relocalizing frame has no motion to
        go by, but a fast turn that lost the track is often still blurring the frame that re-acquires it, and
        XFeat matches on it err far more than their scatter says (HD walk: 7-10 cm / 0.8-1.8 deg reported at a
        predicted 0.3-0.5 cm, on frames blurred 20-25 px).

        When the blur is long enough to blur renders for (``blur_min_px``), the frame is aligned again directly to
        the render's corners cut from the render blurred along it (the blur modelled as a rotation about the axis
        perpendicular to it: fast turns are); a direct pose that passes the gate replaces the XFeat one. XFeat
        against the blurred render is not tried: on the 960x540 walk it relocalized a frame blurred 18 px 6 cm /
        0.75 deg off at a predicted 0.085 deg, and no walk or cold frame measured needed it."""
        if r is None or r.cov is None or self.kf is None or not self.cfg.blur_probe_px:
            return r
        length, angle = self._image_blur(fr, self.kf)
        if length >= self.cfg.blur_min_px:
            a = np.radians(angle)
            turn = Pose.from_rotvec_t(np.array([-np.sin(a), np.cos(a), 0.0]) * length / fr.camera.fx, np.zeros(3))
            saved = fr.motion, fr.exposure_s
            fr.motion, fr.exposure_s = (turn, 1.0), 1.0  # the blur as one frame interval's motion, all exposed
            try:  # directly against the render's corners cut blurred
                r2 = self._direct(self.kf, fr, r.T_wc) if self.cfg.direct_points else None
            finally:
                fr.motion, fr.exposure_s = saved
            if self._good(r2):  # its covariance scaled by this blur
                fr.blur_read_px = length
                return r2
        length = max(length, self._gap_blur_px(r.T_wc, fr))
        fr.blur_read_px = length
        r.cov = self._blur_scaled(r.cov, length * self._base_scale(fr.camera) / r.px_factor)
        return r

    def _reacquire(self, fr: _Frame, T: Pose, kf: Keyframe | None = None, reuse: bool = False,
                   keep_unsure: bool = False) -> PnpResult | None:
        """A pose for a frame without motion (relocalizing, or re-acquiring at the last good pose) from a rough one:
        rendered at and matched until it settles (``kf``: a render at ``T`` already made; ``reuse``: a recent
        verification's render near ``T`` will do for the first match, :meth:`_reusable`), its blur read from the image
        (:meth:`_reloc_blur`), then polished directly. Where no direct alignment replaced XFeat's pose, its position
        covariance is scaled by ``reloc_xfeat_sigma_t``^2. ``keep_unsure``: a pose the render confirms but too uncertain
        to report is returned as it is (for the reason a LOST frame gives), not polished."""
        x = self._render_and_refine(fr, T, self.cfg.reloc_refine_rounds, kf=kf, reuse=reuse, keep_unsure=keep_unsure)
        if x is not None and not self._good(x):
            return x
        r = self._polish(self._reloc_blur(x, fr), fr, fuse=False)
        if x is not None and r is x and r.cov is not None:  # (_reloc_blur scales x's covariance in place)
            k = np.r_[[self.cfg.reloc_xfeat_sigma_t] * 3, [1.0] * 3]
            r = dataclasses.replace(r, cov=r.cov * np.outer(k, k))
        return r

    def _gap_blur_px(self, T_wc: Pose, fr: _Frame) -> float:
        """A frame relocalized at ``T_wc`` soon after the last good pose (``gap_motion_s``): its blur (frame pixels)
        had the camera kept the mean motion between them over the exposure; 0 otherwise or with no exposure known.
        A fast turn that lost the track is likely still turning at the frame that re-acquires it, and reading the
        blur from the image against a render at a pose that is itself off can miss it: office seed 8 frames 106-107,
        relocalized 10 frames after a turn of 5 deg a frame lost the track (~15 px of blur), read 4 px from the image
        and were reported 2.5 cm / 0.97 deg off at a predicted 0.26 cm / 0.097 deg."""
        gap = self._gap_motion(T_wc, fr.stamp)
        return 0.0 if gap is None else self._blur_px(fr, fr.exposure_s or self.exposure_s, motion=gap)

    def _gap_motion(self, T_wc: Pose, stamp: float | None) -> tuple[Pose, float] | None:
        """The mean motion (T_rec^-1 T_wc, seconds) from the last good pose, kept while LOST, to ``T_wc`` at ``stamp``,
        when that pose is at most ``gap_motion_s`` older; else None."""
        if self.recent is None or self.recent[1] is None or stamp is None:
            return None
        gap = stamp - self.recent[1]
        return (self.recent[0].inverse() @ T_wc, gap) if 0 < gap <= self.cfg.gap_motion_s else None

    def _polish(self, r: PnpResult | None, fr: _Frame, fuse: bool = True) -> PnpResult | None:
        """An XFeat pose re-solved by direct alignment to the keyframe's corner patches, starting from it; the
        direct pose replaces it when that passes the report gate. XFeat finds the pose where the prediction was
        too far off for direct alignment to converge, but its poses err more than their scatter says (office
        walks: 0.4-1.9 cm / 0.07-0.36 deg RMSE at 1.7-4.9 sigma, where direct poses are 0.2-0.5 cm at 0.9-1.5 sigma).
        ``fuse``: a direct pose that is only plausible is combined with a reportable XFeat pose (tracking; for a
        relocalization the combination cost the 960x540 walk 13 of 113 frames, so there only a good one counts, and only
        where it agrees with the pose it polishes within their covariances: the patches are cut sharp, and a
        relocalizing frame has no motion to blur them by. A frame blurred 12 px, relocalized from patches cut blurred
        (``_reloc_blur``), was moved 0.5 deg by the polish and reported 2.5 cm / 0.67 deg off at 0.08 deg 1-sigma.
        Since stop 68 a good direct pose also replaces it on a frame whose blur reads sharp (``reloc_sharp_px``), and
        a plausible one that disagrees with it beyond the promise makes the combination ``disputed``: tracked from,
        not reported.)"""
        if not self.cfg.direct_points or self.kf is None or not self._plausible(r):
            return r
        r2 = self._direct(self.kf, fr, r.T_wc)
        if r2 is None or self._far(r2.T_wc, self.kf) or not self._plausible(r2):
            return r
        sharp = fr.blur_read_px is not None and fr.blur_read_px < self.cfg.reloc_sharp_px
        if self._good(r2) and (fuse or _agree(r, r2) or sharp):
            return r2
        if fuse:
            return _fuse(r, r2) if self._good(r) else r  # two weak estimates do not make a reportable one
        # a relocalization's direct pose that disagrees with it by more than the accuracy promised, on a frame not
        # read sharp, says one of the two is wrong: the combination is tracked from, not reported (office seed 8 frame
        # 106, re-acquired from a render 1.9 deg off: XFeat's pose stayed 0.97 deg off through a second render at it,
        # and was reported at 0.097 deg 1-sigma where direct alignment from it settled 0.08 deg from the truth, too
        # uncertain to report alone). Apart by less (a 960x720 frame's 0.5 cm / 0.07 deg, beyond its tiny
        # covariances), it stands
        dt, dr = r.T_wc.distance_to(r2.T_wc)
        gate_m, gate_deg = self._gate(r)
        if _agree(r, r2) or (dt <= gate_m and dr <= gate_deg):
            return r
        why = f"direct alignment from the pose found disagrees with it ({100 * dt:.1f} cm / {dr:.2f} deg apart)"
        return dataclasses.replace(_fuse(r, r2, inflate=False), disputed=why)

    def _checked(self, r: PnpResult, kf: Keyframe, fr: _Frame) -> PnpResult:
        """A direct pose less certain than ``direct_check`` x the report gate, checked by XFeat from it: combined with
        XFeat's pose where the two agree, and where they do not, the more certain of the two. Direct alignment has
        fewer measurements than XFeat has matches (office walk frames 118-145, a view with few corners: 62-130
        aligned patches at 0.2-0.7 cm 1 sigma and 0.2-2.5 cm off at the true pose, XFeat 350-430 inliers at 0.1 cm
        and 0.01-0.3 cm off; the walk reported 2.4-2.9 cm there, benchmarks/RESULTS.md stop 37)."""
        if self.cfg.direct_check <= 0 or self._good(r, self.cfg.direct_check):  # (r passed the gate: only its sigmas differ)
            return r
        x = self._match(kf, fr, r.T_wc)
        if not self._good(x) or self._far(x.T_wc, kf):
            return r
        if x.cov is not None:  # XFeat's poses err about twice their scatter (those frames: 0.17 cm at 0.1 cm 1 sigma)
            x = dataclasses.replace(x, cov=x.cov * self.cfg.direct_check_xfeat_scale ** 2)
        f = _fuse(x, r)
        if f.sigma_t_m <= min(x.sigma_t_m, r.sigma_t_m) + 1e-9:  # they agree (a disagreement inflates the result)
            return f
        return x if x.sigma_t_m < r.sigma_t_m else r

    def _plausible(self, r: PnpResult | None) -> bool:
        """Enough inliers at a small reprojection error, uncertainty within ``track_sigma_factor`` x the
        report gate: a pose to keep tracking from, reported only when also ``_good``."""
        return self._good(r, self.cfg.track_sigma_factor)

    def _good(self, r: PnpResult | None, factor: float = 1.0) -> bool:
        if r is not None and log.isEnabledFor(logging.DEBUG):
            log.debug("candidate: %d inliers, %.2f px, sigma %.1f cm %.2f deg", r.n_inliers, r.reproj_rmse_px,
                      100 * r.sigma_t_m, r.sigma_r_deg)
        if r is None:
            return False
        gate_m, gate_deg = self._gate(r)
        return (r.n_inliers >= self.cfg.min_inliers
                and r.reproj_rmse_px <= self.cfg.max_rmse_px * r.px_factor
                and r.sigma_t_m <= gate_m * factor and r.sigma_r_deg <= gate_deg * factor)

    def _gate(self, r: PnpResult) -> tuple[float, float]:
        """The 1-sigma report gate (m, deg) for ``r``'s camera: a low-resolution camera cannot do better."""
        coarse = max(1.0, r.px_deg / self.cfg.sigma_ref_px_deg)
        return self.cfg.max_sigma_m * coarse, self.cfg.max_sigma_deg * coarse

    def _consistent(self, r: PnpResult, predicted: Pose | None, dt: float) -> bool:
        """Whether a tracked pose is where the motion model could have taken the camera
        (services.localize.innovation, ``innovation_sigmas`` and ``innovation_accel_mps2``)."""
        if predicted is None:
            return True
        ok, off, bound = within_motion(r.T_wc.t, predicted.t, r.sigma_t_m, self.sigma_last, dt,
                                       self.cfg.innovation_sigmas, self.cfg.innovation_accel_mps2)
        if not ok:
            log.debug("tracked pose %.1f cm from the prediction (bound %.1f cm): not reported", 100 * off, 100 * bound)
        return ok

    def _far(self, T: Pose, kf: Keyframe) -> bool:
        dt, dr = T.distance_to(kf.T_wc)
        return dt > self.cfg.rerender_m or dr > self.cfg.rerender_deg

    def _render_and_refine(self, fr: _Frame, T: Pose, rounds: int = 1, kf: Keyframe | None = None,
                           tracking: bool = False, reuse: bool = False, keep_unsure: bool = False) -> PnpResult | None:
        """Render at ``T`` and match, up to ``rounds`` times while the pose still moves; keeps the last keyframe.
        ``kf``: an existing render at ``T`` for the first round. ``tracking``: a plausible pose is enough
        (relocalizations must be good; a plausible one before the last round is rendered at once more: office seed 5's
        cold frames 134 and 230, coarse poses 12 / 54 cm off, matched 5.7 / 5.3 cm off at 1.0 / 1.9 cm sigma first).
        ``reuse``: the first round may match a recent verification's render near ``T`` (:meth:`_reusable`); as before,
        the rounds stop early only on a render within 2 cm of the pose found. ``keep_unsure``: the last round's pose is
        returned when it is plausible though not good, so the frame says it was found but too uncertain (office seed
        90's cold frames 71, 77 and 126 said "no place in the database was confirmed by a render": XFeat 326-352
        inliers at 0.4-0.5 cm / 0.10-0.13 deg 1-sigma there. Polished by direct alignment, such poses were reported
        instead: seed 13 222 -> 227 frames but 0.080 -> 0.087 deg, frame 270 0.36 deg off at 0.099: not so)."""
        accept = self._plausible if tracking else self._good
        r = None
        if kf is None and reuse:
            kf = self._reusable(T, fr)
        for i in range(rounds):
            if i > 0 or kf is None:
                kf = self._keyframe(T, fr)
                if reuse and self.cfg.verify_renders_kept > 0:
                    self.verify_kfs = (self.verify_kfs + [kf])[-self.cfg.verify_renders_kept:]
            r = self._match(kf, fr, T, fresh=True)
            if not accept(r):
                if i + 1 < rounds and self._plausible(r):  # closer, not yet sure: rendered at once more
                    T = r.T_wc
                    continue
                if keep_unsure and self._plausible(r):
                    kf.ref_inliers, self.kf = r.n_inliers, kf  # (a relocalization may keep it: _relocalize)
                    return r
                return None
            kf.ref_inliers = r.n_inliers
            self.kf = kf
            if not self._far(r.T_wc, kf) and kf.T_wc.distance_to(r.T_wc)[0] < 0.02:
                break
            T = r.T_wc
        return r

    def _reusable(self, T: Pose, fr: _Frame) -> Keyframe | None:
        """The nearest of the renders kept from recent verifications (``verify_kfs``) that is not ``_far`` from
        ``T`` and serves the frame's camera, or None. A LOST stretch verifies the same coarse places frame after
        frame (a whip pan, a close-up no view fits): office seed 13's 76 LOST frames made 111 such renders, each
        ~0.2 s and an XFeat pass on it ~0.1 s; a render a few centimetres or degrees from the coarse pose serves its
        first match as well as one at it (tracking matches against renders up to ``rerender_m`` / ``rerender_deg``
        away), and the coarse pose itself is decimetres off."""
        near = [k for k in self.verify_kfs if k.frame_camera == fr.camera and not self._far(T, k)]
        return min(near, key=lambda k: k.T_wc.distance_to(T)[0], default=None)

    def _relocalize(self, fr: _Frame, near: tuple[np.ndarray, float] | None,
                    reach: tuple[np.ndarray, float] | None = None,
                    walk: tuple[np.ndarray, float] | None = None, db: RelocDB | None = None,
                    scale: float | None = None, strong: bool = False,
                    repeats: Callable[[PnpResult], bool] | None = None) -> PnpResult | None:
        """A pose from the database, verified: coarse poses from the best-matching views (one per place), each
        rendered at and matched again until one passes the report gate; refused when two places fit the
        frame about as well (repetitive sites), coarsely or verified. ``near`` = (recent position, radius): search
        only views within reach of it; ``reach`` = (position, radius), else ``near``: refuse a pose beyond it
        (a bay of identical racks 2-4 m on); ``walk`` = (position, metres): refuse a pose the camera cannot have walked
        to from there through the scan's free space (:meth:`_walkable`: the next aisle over). ``db``: views to search
        other than the database (:meth:`_look_around`'s), matched at ``scale`` of the frame's resolution; ``strong``:
        a coarse pose needs ``reloc_min_inliers`` to be verified even where the camera cannot be far; ``repeats``: the
        best coarse pose is verified with fewer (``look_around_repeat``) when this says an earlier frame found it too."""
        cfg = self.cfg
        db = db or self.db
        scale = scale or self._reloc_scale(fr.camera)
        fr.reason = None  # this search's own (the look-around keeps the database's before it)
        feats = self._live(fr, scale)
        t0 = time.perf_counter()
        reach = reach or near
        # a weak coarse pose is verified only where the camera cannot have reached a look-alike place
        weak = not strong and reach is not None and reach[1] <= cfg.reloc_weak_reach_m
        need = cfg.reloc_weak_inliers if weak else cfg.reloc_min_inliers
        ambiguity, far = cfg.reloc_ambiguity, (cfg.reloc_cold_ambiguity if near is None else None)
        floor = min(need, int(min(ambiguity, far or ambiguity) * cfg.reloc_min_inliers))  # rivals may be weaker than the best
        if repeats is not None:
            floor = min(floor, cfg.look_around_repeat[0])
        within = None if reach is None else (reach[0], reach[1] + 0.5)  # coarse poses are a few decimetres off

        def search(feats: Features) -> list[tuple[PnpResult, int]]:
            hyps = db.hypotheses(feats, fr.camera, cfg.reloc_candidates, floor, near=near, within=within)
            if (not hyps or hyps[0][0].n_inliers < need) and cfg.reloc_widen > cfg.reloc_candidates:
                hyps = db.hypotheses(feats, fr.camera, cfg.reloc_widen, floor, near=near, within=within,
                                     known=hyps, skip=cfg.reloc_candidates)
            return hyps

        hyps = search(feats)
        if (not hyps or hyps[0][0].n_inliers < need) and near is None and self.extractor.top_k <= len(feats) < cfg.reloc_top_k:
            # a cold frame no place fits, its keypoint budget used up: something in front of the scene (people) may
            # hold its strongest keypoints. Searched again, and verified, with more of them (only cold: a LOST stretch
            # near a recent pose would pay for it on every frame of a whip pan)
            fr.top_k = cfg.reloc_top_k
            t1 = time.perf_counter()
            feats = self._live(fr, scale)
            t0 += time.perf_counter() - t1  # (features_ms)
            hyps = search(feats)
        fr.best_coarse = hyps[0][0] if hyps else None
        if (repeats is not None and hyps and cfg.look_around_repeat[0] <= hyps[0][0].n_inliers < need
                and repeats(hyps[0][0])):
            need = hyps[0][0].n_inliers  # (this one and its equals only)
            log.debug("a coarse pose with %d inliers repeats the last frame's: verified", need)
        fr.tm["relocalize_ms"] = fr.tm.get("relocalize_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        fr.motion, fr.relocalizing = None, True  # a relocalized frame starts without motion
        if not hyps or hyps[0][0].n_inliers < need:
            fr.reason = "no place in the database fits the frame" if not hyps else \
                f"too few inliers in the database: the best place has {hyps[0][0].n_inliers}, a pose needs {need}"
            return None
        def far_verify(rival: PnpResult) -> bool:
            # a rival more than 2 m away is a place of its own when a render there holds even a pose too uncertain to
            # report; one that holds none was a chance fit (office seed 90's cold frames 151 and 156: 56 and 44 coarse
            # inliers 6 m away, against 64 and 53, refused unseen before stop 64)
            return self._rival_holds(fr, rival.T_wc, unsure=True) is not None

        # near rivals: verified below, in turn; far ones rendered at now
        why = db.ambiguous(hyps, ambiguity, far, verify=lambda _: False, verify_far=far_verify)
        if why:
            fr.reason = f"ambiguous place: {why}"
            return None
        found: tuple[PnpResult, PnpResult, Keyframe] | None = None  # (coarse, verified, its keyframe)
        unsure: tuple[PnpResult, PnpResult, Keyframe] | None = None  # the same for a place too uncertain to report
        for coarse, _ in hyps[:cfg.reloc_verify]:
            if coarse.n_inliers < need or (found is not None and coarse.n_inliers < cfg.reloc_rival_verify * found[0].n_inliers):
                break
            r = self._reacquire(fr, coarse.T_wc, reuse=True, keep_unsure=True)
            if r is None:
                continue
            sure = self._good(r)
            if not sure and fr.reason is None:  # confirmed by its render, but the frame's blur leaves it unsure
                fr.reason = (f"pose too uncertain to report ({100 * r.sigma_t_m:.1f} cm / {r.sigma_r_deg:.2f} deg "
                             f"1-sigma) at the place found")
            if not sure and (not cfg.reloc_track_unsure or unsure is not None or found is not None):
                continue
            if reach is not None and np.linalg.norm(r.T_wc.t - reach[0]) > reach[1]:
                fr.reason = (f"place out of reach: found {np.linalg.norm(r.T_wc.t - reach[0]):.1f} m from where the camera "
                             f"can be ({reach[1]:.1f} m)")
                log.info("relocalization %s", fr.reason)
                continue
            # a place away from where the camera was (or with nothing to say where that was) must also agree with the
            # frame as a picture; near it there is no look-alike to take, and people in front of the camera lower the
            # agreement (office walk with passers-by over 28 % of the frame: 0.28-0.59 at right poses)
            last = (walk or reach or near or (None,))[0]
            jump = last is None or np.linalg.norm(r.T_wc.t - last) > FAR_M
            agreement = self._agreement(fr, self.kf) if jump else float("nan")
            if agreement < self.min_agreement:  # (NaN, too little of the scan in view to judge: not refused)
                fr.reason = (f"render disagrees with the frame: agreement {agreement:.2f}, a pose needs "
                             f"{self.min_agreement:.2f} ({r.n_inliers} inliers)")
                log.info("relocalization refused: %s", fr.reason)
                continue
            if walk is not None and not self._walkable(walk[0], r.T_wc.t, walk[1]):
                fr.reason = (f"place out of reach: {np.linalg.norm(r.T_wc.t - walk[0]):.1f} m away, but not within "
                             f"{walk[1]:.1f} m through the scan's free space")
                log.info("relocalization %s", fr.reason)
                continue
            if not sure:  # a place that passes every check but the report gate: kept (re-acquired at) if none is sure
                unsure = (coarse, r, self.kf)
                continue
            if found is not None and not self._same_place(found[1], r):  # a second place passes too: a repetitive site
                fr.reason = f"ambiguous place: verified at places {found[1].T_wc.distance_to(r.T_wc)[0]:.1f} m apart"
                log.info("relocalization %s", fr.reason)
                return None
            if found is not None:  # the same place again (two coarse poses of it, a metre apart)
                continue
            found = (coarse, r, self.kf)
        if found is None and unsure is None:
            fr.reason = fr.reason or "no place in the database was confirmed by a render"
            return None
        coarse, r, self.kf = found or unsure
        t0 = time.perf_counter()  # about to be reported: is there another place it fits as well?
        fraction = cfg.reloc_check_fraction if near is not None else max(cfg.reloc_check_fraction, cfg.reloc_cold_check_fraction)
        check = max(cfg.reloc_check, int(np.ceil(fraction * db.n_views)))

        def verify(rival: PnpResult) -> bool:  # a near rival is a place of its own when it verifies elsewhere
            v = self._rival_holds(fr, rival.T_wc, unsure=False)
            return v is not None and not self._same_place(r, v)

        rival = db.has_rival(feats, fr.camera, coarse, cfg.reloc_candidates, check,
                             ambiguity=ambiguity, near=near, within=within, far_ambiguity=far, verify=verify,
                             verify_far=far_verify)
        fr.tm["relocalize_ms"] += 1e3 * (time.perf_counter() - t0)
        if rival:
            fr.reason = f"ambiguous place: {rival}"
            return None
        return r

    def _rival_holds(self, fr: _Frame, T: Pose, unsure: bool) -> PnpResult | None:
        """The pose a render at a rival place ``T`` holds (rendered and matched as a relocalization is; ``unsure``: a
        pose too uncertain to report counts too) when the render also agrees with the frame as a picture (a wrong
        aisle is no rival), else None. The tracker's keyframe is left as it was."""
        kf = self.kf
        v = self._render_and_refine(fr, T, self.cfg.reloc_refine_rounds, tracking=unsure, reuse=True)
        if v is not None and self._agreement(fr, self.kf) < self.min_agreement:
            v = None
        self.kf = kf
        return v

    def _look_around(self, fr: _Frame, a: "_Anchor", near, reach, walk) -> PnpResult | None:
        """A pose for a LOST frame soon after the last reported one (``a``) that the database did not place: views
        rendered where the last velocity leads (``a``'s position if none), every way round, with the frame's own
        camera at its tracking resolution, searched and verified as the database is (:meth:`_relocalize`). They are
        rendered again only once the camera is expected ``look_around_step_m`` from them."""
        cfg = self.cfg
        if cfg.look_around_s <= 0 or a.hint or a.stamp is None or fr.stamp is None or not 0 <= fr.stamp - a.stamp <= cfg.look_around_s:
            return None
        pos = a.position + (a.velocity * (fr.stamp - a.stamp) if a.velocity is not None else 0.0)
        scale = self._base_scale(fr.camera)
        if (self.around is None or self.around[1] != fr.camera
                or np.linalg.norm(self.around[0] - pos) > cfg.look_around_step_m):
            t0 = time.perf_counter()
            cam = fr.camera.undistorted().scaled(scale)
            hfov = 2 * np.degrees(np.arctan2(cam.width / 2, cam.fx))
            poses = yaw_sweep(pos, hfov, cfg.look_around_overlap)
            views = view_features(self.renderer, poses, cam, self.extractor,
                                  DBConfig(top_k=self.extractor.top_k, depth_radius=cfg.depth_radius,
                                           depth_max_residual=cfg.depth_max_residual))
            around = RelocDB.from_views(poses, views, self.db.vocab)  # (called with a database only)
            around.match_device = self.match_device
            self.around = (pos, fr.camera, around)
            fr.tm["look_around_ms"] = 1e3 * (time.perf_counter() - t0)
            log.debug("looking around at %s: %d views in %.0f ms", np.round(pos, 2), len(poses), fr.tm["look_around_ms"])
        why = fr.reason
        # (views with the frame's own camera near where it is share more with it than the database's: a weak coarse
        #  pose among them is mostly a blurred frame's chance fit, and verifying each cost ~1 s a frame in a whip pan;
        #  one the frame before found too is not: ``look_around_repeat``)
        last = self.around_prev

        def repeats(coarse: PnpResult) -> bool:  # the frame before's best coarse pose among these views is close
            if last is None or not 0 < fr.stamp - last[0] <= 0.5:
                return False
            d_m, d_deg = coarse.T_wc.distance_to(last[1])
            return (d_m <= cfg.look_around_repeat[1] + cfg.max_speed_mps * (fr.stamp - last[0])
                    and d_deg <= cfg.look_around_repeat[2])

        r = self._relocalize(fr, near, reach, walk, db=self.around[2], scale=scale, strong=True, repeats=repeats)
        self.around_best = None if fr.best_coarse is None else (fr.stamp, fr.best_coarse.T_wc)
        if r is None:
            inner = (fr.reason or "no pose").replace(" in the database", "")
            fr.reason = f"{why} (and among {self.around[2].n_views} views rendered where its motion led: {inner})"
        return r

    def _agreement(self, fr: _Frame, kf: Keyframe) -> float:
        """How well the keyframe's render agrees with the frame as a picture (services.localize.agreement)."""
        t0 = time.perf_counter()
        mean = np.full((1, 3), 1 / 3)  # (the render has the lens's distortion, as the frame: compared as they are)
        a = structure_agreement(cv2.transform(fr.image, mean) if fr.image.ndim == 3 else fr.image,
                                cv2.transform(kf.render.rgb, mean), kf.render.measured)
        fr.tm["relocalize_ms"] = fr.tm.get("relocalize_ms", 0.0) + 1e3 * (time.perf_counter() - t0)
        return a

    def _walkable(self, a: np.ndarray, b: np.ndarray, metres: float) -> bool:
        """Whether the camera can have walked from ``a`` to ``b`` (world) within ``metres`` through the scan's free space
        (the tracker's ``plan``, else :func:`floor_plan` of its renderer, built on first use)."""
        if self._plan is None:
            self._plan = floor_plan(self.renderer)
        return self._plan.walkable_within(a, b, metres)

    @staticmethod
    def _same_place(a: PnpResult, b: PnpResult) -> bool:
        """Two verified poses of one place (within 0.3 m and 5 deg: renders at both matched the frame)."""
        dt, dr = a.T_wc.distance_to(b.T_wc)
        return dt < 0.3 and dr < 5.0

    def correspondences(self, image: np.ndarray, camera: Camera, T_wc: Pose) -> tuple[np.ndarray, np.ndarray]:
        """The frame's 2D-3D correspondences against the scan rendered at ``T_wc`` with ``camera``: (uv (N, 2)
        frame pixels, X (N, 3) world points), every mutual XFeat match re-aligned by Lucas-Kanade, outliers
        included (calibration: services.localize.calibrate)."""
        fr = _Frame(image, camera, {}, None, 0.0, None)
        kf = self._keyframe(T_wc, fr)
        feats, xyz, gray = self._sharp_points(kf, fr)
        live = self._live(fr, kf.scale)
        m = mutual_nn(live.desc, feats.desc, self.cfg.match_cos, self.match_device)
        uv, X = live.kpts[m[:, 0]].astype(np.float64), xyz[m[:, 1]]
        if gray is not None and len(m):
            uv, X = self._refine(fr, uv, X, feats.kpts[m[:, 1]], gray, self.cfg.lk_max_px)
        return uv, X

    # ---- the frame loop --------------------------------------------------------
    def process(self, image: np.ndarray, camera: Camera, prior: Pose | None = None, stamp: float | None = None,
                exposure_s: float | None = None, motion: Pose | None = None, readout_s: float | None = None,
                near: tuple[np.ndarray, float] | None = None) -> FrameResult:
        """Localize one frame.

        ``image``: uint8, any channel order. ``prior``: a pose hint (e.g. from odometry) used when the
        tracker has no pose. ``stamp``: capture time in seconds (mid-exposure); with it the tracker
        predicts motion at constant velocity and matches blurred frames. ``exposure_s``: the frame's
        exposure time when the camera reports it. ``motion``: the camera's motion since the previous
        frame from the device's own odometry (``T_prev^-1 @ T_now``); it replaces the constant-velocity guess.
        ``readout_s``: the camera's rolling-shutter readout for this frame (None: ``cfg.readout_s``; 0: a global shutter).
        ``near``: (world position, radius m) the camera is within at this frame, roughly (a dock, an entrance, a
        robot's own estimate), for when the tracker has no pose: relocalization then searches only as far from it as
        the camera can have gone since (``max_speed_mps``), and a look-alike place beyond does not make it ambiguous
        (a start in an aisle of identical racks). Kept until a pose is reported; ignored while tracking.
        """
        t_start = time.perf_counter()
        self.around_prev, self.around_best = self.around_best, None  # (the look-around's best coarse pose: the frame before's)
        odometry = motion  # the device's, checked against the tracked motion; used only while it agrees
        motion = self.odometry.use(motion)
        consecutive = stamp is not None and self.stamp_last is not None and 0 < stamp - self.stamp_last < 0.5
        fr = _Frame(image, camera, {}, self.motion if consecutive else None,
                    (stamp - self.stamp_last) if consecutive else 0.0, exposure_s, stamp=stamp)
        if motion is not None and consecutive:
            fr.motion = (motion, fr.dt_next)
        readout = self.cfg.readout_s if readout_s is None else float(readout_s)
        unrolled = readout > 0 and fr.motion is not None
        if unrolled:  # rows read while the camera moved: undo that first
            ahead = None if self.T_last is None else self.T_last @ fr.motion[0]  # (where the motion model puts the frame)
            fr.image = unroll_moving(image, camera, *fr.motion, readout, self._scene_depth(ahead, camera))
        rs_settled = self.shutter.step(readout, unrolled, motion is not None)
        status = Status.TRACKING
        r: PnpResult | None = None
        rerendered = False
        cold = False  # relocalized with nothing to say where the camera was (see _Anchor.confirmed)
        unsure: PnpResult | None = None  # a relocalization's place too uncertain to report (reloc_track_unsure)
        predicted: Pose | None = None  # where the motion model put this frame, when it had a motion
        if prior is not None and self.T_last is None:
            self.T_last = prior
        if near is not None and self.T_last is None:
            pos, radius = near_hint(near)
            a = self.anchor
            if a is None or not a.hint or a.radius != radius or not np.array_equal(a.position, pos):
                self.anchor = _Anchor(pos, stamp, None, radius, hint=True)  # (the same hint again keeps its clock)
        carry: Pose | None = None  # where the device's odometry puts this frame, should it be LOST
        if self.T_last is not None:
            T_pred = self.T_last
            if motion is not None:  # the device's odometry
                T_pred = carry = self.T_last @ motion
            elif fr.motion is not None:  # constant velocity
                D, dt = fr.motion
                T_pred = self.T_last @ Pose.identity().interpolate(D, fr.dt_next / dt)
            if motion is not None or (fr.motion is not None and self.motion_tracked):
                predicted = T_pred  # (a motion averaged over a LOST gap is too rough to judge a pose by)
            centred = self._centered(fr, T_pred)
            T_pred, fr.centred = centred or T_pred, centred is not None
            kf = self.kf
            direct = self.cfg.direct_points > 0
            stale = kf is None or kf.frame_camera != camera or self._far(T_pred, kf) or centred is not None
            if not stale and direct:
                r = self._direct(kf, fr, T_pred)  # no XFeat on the frame while the prediction is close
                if self._good(r) and self._far(r.T_wc, kf):
                    # the frame went past the re-render distance that its prediction had not: a new render where the
                    # alignment put it. Matched by XFeat against the old render instead, the pose was drawn back
                    # towards it (the office path at 320x240, frame 56: 4.9 cm / 0.65 deg off at a predicted 0.7 cm /
                    # 0.09 deg, where the far direct pose was 0.9 cm off; the next two frames then refused)
                    T_pred, stale, r = r.T_wc, True, None
                elif not self._good(r):
                    r = None
                else:
                    r = self._checked(r, kf, fr)
            if stale:
                new_kf = None
                # a new render, tracked into directly (XFeat only if that fails): after a tracked frame, or from where
                # the odometry carried a LOST one (its frames in a whip pan were XFeat's alone, too blurred to report)
                if direct and (kf is not None or self.carry.seconds > 0):
                    new_kf = self._keyframe(T_pred, fr)
                    r = self._direct(new_kf, fr, T_pred)
                    if self._good(r) and not self._far(r.T_wc, new_kf):
                        self.kf = new_kf
                        r = self._checked(r, new_kf, fr)
                    else:
                        r = None
                if r is None:
                    r = self._polish(self._render_and_refine(fr, T_pred, tracking=True, kf=new_kf), fr)
                    if self._plausible(r) and self._far(r.T_wc, self.kf):
                        # the prediction was off by more than a re-render's distance (a prior or a pose carried far off):
                        # the features were matched across that parallax (office frame 5 from a prior 20 cm off: 3.4 cm /
                        # 0.51 deg off at 0.27 cm 1-sigma, benchmarks/off_prediction.py). Once more from where they led
                        again = self._polish(self._render_and_refine(fr, r.T_wc, tracking=True), fr)
                        r = again if self._plausible(again) else r
                rerendered = True
            else:
                if r is None:
                    r = self._match(kf, fr, T_pred)
                    if not self._good(r) or self._far(r.T_wc, kf) or r.n_inliers < self.cfg.rerender_inlier_ratio * kf.ref_inliers:
                        r = self._render_and_refine(fr, r.T_wc if self._plausible(r) else T_pred, tracking=True)
                        rerendered = True
                    r = self._polish(r, fr)
            if consecutive and self._plausible(r) and r.cov is not None:
                # the frame's own solved motion can show a faster turn than the frame was matched for: a whip pan
                # starting (office seed 2 frame 138: predicted 4 px from the slow frame before, it had turned 7 deg since,
                # ~22 px of blur, and was reported 1.5-4.1 cm / 0.3-0.6 deg off at a predicted 0.44 cm / 0.07 deg)
                exposure = self._exposure(fr)
                seen = self._blur_px(fr, exposure, motion=(self.T_last.inverse() @ r.T_wc, fr.dt_next))
                matched = self._blur_px(fr, exposure)
                if seen > max(self.cfg.blur_min_px, 2.0 * matched):
                    log.debug("solved motion blurs %.0f px, matched for %.0f px", seen, matched)
                    r.cov = self._blur_scaled(r.cov, seen * self._base_scale(camera) / r.px_factor)
            if fr.motion is None and stamp is not None and self._good(r):
                # no motion to predict the blur by (right after a relocalization not soon after the last pose): read
                # it from the image against a render at the pose, and let it weigh on the pose's uncertainty (office
                # seed 5 frame 230, turning 5 deg a frame after one, was matched sharp and reported 3.3 cm / 0.59 deg
                # off at a predicted 0.45 cm)
                probe = self._keyframe(r.T_wc, fr) if blur_length_px(camera, self.kf.T_wc, r.T_wc) > 2.0 else self.kf
                length, _ = self._image_blur(fr, probe)
                r.cov = self._blur_scaled(r.cov, length * self._base_scale(camera) / r.px_factor)
        if (unrolled and motion is None and fr.motion is not None and self.T_last is not None and self.kf is not None
                and self._plausible(r)):
            r = self._unrolled_again(image, camera, fr, r, readout)
        if not self._good(r) and self.T_last is None and self.recent is not None:
            # re-acquire near the last good pose: a blurred or featureless frame or two should not cost a database query
            T_rec, s_rec = self.recent
            self.lost_frames += 1
            age = (stamp - s_rec) if (stamp is not None and s_rec is not None) else self.lost_frames / 30.0
            if age <= self.cfg.recover_s:
                fr.motion, fr.relocalizing = None, True
                kf = self.recover_kf  # one render at the last good pose serves the whole stretch
                if kf is None or kf.frame_camera != camera or kf.T_wc is not T_rec:
                    self.recover_kf = self._keyframe(T_rec, fr)
                r = self._reacquire(fr, T_rec, kf=self.recover_kf)
                if self._good(r):
                    status = Status.RELOCALIZED
                    self.relocalizations += 1
                    rerendered = True
            else:
                self.recent = None
        if not self._plausible(r) and self.db is not None:
            near = reach = None
            a = self.anchor
            if a is not None and a.stamp is None:  # a hint given before the clock started: from now on
                a.stamp = stamp
            walk = None  # (where the camera was, how far it can have walked since): through free space
            if a is not None and a.confirmed and (a.stamp is None or (stamp is not None and 0 <= stamp - a.stamp <= self.cfg.anchor_s)):
                dt = 0.0 if a.stamp is None or stamp is None else stamp - a.stamp
                near = (a.position, a.radius + self.cfg.max_speed_mps * dt)  # also the reach, unless tightened
                walk = None if a.hint else near
                if a.hint:  # the camera is within it; the views it matches best may stand further off (a wall seen
                    #         from across the room: the small test site's best view of a frame stood 2.3 m away)
                    reach, near = near, (a.position, near[1] + self.cfg.hint_view_reach_m)
                elif a.velocity is not None:  # it kept moving about as it did: at most max_accel away from that
                    tight = self.cfg.reach_m + 0.5 * self.cfg.max_accel_mps2 * dt * dt
                    if tight < near[1]:
                        reach = (a.position + a.velocity * dt, tight)
            r = self._relocalize(fr, near, reach, walk)
            if not self._good(r) and a is not None and near is not None:  # (a place too uncertain to report: looked for
                r = self._look_around(fr, a, near, reach, walk) or r      #  a sure one around, else kept)
            if self._good(r):
                status = Status.RELOCALIZED
                self.relocalizations += 1
                rerendered = True
                cold = near is None
            elif self._plausible(r):  # a place confirmed but too uncertain to report: the next frame is re-acquired at it
                unsure = r           # (as at a last good pose: rendered at and matched again, polished, checked)
        fr.tm["total_ms"] = 1e3 * (time.perf_counter() - t_start)
        if not self._plausible(r) or unsure is not None:
            if unsure is not None:
                self.recent, self.lost_frames = (unsure.T_wc, stamp), 0
            elif self.T_last is not None:
                self.recent, self.lost_frames = (self.T_last, self.stamp_last), 0
            self._lose()
            self.T_last = self.carry.lost(carry, fr.dt_next)
            self.stamp_last = stamp if self.T_last is not None else None
            reason = fr.reason or ("no database to relocalize from" if self.db is None else "no pose")
            return FrameResult(Status.LOST, None, 0 if r is None else r.n_inliers,
                               float("nan") if r is None else r.reproj_rmse_px, rerendered, fr.tm, reason=reason,
                               source=None if r is None else r.source)
        reacquired = self.carry.tracked() and status == Status.TRACKING  # tracked from a pose the odometry carried
        status = Status.RELOCALIZED if reacquired else status
        self.motion_tracked = consecutive and status == Status.TRACKING
        if self.motion_tracked:
            self.motion = (self.T_last.inverse() @ r.T_wc, stamp - self.stamp_last)
            if odometry is not None and self._good(r):
                self.odometry.update(self.motion[0], odometry)
        elif status == Status.RELOCALIZED and consecutive and self.T_last is not None:
            # relocalized straight after a frame that had a pose (tracking slipped in a fast turn): the motion since it
            # predicts the next frame and its blur (with none, frames 21 and 136 of the 960x540 walk were matched sharp
            # in a 20-30 px pan and reported 5-7 cm / 0.75-1.2 deg off)
            self.motion = (self.T_last.inverse() @ r.T_wc, stamp - self.stamp_last)
        elif status == Status.RELOCALIZED or self.T_last is None:
            # back after a short LOST gap (typically a fast turn), reported or only plausible: the mean motion over
            # the gap predicts the next frame and its blur better than none (with none, the next frame of the turn
            # was matched sharp and reported 5.7 cm / 1.3 deg off at a predicted 0.4 cm, 1280x720 walk)
            self.motion = self._gap_motion(r.T_wc, stamp)
        else:
            self.motion = None
        T_prev = self.T_last
        self.T_last, self.stamp_last, self.recent = r.T_wc, stamp, None
        self.verify_kfs = []  # tracking again: the next LOST stretch is elsewhere (and a server's clients hold less)
        # else weakly constrained, or where the motion cannot have taken it: no pose reported, but tracking continues
        good = (self._good(r) and (status != Status.TRACKING or self._consistent(r, predicted, fr.dt_next))
                and rs_settled and r.disputed is None)
        self.sigma_last = r.sigma_t_m
        self.relocalizations += int(good and reacquired)
        if good and stamp is not None:
            v = None  # world velocity, from this frame's tracked motion (none if implausibly fast: stamps too close)
            if self.motion is not None and status == Status.TRACKING and consecutive:
                v = (r.T_wc.t - T_prev.t) / self.motion[1]
                v = v if np.linalg.norm(v) <= self.cfg.max_speed_mps else None
            self.trail = [(s, p) for s, p in self.trail if 0 < stamp - s <= self.cfg.velocity_window_s]
            if v is not None and self.trail and stamp - self.trail[0][0] > 1.5 * self.motion[1]:
                v_mean = (r.T_wc.t - self.trail[0][1]) / (stamp - self.trail[0][0])
                v = v_mean if np.linalg.norm(v_mean) <= self.cfg.max_speed_mps else v
            self.trail.append((stamp, r.T_wc.t))
            a = self.anchor
            if (v is None and not cold and a is not None and not a.hint and a.stamp is not None
                    and 0 < stamp - a.stamp <= self.cfg.gap_motion_s):
                # re-acquired soon after the last reported pose (in a fast turn): the mean velocity since then. Walking
                # goes on through a turn; with none, the views _look_around renders after the next LOST frame stay where
                # the turn began (office seed 2: a 100-degree whip at frame 228, then 60 frames LOST walking 1.3 m/s)
                v = (r.T_wc.t - a.position) / (stamp - a.stamp)
                v = v if np.linalg.norm(v) <= self.cfg.max_speed_mps else None
            # confirmed once tracked; a pose re-acquired near the last one keeps that one's standing
            confirmed = not cold and (status == Status.TRACKING or self.anchor is None or self.anchor.confirmed)
            self.anchor = _Anchor(r.T_wc.t, stamp, v, 1.0, confirmed=confirmed)
        reason = None
        if not good:
            reason = (f"pose too uncertain to report ({100 * r.sigma_t_m:.1f} cm / {r.sigma_r_deg:.2f} deg 1-sigma)"
                      if not self._good(r) else NOT_UNDONE if not rs_settled else r.disputed
                      or "pose away from where the motion leads")
        sigma_m, sigma_deg = with_scan_error(r.sigma_t_m, r.sigma_r_deg, *self._view_floor())
        return FrameResult(status if good else Status.LOST, r.T_wc if good else None, r.n_inliers, r.reproj_rmse_px,
                           rerendered, fr.tm, sigma_m, sigma_deg, self._blur_px(fr, self._exposure(fr)), reason,
                           r.source)

    def _view_floor(self) -> tuple[float, float]:
        """(the stations' disagreement where the camera looks, the median measured depth) of the keyframe the last pose
        was found against, for :func:`with_scan_error` ((scan_sigma_m, NaN) without one)."""
        kf = self.kf
        if kf is None or not self.cfg.scan_sigma_m:
            return self.cfg.scan_sigma_m, float("nan")
        if kf.depth_m is None:
            r = kf.render
            v, u = np.nonzero(r.depth > 0)
            kf.depth_m = float(np.median(r.depth[v, u])) if len(v) else float("nan")
            X = None
            if self.cfg.scan_grid is not None:  # (the points it sees: where on the site the scan's error is read)
                pick = slice(None, None, max(1, len(v) // 400))
                X, _ = r.backproject(np.column_stack([u[pick], v[pick]]).astype(np.float64))
            kf.scan_sigma_m = local_scan_sigma(self.cfg.scan_sigma_m, self.cfg.scan_grid, X)
        return kf.scan_sigma_m, kf.depth_m
