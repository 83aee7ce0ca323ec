"""Train the hole-filling U-Net on simulated sites (``cristal train-renderer``).

Input = the depth-filtered splat of a simulated scan (random views, fields of view and
decimations, plus real-scan-like artefacts: sparser patches and colour noise); target =
the simulator's mesh render of the same view under scan-day lighting. Loss = L1 + 0.2 (1 - SSIM).
Validation uses a held-out site. Small enough to train on a 2-core CPU in minutes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from services.geometry.camera import Camera
from services.geometry.se3 import Pose, rotvec_to_rotmat
from services.io.atomic import atomic_write
from services.io.decimate import random_decimate
from services.io.scans import load_scan
from services.log import progress
from services.render.cloud import PreparedCloud, prepare_cloud
from services.render.depth_filter import FilterConfig, hierarchical_depth_filter
from services.render.quality import ssim_loss_map
from services.render.splat import SplatConfig, splat
from services.render.unet import SIZES, HoleFillNet
from services.sim.site import SimSite, config_for, generate_site

__all__ = ["TrainConfig", "Sample", "training_site", "sample_views", "make_samples", "train_holefill"]

log = logging.getLogger(__name__)
DECIMATIONS = (1.0, 0.5, 0.2, 0.1)


@dataclass(frozen=True)
class TrainConfig:
    size: str = "small"
    steps: int = 1500
    batch: int = 8
    crop: int = 160
    lr: float = 2e-3
    samples: int = 600  # training views (shared over sites and decimations)
    width: int = 320
    height: int = 240
    seed: int = 0


@dataclass
class Sample:
    rgb: np.ndarray  # (H,W,3) uint8 filtered splat, 0 in holes
    mask: np.ndarray  # (H,W) bool
    depth: np.ndarray  # (H,W) float32, 0 in holes
    target: np.ndarray  # (H,W,3) uint8 ground truth
    gt_depth: np.ndarray  # (H,W) float32
    raw_depth: np.ndarray  # (H,W) float32 splat depth before the filter


def training_site(work: Path, preset: str, seed: int) -> Path:
    """A simulated site (scan + mesh, no sequence) for training, generated once and reused."""
    out = work / f"{preset}-{seed}"
    if not (out / "site.json").exists():
        log.info("simulating training site %s", out)
        generate_site(config_for(preset, seed=seed, sequences=0), out)
    return out


def sample_views(site: SimSite, n: int, rng: np.random.Generator, width: int, height: int,
                 max_tries: int = 50) -> list[tuple[Pose, Camera]]:
    """Random camera poses inside the site looking at something (no misses, nothing closer than 0.3 m)."""
    lo, hi = (np.asarray(b, float) for b in site.meta["bounds"])
    views = []
    tries = 0
    while len(views) < n and tries < n * max_tries:
        tries += 1
        p = rng.uniform(lo + [0.4, 0.4, 0.4], [hi[0] - 0.4, hi[1] - 0.4, min(hi[2] - 0.3, 2.6)])
        yaw, pitch, roll = rng.uniform(-np.pi, np.pi), rng.uniform(-0.5, 0.4), rng.normal(0, 0.05)
        fwd = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        R = np.stack([right, np.cross(fwd, right), fwd], 1) @ rotvec_to_rotmat([0, 0, roll])
        cam = Camera.from_fov(width, height, float(rng.uniform(50, 95)))
        T = Pose(R, p)
        _, d = site.render(T, cam.scaled(0.25))
        if (d > 0).mean() < 0.995 or d[d > 0].min() < 0.3:
            continue
        views.append((T, cam))
    return views


def _sparse_patches(rng: np.random.Generator, H: int, W: int) -> np.ndarray:
    """A mask that thins the splat in blobs (regions a real scanner saw sparsely)."""
    g = rng.random((max(2, H // 40), max(2, W // 40))).astype(np.float32)
    import cv2

    g = cv2.resize(g, (W, H), interpolation=cv2.INTER_CUBIC)
    keep_p = np.clip(1.0 - 1.6 * np.clip(g - 0.55, 0, 1) / 0.45, 0.15, 1.0)
    return rng.random((H, W)) < keep_p


def make_samples(site: SimSite, clouds: dict[float, PreparedCloud], views, rng, artefacts: bool = True,
                 splat_cfg: SplatConfig = SplatConfig(), filt: FilterConfig = FilterConfig()) -> list[Sample]:
    out = []
    for T, cam in views:
        frac = float(rng.choice(list(clouds)))
        r = splat(clouds[frac], T, cam, splat_cfg)
        depth, rgb = r.depth.copy(), r.rgb.copy()
        if artefacts and rng.random() < 0.5:
            m = _sparse_patches(rng, cam.height, cam.width)
            depth[~m] = 0
        if artefacts and rng.random() < 0.5:
            rgb += rng.normal(0, rng.uniform(1, 8), rgb.shape).astype(np.float32)
        keep = hierarchical_depth_filter(torch.from_numpy(depth), filt).numpy()
        target, gt_depth = site.render(T, cam)
        rgb8 = (np.clip(rgb, 0, 255) * keep[..., None] + 0.5).astype(np.uint8)
        out.append(Sample(rgb8, keep, np.where(keep, depth, 0).astype(np.float32), target, gt_depth, r.depth))
    return out


def _batch(samples: list[Sample], idx, crop: int, rng) -> tuple[torch.Tensor, ...]:
    rgb, mask, depth, tgt = [], [], [], []
    for i in idx:
        s = samples[i]
        H, W = s.mask.shape
        y, x = rng.integers(0, H - crop + 1), rng.integers(0, W - crop + 1)
        sl = (slice(y, y + crop), slice(x, x + crop))
        flip = rng.random() < 0.5
        f = (lambda a: a[:, ::-1]) if flip else (lambda a: a)
        rgb.append(f(s.rgb[sl]))
        mask.append(f(s.mask[sl]))
        depth.append(f(s.depth[sl]))
        tgt.append(f(s.target[sl]))
    t = lambda a, scale: torch.from_numpy(np.ascontiguousarray(np.stack(a))).float() / scale
    return (t(rgb, 255.0).permute(0, 3, 1, 2), t(mask, 1.0)[:, None], t(depth, 1.0)[:, None], t(tgt, 255.0).permute(0, 3, 1, 2))


def loss_fn(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (pred - target).abs().mean() + 0.2 * (1 - ssim_loss_map(pred, target).mean())


def evaluate_net(net: HoleFillNet | None, samples: list[Sample]) -> dict:
    """Mean L1/SSIM of the network's output (or of the filtered splat itself when ``net`` is None)."""
    l1, ss = [], []
    with torch.no_grad():
        for s in samples:
            rgb, mask, depth, tgt = _batch([s], [0], min(s.mask.shape), np.random.default_rng(0))
            pred = net(rgb, mask, depth) if net is not None else rgb * mask
            l1.append(float((pred - tgt).abs().mean()))
            ss.append(float(ssim_loss_map(pred, tgt).mean()))
    return {"l1": float(np.mean(l1)), "ssim": float(np.mean(ss))}


def prepare_clouds(site_dir: Path, decimations=DECIMATIONS) -> dict[float, PreparedCloud]:
    scan = load_scan(site_dir / "scan.ply")
    return {f: prepare_cloud(scan if f >= 1.0 else random_decimate(scan, f, seed=7)) for f in decimations}


def train_holefill(train: list[Sample], val: list[Sample], cfg: TrainConfig, out: Path) -> dict:
    """Train, keep the best validation SSIM, write weights atomically; returns the training record."""
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    net = HoleFillNet(SIZES[cfg.size])
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=cfg.steps, pct_start=0.1)
    best = {"ssim": -1.0}
    t0 = time.perf_counter()
    history = []
    bar = progress(range(cfg.steps), desc=f"training {cfg.size}", total=cfg.steps, unit="step")
    for step in bar:
        net.train()
        rgb, mask, depth, tgt = _batch(train, rng.integers(0, len(train), cfg.batch), cfg.crop, rng)
        loss = loss_fn(net(rgb, mask, depth), tgt)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if (step + 1) % max(1, cfg.steps // 6) == 0 or step + 1 == cfg.steps:
            net.eval()
            v = evaluate_net(net, val)
            history.append({"step": step + 1, "loss": loss.item(), **v})
            log.info("step %d loss %.4f val ssim %.4f l1 %.4f", step + 1, loss.item(), v["ssim"], v["l1"])
            if v["ssim"] > best["ssim"]:
                best = {**v, "step": step + 1}
                _save(net, out)
    record = {"size": cfg.size, "channels": list(SIZES[cfg.size]), "params": net.n_params(), "steps": cfg.steps,
              "batch": cfg.batch, "crop": cfg.crop, "lr": cfg.lr, "train_samples": len(train), "val_samples": len(val),
              "best": best, "history": history, "train_seconds": round(time.perf_counter() - t0, 1),
              "baseline_val": evaluate_net(None, val)}
    return record


def _save(net: HoleFillNet, out: Path) -> None:
    with atomic_write(out, "wb") as f:
        torch.save({"channels": list(net.channels), "state_dict": net.state_dict(), "version": 1}, f)
