"""PnP's last step, measured: RANSAC's own refinement on its inlier set vs the soft refinement over every plausible match.

    python benchmarks/pnp_refine.py [--site runs/bench-sim/office] [--frames 0 299 12] [--offsets 1] [--seed 1]

For every chosen frame of SITE/seq_00 the keyframe is rendered at the simulator's true pose (and, with --offsets N,
at N more poses drawn 1 cm / 0.25 deg (1 sigma per axis) off it, as a tracker's last pose would be), XFeat matches
the frame to it and Lucas-Kanade refines the matches, by Render & Match's own steps, and the pose is solved twice
from the same matches: ``solve_pnp(..., soft=False)`` (poselib's RANSAC and its refinement on the inliers it kept) and
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

from _site import walk_with_truth  # noqa: E402
from services.features.matching import mutual_nn  # noqa: E402
from services.geometry.pnp import solve_pnp  # noqa: E402
from services.geometry.se3 import Pose  # noqa: E402
from services.io.scans import load_scan  # noqa: E402
from services.localize.cli import _tracking_extractor  # noqa: E402
from services.localize.render_match import RenderMatchTracker, RMConfig, _Frame  # noqa: E402
from services.render.renderer import Renderer  # noqa: E402


def matches(tracker: RenderMatchTracker, image, cam, T_render):
    """What the tracker solves from for a keyframe rendered at ``T_render``: frame keypoints (frame pixels,
    Lucas-Kanade refined against the render) and the world points of the render's matched keypoints."""
    fr = _Frame(image, cam, {}, None, 0.0, None)
    kf = tracker._keyframe(T_render, fr)
    feats, xyz, gray = tracker._sharp_points(kf, fr)
    live = tracker._live(fr, kf.scale)
    m = mutual_nn(live.desc, feats.desc, tracker.cfg.match_cos)
    return tracker._refine(fr, live.kpts[m[:, 0]].astype(np.float64), xyz[m[:, 1]], feats.kpts[m[:, 1]], gray)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--site", default="runs/bench-sim/office")
    ap.add_argument("--frames", type=int, nargs=3, default=[0, 299, 12], metavar=("FIRST", "LAST", "STEP"))
    ap.add_argument("--offsets", type=int, default=1, help="renders per frame off the true pose (besides the true one)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(1)
    site = Path(args.site)
    seq = walk_with_truth(site)
    gt = seq.groundtruth.as_dict()
    renderer = Renderer(load_scan(site / "scan.ply"), device="cpu")
    cfg, cam = RMConfig(), seq.camera
    tracker = RenderMatchTracker(renderer, _tracking_extractor(renderer), None, cfg)
    rng = np.random.default_rng(args.seed)
    res: dict[bool, list] = {False: [], True: []}
    first, last, step = args.frames
    for i in range(first, min(last, len(seq) - 1) + 1, step):
        f = seq.read(i)
        T = gt[f.stamp]
        for o in range(1 + args.offsets):
            off = np.zeros(6) if o == 0 else np.concatenate([rng.normal(0, 0.01, 3), np.radians(rng.normal(0, 0.25, 3))])
            T_r = T @ Pose.from_rotvec_t(off[3:], off[:3])
            uv, X = matches(tracker, f.image, cam, T_r)
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
