"""Renderer speed: milliseconds per stage and points per second.

    python benchmarks/render.py [--site runs/bench/office-1] [--threads 2] [--repeats 10] [--device cpu|cuda] [--lod 8]
    cristal sim --preset office --lidar-step 0.05 --out runs/bench-sim/office-dense   # a 64 M-point scan
    python benchmarks/render.py --site runs/bench-sim/office-dense --lod 0 8           # level of detail off / on
    python benchmarks/render.py --site runs/bench-sim/office --widths 480 --supersample 1 2   # Render & Match's keyframes

Renders the site's ground-truth poses at 640 and 960 px wide (--widths) with the neural point renderer
and prints a table: splat, depth filter, U-Net (full and half resolution), depth fill, total,
and splat throughput in points per second. On CUDA it also times 8 single renders against one
batch of 8. The site is simulated on first use (office preset, seed 1, ~4 M points). ``--lod``: the
level of detail (at most about this many of a chunk's points per pixel; 0 = every point), one table row
set per value, plus a cubemap (six 256 px faces, as the relocalization database renders them). ``--supersample``:
renders splatted at K x the resolution and pooled (Render & Match's keyframes use 2), a row per value.
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
from services.render.splat import SplatConfig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench/office-1")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--lod", type=float, nargs="+", default=[SplatConfig.lod_points_per_px])
    ap.add_argument("--widths", type=int, nargs="+", default=[640, 960],
                    help="image widths to time (the sequence camera scaled; default 640 960)")
    ap.add_argument("--supersample", type=int, nargs="+", default=[1], help="supersampling factors to time (default 1)")
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    torch.set_num_threads(args.threads)
    site = ensure_site(args.site)
    scan = load_scan(site / "scan.ply")
    seq = open_sequence(site / "seq_00")
    poses = [seq.groundtruth.poses[i] for i in np.linspace(0, len(seq) - 1, args.repeats).round().astype(int)]
    print(f"{platform.processor() or platform.machine()}, {args.threads} threads, device {args.device}, "
          f"torch {torch.__version__}, numba {numba.__version__}; scan {len(scan):,} points\n")
    print("| level of detail | resolution | supersample | U-Net scale | splat ms | filter ms | growing + U-Net ms | "
          "depth fill ms | total ms | splat Mpts/s |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    cubes = []
    for lod in args.lod:
        r = Renderer(scan, RenderConfig(SplatConfig(lod_points_per_px=lod)), device=args.device)  # prepared once
        default_scale = r.holefill_scale
        for w, k, scale in ((w, k, s) for w in args.widths for k in args.supersample for s in (1.0, 0.5)):
            cam = seq.camera.scaled(w / seq.camera.width)
            r.holefill_scale = scale
            r.render(poses[0], cam, supersample=k)  # warm-up (compilation, allocations)
            rows = []
            for T in poses:
                t0 = time.perf_counter()
                x = r.render(T, cam, supersample=k)
                tot = 1e3 * (time.perf_counter() - t0)
                rows.append([x.timings["splat_ms"], x.timings["filter_ms"], x.timings["holefill_ms"],
                             x.timings["depthfill_ms"], tot])
            m = np.median(np.array(rows), axis=0)
            print(f"| {lod:g} | {cam.width}x{cam.height} | {k} | {scale} | {m[0]:.1f} | {m[1]:.1f} | {m[2]:.1f} | {m[3]:.1f} | {m[4]:.1f} | "
                  f"{len(scan) / m[0] / 1e3:.0f} |", flush=True)
        r.holefill_scale = default_scale
        t0 = time.perf_counter()
        for T in poses[:3]:
            r.cubemap(T.t)
        cubes.append((lod, 1e3 * (time.perf_counter() - t0) / 3))
    print("\n| level of detail | cubemap (6 faces of 256 px, default U-Net scale) ms |\n|---|---:|")
    for lod, ms in cubes:
        print(f"| {lod:g} | {ms:.0f} |")
    if args.device == "cuda":
        cam = seq.camera.scaled(args.widths[-1] / seq.camera.width)
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
        print(f"\n8 views {cam.width}x{cam.height}: single renders {single * 1e3:.1f} ms, batch {1e3 * (time.perf_counter() - t0):.1f} ms")


if __name__ == "__main__":
    main()
