"""How many of a render's keypoints get a depth, and how many of those are right? Against the simulator's mesh.

    python benchmarks/keypoint_depth.py                                          # warehouse seed 3 (6 M points)
    python benchmarks/keypoint_depth.py --site runs/bench-sim/office --frames 10 150 270
    python benchmarks/keypoint_depth.py --max-residual 0.01 0.03 0.05            # the plane rule's tolerance swept

Render & Match and the relocalization database give each XFeat keypoint of a render the depth of a plane fitted to
the scan points around it (``services.render.depth_sampling.plane_depth``), and refuse one where those points are not
on one plane. A keypoint without depth is no 3D point: where most are refused (a sparse scan: points several pixels
apart, surfaces in front of others through its gaps), too few matches remain to fit or verify a pose. This renders
the site's scan at the true pose of each frame (the tracker's base 480 px and 2x supersampling; the tracker itself
renders coarser where most of a render is holes), takes the render's 1024
XFeat keypoints and compares the depth each is given with the depth of the simulator's mesh along the keypoint's ray.
Per frame and tolerance it prints the keypoints given a depth and how many of those are within 1 % and 3 % of the
mesh's; the last row sums the frames.
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

from services.features.xfeat import XFeatExtractor  # noqa: E402
from services.io.scans import load_scan  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402
from services.localize.render_match import RMConfig  # noqa: E402
from services.render.depth_sampling import plane_depth  # noqa: E402
from services.render.renderer import Renderer  # noqa: E402
from services.sim.mesh import Mesh  # noqa: E402
from services.sim.raytrace import build_bvh, trace  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/warehouse-s3", help="a site from `cristal sim` (scan.ply, mesh.npz, seq_00)")
    ap.add_argument("--frames", type=int, nargs="+", default=[1, 31, 91, 200, 280, 360, 540])
    ap.add_argument("--max-residual", type=float, nargs="+", default=[RMConfig.depth_max_residual],
                    help="plane misfit tolerances to compare (fraction of depth)")
    ap.add_argument("--radius", type=int, default=RMConfig.depth_radius, help="plane window half-size (render pixels)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    site = Path(args.site)
    if not (site / "mesh.npz").is_file():
        sys.exit(f"{site}: no mesh.npz (a site from `cristal sim` or benchmarks/sim.py has one)")
    seq = open_sequence(site / "seq_00")
    mesh = Mesh.load(site / "mesh.npz")
    bvh = build_bvh(mesh.vertices, mesh.faces)
    renderer = Renderer(load_scan(site / "scan.ply"))
    ext = XFeatExtractor(device="cpu", top_k=1024, max_side=480)
    cam = seq.camera.scaled(min(1.0, 480 / max(seq.camera.width, seq.camera.height)))
    print(f"{site}: {cam.width}x{cam.height} renders at the true poses, 2x supersampled; window radius {args.radius} px\n")
    print("| frame | holes | " + " | ".join(f"misfit {m:g}: with depth, within 1 % / 3 %" for m in args.max_residual) + " |")
    print("|---:|---:|" + "---|" * len(args.max_residual))
    total = np.zeros((len(args.max_residual), 3), int)
    for i in args.frames:
        f = seq.read(i)
        T = seq.groundtruth_pose(f.stamp)
        r = renderer.render(T, cam, supersample=2)
        kp = ext.extract(r.rgb).kpts.astype(np.float64)
        rays = cam.backproject(kp, np.ones(len(kp)))  # camera rays of depth 1: the hit distance is the depth
        z_true, *_ = trace(bvh, T.t, rays @ T.R.T)
        cells = []
        for j, m in enumerate(args.max_residual):
            z, ok = plane_depth(r.depth, kp, args.radius, m)
            rel = np.abs(z[ok] - z_true[ok]) / z_true[ok]
            row = (int(ok.sum()), int(np.sum(rel < 0.01)), int(np.sum(rel < 0.03)))
            total[j] += row
            cells.append(f"{row[0]}, {row[1]} / {row[2]}")
        print(f"| {i} | {r.hole_fraction:.0%} | " + " | ".join(cells) + " |", flush=True)
    print("| all | | " + " | ".join(f"**{a}, {b} / {c}** ({b / max(a, 1):.0%} within 1 %)" for a, b, c in total) + " |")


if __name__ == "__main__":
    main()
