"""ORB features with stella_vslam's settings, for Prebuild & Localize (numpy + OpenCV only, no torch).

stella_vslam's extractor (``feature/orb_extractor.cc``): an 8-level pyramid at scale 1.2 (each
level ``cv::resize`` INTER_LINEAR of the previous one); per level, FAST with non-maximum suppression
in 64-pixel cells (plus 6 px overlap) at ``ini_fast_threshold`` (20), retried at
``min_fast_threshold`` (7) in cells where nothing was found; one keypoint (the strongest) per cell of
a distribution grid; intensity-centroid orientation on the level image (radius 15); the 256-bit
rBRIEF descriptor (OpenCV's ``bit_pattern_31`` pairs) on the level image blurred with a 7x7, sigma 2
Gaussian (BORDER_REFLECT_101); keypoints scaled back to level 0.

Here OpenCV's ORB does the detection at the minimum threshold, the orientation and the
descriptor in C++ (same pattern, same blur, same intensity centroid; its pyramid uses
INTER_LINEAR_EXACT, which differs from INTER_LINEAR by at most one grey level on a few pixels),
and numpy then applies stella's selection: per level and 64-px cell, keypoints whose FAST score
reaches the initial threshold when the cell has any (else those of the minimum threshold), then
the strongest keypoint per distribution cell. ``docs/PREBUILD.md`` records how the descriptors
compare with a re-implementation of stella's extractor.

Descriptors are (N, 32) uint8; stella's map file stores each as 8 little-endian uint32
(:func:`desc_to_u32` / :func:`u32_to_desc`).
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import cv2
import numpy as np

__all__ = ["OrbSettings", "OrbFeatures", "OrbExtractor", "desc_to_u32", "u32_to_desc", "hamming", "level_centres"]


@dataclass(frozen=True)
class OrbSettings:
    scale_factor: float = 1.2
    num_levels: int = 8
    ini_fast_threshold: int = 20
    min_fast_threshold: int = 7
    max_keypoints: int = 1500  # upper bound over all levels (split geometrically like ORB-SLAM / OpenCV)
    distribution_cell: int = 12  # px at level 0: at most one keypoint per cell of this size (stella: sqrt(min_area))
    fast_cell: int = 64  # stella's FAST cell size (ini/min threshold decided per cell)
    edge: int = 19  # stella's orb_patch_radius: no keypoint closer to the level image border

    @property
    def scale_factors(self) -> np.ndarray:
        return self.scale_factor ** np.arange(self.num_levels)


@dataclass
class OrbFeatures:
    kpts: np.ndarray  # (N, 2) float32 pixels in the image the features were extracted from (level 0)
    angles: np.ndarray  # (N,) float32 degrees [0, 360)
    octaves: np.ndarray  # (N,) int32 pyramid level
    responses: np.ndarray  # (N,) float32 FAST score
    desc: np.ndarray  # (N, 32) uint8

    def __len__(self) -> int:
        return int(len(self.kpts))

    def subset(self, idx: np.ndarray) -> "OrbFeatures":
        return OrbFeatures(self.kpts[idx], self.angles[idx], self.octaves[idx], self.responses[idx], self.desc[idx])


def desc_to_u32(desc: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 -> (N, 8) uint32, the little-endian view stella_vslam writes."""
    return np.ascontiguousarray(desc, dtype=np.uint8).view("<u4").reshape(-1, 8)


def u32_to_desc(u32) -> np.ndarray:
    """(N, 8) uint32 (little-endian view) -> (N, 32) uint8 bytes."""
    a = np.asarray(u32, dtype=np.int64).reshape(-1, 8)
    if a.size and (a.min() < 0 or a.max() > 0xFFFFFFFF):
        raise ValueError("descriptor words must be uint32")
    return np.ascontiguousarray(a.astype("<u4")).view(np.uint8).reshape(-1, 32)


def level_centres(kpts: np.ndarray, octaves: np.ndarray, scale_factor: float) -> np.ndarray:
    """Level-0 pixel centres of keypoints (float64).

    stella_vslam and OpenCV report a level-L keypoint at ``x_L * s`` (``s = scale_factor ** L``), which is
    ``0.5 (s - 1)`` pixels up-left of where that level pixel's centre lies in the full image
    (``(x_L + 0.5) s - 0.5``); up to 1.3 px at level 7. The map stores keypoints as stella computes
    them; geometry (back-projection, pose optimisation) uses the centres.
    """
    s = np.asarray(scale_factor, np.float64) ** np.asarray(octaves, np.float64)
    return np.asarray(kpts, np.float64) + (0.5 * (s - 1.0))[:, None]


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Element-wise Hamming distance of broadcastable (..., 32) uint8 descriptor arrays."""
    x = np.bitwise_xor(np.ascontiguousarray(a).view(np.uint64), np.ascontiguousarray(b).view(np.uint64))
    return np.bitwise_count(x).sum(axis=-1, dtype=np.int32)


def _umax(half: int = 15) -> np.ndarray:
    """stella_vslam's / OpenCV's circular patch extent per row for the intensity centroid."""
    u = np.zeros(half + 1, np.int64)
    vmax = int(math.floor(half * math.sqrt(2.0) / 2 + 1))
    vmin = int(math.ceil(half * math.sqrt(2.0) / 2))
    for v in range(vmax + 1):
        u[v] = int(round(math.sqrt(half * half - v * v)))
    v0 = 0
    for v in range(half, vmin - 1, -1):
        while u[v0] == u[v0 + 1]:
            v0 += 1
        u[v] = v0
        v0 += 1
    return u


_UMAX = _umax()
_PATCH = np.array([(du, dv) for dv in range(-15, 16) for du in range(-_UMAX[abs(dv)], _UMAX[abs(dv)] + 1)], np.int64)


def stella_pyramid(gray: np.ndarray, num_levels: int = 8, scale_factor: float = 1.2) -> list[np.ndarray]:
    """stella_vslam's image pyramid: level L = cv::resize(level L-1, round(size / s^L), INTER_LINEAR)."""
    pyr = [gray]
    for L in range(1, num_levels):
        s = scale_factor ** L
        pyr.append(cv2.resize(pyr[-1], (int(round(gray.shape[1] / s)), int(round(gray.shape[0] / s))),
                              interpolation=cv2.INTER_LINEAR))
    return pyr


def ic_angles(level: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Intensity-centroid orientation (degrees, cv::fastAtan2) at level-image points, as stella_vslam's ic_angle."""
    c = np.round(pts).astype(np.int64)  # cvRound
    img = level.astype(np.int64)
    x = c[:, 0, None] + _PATCH[None, :, 0]
    y = c[:, 1, None] + _PATCH[None, :, 1]
    vals = img[y, x]
    m10 = (vals * _PATCH[None, :, 0]).sum(1)
    m01 = (vals * _PATCH[None, :, 1]).sum(1)
    return np.array([cv2.fastAtan2(float(b), float(a)) for a, b in zip(m10, m01)], np.float32)


class OrbExtractor:
    """stella_vslam-style ORB on a grey (or BGR) uint8 image."""

    def __init__(self, settings: OrbSettings = OrbSettings()):
        self.s = settings
        # detect generously at the minimum threshold; the stella selection below keeps what stella would
        self._orb = cv2.ORB_create(nfeatures=settings.max_keypoints * 3, scaleFactor=settings.scale_factor,
                                   nlevels=settings.num_levels, edgeThreshold=settings.edge, firstLevel=0, WTA_K=2,
                                   scoreType=cv2.ORB_FAST_SCORE, patchSize=31, fastThreshold=settings.min_fast_threshold)
        sf = settings.scale_factors
        # per-level share of max_keypoints, geometric like stella / ORB-SLAM
        w = (1 / settings.scale_factor) ** np.arange(settings.num_levels)
        self._per_level = np.maximum(1, np.round(settings.max_keypoints * w / w.sum())).astype(int)
        self._sf = sf

    def extract(self, image: np.ndarray, mask: np.ndarray | None = None) -> OrbFeatures:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        kps, desc = self._orb.detectAndCompute(gray, mask)
        if not kps or desc is None:
            return OrbFeatures(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32),
                               np.zeros(0, np.float32), np.zeros((0, 32), np.uint8))
        n = len(kps)
        arr = np.array([(k.pt[0], k.pt[1], k.angle, k.octave, k.response) for k in kps], dtype=np.float64).reshape(n, 5)
        return self._select(arr, desc)

    def extract_stella(self, image: np.ndarray) -> OrbFeatures:
        """As :meth:`extract`, then orientation and descriptor recomputed exactly as stella_vslam does.

        The keypoints are OpenCV's; each level's angle is the intensity centroid on stella's
        INTER_LINEAR pyramid and the descriptor OpenCV's rBRIEF (the pattern stella copies) on that
        level image blurred 7x7, sigma 2. Level 0 is bit-identical to :meth:`extract`; higher levels
        differ from OpenCV's pyramid by a few bits (``docs/PREBUILD.md``). Used for maps stella loads.
        """
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        f = self.extract(gray)
        if len(f) == 0:
            return f
        s = self.s
        pyr = stella_pyramid(gray, s.num_levels, s.scale_factor)
        if not hasattr(self, "_one"):
            self._one = cv2.ORB_create(nfeatures=1, scaleFactor=s.scale_factor, nlevels=1, edgeThreshold=s.edge,
                                       firstLevel=0, WTA_K=2, scoreType=cv2.ORB_FAST_SCORE, patchSize=31)
        angles = f.angles.copy()
        desc = f.desc.copy()
        keep = np.ones(len(f), bool)
        for L in range(s.num_levels):
            sel = np.flatnonzero(f.octaves == L)
            if len(sel) == 0:
                continue
            sc = s.scale_factor ** L
            pts = f.kpts[sel].astype(np.float64) / sc
            ang = ic_angles(pyr[L], pts) if L > 0 else f.angles[sel]
            kps = [cv2.KeyPoint(float(p[0]), float(p[1]), 31.0, float(a), 0.0, 0) for p, a in zip(pts, ang)]
            kps2, d = self._one.compute(pyr[L], kps)
            if len(kps2) != len(kps):  # compute() dropped border keypoints: align by position
                pos = {(k.pt[0], k.pt[1]): j for j, k in enumerate(kps2)}
                j = np.array([pos.get((k.pt[0], k.pt[1]), -1) for k in kps])
                keep[sel[j < 0]] = False
                sel, ang, j = sel[j >= 0], ang[j >= 0], j[j >= 0]
                d = d[j] if d is not None else np.zeros((0, 32), np.uint8)
            angles[sel] = ang
            desc[sel] = d
        out = OrbFeatures(f.kpts, angles, f.octaves, f.responses, desc)
        return out if keep.all() else out.subset(np.flatnonzero(keep))

    def _select(self, arr: np.ndarray, desc: np.ndarray) -> OrbFeatures:
        s = self.s
        oct_ = arr[:, 3].astype(np.int64)
        resp = arr[:, 4]
        scale = self._sf[oct_]
        lx, ly = arr[:, 0] / scale, arr[:, 1] / scale  # level coordinates
        # stella: ini threshold where a FAST cell has any such corner, else the min threshold
        fc = ((oct_ * 4096 + (ly // s.fast_cell).astype(np.int64)) * 4096 + (lx // s.fast_cell).astype(np.int64))
        strong = resp >= s.ini_fast_threshold
        _, inv = np.unique(fc, return_inverse=True)
        cell_has_strong = np.zeros(inv.max() + 1, bool)
        cell_has_strong[inv[strong]] = True
        keep = strong | ~cell_has_strong[inv]
        # distribution: the strongest keypoint per grid cell (cell shrinks with the level like stella's)
        dc = s.distribution_cell / scale
        gc = ((oct_ * 8192 + (ly // dc).astype(np.int64)) * 8192 + (lx // dc).astype(np.int64))
        idx = np.flatnonzero(keep)
        order = idx[np.lexsort((-resp[idx], gc[idx]))]
        first = np.ones(len(order), bool)
        first[1:] = gc[order[1:]] != gc[order[:-1]]
        sel = order[first]
        # per-level cap, strongest first
        sel = sel[np.lexsort((-resp[sel], oct_[sel]))]
        lvl = oct_[sel]
        start = np.searchsorted(lvl, np.arange(s.num_levels))
        rank = np.arange(len(sel)) - start[lvl]
        sel = np.sort(sel[rank < self._per_level[lvl]])
        return OrbFeatures(arr[sel, :2].astype(np.float32), (arr[sel, 2] % 360.0).astype(np.float32),
                           oct_[sel].astype(np.int32), resp[sel].astype(np.float32), desc[sel])
