"""Render & Match with and without the device's own odometry, on simulated walks.

    python benchmarks/odometry.py [--sites runs/bench-sim/office runs/bench-sim/office-s2 ...] [--seed 0]
                                  [--noise ROT_DEG TRANS_FRAC SCALE]

For each site (its scan.ply, reloc.npz and seq_00 with ground truth; build them with `cristal sim` and
`cristal build-db`): the walk localized from images alone, then again with simulated odometry
(services/sim/odometry.py: per frame 0.03 deg and 1 % of the step of noise, 1 % scale bias, in a frame of its
own), each from a cold start. Prints a table: frames reported, relocalizations (with odometry: also the
re-acquisitions from a pose the odometry carried through LOST), APE with no alignment, the worst reported
frame and how many are over 5 cm or 1 degree off, FPS, LOST by reason.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from services.eval.ape import ape_first_frames  # noqa: E402
from services.io.scans import load_scan  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402
from services.localize.cli import _tracking_extractor  # noqa: E402
from services.localize.render_match import RenderMatchTracker  # noqa: E402
from services.localize.runner import localize_sequence  # noqa: E402
from services.relocalize.database import RelocDB  # noqa: E402
from services.render.renderer import Renderer  # noqa: E402
from services.sim.odometry import OdometryNoise, simulate_odometry  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sites", nargs="+", default=["runs/bench-sim/office"])
    ap.add_argument("--frames", type=int, help="only the first N frames")
    ap.add_argument("--seed", type=int, default=0, help="odometry noise seed")
    ap.add_argument("--noise", type=float, nargs=3, metavar=("ROT_DEG", "TRANS_FRAC", "SCALE"),
                    help="odometry noise per frame (1 sigma, each axis) and scale bias (default: "
                         "services/sim/odometry.py's OdometryNoise, 0.03 0.01 1.01)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)
    rows = []
    for site in map(Path, args.sites):
        seq = open_sequence(site / "seq_00")
        n = min(len(seq), args.frames or len(seq))
        renderer = Renderer(load_scan(site / "scan.ply"))
        db = RelocDB.load(site / "reloc.npz")
        noise = OdometryNoise(*args.noise[:2], scale=args.noise[2]) if args.noise else OdometryNoise()
        odo = simulate_odometry(seq.groundtruth, noise, seed=args.seed)
        for name, o in (("images only", None), ("+ odometry", odo)):
            tr = RenderMatchTracker(renderer, _tracking_extractor(renderer), db)
            t0 = time.perf_counter()
            traj, counts, _, dt, why, _ = localize_sequence(tr, seq, n, progress_desc=f"{site.name} {name}", stamped=True,
                                                         odometry=o)
            _, ape = ape_first_frames(seq.groundtruth, traj, n)
            gt = seq.groundtruth.as_dict()
            err = np.array([gt[s].distance_to(T) for s, T in traj if s in gt]).reshape(-1, 2)
            worst = err.max(0) if len(err) else np.zeros(2)
            rows.append((site.name, name, len(traj), n, tr.relocalizations, 100 * ape.get("ape_none_trans_rmse_m", np.nan),
                         ape.get("ape_none_rot_rmse_deg", np.nan), 100 * worst[0], worst[1],
                         int(np.sum((err[:, 0] > 0.05) | (err[:, 1] > 1.0))), n / (time.perf_counter() - t0), why))
    print("| walk | input | frames reported | relocalizations | APE t cm | APE r deg | worst cm / deg | > 5 cm or 1 deg "
          "| FPS | LOST by reason |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for site, name, k, n, rel, t, r, wt, wr, bad, fps, why in rows:
        lost = ", ".join(f"{v} {w}" for w, v in sorted(why.items(), key=lambda kv: -kv[1]))
        print(f"| {site} | {name} | {k}/{n} ({100 * k / n:.1f} %) | {rel} | {t:.2f} | {r:.3f} | {wt:.1f} / {wr:.2f} | {bad} "
              f"| {fps:.1f} | {lost} |")


if __name__ == "__main__":
    main()
