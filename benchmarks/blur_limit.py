"""How well can a frame be localized at all? Render & Match from a perfect prediction, frame by frame.

    python benchmarks/blur_limit.py                                     # office seed 1, frames 260-299 (the whip pan)
    python benchmarks/blur_limit.py --site runs/bench-sim/office-s2 --frames 50 70 --step 1

For each frame the keyframe is rendered at the *previous* frame's ground-truth pose, the motion between the two
is the ground truth's, and the exposure is the simulator's: tracking cannot be better prepared than this. It
then prints, per frame, the predicted blur, and for direct tracking (corner patches of the render, blurred
like the frame) and XFeat matching (the blurred render) the inliers, the error against ground truth, the
predicted 1-sigma and whether the pose passes the report gate. Frames that fail here are lost by any tracker
built on these measurements; frames that pass here but are lost in a real run are lost by the tracking chain
(prediction, keyframe choice), which is what to work on.
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402
from _site import ensure_site  # noqa: E402

from services.features.xfeat import XFeatExtractor  # noqa: E402
from services.io.scans import load_scan  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402
from services.localize.render_match import RenderMatchTracker, RMConfig, _Frame  # noqa: E402
from services.render.renderer import Renderer  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/office")
    ap.add_argument("--frames", type=int, nargs=2, default=(260, 299), metavar=("FIRST", "LAST"))
    ap.add_argument("--step", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(1)
    site = ensure_site(args.site)
    seq = open_sequence(site / "seq_00")
    exposure = json.loads((site / "site.json").read_text())["config"]["sensor"]["exposure_time_s"]
    tr = RenderMatchTracker(Renderer(load_scan(site / "scan.ply")), XFeatExtractor(device="cpu", top_k=1024, max_side=480),
                            None, RMConfig(exposure_s=exposure))
    print(f"{site}, exposure {1e3 * exposure:.1f} ms, keyframe at the previous frame's true pose, true motion\n")
    print("| frame | blur px | direct: inliers, error cm / deg, sigma cm / deg, gate | XFeat: inliers, error cm / deg, sigma cm / deg, gate |")
    print("|---:|---:|---|---|")
    for i in range(max(1, args.frames[0]), min(len(seq) - 1, args.frames[1]) + 1, args.step):
        f, prev = seq.read(i), seq.read(i - 1)
        G, Gp = seq.groundtruth_pose(f.stamp), seq.groundtruth_pose(prev.stamp)
        dt = float(f.stamp) - float(prev.stamp)
        fr = _Frame(f.image, seq.camera, {}, (Gp.inverse() @ G, dt), dt, exposure)
        kf = tr._keyframe(Gp, fr)
        cells = []
        for solve in (lambda: tr._direct(kf, fr, G), lambda: tr._match(kf, fr, G)):
            r = solve()
            if r is None:
                cells.append("none")
                continue
            e = r.T_wc.distance_to(G)
            cells.append(f"{r.n_inliers}, {100 * e[0]:.2f} / {e[1]:.3f}, {100 * r.sigma_t_m:.2f} / {r.sigma_r_deg:.3f}, "
                         f"{'pass' if tr._good(r) else 'fail'}")
        print(f"| {i} | {tr._blur_px(fr, exposure):.1f} | {cells[0]} | {cells[1]} |", flush=True)


if __name__ == "__main__":
    main()
