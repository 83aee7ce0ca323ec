"""Prebuild: a stella_vslam map whose keyframes and landmarks come straight from the scan.

Paper section "Prebuild & Localize". Positions on a uniform grid in the region of interest (the
sampler the relocalization database uses); at each, views with the target camera's intrinsics
(without its distortion, so keypoints are already undistorted) covering every yaw direction, two
per direction (pitched up and down), rendered by the neural renderer. ORB with stella_vslam's
settings on each view; each keypoint gets its depth (and surface normal) from a plane fitted to the
scan points within a few pixels, so keypoints between the points of a sparse render count too, and
none is made where those points do not lie on one plane (a depth edge): see
:mod:`services.render.depth_sampling`.

Merging: every keyframe's candidate points are projected into each nearby keyframe (close position,
overlapping view direction); a point matches a keypoint there when that keypoint lies within the
3x3 pixel window around the projection, its own back-projected point agrees in depth, and the ORB
descriptors are close (Hamming). Matches are joined with union-find; a cluster keeps at most one
keypoint per keyframe (the one nearest the cluster's median point) and only observations that agree
with the median in 3D. Clusters seen by fewer than ``min_observations`` keyframes are dropped, the
rest become landmarks at the mean of their observations. Keyframes without landmarks are dropped;
the spanning tree is the maximum spanning tree of the covisibility graph (shared landmarks), so
parents are the most covisible keyframes, as SLAM would have linked them. Each landmark's patch is then aligned
into the other keyframes that observe it (renders at exact poses), and where one depth along the source ray
explains them all within a pixel, the patch file gets that depth for alignment (``LandmarkPatches.pos``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from services.features.orb import OrbExtractor, OrbFeatures, OrbSettings, hamming, level_centres
from services.geometry.camera import Camera
from services.geometry.se3 import Pose, yaw_sweep
from services.log import progress
from services.prebuild.patches import LandmarkPatches, align_to_patches, hole_noise, map_fingerprint, sample_patches
from services.prebuild.stella_map import DEFAULT_ORB_NAME, MapCamera, MapKeyframe, OrbParams, StellaMap
from services.render.depth_sampling import plane_normals

__all__ = ["BuildConfig", "view_poses", "build_map"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BuildConfig:
    yaw_overlap: float = 0.7  # yaw step = this fraction of the horizontal field of view
    pitch_deg: float | None = None  # +- pitch of the two views per direction; None: a third of the vertical FOV
    stage: str = "full"  # renderer stage: "full" (neural) or "splat" (ablation) or "filter"
    supersample: int = 1  # keyframes rendered at this many times their resolution and pooled (Renderer.render), so
    #                       keypoints on edges sit where the scan's samples put them. 2: office walk 0.41 -> 0.33 cm
    #                       (stop 38), and with patches weighed by hole_noise 0.35 -> 0.31 cm, > 3 sigma 22 -> 15
    #                       frames; but on the tests' 0.6-degree scan three P&L tests fail by a hair (a crowded cold
    #                       frame, dim frames, a turn's hand-over; benchmarks/RESULTS.md, stop 40): not the default yet
    orb: OrbSettings = field(default_factory=lambda: OrbSettings(max_keypoints=2000))
    distribution_cell: int | None = None  # px; None: 10 at 640 px width, scaled with the width
    depth_radius: int = 4  # px: a keypoint's depth and normal come from a plane fitted to the scan points this close ...
    depth_max_residual: float = 0.01  # ... all within this fraction of their depth of it (no landmark on a depth edge)
    window_px: float = 1.5  # merge: keypoint within the 3x3 window around the projection
    max_hamming: int = 64  # merge: descriptor distance
    depth_tol: float = 0.03  # merge: relative depth agreement of the two back-projected points
    merge_radius_m: float | None = None  # merge with keyframes whose positions are this close; None: 2.5 x spacing
    min_observations: int = 2  # drop landmarks seen by fewer keyframes
    cluster_tol_m: float = 0.02  # observations farther than this (+1 % of depth) from the cluster median are dropped
    camera_name: str = "cristal camera"
    patch_size: int = 23  # landmark patches (pixels, odd) stored beside the map for live alignment; 0 = none
    refine_max_px: float = 1.0  # each patch is aligned into its landmark's other keyframes' renders (exact poses) and
    #                             its depth along the source ray fitted to them; kept where it explains every one of them
    #                             within this (px at 640 wide), else the render's depth stays (0 = no refit). Depth read
    #                             off a render at a keypoint errs where the scan points around it straddle surfaces, and
    #                             live P&L inherited that as a per-landmark bias its 1-sigma did not show
    fps: float = 30.0


def view_poses(positions: np.ndarray, camera: Camera, cfg: BuildConfig = BuildConfig()) -> list[Pose]:
    """Camera-to-world poses: at each position, every yaw direction, pitched up and down (world z up)."""
    hfov = 2 * math.degrees(math.atan2(camera.width / 2, camera.fx))
    vfov = 2 * math.degrees(math.atan2(camera.height / 2, camera.fy))
    pitch = cfg.pitch_deg if cfg.pitch_deg is not None else vfov / 3
    return [T for p in np.asarray(positions, float).reshape(-1, 3)
            for T in yaw_sweep(p, hfov, cfg.yaw_overlap, (pitch, -pitch))]


@dataclass
class _View:
    T_wc: Pose
    feats: OrbFeatures
    X: np.ndarray  # (N, 3) world points
    z: np.ndarray  # (N,) depth in this view
    pos_index: int
    uvc: np.ndarray  # (N, 2) level-0 pixel centres of the keypoints
    gray: np.ndarray | None = None  # the render in grey (landmark patches)
    normals: np.ndarray | None = None  # (N, 3) world surface normals at the keypoints, towards the camera
    noise: np.ndarray | None = None  # (N,) a patch here aligns this much noisier (holes nearby: patches.hole_noise)


class _UnionFind:
    def __init__(self, n: int):
        self.p = np.arange(n)

    def find_all(self) -> np.ndarray:
        p = self.p
        while True:
            q = p[p]
            if np.array_equal(q, p):
                return p
            p = q

    def union_pairs(self, a: np.ndarray, b: np.ndarray) -> None:
        for x, y in zip(a.tolist(), b.tolist()):
            rx = x
            while self.p[rx] != rx:
                rx = self.p[rx]
            ry = y
            while self.p[ry] != ry:
                ry = self.p[ry]
            if rx != ry:
                self.p[max(rx, ry)] = min(rx, ry)
            # path compression on both chains
            while self.p[x] != rx:
                self.p[x], x = rx, self.p[x]
            while self.p[y] != ry:
                self.p[y], y = ry, self.p[y]


def _render_views(renderer, poses: list[Pose], pos_index: list[int], cam: Camera, cfg: BuildConfig) -> tuple[list[_View], dict]:
    from dataclasses import replace

    cell = cfg.distribution_cell or max(3, round(10 * cam.width / 640))
    ext = OrbExtractor(replace(cfg.orb, distribution_cell=cell))
    views: list[_View] = []
    tm = {"render_s": 0.0, "orb_s": 0.0}
    for T, pi in progress(list(zip(poses, pos_index)), desc="rendering keyframes", unit="view"):
        t0 = time.perf_counter()
        r = renderer.render(T, cam, stage=cfg.stage, supersample=cfg.supersample)
        t1 = time.perf_counter()
        gray = cv2.cvtColor(r.rgb, cv2.COLOR_RGB2GRAY)
        f = ext.extract_stella(gray)  # descriptors exactly as stella_vslam computes them
        # depth from the scan points around each keypoint: also between the points of a sparse render
        uvc = level_centres(f.kpts, f.octaves, cfg.orb.scale_factor)
        X, ok, planes = r.surface_points(uvc, cfg.depth_radius, cfg.depth_max_residual)
        sel = np.flatnonzero(ok)
        f, uvc, X = f.subset(sel), uvc[sel], X[sel]
        z = T.inverse().transform(X)[:, 2]
        normals = noise = None
        if cfg.patch_size:
            c = r.camera
            normals = plane_normals(uvc, planes[sel], c.fx, c.fy, c.cx, c.cy) @ T.R.T  # world axes
            noise = hole_noise(r.measured, uvc, cam.width)
        views.append(_View(T, f, X, z, pi, uvc, gray if cfg.patch_size else None, normals, noise))
        tm["render_s"] += t1 - t0
        tm["orb_s"] += time.perf_counter() - t1
    return views, tm


def _merge(views: list[_View], cam: Camera, positions: np.ndarray, cfg: BuildConfig, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Union-find of matching observations. Returns (view index, keypoint index, cluster label) per observation."""
    starts = np.cumsum([0] + [len(v.feats) for v in views])
    n_obs = int(starts[-1])
    uf = _UnionFind(n_obs)
    centers = np.array([v.T_wc.t for v in views])
    axes = np.array([v.T_wc.R[:, 2] for v in views])
    hfov = 2 * math.atan2(cam.width / 2, cam.fx)
    cos_lim = math.cos(min(math.pi, hfov * 1.2))
    W, H = cam.width, cam.height
    all_X = np.concatenate([v.X for v in views]) if n_obs else np.zeros((0, 3))
    all_desc = np.concatenate([v.feats.desc for v in views]) if n_obs else np.zeros((0, 32), np.uint8)
    all_view = np.repeat(np.arange(len(views)), np.diff(starts))
    offs = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    for b, vb in enumerate(progress(views, desc="merging landmarks", unit="kf")):
        if len(vb.feats) == 0:
            continue
        near = np.flatnonzero((np.linalg.norm(centers - vb.T_wc.t, axis=1) <= radius) & (axes @ axes[b] >= cos_lim))
        near = near[near > b]  # each pair once (matching is symmetric enough for union-find)
        if len(near) == 0:
            continue
        idx = np.concatenate([np.arange(starts[a], starts[a + 1]) for a in near])
        if len(idx) == 0:
            continue
        T_cw = vb.T_wc.inverse()
        Xc = T_cw.transform(all_X[idx])
        front = Xc[:, 2] > 0.05
        idx, Xc = idx[front], Xc[front]
        u = cam.fx * Xc[:, 0] / Xc[:, 2] + cam.cx
        v = cam.fy * Xc[:, 1] / Xc[:, 2] + cam.cy
        inside = (u > -1) & (u < W) & (v > -1) & (v < H)
        idx, u, v, zc = idx[inside], u[inside], v[inside], Xc[inside, 2]
        if len(idx) == 0:
            continue
        # keypoint index image of view b (pixel of each keypoint -> its index)
        grid = -np.ones((H + 2, W + 2), np.int64)
        kp = np.clip(np.round(vb.uvc).astype(int), -1, [W, H])
        grid[kp[:, 1] + 1, kp[:, 0] + 1] = np.arange(len(kp))
        ui, vi = np.round(u).astype(int), np.round(v).astype(int)
        cand = grid[np.clip(vi[:, None] + offs[None, :, 1] + 1, 0, H + 1), np.clip(ui[:, None] + offs[None, :, 0] + 1, 0, W + 1)]
        valid = cand >= 0
        cj = np.where(valid, cand, 0)
        du = vb.uvc[cj, 0] - u[:, None]
        dv = vb.uvc[cj, 1] - v[:, None]
        valid &= (np.abs(du) <= cfg.window_px) & (np.abs(dv) <= cfg.window_px)
        valid &= np.abs(vb.z[cj] - zc[:, None]) <= cfg.depth_tol * zc[:, None]
        hd = hamming(all_desc[idx][:, None, :], vb.feats.desc[cj])
        hd = np.where(valid, hd, 1 << 20)
        best = np.argmin(hd, axis=1)
        bd = hd[np.arange(len(idx)), best]
        ok = bd <= cfg.max_hamming
        if not ok.any():
            continue
        a_obs = idx[ok]
        b_obs = starts[b] + cj[np.arange(len(idx)), best][ok]
        uf.union_pairs(a_obs, b_obs)
    labels = uf.find_all()
    kp_index = np.arange(n_obs) - starts[all_view]
    return all_view, kp_index, labels


def _spanning_tree(kf_ids: list[int], obs_kf: np.ndarray, obs_lm: np.ndarray, centers: np.ndarray) -> dict[int, int]:
    """Maximum spanning tree of the covisibility graph (Prim); components joined by the nearest keyframe."""
    import heapq

    n = len(kf_ids)
    pos = {k: i for i, k in enumerate(kf_ids)}
    # covisibility weights: pairs of keyframes observing the same landmark
    order = np.lexsort((obs_kf, obs_lm))
    lm_s, kf_s = obs_lm[order], obs_kf[order]
    bounds = np.flatnonzero(np.r_[True, lm_s[1:] != lm_s[:-1], True])
    w: dict[tuple[int, int], int] = {}
    for s, e in zip(bounds[:-1], bounds[1:]):
        ks = kf_s[s:e].tolist()
        for i in range(len(ks)):
            for j in range(i + 1, len(ks)):
                key = (ks[i], ks[j]) if ks[i] < ks[j] else (ks[j], ks[i])
                w[key] = w.get(key, 0) + 1
    adj: dict[int, list[tuple[int, int]]] = {k: [] for k in kf_ids}
    for (a, b), c in w.items():
        adj[a].append((c, b))
        adj[b].append((c, a))
    parent = {kf_ids[0]: -1}
    in_tree = np.zeros(n, bool)
    in_tree[0] = True
    heap = [(-c, kf_ids[0], b) for c, b in adj[kf_ids[0]]]
    heapq.heapify(heap)
    while len(parent) < n:
        while heap:
            negc, a, b = heapq.heappop(heap)
            if b in parent:
                continue
            parent[b] = a
            in_tree[pos[b]] = True
            for c, nb in adj[b]:
                if nb not in parent:
                    heapq.heappush(heap, (-c, b, nb))
        if len(parent) < n:  # another component: attach its keyframe nearest to the tree
            out_i = np.flatnonzero(~in_tree)
            tin = np.flatnonzero(in_tree)
            d = np.linalg.norm(centers[out_i][:, None] - centers[tin][None], axis=2)
            i, j = np.unravel_index(np.argmin(d), d.shape)
            b, a = kf_ids[out_i[i]], kf_ids[tin[j]]
            parent[b] = a
            in_tree[pos[b]] = True
            heap = [(-c, b, nb) for c, nb in adj[b] if nb not in parent]
            heapq.heapify(heap)
    return parent


def build_map(renderer, positions: np.ndarray, camera: Camera, cfg: BuildConfig = BuildConfig(),
              spacing: float = 1.0) -> tuple[StellaMap, dict, LandmarkPatches | None]:
    """Render, extract, merge and assemble the map. Returns (map, stats, landmark patches or None)."""
    t_start = time.perf_counter()
    cam = camera.undistorted()
    poses: list[Pose] = []
    pos_index: list[int] = []
    for i, p in enumerate(np.asarray(positions, float).reshape(-1, 3)):
        vp = view_poses(p[None], cam, cfg)
        poses += vp
        pos_index += [i] * len(vp)
    log.info("prebuild: %d positions, %d views of %dx%d (stage %s)", len(positions), len(poses), cam.width, cam.height, cfg.stage)
    views, tm = _render_views(renderer, poses, pos_index, cam, cfg)
    t_merge = time.perf_counter()
    radius = cfg.merge_radius_m if cfg.merge_radius_m is not None else 2.5 * spacing
    obs_view, obs_kp, labels = _merge(views, cam, np.asarray(positions), cfg, radius)
    all_X = np.concatenate([v.X for v in views]) if len(obs_view) else np.zeros((0, 3))
    all_z = np.concatenate([v.z for v in views]) if len(obs_view) else np.zeros(0)
    all_oct = np.concatenate([v.feats.octaves for v in views]) if len(obs_view) else np.zeros(0, np.int32)
    all_noise = np.concatenate([v.noise if v.noise is not None else np.ones(len(v.feats), np.float32) for v in views]) \
        if len(obs_view) else np.zeros(0, np.float32)
    # clusters: median point, drop far observations, one observation per keyframe, >= min_observations keyframes
    order = np.lexsort((obs_view, labels))
    lab_s = labels[order]
    bounds = np.flatnonzero(np.r_[True, lab_s[1:] != lab_s[:-1], True])
    sizes = np.diff(bounds)
    keep_obs: list[np.ndarray] = []
    lm_pos: list[np.ndarray] = []
    lm_src: list[int] = []  # the observation whose keyframe gives the landmark's patch
    for s, e in zip(bounds[:-1][sizes >= cfg.min_observations], bounds[1:][sizes >= cfg.min_observations]):
        o = order[s:e]
        X = all_X[o]
        med = np.median(X, axis=0)
        dist = np.linalg.norm(X - med, axis=1)
        o = o[dist <= cfg.cluster_tol_m + 0.01 * all_z[o]]
        if len(o) < cfg.min_observations:
            continue
        # one keypoint per keyframe: the nearest to the median
        dist = np.linalg.norm(all_X[o] - med, axis=1)
        o = o[np.lexsort((dist, obs_view[o]))]
        first = np.r_[True, obs_view[o][1:] != obs_view[o][:-1]]
        o = o[first]
        if len(o) < cfg.min_observations:
            continue
        keep_obs.append(o)
        oc = all_oct[o]
        lm_pos.append(all_X[o[oc == oc.min()]].mean(axis=0))  # the finest pyramid level locates the corner best
        fine = o[oc == oc.min()]
        lm_src.append(int(fine[np.argmin(all_noise[fine])]))  # of those, the one with the scan's own colours around it
    # keyframes that observe at least one landmark; ids in view order
    obs_lm = np.concatenate([np.full(len(o), i) for i, o in enumerate(keep_obs)]) if keep_obs else np.zeros(0, int)
    obs_all = np.concatenate(keep_obs) if keep_obs else np.zeros(0, int)
    used_views = np.unique(obs_view[obs_all])
    kf_id_of_view = -np.ones(len(views), np.int64)
    kf_id_of_view[used_views] = np.arange(len(used_views))
    lm_of_obs = -np.ones(len(obs_view), np.int64)
    lm_of_obs[obs_all] = obs_lm
    starts = np.cumsum([0] + [len(v.feats) for v in views])
    keyframes: dict[int, MapKeyframe] = {}
    for vi in used_views.tolist():
        v = views[vi]
        lm = lm_of_obs[starts[vi]:starts[vi + 1]]
        sel = np.flatnonzero(lm >= 0)  # keep only keypoints with a landmark: a lean map
        f = v.feats.subset(sel)
        kid = int(kf_id_of_view[vi])
        keyframes[kid] = MapKeyframe(kid, v.T_wc, f.kpts, f.angles, f.octaves, f.desc, lm[sel].astype(np.int64),
                                     cfg.camera_name, DEFAULT_ORB_NAME, ts=float(kid))
    # landmarks: first and reference keyframe = the lowest keyframe id that observes it
    first_kf = np.full(len(keep_obs), np.iinfo(np.int64).max, np.int64)
    np.minimum.at(first_kf, obs_lm, kf_id_of_view[obs_view[obs_all]])
    n_obs = np.bincount(obs_lm, minlength=len(keep_obs)).astype(np.int64)
    kf_ids = sorted(keyframes)
    if kf_ids:
        parent = _spanning_tree(kf_ids, kf_id_of_view[obs_view[obs_all]], obs_lm, np.array([keyframes[k].T_wc.t for k in kf_ids]))
        for k, p in parent.items():
            keyframes[k].span_parent = int(p)
            if p >= 0:
                keyframes[p].span_children.append(int(k))
    o = cfg.orb
    m = StellaMap(
        cameras={cfg.camera_name: MapCamera.from_camera(cfg.camera_name, camera, cfg.fps)},
        orb_params={DEFAULT_ORB_NAME: OrbParams(DEFAULT_ORB_NAME, o.scale_factor, o.num_levels, o.ini_fast_threshold, o.min_fast_threshold)},
        keyframes=keyframes,
        lm_ids=np.arange(len(keep_obs), dtype=np.int64),
        lm_pos=np.array(lm_pos, np.float64).reshape(-1, 3),
        lm_first_kf=first_kf, lm_ref_kf=first_kf.copy(), lm_n_vis=n_obs, lm_n_fnd=n_obs.copy(),
        keyframe_next_id=len(kf_ids), landmark_next_id=len(keep_obs), frame_next_id=len(kf_ids),
    )
    patches = _landmark_patches(views, obs_view, np.array(lm_src, np.int64), m.lm_pos, cam, cfg) if cfg.patch_size else None
    if patches is not None:
        patches.map_fp = map_fingerprint(m.lm_ids, m.lm_pos)
    refined = {}
    if patches is not None and cfg.refine_max_px > 0 and keep_obs:
        patches.pos, refined = _refit_patch_depths(views, obs_view, keep_obs, lm_pos, lm_src, patches, cam, cfg)
    stats = {"positions": int(len(positions)), "views": len(views), "keyframes": m.n_keyframes, "landmarks": m.n_landmarks,
             "observations": int(len(obs_all)), "candidates": int(len(obs_view)),
             "render_s": round(tm["render_s"], 2), "orb_s": round(tm["orb_s"], 2),
             "merge_s": round(time.perf_counter() - t_merge, 2), **refined, "build_s": round(time.perf_counter() - t_start, 2)}
    log.info("prebuild: %d keyframes, %d landmarks (%d observations of %d candidates) in %.1f s", m.n_keyframes,
             m.n_landmarks, stats["observations"], stats["candidates"], stats["build_s"])
    return m, stats, patches


def _refit_patch_depths(views: list[_View], obs_view: np.ndarray, keep_obs: list[np.ndarray], lm_pos: list[np.ndarray],
                        lm_src: list[int], lp: LandmarkPatches, cam: Camera, cfg: BuildConfig) -> tuple[np.ndarray, dict]:
    """Where patch alignment should place each landmark: its patch (from the source keyframe) is aligned into each
    other keyframe that observes it (renders at exact poses), and its depth along the source keyframe's ray is
    fitted to where it aligned (Gauss-Newton on the reprojection error). The fit is kept where it lies within
    ``refine_max_px`` of every alignment; elsewhere (a corner that slides with the viewpoint, an occlusion's
    T-junction, a patch that aligned onto something else) and where the patch aligns in no other keyframe, the
    render's depth stays. The patch stays valid: moving along the source ray keeps its projection there. These
    positions are for the patches only: ORB corners sit 1.5-2 px from where patches align, and keypoint poses
    solved against refitted positions got worse (a sparse scan lost frames), so ``map.msg`` keeps the mean of the
    corners' points. ``lp``: the landmarks' patches (:func:`_landmark_patches`). Returns the positions (N, 3) and stats."""
    t0 = time.perf_counter()
    n = len(keep_obs)
    P0 = np.array(lm_pos, np.float64).reshape(-1, 3)
    K = cam.K
    lm_of = np.concatenate([np.full(len(o), i) for i, o in enumerate(keep_obs)])
    ob = np.concatenate(keep_obs)
    other = ob != np.array(lm_src, np.int64)[lm_of]
    lm_of, ob_view = lm_of[other], obs_view[ob[other]]
    Rv = np.array([v.T_wc.R.T for v in views]).reshape(-1, 3, 3)  # every keyframe's world-to-camera, once
    tv = -np.einsum("nij,nj->ni", Rv, np.array([v.T_wc.t for v in views]).reshape(-1, 3))
    q = np.zeros((len(lm_of), 2))
    ok = np.zeros(len(lm_of), bool)
    for vi in np.unique(ob_view).tolist():
        sel = np.flatnonzero(ob_view == vi)
        q[sel], ok[sel], _ = align_to_patches(lp, lm_of[sel], P0[lm_of[sel]], Rv[vi], tv[vi], K,
                                              views[vi].gray.astype(np.float32))
    lm_of, ob_view, q = lm_of[ok], ob_view[ok], q[ok]
    # depth s along the source ray X = C + s d, fitted to the alignments (a few Gauss-Newton steps, all at once)
    C = np.array([views[v].T_wc.t for v in obs_view[np.array(lm_src, np.int64)]]).reshape(-1, 3)
    d = P0 - C
    s = np.linalg.norm(d, axis=1)
    d /= s[:, None]
    R, t = Rv[ob_view], tv[ob_view]  # each alignment's world-to-camera
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]

    def residuals(s):
        Xc = np.einsum("nij,nj->ni", R, C[lm_of] + s[lm_of, None] * d[lm_of]) + t
        z = np.where(Xc[:, 2] > 1e-6, Xc[:, 2], np.nan)
        return Xc, z, np.column_stack([fx * Xc[:, 0] / z + cx, fy * Xc[:, 1] / z + cy]) - q

    for _ in range(5):
        Xc, z, r = residuals(s)
        dXc = np.einsum("nij,nj->ni", R, d[lm_of])  # d Xc / d s
        J = np.column_stack([fx * (dXc[:, 0] * z - Xc[:, 0] * dXc[:, 2]) / z ** 2, fy * (dXc[:, 1] * z - Xc[:, 1] * dXc[:, 2]) / z ** 2])
        g = np.bincount(lm_of, np.nan_to_num((J * r).sum(1)), n)
        h = np.bincount(lm_of, np.nan_to_num((J * J).sum(1)), n)
        s = np.where(h > 1e-9, np.maximum(s - g / np.maximum(h, 1e-9), 0.05), s)
    err = np.nan_to_num(np.linalg.norm(residuals(s)[2], axis=1), nan=np.inf)
    worst = np.zeros(n)
    np.maximum.at(worst, lm_of, err)
    checked = np.bincount(lm_of, minlength=n) > 0
    fit = checked & (worst <= cfg.refine_max_px * max(1.0, cam.width / 640))
    P = np.where(fit[:, None], C + s[:, None] * d, P0)
    moved = np.linalg.norm(P - P0, axis=1)[fit]
    stats = {"refine_checked": int(checked.sum()), "refine_refitted": int(fit.sum()),
             "refine_moved_cm_p90": round(float(np.percentile(moved, 90) * 100), 2) if fit.any() else 0.0,
             "refine_s": round(time.perf_counter() - t0, 2)}
    log.info("prebuild: %d of %d landmark patches' depths refitted to their other keyframes (90 %% moved under %.2f cm; "
             "%d left as rendered, unexplained by any depth) in %.1f s", stats["refine_refitted"], n, stats["refine_moved_cm_p90"],
             int((checked & ~fit).sum()), stats["refine_s"])
    return P, stats


def _landmark_patches(views: list[_View], obs_view: np.ndarray, src_obs: np.ndarray, lm_pos: np.ndarray, cam: Camera,
                      cfg: BuildConfig) -> LandmarkPatches:
    """Each landmark's patch (centred on its projection), normal and keyframe pose from its source observation."""
    n = len(src_obs)
    patches = np.zeros((n, cfg.patch_size, cfg.patch_size), np.uint8)
    normals = np.zeros((n, 3), np.float32)
    noise = np.ones(n, np.float32)
    src_view = obs_view[src_obs] if n else np.zeros(0, np.int64)
    starts = np.cumsum([0] + [len(v.feats) for v in views])
    used, src = np.unique(src_view, return_inverse=True)
    src_T_cw = np.zeros((len(used), 3, 4))
    for j, vi in enumerate(used.tolist()):
        v = views[vi]
        T_cw = v.T_wc.inverse()
        src_T_cw[j] = np.column_stack([T_cw.R, T_cw.t])
        sel = np.flatnonzero(src_view == vi)
        uv, _ = cam.project(T_cw.transform(lm_pos[sel]))
        patches[sel] = np.clip(sample_patches(v.gray, uv, cfg.patch_size) + 0.5, 0, 255).astype(np.uint8)
        normals[sel] = v.normals[src_obs[sel] - starts[vi]]
        if v.noise is not None:
            noise[sel] = v.noise[src_obs[sel] - starts[vi]]
    return LandmarkPatches(np.arange(n, dtype=np.int64), patches, normals, src.astype(np.int64), src_T_cw, cam.K.copy(),
                           noise=noise)
