"""Does a blurred frame's pose follow the render's? XFeat and phase correlation against renders turned off the truth.

    python benchmarks/blur_bias.py                                       # office seed 2, its first fast pan
    python benchmarks/blur_bias.py --site runs/bench-sim/office --frames 262 270 --offset 0.3

Render & Match solves a frame against a render at the predicted pose. On a sharp frame it does not matter whether
that prediction was a few tenths of a degree off: the features say where the frame is. This checks that on frames
blurred by a fast turn. For each frame the keyframe is rendered at the frame's *true* pose turned by -OFFSET, 0 and
+OFFSET degrees about the turn's axis (the true motion since the previous frame), blurred with the true motion and
the simulator's exposure, and the frame is solved against it (XFeat matches, PnP, as tracking does). It prints the
pose's error about that axis, signed: an estimate that measures the frame reads about 0 at every offset; one that
stays where the render was reads the offset itself. Beside it, what the phase correlation of the blurred render with
the frame reads as the render's offset about the same axis (a global image shift, from the content alone), and the
error of the pose solved against a render turned back by that reading: what Render & Match does since stop 47 for a
frame blurred over ``blur_min_px`` (RMConfig.blur_center).

Stop 47 measured (benchmarks/RESULTS.md): at 10-17 px of blur the XFeat pose stays where the render was (its error
is about the offset), while the phase correlation reads the offset to within 0.04 deg; a sharp frame's pose does not
move with the render.
"""

from __future__ import annotations

import argparse
import json
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _site import ensure_site  # noqa: E402

from services.features.xfeat import XFeatExtractor  # noqa: E402
from services.geometry.se3 import Pose  # noqa: E402
from services.io.scans import load_scan  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402
from services.localize.render_match import RenderMatchTracker, RMConfig, _Frame, normalised_gray, phase_turn  # noqa: E402
from services.render.renderer import Renderer  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/office-s2")
    ap.add_argument("--frames", type=int, nargs=2, default=(58, 70), metavar=("FIRST", "LAST"))
    ap.add_argument("--step", type=int, default=2)
    ap.add_argument("--offset", type=float, default=0.3, help="degrees the render is turned off the truth")
    ap.add_argument("--seed", type=int, default=2, help="the office seed to simulate when --site has no site yet")
    args = ap.parse_args()
    torch.set_num_threads(1)
    site = ensure_site(args.site, seed=args.seed)
    seq = open_sequence(site / "seq_00")
    exposure = json.loads((site / "site.json").read_text())["config"]["sensor"]["exposure_time_s"]
    tr = RenderMatchTracker(Renderer(load_scan(site / "scan.ply")), XFeatExtractor(device="cpu", top_k=1024, max_side=480),
                            None, RMConfig(exposure_s=exposure))
    offsets = (-args.offset, 0.0, args.offset)
    cols = " / ".join(f"{o:+.2f}" for o in offsets)
    print(f"{site}, exposure {1e3 * exposure:.1f} ms; render at the true pose turned {cols} deg about the turn's axis\n")
    print(f"| frame | turn deg/frame | blur px | XFeat pose error about the axis, deg ({cols}) | inliers | "
          f"phase correlation reads ({cols}) | error against the render turned back by it ({cols}) |")
    print("|---:|---:|---:|---|---|---|---|")
    for i in range(max(1, args.frames[0]), min(len(seq) - 1, args.frames[1]) + 1, args.step):
        f, prev = seq.read(i), seq.read(i - 1)
        G, Gp = seq.groundtruth_pose(f.stamp), seq.groundtruth_pose(prev.stamp)
        dt = float(f.stamp) - float(prev.stamp)
        M = Gp.inverse() @ G
        turn = M.rotvec()
        if np.linalg.norm(turn) < 1e-4:
            continue
        axis = turn / np.linalg.norm(turn)
        errors, inliers, reads, centred = [], [], [], []
        for o in offsets:
            P = G @ Pose.from_rotvec_t(axis * np.radians(o), np.zeros(3))
            fr = _Frame(f.image, seq.camera, {}, (M, dt), dt, exposure)
            kf = tr._keyframe(P, fr)
            r = tr._match(kf, fr, P)
            errors.append("none" if r is None else f"{float(np.degrees((G.inverse() @ r.T_wc).rotvec()) @ axis):+.3f}")
            inliers.append("0" if r is None else str(r.n_inliers))
            img = tr._blurred_image(kf, fr, exposure)[0] if tr._blur_px(fr, exposure) >= tr.cfg.blur_min_px else kf.gray
            turn_back, _ = phase_turn(normalised_gray(img), normalised_gray(f.image, img.shape[::-1]), kf.render.camera)
            reads.append(f"{-float(np.degrees(turn_back) @ axis):+.3f}")  # the render's offset, as read
            Pc = P @ Pose.from_rotvec_t(turn_back, np.zeros(3))
            rc = tr._match(tr._keyframe(Pc, fr), fr, Pc)
            centred.append("none" if rc is None else f"{float(np.degrees((G.inverse() @ rc.T_wc).rotvec()) @ axis):+.3f}")
        print(f"| {i} | {np.degrees(np.linalg.norm(turn)):.2f} | {tr._blur_px(fr, exposure):.1f} | {' / '.join(errors)} | "
              f"{' / '.join(inliers)} | {' / '.join(reads)} | {' / '.join(centred)} |", flush=True)


if __name__ == "__main__":
    main()
