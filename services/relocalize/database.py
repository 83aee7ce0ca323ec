"""The relocalization database: XFeat features of cubemap renders, with the 3D scan points behind them.

Built offline (``cristal build-db``): at every position sampled in the region of interest, the
neural renderer draws the horizontal cubemap faces (optionally up and down); XFeat runs on each
face; keypoints are back-projected to world points with the depth of the scan points around them
(a plane fitted within a few pixels, none on a depth edge: services.render.depth_sampling). Each face also gets a
VLAD global descriptor over a small vocabulary learnt from the database itself, so a query
compares one vector per view before matching features against a handful of candidates: this
keeps relocalization fast with thousands of cubemaps (a 60 x 40 m site).

Written atomically as one ``.npz`` with a format version and the scan it belongs to.
"""

from __future__ import annotations

import json
import logging
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from services.features.matching import mutual_nn
from services.features.xfeat import Features, XFeatExtractor
from services.geometry.camera import Camera
from services.geometry.pnp import PnpResult, solve_pnp
from services.geometry.se3 import Pose
from services.io.atomic import atomic_write
from services.log import progress
from services.relocalize.ambiguity import distinct as _distinct
from services.relocalize.ambiguity import rival

__all__ = ["RelocDB", "DBConfig", "build_database", "DB_FORMAT_VERSION"]

log = logging.getLogger(__name__)
DB_FORMAT_VERSION = 1


@dataclass(frozen=True)
class DBConfig:
    face_size: int = 320  # pixels per cubemap face (90 degrees)
    faces: str = "horizontal"  # "horizontal" (4 faces) or "all" (6)
    top_k: int = 1024  # XFeat keypoints per face
    vocabulary: int = 32  # VLAD words
    depth_radius: int = 4  # px: a keypoint's depth is a plane fitted to the scan points this close ...
    depth_max_residual: float = 0.01  # ... within this fraction of their depth (see services.render.depth_sampling)


def _vlad(desc: np.ndarray, vocab: np.ndarray) -> np.ndarray:
    """Intra-normalised, L2-normalised VLAD of descriptors against a vocabulary (K, 64) -> (K*64,)."""
    if len(desc) == 0:
        return np.zeros(vocab.size, np.float32)
    a = np.argmax(desc @ vocab.T, axis=1)
    v = np.zeros_like(vocab)
    np.add.at(v, a, desc - vocab[a])
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    v = v.ravel()
    return (v / max(np.linalg.norm(v), 1e-12)).astype(np.float32)


@dataclass
class RelocDB:
    view_poses: np.ndarray  # (V, 7) tx ty tz qx qy qz qw, camera-to-world of each face
    view_start: np.ndarray  # (V+1,) int64 offsets into the keypoint arrays
    xyz: np.ndarray  # (M, 3) float64 world points
    desc: np.ndarray  # (M, 64) float32
    vlad: np.ndarray  # (V, K*64) float32
    vocab: np.ndarray  # (K, 64) float32
    meta: dict = field(default_factory=dict)
    match_device: object = None  # a torch device to match descriptors on (the extractor's GPU); None = numpy

    @property
    def n_views(self) -> int:
        return int(len(self.view_poses))

    def view(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        s, e = self.view_start[i], self.view_start[i + 1]
        return self.xyz[s:e], self.desc[s:e]

    def view_pose(self, i: int) -> Pose:
        return Pose.from_tum(self.view_poses[i])

    @classmethod
    def from_views(cls, poses: list[Pose], views: list[tuple[np.ndarray, np.ndarray]], vocab: np.ndarray,
                   meta: dict | None = None) -> "RelocDB":
        """A database of views (``view_features``' output) rendered at camera-to-world ``poses``, with the VLAD words
        ``vocab`` (K, 64) its global descriptors are made of (a database's own)."""
        starts = np.cumsum([0] + [len(x) for x, _ in views]).astype(np.int64)
        xyz = np.concatenate([x for x, _ in views]) if views else np.zeros((0, 3))
        desc = np.concatenate([d for _, d in views]).astype(np.float32) if views else np.zeros((0, 64), np.float32)
        vlad = np.stack([_vlad(d, vocab) for _, d in views]) if views else np.zeros((0, vocab.size), np.float32)
        return cls(np.array([T.to_tum() for T in poses]).reshape(-1, 7), starts, xyz, desc, vlad, vocab, dict(meta or {}))

    # ---- query -------------------------------------------------------------
    def candidates(self, feats: Features, k: int = 8, near: tuple[np.ndarray, float] | None = None) -> np.ndarray:
        """The ``k`` views whose global descriptor is most similar to the query's; with ``near`` =
        (world position, radius m), only among the views rendered within that radius of it."""
        q = _vlad(feats.desc, self.vocab)
        sim = self.vlad @ q
        order = np.argsort(-sim)
        if near is None:
            return order[:k]
        centre, radius = near
        inside = np.linalg.norm(self.view_poses[:, :3] - np.asarray(centre, float), axis=1) <= radius
        return order[inside[order]][:k]

    def _solve_views(self, feats: Features, camera: Camera, views, min_inliers: int,
                     max_error_px: float) -> list[tuple[PnpResult, int]]:
        out = []
        for v in views:
            xyz, desc = self.view(v)
            m = mutual_nn(feats.desc, desc, min_cos=0.8, device=self.match_device)
            if len(m) < min_inliers:
                continue
            # hard RANSAC counts, not the soft refinement's: these counts decide which places are rivals, and a soft
            # solve over every match within 5 thresholds lifts a wrong place's count too (test site: two places 7 m
            # off reached half the true one's and made a clean frame ambiguous). The refined pose comes later.
            r = solve_pnp(feats.kpts[m[:, 0]], xyz[m[:, 1]], camera, max_error_px=max_error_px, soft=False)
            if r is not None and r.n_inliers >= min_inliers:
                out.append((r, int(v)))
        return out

    def localize(self, feats: Features, camera: Camera, k: int = 8, min_inliers: int = 30,
                 max_error_px: float = 3.0, ambiguity: float = 0.8, check: int = 32,
                 near: tuple[np.ndarray, float] | None = None) -> tuple[PnpResult | None, int]:
        """Coarse pose of a query: match against the top-``k`` views, PnP-RANSAC; best by inliers. Returns (result, view).

        Repetitive sites (identical rack aisles, office floors) give several self-consistent poses at
        different places. When a pose more than 1 m or 20 degrees away from the best one has at least
        ``ambiguity`` times its inliers, the place is ambiguous and the answer is None, not a coin toss.
        Rivals are sought among the top-``check`` views, not only the ``k`` searched (``has_rival``).
        ``near`` = (position, radius): search only views within reach of a recent pose (``candidates``).
        """
        # weaker solutions too: a rival only needs ``ambiguity`` x the best's inliers, which may be below min_inliers
        hyps = self.hypotheses(feats, camera, k, max(6, int(ambiguity * min_inliers)), max_error_px, near)
        if not hyps or hyps[0][0].n_inliers < min_inliers or self.ambiguous(hyps, ambiguity) is not None:
            return None, -1
        best, best_view = hyps[0]
        if check > k and self.has_rival(feats, camera, best, k, check, max_error_px, ambiguity, near):
            return None, -1
        return best, best_view

    def hypotheses(self, feats: Features, camera: Camera, k: int = 8, min_inliers: int = 12, max_error_px: float = 3.0,
                   near: tuple[np.ndarray, float] | None = None, within: tuple[np.ndarray, float] | None = None,
                   known: list[tuple[PnpResult, int]] | None = None, skip: int = 0) -> list[tuple[PnpResult, int]]:
        """Coarse poses from the top-``k`` views with at least ``min_inliers`` inliers, the best per place
        (places differ by more than 1 m or 20 degrees), best first, each with its view.

        For callers that verify a pose before trusting it (Render & Match renders at it and matches
        again): a view a metre from a close-up camera shares few features with it (12-25 inliers, yet
        within 5 cm / 2 degrees), where ``localize`` needs 30 to trust a pose it cannot check.
        ``within`` = (position, radius): poses further from it are not hypotheses (the camera cannot be there).
        ``known``, ``skip``: the answer of a call for the top ``skip`` views; the search widens to the top ``k`` without
        solving those again."""
        order = self.candidates(feats, k, near)[skip:]
        solved = _inside(self._solve_views(feats, camera, order, min_inliers, max_error_px), within)
        results = sorted(list(known or []) + solved, key=lambda rv: -rv[0].n_inliers)
        places: list[tuple[PnpResult, int]] = []
        for r, v in results:
            if all(_distinct(r.T_wc, p.T_wc) for p, _ in places):
                places.append((r, v))
        return places

    @staticmethod
    def ambiguous(hyps: list[tuple[PnpResult, int]], ambiguity: float = 0.8, far_ambiguity: float | None = None,
                  verify: Callable[[PnpResult], bool] | None = None,
                  verify_far: Callable[[PnpResult], bool] | None = None) -> str | None:
        """Why another place of ``hypotheses`` fits about as well as the first (``ambiguity`` x its inliers), or,
        with ``far_ambiguity``, two places more than 2 m away fit with that share of them; None if none does.
        ``verify`` / ``verify_far``: asked about rivals within / beyond 2 m instead of counting them
        (services.relocalize.ambiguity)."""
        return RelocDB._rival_in(hyps[0][0], hyps[0][1], hyps[1:], ambiguity, far_ambiguity, verify=verify,
                                 verify_far=verify_far) if len(hyps) > 1 else None

    def has_rival(self, feats: Features, camera: Camera, best: PnpResult, skip: int = 8, check: int = 32,
                  max_error_px: float = 3.0, ambiguity: float = 0.8,
                  near: tuple[np.ndarray, float] | None = None, within: tuple[np.ndarray, float] | None = None,
                  far_ambiguity: float | None = None, verify: Callable[[PnpResult], bool] | None = None,
                  verify_far: Callable[[PnpResult], bool] | None = None) -> str | None:
        """Why (None: not) views ranked ``skip``..``check`` for this query hold another place that fits it about as
        well as ``best``. In the simulated warehouse the true aisle ranked outside the top 8 twice, and a
        wrong aisle 24-30 m away was accepted and then confirmed by its own render; the top 32 held a rival
        both times. Callers that refine the coarse pose first (Render & Match) ask only once it passed,
        so a LOST stretch does not pay for it on every frame. ``within``: as for ``hypotheses``, a place where
        the camera cannot be is no rival."""
        order = self.candidates(feats, check, near)[skip:]
        floor = max(6, int(min(ambiguity, far_ambiguity or ambiguity) * best.n_inliers))  # weaker solutions cannot be rivals
        found = _inside(self._solve_views(feats, camera, order, floor, max_error_px), within)
        # the best place's support: its own views ranked lower may fit better (the office: 50 inliers in the top 8, 91 below)
        support = max([best.n_inliers] + [r.n_inliers for r, _ in found if not _distinct(best.T_wc, r.T_wc)])
        return self._rival_in(best, -1, found, ambiguity, far_ambiguity, support, verify, verify_far)

    @staticmethod
    def _rival_in(best: PnpResult, best_view: int, others, ambiguity: float, far_ambiguity: float | None = None,
                  support: int | None = None, verify: Callable[[PnpResult], bool] | None = None,
                  verify_far: Callable[[PnpResult], bool] | None = None) -> str | None:
        """Why ``others`` ((result, view) pairs) hold a rival place of ``best`` (services.relocalize.ambiguity), or None."""
        why = rival(best.T_wc, support or best.n_inliers, [(r.T_wc, r.n_inliers, r) for r, _ in others], ambiguity,
                    far_ambiguity, verify, verify_far)
        if why:
            log.info("relocalization ambiguous (view %d): %s", best_view, why)
        return why

    # ---- storage -----------------------------------------------------------
    def save(self, path: str | Path) -> None:
        with atomic_write(path, "wb") as f:
            np.savez(f, view_poses=self.view_poses, view_start=self.view_start, xyz=self.xyz,
                     desc=self.desc.astype(np.float16), vlad=self.vlad.astype(np.float16), vocab=self.vocab,
                     meta=np.array(json.dumps({**self.meta, "format_version": DB_FORMAT_VERSION})))

    @staticmethod
    def load_meta(path: str | Path) -> dict:
        """The database's meta alone (one small array of the archive); {} when it cannot be read (``load`` says why)."""
        try:
            with np.load(path) as z:
                return json.loads(str(z["meta"]))
        except (OSError, KeyError, ValueError, zipfile.BadZipFile):
            return {}

    @classmethod
    def load(cls, path: str | Path) -> "RelocDB":
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no relocalization database (build one with 'cristal build-db')")
        if not zipfile.is_zipfile(path):  # (np.load would read a scan or a text file as a pickle it refuses)
            raise ValueError(f"{path}: not a relocalization database (an .npz from 'cristal build-db')")
        try:
            with np.load(path) as z:
                meta = json.loads(str(z["meta"]))
                if meta.get("format_version") != DB_FORMAT_VERSION:
                    raise ValueError(f"{path}: database format {meta.get('format_version')} is not {DB_FORMAT_VERSION}; rebuild it")
                return cls(z["view_poses"], z["view_start"], z["xyz"], z["desc"].astype(np.float32),
                           z["vlad"].astype(np.float32), z["vocab"], meta)
        except (OSError, KeyError, json.JSONDecodeError) as e:
            raise ValueError(f"{path}: not a relocalization database ({e})") from None


def _inside(results: list[tuple[PnpResult, int]], within: tuple[np.ndarray, float] | None) -> list[tuple[PnpResult, int]]:
    if within is None:
        return results
    centre, radius = within
    return [(r, v) for r, v in results if np.linalg.norm(r.T_wc.t - np.asarray(centre, float)) <= radius]


def build_database(renderer, positions: np.ndarray, extractor: XFeatExtractor, cfg: DBConfig = DBConfig(),
                   meta: dict | None = None) -> RelocDB:
    """Render cubemaps at ``positions``, extract and back-project features, learn the vocabulary."""
    from services.render.renderer import cubemap_poses

    t0 = time.perf_counter()
    size = cfg.face_size
    cam = Camera(size, size, size / 2.0, size / 2.0, (size - 1) / 2.0, (size - 1) / 2.0)
    n_faces = 4 if cfg.faces == "horizontal" else 6
    poses = [T for p in positions for T in cubemap_poses(p)[:n_faces]]
    it = progress(range(0, len(poses), n_faces), desc="cubemaps", total=len(positions), unit="position")
    views = [v for i in it for v in view_features(renderer, poses[i:i + n_faces], cam, extractor, cfg)]
    if sum(len(x) for x, _ in views) < cfg.vocabulary:
        raise ValueError(f"only {sum(len(x) for x, _ in views)} features in the whole database: is the region of "
                         f"interest inside the scan?")
    desc = np.concatenate([d for _, d in views]).astype(np.float32)
    rng = np.random.default_rng(0)
    sample = desc[rng.choice(len(desc), min(len(desc), 50000), replace=False)]
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 20, 1e-4)
    cv2.setRNGSeed(0)
    _, _, centres = cv2.kmeans(sample, cfg.vocabulary, None, crit, 2, cv2.KMEANS_PP_CENTERS)
    vocab = (centres / np.linalg.norm(centres, axis=1, keepdims=True)).astype(np.float32)
    db = RelocDB.from_views(poses, views, vocab)
    m = {"positions": len(positions), "views": db.n_views, "features": int(len(desc)), "face_size": size,
         "faces": cfg.faces, "top_k": cfg.top_k, "build_seconds": round(time.perf_counter() - t0, 1), **(meta or {})}
    log.info("database: %d positions, %d views, %d features in %.1f s", len(positions), db.n_views, len(desc), m["build_seconds"])
    db.meta = m
    return db


def view_features(renderer, poses: list[Pose], camera: Camera, extractor: XFeatExtractor,
                  cfg: DBConfig = DBConfig()) -> list[tuple[np.ndarray, np.ndarray]]:
    """Render each of ``poses`` with ``camera``, XFeat on it, keypoints back-projected with the render's depth:
    per view (world points (N, 3), descriptors (N, 64)), only keypoints on measured, smooth depth."""
    out = []
    for T in poses:
        r = renderer.render(T, camera)
        f = extractor.extract(r.rgb, top_k=cfg.top_k)
        X, ok, _ = r.surface_points(f.kpts, cfg.depth_radius, cfg.depth_max_residual)
        out.append((X[ok], f.desc[ok]))
    return out
