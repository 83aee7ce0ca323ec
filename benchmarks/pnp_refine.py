"""PnP's last step, measured: RANSAC's own refinement on its inlier set vs the soft refinement over every plausible match.

    python benchmarks/pnp_refine.py [--site runs/bench-sim/office] [--frames 0 299 12] [--offsets 1] [--seed 1]

For every chosen frame of SITE/seq_00 the keyframe is rendered at the simulator's true pose (and, with --offsets N,
at N more poses drawn 1 cm / 0.25 deg (1 sigma per axis) off it, as a tracker's last pose would be), XFeat matches
the frame to it and the matches are Lucas-Kanade refined as Render & Match does, and the pose is solved twice from
the same matches: ``solve_pnp(..., soft=False)`` (poselib's RANSAC and its refinement on the inliers it kept) and
``soft=True`` (then a Cauchy refinement over every match within 5 thresholds, services.geometry.pnp._soft_refine).
Prints a line per render and a table: RMS / median / max error against the truth, and the share of poses whose
angle error exceeds 3 x their own reported 1 sigma.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from services.features.matching import mutual_nn  # noqa: E402
from services.geometry.pnp import solve_pnp  # noqa: E402
from services.geometry.se3 import Pose  # noqa: E402
from services.io.scans import load_scan  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402
from services.localize.cli import _tracking_extractor  # noqa: E402
from services.localize.render_match import RMConfig, normalised_gray, refine_matches_lk  # noqa: E402
from services.render.renderer import Renderer  # noqa: E402


def matches(ext, renderer, image, cam, T_render, scale, cfg: RMConfig):
    """Frame keypoints (frame pixels, LK-refined) and the world points of the render's matched keypoints."""
    camr = cam.scaled(scale) if scale < 1 else cam
    r = renderer.render(T_render, camr)
    kf = ext.extract(r.rgb, max_side=10 ** 6)
    X, ok, _ = r.surface_points(kf.kpts, cfg.depth_radius, cfg.depth_max_residual)
    kf, X = kf.subset(ok), X[ok]
    live = ext.extract(image, max_side=round(scale * max(image.shape[:2])))
    m = mutual_nn(live.desc, kf.desc, cfg.match_cos)
    uv, Xm = live.kpts[m[:, 0]].astype(np.float64), X[m[:, 1]]
    g = normalised_gray(r.rgb)
    size = (g.shape[1], g.shape[0])
    sx, sy = size[0] / cam.width, size[1] / cam.height
    start = np.column_stack([(uv[:, 0] + 0.5) * sx - 0.5, (uv[:, 1] + 0.5) * sy - 0.5])
    q, conv = refine_matches_lk(g, normalised_gray(image, size), kf.kpts[m[:, 1]].astype(np.float64), start,
                                cfg.lk_window, cfg.lk_max_px)
    q = np.column_stack([(q[:, 0] + 0.5) / sx - 0.5, (q[:, 1] + 0.5) / sy - 0.5])
    return np.where(conv[:, None], q, uv), Xm


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--site", default="runs/bench-sim/office")
    ap.add_argument("--frames", type=int, nargs=3, default=[0, 299, 12], metavar=("FIRST", "LAST", "STEP"))
    ap.add_argument("--offsets", type=int, default=1, help="renders per frame off the true pose (besides the true one)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(1)
    site = Path(args.site)
    seq = open_sequence(site / "seq_00")
    if seq.groundtruth is None:
        raise SystemExit(f"{site}/seq_00 has no groundtruth.txt")
    gt = seq.groundtruth.as_dict()
    renderer = Renderer(load_scan(site / "scan.ply"), device="cpu")
    ext = _tracking_extractor(renderer)
    cfg, cam = RMConfig(), seq.camera
    scale = min(1.0, (ext.max_side or max(cam.width, cam.height)) / max(cam.width, cam.height))
    rng = np.random.default_rng(args.seed)
    res: dict[bool, list] = {False: [], True: []}
    first, last, step = args.frames
    for i in range(first, min(last, len(seq) - 1) + 1, step):
        f = seq.read(i)
        T = gt[f.stamp]
        for o in range(1 + args.offsets):
            off = np.zeros(6) if o == 0 else np.concatenate([rng.normal(0, 0.01, 3), np.radians(rng.normal(0, 0.25, 3))])
            T_r = T @ Pose.from_rotvec_t(off[3:], off[:3])
            uv, X = matches(ext, renderer, f.image, cam, T_r, scale, cfg)
            line, rows = f"{i:4d} render {o}:", {}
            for soft in (False, True):
                r = solve_pnp(uv, X, cam, cfg.ransac_px, initial=T_r, min_iterations=cfg.ransac_min_iterations, soft=soft)
                if r is None or r.n_inliers < cfg.min_inliers:
                    break
                dt, dr = T.distance_to(r.T_wc)
                rows[soft] = (100 * dt, dr, r.sigma_r_deg)
                line += f"  {'soft' if soft else 'RANSAC set'} {r.n_inliers:3d} inliers {100 * dt:5.2f} cm {dr:6.3f} deg"
            if len(rows) == 2:
                for soft, row in rows.items():
                    res[soft].append(row)
                print(line, flush=True)
    print(f"\n{site}, {len(res[True])} renders (frames {first}-{last} every {step}, {args.offsets} off the truth each)\n")
    print("| last step | RMS cm / deg | median cm / deg | max cm / deg | angle > 3 sigma |")
    print("|---|---|---|---|---:|")
    for soft, name in ((False, "RANSAC's inlier set"), (True, "soft, every match within 5 thresholds")):
        e = np.array(res[soft]).reshape(-1, 3)
        if not len(e):
            continue
        print(f"| {name} | {np.sqrt((e[:, 0] ** 2).mean()):.2f} / {np.sqrt((e[:, 1] ** 2).mean()):.3f} | "
              f"{np.median(e[:, 0]):.2f} / {np.median(e[:, 1]):.3f} | {e[:, 0].max():.2f} / {e[:, 1].max():.3f} | "
              f"{100 * np.mean(e[:, 1] > 3 * e[:, 2]):.0f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
