"""Landmark patches: what each map landmark looks like, for aligning live keypoints to it (no torch).

ORB puts a corner where its detector fires, and the detector fires at different places on the same
surface seen from different viewpoints: matched against landmarks built from renders, live ORB
keypoints sit 1-2 px from where the landmarks project even at the true pose, and P&L poses inherit
that (measured on the office: 1.8 cm / 0.29 deg median). Aligning each match photometrically instead
(the surroundings of the landmark, seen as the live camera would see them, tracked into the live frame)
removes the detector from the measurement: 0.6 cm / 0.08 deg median with a render at the pose.

The light client has no renderer, so the map carries, beside ``map.msg`` (which stays exactly the
stella_vslam format), ``patches.npz``: for every landmark a small grey patch from one keyframe render
centred on the landmark's projection, the surface normal there and that keyframe's pose. At run time
the patch is warped into the live view by the homography of the landmark's tangent plane and the live
frame is aligned to it by Lucas-Kanade on zero-mean, unit-variance patches (exposure and white balance
differ between the scan and the camera).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from services.io.atomic import atomic_write
from services.kernels import optional_kernels
from services.render.depth_sampling import hole_depth

__all__ = ["PATCH_FILE", "PATCH_FORMAT_VERSION", "LandmarkPatches", "map_fingerprint", "sample_patches", "align_to_patches", "hole_noise",
           "alignment_backend", "corner_scores", "search_patches"]

PATCH_FILE = "patches.npz"
PATCH_FORMAT_VERSION = 1


@dataclass
class LandmarkPatches:
    lm_ids: np.ndarray  # (N,) int64 landmark ids of the map
    patches: np.ndarray  # (N, S, S) uint8, centred on the landmark's projection in its source keyframe
    normals: np.ndarray  # (N, 3) float32 unit surface normals (world), towards the source camera
    src: np.ndarray  # (N,) int32 index into src_T_cw
    src_T_cw: np.ndarray  # (V, 3, 4) float64 world-to-camera of the source keyframes
    K: np.ndarray  # (3, 3) float64 pinhole intrinsics of the source renders (undistorted)
    map_fp: str = ""  # map_fingerprint() of the map these patches belong to
    pos: np.ndarray | None = None  # (N, 3) float64 where alignment places each landmark: its depth along the source ray
    #                                refitted to the other keyframes' renders (the map's ORB position stays in map.msg);
    #                                None (a file from before them): the map's positions
    noise: np.ndarray | None = None  # (N,) float32 >= 1: how much noisier than a patch cut from measured surroundings
    #                                  each patch aligns (:func:`hole_noise`); None (a file from before it): all 1

    def __post_init__(self) -> None:
        # one dtype and layout per field, whoever made them (the map's file, a keyframe's render, the builder): the
        # compiled kernels take each combination as a signature of its own, ~2 s to compile on first use (nine there were)
        self.lm_ids = np.ascontiguousarray(self.lm_ids, np.int64)
        self.patches = np.ascontiguousarray(self.patches, np.uint8)
        self.normals = np.ascontiguousarray(self.normals, np.float64)
        self.src = np.ascontiguousarray(self.src, np.int64)
        self.src_T_cw = np.ascontiguousarray(self.src_T_cw, np.float64)
        self.K = np.ascontiguousarray(self.K, np.float64)
        if self.pos is not None:
            self.pos = np.ascontiguousarray(self.pos, np.float64)
        if self.noise is not None:
            self.noise = np.ascontiguousarray(self.noise, np.float32)

    @property
    def size(self) -> int:
        return int(self.patches.shape[1])

    def save(self, path: str | Path) -> None:
        meta = {"format_version": PATCH_FORMAT_VERSION, "count": int(len(self.lm_ids)), "size": self.size,
                "map_fingerprint": self.map_fp}
        with atomic_write(path, "wb") as f:
            extra = {} if self.pos is None else {"pos": np.asarray(self.pos, np.float64)}
            if self.noise is not None:
                extra["noise"] = np.asarray(self.noise, np.float32)
            np.savez(f, lm_ids=self.lm_ids, patches=self.patches, normals=self.normals.astype(np.float32),
                     src=self.src.astype(np.int32), src_T_cw=self.src_T_cw, K=self.K, meta=np.array(json.dumps(meta)), **extra)

    @classmethod
    def load(cls, path: str | Path) -> "LandmarkPatches":
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["meta"]))
                arrays = {k: z[k] for k in ("lm_ids", "patches", "normals", "src", "src_T_cw", "K")}
                pos = z["pos"] if "pos" in z.files else None  # optional: older files lack it
                noise = z["noise"] if "noise" in z.files else None  # (so does this)
        except (OSError, KeyError, ValueError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: not a landmark patch file ({e})") from None
        if meta.get("format_version") != PATCH_FORMAT_VERSION:
            raise ValueError(f"{path}: landmark patches format {meta.get('format_version')} is not {PATCH_FORMAT_VERSION}; "
                             "rebuild the map")
        p = cls(arrays["lm_ids"], arrays["patches"], arrays["normals"], arrays["src"], arrays["src_T_cw"], arrays["K"],
                str(meta.get("map_fingerprint", "")), pos, noise)  # (__post_init__ gives each field its dtype)
        n = len(p.lm_ids)
        if p.patches.shape[0] != n or p.normals.shape != (n, 3) or len(p.src) != n or (n and p.src.max() >= len(p.src_T_cw)) \
                or (pos is not None and (pos.shape != (n, 3) or not np.isfinite(pos).all())) \
                or (noise is not None and (noise.shape != (n,) or not (noise >= 1).all())):
            raise ValueError(f"{path}: inconsistent landmark patch arrays")
        return p


def hole_noise(measured: np.ndarray, uv: np.ndarray, width: int) -> np.ndarray:
    """(N,) float32 >= 1: how much noisier a patch centred at each of ``uv`` in a render aligns, from how far the
    pixels within 8 px (at 480 wide) of it lie from the render's measured pixels (``measured``): deepest in a hole.
    Hole filling makes up the colours there, and a made-up edge is drawn where the scene has none.

    Measured on the tests' 0.6 degree scan (patches from the render against the same from the simulator's mesh,
    aligned into live frames at the true pose): 0.12-0.19 px median where every pixel within 8 px is at most 1.4 px
    from a measured one, 0.33 px up to 2.3 px, 0.8-0.9 px beyond: roughly (d / 1.4)^2 for the largest distance d (px
    at 480 wide). Weighing alignments by that in full held back 19 more poses as too uncertain on the office seed 8
    walk (189 vs 208 of 300, at the same 0.25 cm); by its square root, d / 1.4 (this), 212, while the office walk's
    error still fell 0.41 -> 0.35 cm and its poses beyond 3 sigma 30 -> 22 (benchmarks/RESULTS.md, stop 40)."""
    d = hole_depth(measured, uv, max(4, 8 * width // 480)) * (480.0 / width)
    return np.maximum(1.0, d / 1.4).astype(np.float32)


def corner_scores(patches: np.ndarray, half: int = 6) -> np.ndarray:
    """How corner-like each patch (N, S, S) is around its centre: the smaller eigenvalue of the gradient
    structure over their sum (0 on an edge or a flat patch, 0.5 on an isotropic corner)."""
    c = (patches.shape[1] - 1) // 2
    a = patches[:, c - half - 1: c + half + 2, c - half - 1: c + half + 2].astype(np.float32)
    gx = 0.5 * (a[:, 1:-1, 2:] - a[:, 1:-1, :-2])
    gy = 0.5 * (a[:, 2:, 1:-1] - a[:, :-2, 1:-1])
    sxx, sxy, syy = (gx * gx).sum((1, 2)), (gx * gy).sum((1, 2)), (gy * gy).sum((1, 2))
    tr = sxx + syy
    lmin = 0.5 * (tr - np.sqrt((sxx - syy) ** 2 + 4 * sxy * sxy))
    return np.where(tr > 1e-6, lmin / np.maximum(tr, 1e-6), 0.0)


def map_fingerprint(lm_ids: np.ndarray, lm_pos: np.ndarray) -> str:
    """Which map a patch file belongs to: a hash of the landmarks' ids and positions (to the millimetre)."""
    import hashlib

    h = hashlib.sha256(np.ascontiguousarray(lm_ids, np.int64).tobytes())
    h.update(np.round(np.asarray(lm_pos, np.float64) * 1000).astype(np.int64).tobytes())
    return h.hexdigest()[:16]


def _kernels():
    """The compiled alignment kernels (:mod:`services.prebuild.patch_kernels`), or None (numba not installed, or
    ``CRISTAL_KERNELS=numpy``): then numpy does the same arithmetic."""
    return optional_kernels("services.prebuild.patch_kernels")


def alignment_backend(warm: bool = False) -> str:
    """Which path :func:`align_to_patches` takes: "numba" (compiled kernels) or "numpy". ``warm``: compile the kernels
    now (a second or so, from numba's on-disk cache after the first time) rather than on the first frame aligned."""
    kern = _kernels()
    if kern is None:
        return "numpy"
    if warm:
        lp = LandmarkPatches(np.zeros(1, np.int64), np.zeros((1, 23, 23), np.uint8), np.array([[0.0, 0.0, -1.0]]),
                             np.zeros(1, np.int64), np.array([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]]),
                             np.array([[100.0, 0, 32], [0, 100, 32], [0, 0, 1]]))
        align_to_patches(lp, np.zeros(1, np.int64), np.array([[0.0, 0.0, 2.0]]), np.eye(3), np.zeros(3), lp.K,
                         np.zeros((64, 64), np.float32))
    return "numba"


def sample_patches(img: np.ndarray, centres: np.ndarray, size: int) -> np.ndarray:
    """(N, size, size) float32 bilinear samples of ``img`` on a pixel grid centred at each of ``centres`` (N, 2)."""
    h = (size - 1) / 2.0
    o = np.arange(size, dtype=np.float32) - np.float32(h)
    src = np.asarray(img, np.float32)
    step = max(1, (32767 - 1) // size)  # one remap's map is at most 32767 rows (OpenCV): patches stacked in chunks
    out = np.empty((len(centres), size, size), np.float32)
    for i in range(0, len(centres), step):
        c = centres[i:i + step]
        n = len(c)
        mx = np.broadcast_to(c[:, 0, None, None].astype(np.float32) + o[None, None, :], (n, size, size))
        my = np.broadcast_to(c[:, 1, None, None].astype(np.float32) + o[None, :, None], (n, size, size))
        out[i:i + n] = cv2.remap(src, np.ascontiguousarray(mx.reshape(n * size, size)), np.ascontiguousarray(
            my.reshape(n * size, size)), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(n, size, size)
    return out


def _homographies(lp: LandmarkPatches, idx: np.ndarray, P_w: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray,
                  K: np.ndarray) -> np.ndarray:
    """(M, 3, 3) float64: live pixels to source-keyframe pixels through each landmark's tangent plane, scaled to
    H[2, 2] = 1. Each window pixel's ray meets the plane n.X = n.P; seen from the source keyframe (X_s = A X + b,
    A = R_s R^T, b = t_s - A t) the plane maps live pixels to source pixels by H = K_s (dpl A + b n^T) K^-1, dpl = n.P
    (live camera coordinates)."""
    kern = _kernels()
    if kern is not None:
        H = np.empty((len(idx), 3, 3))
        # the pose C-ordered and writable: a read-only or transposed one compiled the kernel anew
        R, t = np.array(R_cw, np.float64, order="C"), np.array(t_cw, np.float64)
        kern.homographies(lp.K, lp.src_T_cw, lp.src, lp.normals, np.ascontiguousarray(idx, np.int64),
                          np.ascontiguousarray(P_w, np.float64), R, t, np.ascontiguousarray(K, np.float64), H)
        return H
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Xc = P_w @ R_cw.T + t_cw
    n_c = lp.normals[idx] @ R_cw.T
    dpl = np.einsum("mj,mj->m", n_c, Xc)
    S = lp.src_T_cw[lp.src[idx]]
    A = S[:, :, :3] @ R_cw.T
    b = S[:, :, 3] - np.einsum("mij,j->mi", A, t_cw)
    Kinv = np.array([[1 / fx, 0, -cx / fx], [0, 1 / fy, -cy / fy], [0, 0, 1.0]])
    H = lp.K @ (dpl[:, None, None] * A + b[:, :, None] * n_c[:, None, :]) @ Kinv  # (M, 3, 3)
    return H / np.where(np.abs(H[:, 2:3, 2:3]) > 1e-12, H[:, 2:3, 2:3], 1e-12)


def warp_noise_factor(H: np.ndarray, u0: np.ndarray) -> np.ndarray:
    """(M,) how much noisier than a template seen at its source's own scale an alignment through the live-to-source
    homographies ``H`` at live pixels ``u0`` is: the warp's Jacobian has singular values s_max >= s_min (source px
    per live px); a template stretched (s_min < 1: the live camera nearer or more oblique than the source keyframe)
    has lost the detail that places it, and one shrunk by over 2x (s_max > 2) aliases. Measured at the true poses of
    three office walks (34 k alignments): the median error grows from 0.2 px at s_min >= 1 to 0.45 px at 0.6 and 1.0
    px below 0.3, and to 0.4-0.8 px at s_max 2-4; divided by max(1, 1/s_min) max(1, s_max/2)^1.5 it is 0.16-0.30 px
    across all of them."""
    u = np.column_stack([u0, np.ones(len(u0))])
    h = np.einsum("mij,mj->mi", H, u)
    w = h[:, 2]
    J = (H[:, :2, :2] - h[:, :2, None] * H[:, 2, None, :2] / w[:, None, None]) / w[:, None, None]  # d(src)/d(live)
    sv = np.linalg.svd(J, compute_uv=False)
    s_max, s_min = sv[:, 0], np.maximum(sv[:, 1], 1e-6)
    return np.maximum(1.0, 1.0 / s_min) * np.maximum(1.0, s_max / 2.0) ** 1.5


def _source_pixels(lp: LandmarkPatches, idx: np.ndarray, P_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each landmark ``P_w`` projects in its source keyframe (the stored patch's centre), float32 (u, v)."""
    S = lp.src_T_cw[lp.src[idx]]
    Ps = np.einsum("mij,mj->mi", S[:, :, :3], P_w) + S[:, :, 3]
    Ks = lp.K
    return ((Ks[0, 0] * Ps[:, 0] / Ps[:, 2] + Ks[0, 2]).astype(np.float32),
            (Ks[1, 1] * Ps[:, 1] / Ps[:, 2] + Ks[1, 2]).astype(np.float32))


def _template(lp: LandmarkPatches, idx: np.ndarray, P_w: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray, K: np.ndarray,
              u0: np.ndarray, half: int, H: np.ndarray | None = None, src_px: tuple | None = None) -> np.ndarray:
    """The stored patches as the live camera (``R_cw``, ``t_cw``, ``K``) sees them in the (2 half + 1)^2 windows at
    ``u0`` (M, 2): (M, k^2) float32. ``H``: their :func:`_homographies`, ``src_px``: their :func:`_source_pixels`,
    when already computed."""
    M, k = len(idx), 2 * half + 1
    H = (_homographies(lp, idx, P_w, R_cw, t_cw, K) if H is None else H).astype(np.float32)
    ups, vps = _source_pixels(lp, idx, P_w) if src_px is None else src_px
    kern = _kernels()
    if kern is not None:
        out = np.empty((M, k * k), np.float32)
        kern.warp_template(lp.patches, np.ascontiguousarray(idx, np.int64), np.ascontiguousarray(H),
                           np.ascontiguousarray(u0, np.float32), ups, vps, half, out)
        return out
    o = np.arange(k, dtype=np.float32) - half
    gx = (u0[:, 0, None].astype(np.float32) + o)[:, None, :]  # (M, 1, k): columns
    gy = (u0[:, 1, None].astype(np.float32) + o)[:, :, None]  # (M, k, 1): rows

    def row(i):
        return H[:, i, 0, None, None] * gx + (H[:, i, 1, None, None] * gy + H[:, i, 2, None, None])

    wz = row(2)
    wz = np.where(np.abs(wz) > 1e-6, wz, 1e-6)
    us, vs = row(0) / wz, row(1) / wz
    hs = (lp.size - 1) / 2.0
    px = np.clip(us - ups[:, None, None] + hs, 0, lp.size - 1)
    py = np.clip(vs - vps[:, None, None] + hs, 0, lp.size - 1) + (np.arange(M, dtype=np.float32) * lp.size)[:, None, None]
    stack = lp.patches[idx].reshape(M * lp.size, lp.size).astype(np.float32)
    return cv2.remap(stack, px.reshape(M * k, k).astype(np.float32), py.reshape(M * k, k).astype(np.float32),
                     cv2.INTER_LINEAR).reshape(M, k * k)


def _rowdot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (N, k) arrays, without a temporary (N, k) product."""
    return np.einsum("ij,ij->i", x, y)


def _normalise(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zero mean, unit variance per patch (rows of (N, k)); returns the patches and their std."""
    a = a - a.mean(1, keepdims=True)
    s = np.sqrt(_rowdot(a, a) / a.shape[1]) + 1e-6
    a /= s[:, None]
    return a, s


def _smeared_template(lp: LandmarkPatches, idx: np.ndarray, P_w: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray,
                      K: np.ndarray, u0: np.ndarray, half: int, blur: list | None, H: np.ndarray | None = None) -> np.ndarray:
    """:func:`_template`, or with ``blur`` (more world-to-camera poses passed through during the exposure) the mean of
    the views from each pose in the same window: a moving frame's smear. ``H``: the frame pose's homographies."""
    src_px = _source_pixels(lp, idx, P_w)
    tmpl = _template(lp, idx, P_w, R_cw, t_cw, K, u0, half, H, src_px)
    if blur:
        tmpl = (tmpl + sum(_template(lp, idx, P_w, R_i, t_i, K, u0, half, src_px=src_px) for R_i, t_i in blur)) / (1 + len(blur))
    return tmpl


def _align_windows_numpy(gray: np.ndarray, u0f: np.ndarray, T: np.ndarray, half: int, iterations: int):
    """:func:`services.prebuild.patch_kernels.align_windows` in numpy, all windows at once (the light client's path
    when numba is not installed): returns the shifts (M, 2), the not-an-edge mask, the last zero-mean normalised
    correlations and the gradient structures (a, b, c) of the windows."""
    M, k = len(u0f), 2 * half + 1
    d = np.zeros((M, 2), np.float32)
    ok = np.ones(M, bool)
    # the live window is sampled one pixel wider on every side: central differences give the gradients
    oe = np.arange(k + 2, dtype=np.float32) - (half + 1)
    ox, oy = np.broadcast_to(oe[None, :], (k + 2, k + 2)), np.broadcast_to(oe[:, None], (k + 2, k + 2))
    r = np.zeros_like(T)
    a, bb, c = np.zeros(M, np.float32), np.zeros(M, np.float32), np.zeros(M, np.float32)
    act = np.arange(M)  # windows still moving
    kk = k * k
    for _ in range(iterations):
        n = len(act)
        if n == 0:
            break
        cx_ = u0f[act, 0] + d[act, 0]
        cy_ = u0f[act, 1] + d[act, 1]
        mx = (cx_[:, None, None] + ox).reshape(n * (k + 2), k + 2)
        my = (cy_[:, None, None] + oy).reshape(n * (k + 2), k + 2)
        w = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(n, k + 2, k + 2)
        In, sd = _normalise(w[:, 1:-1, 1:-1].reshape(n, kk))
        # central differences of the normalised window: 0.5 (right - left) / sd, the scale applied to the sums
        gx = (w[:, 1:-1, 2:] - w[:, 1:-1, :-2]).reshape(n, kk)
        gy = (w[:, 2:, 1:-1] - w[:, :-2, 1:-1]).reshape(n, kk)
        s1 = 0.5 / sd
        s2 = s1 * s1
        ra = In - (T if n == M else T[act])
        r[act] = ra
        aa, bbb, cc = _rowdot(gx, gx) * s2, _rowdot(gx, gy) * s2, _rowdot(gy, gy) * s2
        a[act], bb[act], c[act] = aa, bbb, cc
        ga, gb = _rowdot(gx, ra) * s1, _rowdot(gy, ra) * s1
        det = aa * cc - bbb * bbb
        well = det > 1e-3 * (aa + cc) ** 2  # not an edge: along an edge the shift is free
        ok[act] &= well
        det = np.where(well, det, 1.0)
        step = -np.column_stack([(cc * ga - bbb * gb) / det, (aa * gb - bbb * ga) / det])
        keep = well & (np.abs(step).max(axis=1) >= 0.01)
        d[act] += np.where(well[:, None], step, 0.0)
        act = act[keep]
    zncc = 1.0 - 0.5 * (r * r).mean(1)  # both unit variance: mean squared difference = 2 (1 - zncc)
    return d, ok, zncc, a, bb, c


def align_to_patches(lp: LandmarkPatches, idx: np.ndarray, P_w: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray,
                     K: np.ndarray, gray: np.ndarray, half: int = 6, iterations: int = 8, max_px: float = 6.0,
                     min_zncc: float = 0.75, blur: list | None = None, warp_noise_ref: float = 0.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where landmarks ``P_w`` (M, 3) with patches ``idx`` (M,) appear in the live frame.

    The live camera is (``R_cw``, ``t_cw``, pinhole ``K``); ``gray`` is the undistorted live frame (float32).
    For each landmark the
    (2 half + 1)^2 pixel window around its projection is mapped through the landmark's tangent plane
    into its source keyframe and sampled from the stored patch (the template, as the live camera would
    see it); the live window is then shifted by Gauss-Newton until it matches. Returns the refined
    pixels (M, 2), a mask of those that converged within ``max_px`` of the projection, on a patch
    that is not an edge, with a zero-mean normalised correlation of at least ``min_zncc``, and each
    measurement's shape of information (M, 2, 2): the patch's gradient structure scaled to trace 2, so a
    corner weighs like an isotropic 1 px measurement and a near-edge mostly across the edge (along it the
    alignment barely moves from where it started, and a pose solve must not be held there).

    ``blur``: more world-to-camera poses (R, t) the camera passed through during the exposure; each template
    is then the mean of the patch seen from all of them in the same window (a moving frame's smear).

    ``warp_noise_ref`` > 0: each information is scaled by (warp_noise_ref / :func:`warp_noise_factor`)^2, so a template
    stretched or shrunk by its warp weighs less than one seen near its source's scale, and one with the factor
    ``warp_noise_ref`` weighs as before.

    ``max_px`` must leave room for the error of the pose given: the windows converge from 4 px and more,
    and a bound close to the pose's error keeps the windows that did not move, which pulls a pose solved
    from them back to the pose given.
    """
    M = len(idx)
    if M == 0:
        return np.zeros((0, 2)), np.zeros(0, bool), np.zeros((0, 2, 2))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    Xc = P_w @ R_cw.T + t_cw
    z = np.maximum(Xc[:, 2], 1e-6)
    u0 = np.column_stack([fx * Xc[:, 0] / z + cx, fy * Xc[:, 1] / z + cy])
    H = _homographies(lp, idx, P_w, R_cw, t_cw, K)
    T, _ = _normalise(_smeared_template(lp, idx, P_w, R_cw, t_cw, K, u0, half, blur, H))
    u0f = u0.astype(np.float32)
    kern = _kernels()
    if kern is not None:
        d, ok, zncc, abc = np.zeros((M, 2), np.float32), np.ones(M, bool), np.zeros(M), np.zeros((M, 3))
        kern.align_windows(np.ascontiguousarray(gray, np.float32), u0f, T, half, iterations, d, ok, zncc, abc)
        a, bb, c = abc.T
    else:
        d, ok, zncc, a, bb, c = _align_windows_numpy(gray, u0f, T, half, iterations)
    ok &= (np.linalg.norm(d, axis=1) <= max_px) & (zncc >= min_zncc)
    tr = np.maximum(a + c, 1e-9)
    info = (2.0 / tr)[:, None, None] * np.stack([np.stack([a, bb], 1), np.stack([bb, c], 1)], 1)
    if warp_noise_ref > 0:
        info = info * (warp_noise_ref / warp_noise_factor(H, u0))[:, None, None] ** 2
    if lp.noise is not None:
        info = info / lp.noise[idx][:, None, None] ** 2
    return u0 + d, ok, info


def search_patches(lp: LandmarkPatches, idx: np.ndarray, P_w: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray,
                   K: np.ndarray, gray: np.ndarray, radius: int = 24, half: int = 6, min_ncc: float = 0.8,
                   blur: list | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where the landmarks ``P_w`` with patches ``idx`` appear in the live frame (``gray``, undistorted float32), searched
    by normalised cross-correlation within ``radius`` px of their projections by the camera (``R_cw``, ``t_cw``, pinhole
    ``K``), each template built as :func:`align_to_patches` builds it. Returns the best pixels (M, 2) and a mask of
    those that peak at ``min_ncc`` or more. For a camera pose too far off for the alignment's windows to converge (a
    few px): a turn that changed speed or direction between two frames. ``blur``: as for :func:`align_to_patches`."""
    M = len(idx)
    uv, found = np.zeros((M, 2)), np.zeros(M, bool)
    if M == 0:
        return uv, found
    k = 2 * half + 1
    Xc = P_w @ R_cw.T + t_cw
    z = np.maximum(Xc[:, 2], 1e-6)
    u0 = np.column_stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]])
    tmpl = _smeared_template(lp, idx, P_w, R_cw, t_cw, K, u0, half, blur).reshape(M, k, k)
    h, w = gray.shape
    for i in range(M):
        x0, y0 = int(round(u0[i, 0])) - half - radius, int(round(u0[i, 1])) - half - radius
        x1, y1 = max(x0, 0), max(y0, 0)  # the search window, clipped to the image
        x2, y2 = min(x0 + k + 2 * radius, w), min(y0 + k + 2 * radius, h)
        if x2 - x1 < k or y2 - y1 < k or tmpl[i].std() < 1e-3:
            continue
        res = cv2.matchTemplate(gray[y1:y2, x1:x2], tmpl[i], cv2.TM_CCOEFF_NORMED)
        _, best, _, (bx, by) = cv2.minMaxLoc(res)
        uv[i] = (x1 + bx + half, y1 + by + half)
        found[i] = best >= min_ncc
    return uv, found
