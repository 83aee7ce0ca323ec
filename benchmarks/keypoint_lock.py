"""Do XFeat keypoints follow the picture, or stick to their image cells? Against the simulator's exact pictures.

    python benchmarks/keypoint_lock.py                                          # office-s61-sparse, frames 80 100 120
    python benchmarks/keypoint_lock.py --site runs/bench-sim/office --frames 50 150 250
    python benchmarks/keypoint_lock.py --ratios 1.0 1.05 1.1 --turns 0.1 0.3 0.6 1.5

Render & Match matches a live frame against a render made near (not at) the frame's pose, and both are cut into
XFeat's 8 x 8-pixel cells. If a keypoint's position depended only on the picture, a render turned by a small angle
would show every keypoint moved by the flow that turn makes. This takes each chosen frame of SITE/seq_00 (the real
frame: noise, blur, JPEG and all) and the simulator's own picture of the mesh (scan lighting) from the true pose turned
about the camera's y axis by each of ``--turns`` degrees, at ``ratio`` x the tracker's feature resolution; XFeat on
both (the frame at the tracker's 480 px, the picture at its own size), mutual matches, and compares each matched
keypoint in the picture with where the frame's keypoint's ray lands there, exactly. It prints, per ratio and turn:
matches, the median keypoint error, and the *pull*: the share of the flow the matched keypoints fail to follow
(0 = they follow the picture; 0.3 = a pose solved from them lands 30 % of the way back to the render's).

Stop 58 found that at ratio 1 (render and frame cut into the same cells) the pull is 0.3-0.45 for flows up to ~3 px
on weakly textured walls and vanishes past ~4 px (half a cell); at ratio 1.1 it is gone (benchmarks/RESULTS.md).
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
from services.features.xfeat import XFeatExtractor  # noqa: E402
from services.geometry.se3 import Pose  # noqa: E402
from services.sim.site import SimSite  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--site", default="runs/bench-sim/office-s61-sparse", help="a simulated site (needs SITE/mesh.npz)")
    ap.add_argument("--frames", type=int, nargs="+", default=[80, 100, 120])
    ap.add_argument("--ratios", type=float, nargs="+", default=[1.0, 1.1],
                    help="the picture's resolution over the frame's feature resolution")
    ap.add_argument("--turns", type=float, nargs="+", default=[0.1, 0.2, 0.3, 0.6, 1.5], help="degrees about y")
    ap.add_argument("--side", type=int, default=480, help="the frame's feature resolution (the tracker's max_side)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    site = Path(args.site)
    seq = walk_with_truth(site)
    sim = SimSite(site)
    cam = seq.camera
    base = min(1.0, args.side / max(cam.width, cam.height))
    ext = XFeatExtractor(device="cpu", top_k=1024)
    gt = seq.groundtruth.as_dict()
    frames = []  # (true pose, the frame's features), each frame read and extracted once for every ratio and turn
    for i in args.frames:
        f = seq.read(i)
        frames.append((gt[f.stamp], ext.extract(f.image, max_side=args.side)))
    print("| ratio | turn (deg) | mean flow (px) | matches | median keypoint error (px) | pull |")
    print("|---:|---:|---:|---:|---:|---:|")
    for ratio in args.ratios:
        pic_cam = cam.scaled(base * ratio)
        for turn in args.turns:
            D = Pose.from_rotvec_t(np.array([0.0, np.radians(turn), 0.0]), np.zeros(3))
            rows = []
            for T, live in frames:
                pic = sim.render(T @ D, pic_cam, lighting="scan")[0]
                feats = ext.extract(pic, max_side=max(pic.shape[:2]))
                m = mutual_nn(live.desc, feats.desc, 0.8, "cpu")
                rays = cam.backproject(live.kpts[m[:, 0]].astype(np.float64), np.ones(len(m)))
                at_rest, _ = pic_cam.project(rays)  # where the ray lands in the picture had it not turned
                truth, _ = pic_cam.project(D.inverse().transform(rays))
                err = feats.kpts[m[:, 1]] - truth
                flow = truth - at_rest
                ok = np.linalg.norm(err, axis=1) < 3.0  # wrong matches say nothing about where keypoints sit
                rows.append((float(np.linalg.norm(flow[ok], axis=1).mean()), int(ok.sum()),
                             float(np.median(np.linalg.norm(err[ok], axis=1))),
                             -float(np.sum(err[ok] * flow[ok]) / max(np.sum(flow[ok] ** 2), 1e-9))))
            r = np.array(rows).mean(0)
            print(f"| {ratio:g} | {turn:g} | {r[0]:.2f} | {r[1]:.0f} | {r[2]:.2f} | {r[3]:+.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
