"""Does a localizer report a wrong pose when its prediction is off? Each method from a prediction a few cm away.

    python benchmarks/off_prediction.py                                  # office, both methods, every 5th frame
    python benchmarks/off_prediction.py --site runs/bench-sim/office-s8 --methods pnl --offsets 0.03 0.1

Tracking predicts each frame from the last pose and velocity; after a sudden stop, a LOST frame coasted through on
the last velocity, a pose carried by a device's odometry or a hand-over, the prediction can be centimetres off. A
localizer must then find the true pose or say LOST, never report a pose far off with a small uncertainty. For every
``--step``-th frame of the site's walk and each offset, this hands the frame to a fresh localizer with a prediction
(``process(prior=...)``) moved that far in a random direction and turned 10 degrees per metre of it (seeded), and
counts the frames reported LOST, reported, and reported beyond 3 cm or 0.5 degrees of the simulator's truth ("off":
it must stay 0), with the worst of those and its reported 1-sigma. Render & Match needs SITE/reloc.npz only to load
its tracker (no database search: the prediction is where it tracks from); Prebuild & Localize needs SITE/map.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
from _site import ensure_site  # noqa: E402

from services.geometry.se3 import Pose, rotvec_to_rotmat  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402


def _localizer(method: str, site):
    if method == "pnl":
        from services.localize.pnl import PnlLocalizer

        return PnlLocalizer.load(site / "map")
    import torch

    from services.features.xfeat import XFeatExtractor
    from services.io.scans import load_scan
    from services.localize.render_match import RenderMatchTracker
    from services.render.renderer import Renderer

    torch.set_num_threads(1)
    return RenderMatchTracker(Renderer(load_scan(site / "scan.ply")), XFeatExtractor(device="cpu", top_k=1024, max_side=480))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/office")
    ap.add_argument("--methods", nargs="+", choices=["rm", "pnl"], default=["pnl", "rm"])
    ap.add_argument("--offsets", type=float, nargs="+", default=[0.03, 0.1, 0.2], help="prediction offsets (m)")
    ap.add_argument("--step", type=int, default=5, help="every this many frames of the walk")
    ap.add_argument("--tries", type=int, default=2, help="random directions per frame and offset")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    site = ensure_site(args.site)
    seq = open_sequence(site / "seq_00")
    print(f"{site}: frames 0-{len(seq) - 1} every {args.step}, {args.tries} directions each, prediction turned 10 deg/m\n")
    print("| method | prediction off | LOST | reported | off (> 3 cm / 0.5 deg) | worst off: frame, error, reported 1-sigma |")
    print("|---|---:|---:|---:|---:|---|")
    for method in args.methods:
        loc = _localizer(method, site)
        rng = np.random.default_rng(args.seed)
        for off in args.offsets:
            lost = reported = 0
            bad: list[tuple[float, str]] = []
            for i in range(0, len(seq), args.step):
                f = seq.read(i)
                G = seq.groundtruth_pose(f.stamp)
                for _ in range(args.tries):
                    d, a = rng.standard_normal(3), rng.standard_normal(3)
                    P = Pose(rotvec_to_rotmat(a / np.linalg.norm(a) * np.radians(10 * off)) @ G.R, G.t + off * d / np.linalg.norm(d))
                    loc.reset()
                    r = loc.process(f.image, seq.camera, prior=P, stamp=float(f.stamp))
                    if r.T_wc is None:
                        lost += 1
                        continue
                    reported += 1
                    e_t, e_r = r.T_wc.distance_to(G)
                    if e_t > 0.03 or e_r > 0.5:
                        bad.append((e_t, f"{i}, {100 * e_t:.1f} cm / {e_r:.2f} deg, {100 * r.sigma_m:.2f} cm / {r.sigma_deg:.3f} deg"))
            worst = max(bad)[1] if bad else "-"
            print(f"| {method} | {100 * off:.0f} cm | {lost} | {reported} | {len(bad)} | {worst} |", flush=True)


if __name__ == "__main__":
    main()
