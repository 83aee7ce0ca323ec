"""Surface materials of simulated sites: photographic and procedural textures, mip-mapped.

Photographs come from scikit-image's bundled sample images (no download); procedural
materials (wood, concrete, carpet, tiles, cardboard, painted metal...) are generated from
a seed. Everything is deterministic. Textures are stored linear (sRGB decoded) in one
flat float32 buffer with per-(material, level) offsets so numba kernels can sample them.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

__all__ = ["Material", "MaterialLibrary", "MATERIALS", "srgb_to_linear", "linear_to_srgb"]

TEX_SIZE = 512
N_LEVELS = 8  # 512 .. 4


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


@dataclass(frozen=True)
class Material:
    """``size_m``: metres covered by one texture repeat (0 = stretched once over the surface, for posters)."""

    name: str
    source: str  # "skimage:<name>" or "proc:<kind>"
    size_m: float = 1.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    specular: float = 0.0  # Blinn-Phong weight: view-dependent highlights differ between scan and camera
    shininess: float = 32.0


# The library every scene draws from. Order is the material id; append only.
MATERIALS: list[Material] = [
    Material("concrete_floor", "proc:concrete", 2.0, (0.85, 0.83, 0.8), 0.15, 24),
    Material("painted_wall", "proc:plaster", 2.5, (0.92, 0.9, 0.85)),
    Material("brick_wall", "skimage:brick", 1.6, (0.95, 0.55, 0.42)),
    Material("carpet", "proc:carpet", 1.0, (0.45, 0.5, 0.62)),
    Material("wood", "proc:wood", 1.2, (1.0, 1.0, 1.0), 0.2, 40),
    Material("ceiling", "proc:ceiling_tiles", 1.2, (0.95, 0.95, 0.95)),
    Material("poster_astronaut", "skimage:astronaut", 0.0),
    Material("poster_coffee", "skimage:coffee", 0.0),
    Material("poster_chelsea", "skimage:chelsea", 0.0),
    Material("poster_rocket", "skimage:rocket", 0.0),
    Material("poster_hubble", "skimage:hubble_deep_field", 0.0),
    Material("whiteboard", "proc:whiteboard", 0.0, (1.0, 1.0, 1.0), 0.5, 60),
    Material("gravel", "skimage:gravel", 0.8, (0.8, 0.78, 0.72)),
    Material("grass_mat", "skimage:grass", 0.8, (0.45, 0.7, 0.35)),
    Material("cardboard", "proc:cardboard", 0.6, (0.78, 0.6, 0.4)),
    Material("blue_metal", "proc:painted_metal", 1.0, (0.15, 0.3, 0.65), 0.35, 48),
    Material("orange_metal", "proc:painted_metal", 1.0, (0.9, 0.45, 0.1), 0.35, 48),
    Material("pallet_wood", "proc:wood", 0.5, (0.85, 0.72, 0.5)),
    Material("floor_tiles", "proc:tiles", 1.2, (0.9, 0.88, 0.85), 0.25, 30),
    Material("poster_coins", "skimage:coins", 0.0, (0.95, 0.9, 0.75)),
    Material("poster_camera", "skimage:camera", 0.0),
    Material("poster_text", "skimage:page", 0.0),
    Material("fabric", "proc:fabric", 0.5, (0.55, 0.25, 0.25)),
    Material("dark_plastic", "proc:plaster", 1.0, (0.18, 0.18, 0.2), 0.3, 40),
    Material("shelf_labels", "proc:labels", 2.0, (1.0, 1.0, 1.0)),
]
MATERIAL_ID = {m.name: i for i, m in enumerate(MATERIALS)}


def _value_noise(rng: np.random.Generator, size: int, octaves: list[tuple[int, float]]) -> np.ndarray:
    """Tileable multi-octave value noise in [0, 1]: sum of upsampled random grids."""
    out = np.zeros((size, size), np.float32)
    total = 0.0
    for cells, amp in octaves:
        g = rng.random((cells, cells)).astype(np.float32)
        g = np.tile(g, (3, 3))  # tileable cubic upsampling
        up = cv2.resize(g, (size * 3, size * 3), interpolation=cv2.INTER_CUBIC)[size:2 * size, size:2 * size]
        out += amp * up
        total += amp
    out /= total
    return (out - out.min()) / max(1e-6, out.max() - out.min())


def _procedural(kind: str, seed: int) -> np.ndarray:
    """A tileable (TEX_SIZE, TEX_SIZE, 3) sRGB texture in [0, 1] before tinting."""
    rng = np.random.default_rng(seed)
    S = TEX_SIZE
    yy, xx = np.mgrid[0:S, 0:S].astype(np.float32) / S
    if kind == "concrete":
        n = _value_noise(rng, S, [(4, 1.0), (16, 0.6), (64, 0.4), (256, 0.3)])
        spots = (rng.random((S, S)) > 0.997).astype(np.float32)
        spots = cv2.GaussianBlur(spots, (0, 0), 2.0) * 8
        g = 0.45 + 0.35 * n - 0.25 * np.clip(spots, 0, 1)
    elif kind == "plaster":
        n = _value_noise(rng, S, [(8, 1.0), (32, 0.5), (128, 0.5)])
        g = 0.75 + 0.18 * n
    elif kind == "carpet":
        n = _value_noise(rng, S, [(32, 0.5), (128, 1.0), (256, 0.8)])
        stripes = 0.5 + 0.5 * np.sin(2 * np.pi * 8 * yy)
        g = 0.35 + 0.4 * n + 0.15 * stripes
    elif kind == "wood":
        n = _value_noise(rng, S, [(4, 1.0), (16, 0.3)])
        planks = np.floor(yy * 6)
        offs = rng.random(6)[planks.astype(int)]
        rings = 0.5 + 0.5 * np.sin(2 * np.pi * (xx * 3 + offs * 5 + 2.0 * n) * 4)
        seams = (np.abs((yy * 6) - np.round(yy * 6)) < 0.02).astype(np.float32)
        base = 0.45 + 0.25 * rings + 0.15 * offs[..., None][..., 0]
        g3 = np.stack([base * 0.85, base * 0.6, base * 0.38], -1)
        return np.clip(g3 * (1 - 0.6 * seams[..., None]), 0, 1)
    elif kind == "ceiling_tiles":
        n = _value_noise(rng, S, [(64, 1.0), (256, 1.0)])
        grid = ((np.abs(xx * 2 - np.round(xx * 2)) < 0.012) | (np.abs(yy * 2 - np.round(yy * 2)) < 0.012)).astype(np.float32)
        g = 0.82 + 0.1 * n - 0.45 * grid
    elif kind == "tiles":
        n = _value_noise(rng, S, [(8, 1.0), (64, 0.6)])
        tx, ty = np.floor(xx * 4).astype(int), np.floor(yy * 4).astype(int)
        shade = rng.random((4, 4))[ty, tx]
        grout = ((np.abs(xx * 4 - np.round(xx * 4)) < 0.03) | (np.abs(yy * 4 - np.round(yy * 4)) < 0.03)).astype(np.float32)
        g = (0.6 + 0.2 * shade + 0.15 * n) * (1 - 0.55 * grout)
    elif kind == "whiteboard":
        img = np.full((S, S, 3), 242, np.uint8)  # OpenCV draws text on 8-bit images only
        for _ in range(14):  # marker strokes: diagrams people leave on boards
            col = [(25, 25, 150), (180, 25, 25), (25, 128, 40), (25, 25, 25)][rng.integers(4)]
            pts = (rng.random((rng.integers(3, 7), 2)) * S * 0.9 + S * 0.05).astype(np.int32)
            cv2.polylines(img, [pts], bool(rng.integers(2)), col, int(rng.integers(2, 5)), cv2.LINE_AA)
        for _ in range(6):
            cv2.putText(img, "".join(rng.choice(list("ABCDEFGHKLMNPRSTXYZ0123456789+=-"), 5)),
                        (int(rng.integers(10, S - 200)), int(rng.integers(30, S - 10))), cv2.FONT_HERSHEY_SIMPLEX,
                        float(rng.uniform(0.8, 1.6)), (40, 40, 50), 2, cv2.LINE_AA)
        return img.astype(np.float32) / 255
    elif kind == "cardboard":
        n = _value_noise(rng, S, [(16, 1.0), (128, 0.4)])
        img = np.stack([0.6 + 0.25 * n] * 3, -1).astype(np.float32)
        tape = (np.abs(yy - 0.5) < 0.06).astype(np.float32)[..., None]
        img = img * (1 - tape) + tape * np.array([0.85, 0.8, 0.65], np.float32)
        img8 = (np.clip(img, 0, 1) * 255).astype(np.uint8)
        for _ in range(3):  # printed labels
            x0, y0 = int(rng.integers(20, S - 180)), int(rng.integers(20, S - 120))
            cv2.rectangle(img8, (x0, y0), (x0 + 150, y0 + 90), (242, 242, 242), -1)
            cv2.putText(img8, f"{rng.integers(1000, 9999)}", (x0 + 10, y0 + 55), cv2.FONT_HERSHEY_SIMPLEX, 1.3,
                        (12, 12, 12), 3, cv2.LINE_AA)
        return img8.astype(np.float32) / 255
    elif kind == "painted_metal":
        n = _value_noise(rng, S, [(8, 1.0), (64, 0.3), (256, 0.3)])
        scratches = np.zeros((S, S), np.float32)
        for _ in range(40):
            p = rng.integers(0, S, 2)
            q = p + rng.integers(-60, 60, 2)
            cv2.line(scratches, tuple(int(v) for v in p), tuple(int(v) for v in q), 1.0, 1, cv2.LINE_AA)
        g = 0.75 + 0.15 * n + 0.25 * scratches
    elif kind == "fabric":
        n = _value_noise(rng, S, [(64, 1.0), (256, 1.0)])
        weave = 0.5 + 0.25 * (np.sin(2 * np.pi * 64 * xx) + np.sin(2 * np.pi * 64 * yy))
        g = 0.5 + 0.25 * n + 0.2 * weave
    elif kind == "labels":
        img = np.empty((S, S, 3), np.uint8)
        img[:, :] = (230, 140, 25)
        for i in range(4):
            x0 = i * S // 4 + 8
            cv2.rectangle(img, (x0, S // 2 - 40), (x0 + S // 4 - 16, S // 2 + 40), (247, 247, 247), -1)
            cv2.putText(img, f"{chr(65 + rng.integers(26))}{rng.integers(10, 99)}", (x0 + 8, S // 2 + 15),
                        cv2.FONT_HERSHEY_SIMPLEX, 1.2, (12, 12, 12), 3, cv2.LINE_AA)
        return img.astype(np.float32) / 255
    else:
        raise ValueError(f"unknown procedural material {kind!r}")
    g = np.clip(g, 0, 1).astype(np.float32)
    return np.stack([g, g, g], -1)


def _skimage(name: str) -> np.ndarray:
    from skimage import data

    img = getattr(data, name)()
    img = img.astype(np.float32) / (255.0 if img.dtype == np.uint8 else max(1.0, float(img.max())))
    if img.ndim == 2:
        img = np.stack([img] * 3, -1)
    img = img[..., :3]
    h, w = img.shape[:2]
    s = min(h, w)  # centre square crop
    img = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    return cv2.resize(img, (TEX_SIZE, TEX_SIZE), interpolation=cv2.INTER_AREA)


@lru_cache(maxsize=4)
def _build_library(seed: int) -> tuple[np.ndarray, np.ndarray]:
    levels = []
    for mi, m in enumerate(MATERIALS):
        kind, name = m.source.split(":", 1)
        img = _skimage(name) if kind == "skimage" else _procedural(name, seed * 1000 + mi)
        img = np.clip(img * np.asarray(m.tint, np.float32), 0, 1)
        lin = srgb_to_linear(img)
        pyr = [lin]
        for _ in range(1, N_LEVELS):
            pyr.append(cv2.resize(pyr[-1], (pyr[-1].shape[1] // 2, pyr[-1].shape[0] // 2), interpolation=cv2.INTER_AREA))
        levels.append(pyr)
    offsets = np.zeros((len(MATERIALS), N_LEVELS), np.int64)
    chunks = []
    pos = 0
    for mi, pyr in enumerate(levels):
        for li, a in enumerate(pyr):
            offsets[mi, li] = pos
            chunks.append(a.reshape(-1))
            pos += a.size
    return np.concatenate(chunks).astype(np.float32), offsets


class MaterialLibrary:
    """Flat texture buffer + per-material parameters, as numba kernels want them."""

    def __init__(self, seed: int = 0):
        self.buffer, self.offsets = _build_library(int(seed))
        self.size_m = np.array([m.size_m for m in MATERIALS], np.float64)
        self.specular = np.array([m.specular for m in MATERIALS], np.float64)
        self.shininess = np.array([m.shininess for m in MATERIALS], np.float64)
        self.tex_size = TEX_SIZE
        self.n_levels = N_LEVELS

    @staticmethod
    def id(name: str) -> int:
        return MATERIAL_ID[name]
