"""Renderer speed: milliseconds per stage and points per second.

    python benchmarks/render.py [--site runs/bench/office-1] [--threads 2] [--repeats 10] [--device cpu|cuda]

Renders the site's ground-truth poses at 640x480 (and 960x720) with the neural point renderer
and prints a table: splat, depth filter, U-Net (full and half resolution), depth fill, total,
and splat throughput in points per second. On CUDA it also times 8 single renders against one
batch of 8. The site is simulated on first use (office preset, seed 1, ~4 M points).
Thread counts are set on purpose: numba and torch get --threads each.
"""

from __future__ import annotations

import argparse
import platform
import time

import numba
import numpy as np
import torch

from _site import ensure_site

from services.io.scans import load_scan
from services.io.sequence import open_sequence
from services.render.renderer import RenderConfig, Renderer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench/office-1")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    torch.set_num_threads(args.threads)
    site = ensure_site(args.site)
    scan = load_scan(site / "scan.ply")
    seq = open_sequence(site / "seq_00")
    poses = [seq.groundtruth.poses[i] for i in np.linspace(0, len(seq) - 1, args.repeats).round().astype(int)]
    print(f"{platform.processor() or platform.machine()}, {args.threads} threads, device {args.device}, "
          f"torch {torch.__version__}, numba {numba.__version__}; scan {len(scan):,} points\n")
    print("| resolution | U-Net scale | splat ms | filter ms | U-Net ms | depth fill ms | total ms | splat Mpts/s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for w, h in ((640, 480), (960, 720)):
        cam = seq.camera.scaled(w / seq.camera.width)
        for scale in (1.0, 0.5):
            r = Renderer(scan, RenderConfig(holefill_scale=scale), device=args.device)
            r.render(poses[0], cam)  # warm-up (compilation, allocations)
            rows = []
            for T in poses:
                t0 = time.perf_counter()
                x = r.render(T, cam)
                tot = 1e3 * (time.perf_counter() - t0)
                rows.append([x.timings["splat_ms"], x.timings["filter_ms"], x.timings["holefill_ms"],
                             x.timings["depthfill_ms"], tot])
            m = np.median(np.array(rows), axis=0)
            print(f"| {w}x{h} | {scale} | {m[0]:.1f} | {m[1]:.1f} | {m[2]:.1f} | {m[3]:.1f} | {m[4]:.1f} | "
                  f"{len(scan) / m[0] / 1e3:.0f} |", flush=True)
    if args.device == "cuda":
        cam = seq.camera.scaled(960 / seq.camera.width)
        r = Renderer(scan, device="cuda")
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        for T in poses[:8]:
            r.render(T, cam)
        torch.cuda.synchronize()
        single = time.perf_counter() - t0
        t0 = time.perf_counter()
        r.render_batch(poses[:8], cam)
        torch.cuda.synchronize()
        print(f"\n8 views 960x720: single renders {single * 1e3:.1f} ms, batch {1e3 * (time.perf_counter() - t0):.1f} ms")


if __name__ == "__main__":
    main()
