"""``cristal render`` (look at the point renderer's output), ``cristal density`` (is a scan dense enough for a camera)
and ``cristal train-renderer``."""

from __future__ import annotations

import argparse

RENDER_EPILOG = """\
examples:
  cristal render site/scan.ply --pose "3 2.5 1.5 -0.5 0.5 -0.5 0.5" --camera site/seq_00/camera.json --out r.png
  cristal render site/scan.ply --pose "..." --camera cam.json --out r.png --stage splat     raw splat (see the leaks)
  cristal render site/scan.ply --pose "..." --camera cam.json --out r.png --depth d.npy --compare site/

stages: splat (three-pass point splat), filter (+ hierarchical depth filter, holes stay black),
full (+ U-Net hole filling; default). --compare SITE also writes r_compare.png: the render next to
the simulator's ground truth at the same pose, with PSNR/SSIM/leakage in the summary.
The pose is camera-to-world 'tx ty tz qx qy qz qw' in the scan's frame (OpenCV camera axes).
"""

DENSITY_EPILOG = """\
examples:
  cristal density site/scan.ply --camera site/seq_00/camera.json --out runs/density      the default tracker
  cristal density survey.e57 --camera headset.json --max-side 0 --spacing 2 --out d/    full-resolution keyframes (GPU)

A scan places an edge between two surfaces or materials only to within its sample spacing, and the render draws it
where the last sample on its side fell: where neighbouring scan points are further apart than the pixels the
tracker renders at, the render, not the method, limits accuracy (benchmarks/RESULTS.md, stop 37: a scan twice as
dense took a 960x540 walk from 92 to 128 of 150 frames, 0.90 to 0.58 cm). This renders the scan from every position
of the region of interest (the sampler of build-db and prebuild) at --yaws level headings, with the camera's
intrinsics at the tracker's keyframe resolution (--max-side, as `cristal localize`), and measures how many pixels
apart the scan's samples are. Prints the spread over views and which share is coarser than 1 px; writes
OUT/density.png (a floor plan: a disc per position and a spoke per heading, green to red) and OUT/density.json
(every view's median). At 1 px or finer the scan is not what limits accuracy. Coarser: track at a lower resolution
(--max-side, fewer frames lost but less accurate), or rescan denser where it matters.
"""

TRAIN_EPILOG = """\
examples:
  cristal train-renderer --out services/render/weights/holefill_small.pt          the shipped model
  cristal train-renderer --size tiny --steps 300 --samples 200 --out /tmp/t.pt   a quick one

Simulates training sites into --work (reused between runs), renders filtered splats of random
views at several decimations with artefacts, and trains against the mesh ground truth.
Writes the weights and <out>.json (data, steps, loss, validation metrics) for the model card.
"""


def register(sub) -> None:
    p = sub.add_parser("render", help="render a scan from a pose with the neural point renderer",
                       description="Render a scan from a camera pose: splat, depth filter, U-Net hole filling.",
                       epilog=RENDER_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scan", help="scan file (.ply .e57 .las .laz)")
    p.add_argument("--pose", required=True, help="camera-to-world 'tx ty tz qx qy qz qw'")
    p.add_argument("--camera", required=True, help="camera.json (intrinsics, distortion)")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--depth", help="also write the measured depth (metres, float32, 0 = none) as .npy")
    p.add_argument("--stage", choices=["splat", "filter", "full"], default="full",
                   help="splat: points only; filter: background seen through holes removed; full: holes filled too (default)")
    p.add_argument("--device", default="auto", help="cpu, cuda or auto (default)")
    p.add_argument("--compare", metavar="SITE", help="a simulated site folder: compare with its ground truth")
    p.set_defaults(func=run_render)

    d = sub.add_parser("density", help="is a scan dense enough for a camera: scan samples per tracker pixel, floor plan",
                       description="How many of the tracker's pixels apart a scan's samples are, all over the region "
                                   "where cameras go.", epilog=DENSITY_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    d.add_argument("scan", help="scan file (.ply .e57 .las .laz)")
    d.add_argument("--camera", required=True, help="camera.json of the camera that will be tracked")
    d.add_argument("--out", required=True, help="folder for density.png and density.json")
    d.add_argument("--max-side", type=int, default=480, help="the tracker's keyframe resolution: the camera scaled to this "
                   "many pixels on its longer side (`cristal localize --max-side`; default 480, the CPU tracker's; 0: full)")
    d.add_argument("--spacing", type=float, default=1.0, help="metres between surveyed positions (default 1.0)")
    d.add_argument("--yaws", type=int, default=8, help="level headings per position (default 8)")
    d.add_argument("--device", default="auto", help="cpu, cuda or auto (default)")
    d.set_defaults(func=run_density)

    t = sub.add_parser("train-renderer", help="train the hole-filling U-Net on simulated sites",
                       description="Train the renderer's hole-filling network.", epilog=TRAIN_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    t.add_argument("--out", required=True, help="weights file (.pt); a .json record is written beside it")
    t.add_argument("--size", default="small", choices=["tiny", "small", "base"], help="network width (default small, the shipped one)")
    t.add_argument("--steps", type=int, default=1500, help="optimiser steps (default 1500)")
    t.add_argument("--samples", type=int, default=600, help="training views")
    t.add_argument("--batch", type=int, default=8, help="views per step (default 8)")
    t.add_argument("--work", default="runs/train-renderer", help="folder for the simulated training sites")
    t.add_argument("--threads", type=int, default=2, help="torch threads")
    t.set_defaults(func=run_train)


def run_render(args) -> int:
    import cv2
    import numpy as np

    from services.cli import emit_summary, parse_pose
    from services.geometry.camera import Camera
    from services.io.atomic import atomic_write, atomic_write_bytes
    from services.io.scans import load_scan
    from services.render.renderer import Renderer

    T_wc = parse_pose(args.pose)
    cam = Camera.load(args.camera)
    scan = load_scan(args.scan)
    r = Renderer(scan, device=args.device, holefill=args.stage == "full").render(T_wc, cam, args.stage)
    atomic_write_bytes(args.out, cv2.imencode(".png", r.rgb[..., ::-1])[1].tobytes())
    if args.depth:
        with atomic_write(args.depth, "wb") as f:
            np.save(f, r.depth)
    summary = {"out": args.out, "stage": args.stage, "hole_fraction": round(r.hole_fraction, 4),
               **{k: round(v, 2) for k, v in r.timings.items()}}
    if args.compare:
        from pathlib import Path

        from services.render.quality import leakage, psnr, ssim
        from services.sim.site import SimSite

        gt, gt_depth = SimSite(args.compare).render(T_wc, cam)
        summary.update(psnr=round(psnr(r.rgb, gt), 2), ssim=round(ssim(r.rgb, gt), 4), leakage=round(leakage(r.depth, gt_depth), 4))
        side = np.concatenate([r.rgb, gt], 1)[..., ::-1]
        cmp_path = str(Path(args.out).with_name(Path(args.out).stem + "_compare.png"))
        atomic_write_bytes(cmp_path, cv2.imencode(".png", side)[1].tobytes())
        summary["compare"] = cmp_path
    print(f"rendered {args.out} ({args.stage}): {r.hole_fraction:.1%} holes before filling; "
          + ", ".join(f"{k} {v:.1f}" for k, v in r.timings.items()))
    emit_summary(summary)
    return 0


def run_density(args) -> int:
    import json
    import time
    from pathlib import Path

    import cv2
    import numpy as np

    from services.cli import emit_summary
    from services.geometry.camera import Camera
    from services.io.atomic import atomic_write_bytes, atomic_write_text
    from services.io.scans import load_scan
    from services.log import progress
    from services.relocalize.roi import RoiConfig, sample_positions
    from services.render.density import floor_plan, survey
    from services.render.renderer import Renderer

    if args.yaws < 1 or args.spacing <= 0 or args.max_side < 0:
        raise ValueError("--yaws must be >= 1, --spacing > 0 and --max-side >= 0")
    t0 = time.perf_counter()
    cam = Camera.load(args.camera)
    scale = min(1.0, args.max_side / max(cam.width, cam.height)) if args.max_side else 1.0
    cam_kf = cam.scaled(scale) if scale < 1 else cam
    scan = load_scan(args.scan)
    positions = sample_positions(scan, RoiConfig(spacing=args.spacing))
    if not len(positions):
        raise ValueError(f"{args.scan}: no position in free space inside the scan (try a smaller --spacing)")
    renderer = Renderer(scan, device=args.device, holefill=False)
    sp = survey(renderer, positions, cam_kf, args.yaws,
                progress=lambda it: progress(it, desc="views", total=len(positions) * args.yaws, unit="view"))
    v = sp[np.isfinite(sp)]
    if not len(v):
        raise ValueError(f"{args.scan}: no surveyed view sees the scan's surface")
    coarse = float(np.mean(v > 1.0))
    p50, p90 = float(np.median(v)), float(np.percentile(v, 90))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    title = (f"{Path(args.scan).name}: scan sample spacing in {cam_kf.width}x{cam_kf.height} keyframe pixels "
             f"(median {p50:.2f}, 90th pct {p90:.2f}; {coarse:.0%} of views > 1 px)")
    xy = scan.world_xyz(slice(None, None, max(1, len(scan) // 300_000)))[:, :2]
    stations = np.array([st.t[:2] for st in scan.stations]) if scan.stations else None
    img = floor_plan(xy, positions, sp, title, stations)
    atomic_write_bytes(out / "density.png", cv2.imencode(".png", img)[1].tobytes())
    record = {"scan": str(args.scan), "camera": str(args.camera), "keyframe_size": [cam_kf.width, cam_kf.height],
              "scale": scale, "yaws": args.yaws, "positions": np.round(positions, 3).tolist(),
              "median_spacing_px": [[None if not np.isfinite(x) else round(float(x), 3) for x in row] for row in sp]}
    atomic_write_text(out / "density.json", json.dumps(record) + "\n")
    print(f"{args.scan}: {len(positions)} positions x {args.yaws} headings, camera {cam.width}x{cam.height} rendered at "
          f"{cam_kf.width}x{cam_kf.height}")
    print(f"  scan sample spacing, median per view: median {p50:.2f} px, 90th percentile {p90:.2f} px, worst {v.max():.2f} px "
          f"(at full resolution x {1 / scale:.2f})")
    print(f"  views coarser than 1 px: {coarse:.0%}"
          + ("  -> the render, not the method, limits accuracy there (see `cristal density --help`)" if coarse > 0.1 else
             "  -> dense enough for this camera"))
    print(f"  picture: {out / 'density.png'}")
    emit_summary({"out": str(out), "positions": len(positions), "views": int(sp.size), "median_px": round(p50, 3),
                  "p90_px": round(p90, 3), "share_above_1px": round(coarse, 4), "keyframe_size": [cam_kf.width, cam_kf.height],
                  "seconds": round(time.perf_counter() - t0, 1)})
    return 0


def run_train(args) -> int:
    import json
    from pathlib import Path

    import numpy as np
    import torch

    from services.cli import emit_summary
    from services.io.atomic import atomic_write_text
    from services.render.train import TrainConfig, make_samples, prepare_clouds, sample_views, train_holefill, training_site
    from services.sim.site import SimSite

    torch.set_num_threads(args.threads)
    work = Path(args.work)
    cfg = TrainConfig(size=args.size, steps=args.steps, batch=args.batch, samples=args.samples)
    rng = np.random.default_rng(cfg.seed)
    train_sites = [("office", 11), ("office", 12), ("warehouse", 13)]
    train, val = [], []
    for k, (preset, seed) in enumerate(train_sites):
        d = training_site(work, preset, seed)
        site, clouds = SimSite(d), prepare_clouds(d)
        n = cfg.samples // len(train_sites)
        train += make_samples(site, clouds, sample_views(site, n, rng, cfg.width, cfg.height), rng)
        print(f"training data: {preset} seed {seed}: {n} views", flush=True)
    d = training_site(work, "office", 99)  # held out
    site, clouds = SimSite(d), prepare_clouds(d)
    val = make_samples(site, clouds, sample_views(site, max(24, cfg.samples // 10), rng, cfg.width, cfg.height), rng,
                       artefacts=False)
    record = train_holefill(train, val, cfg, Path(args.out))
    record["data"] = {"train_sites": [f"{p}-{s}" for p, s in train_sites], "val_site": "office-99",
                      "decimations": [1.0, 0.5, 0.2, 0.1], "resolution": [cfg.width, cfg.height], "hfov_deg": [50, 95]}
    atomic_write_text(Path(args.out).with_suffix(".json"), json.dumps(record, indent=2) + "\n")
    print(f"weights {args.out}: {record['params']:,} parameters, best val SSIM {record['best']['ssim']:.4f} "
          f"(filtered splat alone {record['baseline_val']['ssim']:.4f}) in {record['train_seconds']} s")
    emit_summary({"out": args.out, "params": record["params"], "val_ssim": record["best"]["ssim"],
                  "baseline_ssim": record["baseline_val"]["ssim"], "seconds": record["train_seconds"]})
    return 0
