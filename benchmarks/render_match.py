"""Render & Match on a simulated site: accuracy, coverage and speed per stage, and the renderer ablation.

    python benchmarks/render_match.py                                   # office seq_00, full renderer, 100 % scan
    python benchmarks/render_match.py --stages full splat --decimations 1 0.5 0.1   # the paper's ablation
    python benchmarks/render_match.py --site runs/bench-sim/warehouse --preset warehouse

For every (scan decimation, renderer stage) it builds the relocalization database with that renderer, then
localizes the whole sequence from a cold start (first frame relocalized, no prior) with frame timestamps,
and prints one table row: frames localized, relocalizations, APE (no alignment) against the simulator's
ground truth, FPS and mean milliseconds per stage. Threads: 1 for torch unless -j/--threads.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _site import ensure_site  # noqa: E402

from services.eval.ape import compute_ape  # noqa: E402
from services.features.xfeat import XFeatExtractor  # noqa: E402
from services.io.decimate import random_decimate  # noqa: E402
from services.io.scans import load_scan  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402
from services.io.trajectory import Trajectory  # noqa: E402
from services.localize.render_match import RenderMatchTracker, RMConfig, Status  # noqa: E402
from services.localize.runner import localize_sequence  # noqa: E402
from services.relocalize.database import build_database  # noqa: E402
from services.relocalize.roi import RoiConfig, sample_positions  # noqa: E402
from services.render.renderer import Renderer  # noqa: E402

STAGE_NAMES = {"full": "full (filter + U-Net)", "filter": "splat + filter", "splat": "splat only"}


def run(scan, seq, stage: str, frames: int, max_side: int, top_k: int, spacing: float, cfg: RMConfig) -> dict:
    renderer = Renderer(scan, stage=stage)
    ext = XFeatExtractor(device="cpu", top_k=top_k, max_side=max_side)
    t0 = time.perf_counter()
    db = build_database(renderer, sample_positions(scan, RoiConfig(spacing=spacing)), ext)
    db_s = time.perf_counter() - t0
    tracker = RenderMatchTracker(renderer, ext, db, cfg)
    traj, counts, stage_ms, wall, _, _ = localize_sequence(tracker, seq, frames, stamped=True)
    gt = seq.groundtruth
    a = compute_ape(Trajectory(gt.stamps[:frames], gt.poses[:frames]), traj, "none") if len(traj) else None
    return {"localized": len(traj), "frames": frames, "reloc": counts[Status.RELOCALIZED], "fps": frames / wall,
            "t_cm": 100 * a.trans_rmse if a else float("nan"), "r_deg": a.rot_rmse_deg if a else float("nan"),
            "db_s": db_s, "views": db.n_views, "exposure_ms": 1e3 * (tracker.exposure_s or 0.0), **stage_ms}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/office")
    ap.add_argument("--preset", default="office", help="preset to simulate if --site does not exist yet")
    ap.add_argument("--sequence", default="seq_00")
    ap.add_argument("--frames", type=int, help="only the first N frames")
    ap.add_argument("--stages", nargs="+", default=["full"], choices=list(STAGE_NAMES))
    ap.add_argument("--decimations", type=float, nargs="+", default=[1.0], help="fractions of the scan's points kept")
    ap.add_argument("--max-side", type=int, default=480, help="XFeat input size on the CPU (0: full frame)")
    ap.add_argument("--top-k", type=int, default=1024, help="XFeat keypoints per image")
    ap.add_argument("--spacing", type=float, default=1.0, help="relocalization database grid (m)")
    ap.add_argument("-j", "--threads", type=int, default=1)
    ap.add_argument("--max-sigma-deg", type=float, default=RMConfig.max_sigma_deg, help="pose gate (see cristal localize --help)")
    ap.add_argument("--max-sigma-cm", type=float, default=100 * RMConfig.max_sigma_m, help="pose gate, centimetres")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    site = ensure_site(args.site, args.preset)
    full = load_scan(site / "scan.ply")
    seq = open_sequence(site / args.sequence)
    frames = min(len(seq), args.frames or len(seq))
    print(f"{site}/{args.sequence}: {frames} frames {seq.camera.width}x{seq.camera.height}, scan {len(full):,} points, "
          f"torch threads {args.threads}, XFeat top-{args.top_k} at {args.max_side or 'full'} px, "
          f"gates 1-sigma {args.max_sigma_cm:g} cm / {args.max_sigma_deg:g} deg")
    cfg = RMConfig(max_sigma_deg=args.max_sigma_deg, max_sigma_m=args.max_sigma_cm / 100)
    cols = ["render_ms", "features_ms", "kf_features_ms", "blur_ms", "match_ms", "pose_ms", "relocalize_ms", "total_ms"]
    print("| points | renderer | localized | reloc | APE t cm | APE r deg | FPS | " + " | ".join(c[:-3] for c in cols)
          + " | DB views / s | exposure ms |")
    print("|---:|---|---:|---:|---:|---:|---:|" + "---:|" * len(cols) + "---:|---:|")
    for frac in args.decimations:
        scan = full if frac >= 1.0 else random_decimate(full, frac)
        for stage in args.stages:
            r = run(scan, seq, stage, frames, args.max_side or None, args.top_k, args.spacing, cfg)
            print(f"| {len(scan):,} ({100 * frac:.0f} %) | {STAGE_NAMES[stage]} | {r['localized']}/{r['frames']} "
                  f"({100 * r['localized'] / r['frames']:.1f} %) | {r['reloc']} | {r['t_cm']:.2f} | {r['r_deg']:.3f} | "
                  f"{r['fps']:.1f} | " + " | ".join(f"{r.get(c, 0.0):.1f}" for c in cols)
                  + f" | {r['views']} / {r['db_s']:.0f} | {r['exposure_ms']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
