"""Render quality against simulator ground truth: splat / +filter / +U-Net at several decimations.

    python benchmarks/render_quality.py [--site runs/bench/office-1] [--views 10] [--weights a.pt b.pt ...]

For each decimation (100/50/20/10 % of the points) and stage, renders the ground-truth poses of
the site's sequence (every k-th frame) and prints mean PSNR, SSIM, hole fraction (pixels with no
measured depth) and background leakage (valid pixels > 5 % behind the true surface). With several
--weights, also compares network sizes (parameters, SSIM at 20 %, CPU milliseconds at 640x480).
The site is simulated on first use (office preset, seed 1: not a training seed).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from _site import ensure_site

from services.io.decimate import random_decimate
from services.io.scans import load_scan
from services.io.sequence import open_sequence
from services.render.quality import leakage, psnr, ssim
from services.render.renderer import RenderConfig, Renderer
from services.sim.site import SimSite


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench/office-1")
    ap.add_argument("--preset", default="office")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--weights", nargs="*", default=[], help="extra weight files to compare (network size table)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--figure", help="write a picture: ground truth | splat | +filter | +U-Net, at 100 %% and 20 %%")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    site_dir = ensure_site(args.site, args.preset, args.seed)
    site = SimSite(site_dir)
    seq = open_sequence(site_dir / "seq_00")
    cam = seq.camera
    idx = np.linspace(0, len(seq) - 1, args.views).round().astype(int)
    poses = [seq.groundtruth.poses[i] for i in idx]
    gts = [site.render(T, cam) for T in poses]
    scan = load_scan(site_dir / "scan.ply")

    print(f"site {site_dir} ({len(scan):,} points), {len(poses)} ground-truth views at {cam.width}x{cam.height}\n")
    fig_rows = []
    print("| points | stage | PSNR dB | SSIM | holes | leakage |")
    print("|---|---|---:|---:|---:|---:|")
    for frac in (1.0, 0.5, 0.2, 0.1):
        sc = scan if frac >= 1 else random_decimate(scan, frac, seed=0)
        r = Renderer(sc, RenderConfig(holefill_scale=1.0))
        half = Renderer(sc, RenderConfig(holefill_scale=0.5))
        for name, rr, stage in (("splat", r, "splat"), ("+filter", r, "filter"), ("+U-Net", r, "full"),
                                ("+U-Net at half res.", half, "full")):
            m = np.array([[psnr(x.rgb, g), ssim(x.rgb, g), x.hole_fraction, leakage(x.depth, gd)]
                          for x, (g, gd) in ((rr.render(T, cam, stage), gt) for T, gt in zip(poses, gts))]).mean(0)
            print(f"| {frac:.0%} | {name} | {m[0]:.2f} | {m[1]:.4f} | {m[2]:.3f} | {m[3]:.4f} |", flush=True)
        if args.figure and frac in (1.0, 0.2):
            k = len(poses) // 2
            row = [gts[k][0]] + [r.render(poses[k], cam, s).rgb for s in ("splat", "filter")] + [half.render(poses[k], cam).rgb]
            fig_rows.append(np.concatenate([x[::2, ::2] for x in row], 1))
    if args.figure:
        import cv2

        from services.io.atomic import atomic_write_bytes

        img = np.concatenate(fig_rows, 0)[..., ::-1]
        atomic_write_bytes(args.figure, cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])[1].tobytes())

    if args.weights:
        from services.render.unet import load_holefill

        sc = random_decimate(scan, 0.2, seed=0)
        big = cam.scaled(640 / cam.width)
        print(f"\n| weights | params | SSIM @20 % (full res.) | U-Net ms 640x480 (CPU, {args.threads} thread) |")
        print("|---|---:|---:|---:|")
        for w in args.weights:
            r = Renderer(sc, RenderConfig(weights=w, holefill_scale=1.0))
            s = np.mean([ssim(r.render(T, cam).rgb, g) for T, (g, _) in zip(poses, gts)])
            x = r.render(poses[0], big, "filter")
            rgb = torch.from_numpy(x.rgb).permute(2, 0, 1)[None].float() / 255
            mask = torch.from_numpy(x.measured)[None, None].float()
            d = torch.from_numpy(x.depth)[None, None]
            with torch.no_grad():
                r.net(rgb, mask, d)
                t0 = time.perf_counter()
                for _ in range(3):
                    r.net(rgb, mask, d)
            ms = (time.perf_counter() - t0) / 3 * 1e3
            print(f"| {Path(w).name} | {load_holefill(w).n_params():,} | {s:.4f} | {ms:.0f} |", flush=True)


if __name__ == "__main__":
    main()
