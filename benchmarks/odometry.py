"""Render & Match with and without the device's own odometry, on simulated walks.

    python benchmarks/odometry.py [--sites runs/bench-sim/office runs/bench-sim/office-s2 ...] [--seed 0]

For each site (its scan.ply, reloc.npz and seq_00 with ground truth; build them with `cristal sim` and
`cristal build-db`): the walk localized from images alone, then again with simulated odometry
(services/sim/odometry.py: per frame 0.03 deg and 1 % of the step of noise, 1 % scale bias, in a frame of its
own), each from a cold start. Prints a table: frames reported, relocalizations (with odometry: also the
re-acquisitions from a pose the odometry carried through LOST), APE with no alignment, FPS, LOST by reason.
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
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)
    rows = []
    for site in map(Path, args.sites):
        seq = open_sequence(site / "seq_00")
        n = min(len(seq), args.frames or len(seq))
        renderer = Renderer(load_scan(site / "scan.ply"))
        db = RelocDB.load(site / "reloc.npz")
        odo = simulate_odometry(seq.groundtruth, OdometryNoise(), seed=args.seed)
        for name, o in (("images only", None), ("+ odometry", odo)):
            tr = RenderMatchTracker(renderer, _tracking_extractor(renderer), db)
            t0 = time.perf_counter()
            traj, counts, _, dt, why = localize_sequence(tr, seq, n, progress_desc=f"{site.name} {name}", stamped=True,
                                                         odometry=o)
            _, ape = ape_first_frames(seq.groundtruth, traj, n)
            rows.append((site.name, name, len(traj), n, tr.relocalizations, 100 * ape.get("ape_none_trans_rmse_m", np.nan),
                         ape.get("ape_none_rot_rmse_deg", np.nan), n / (time.perf_counter() - t0), why))
    print("| walk | input | frames reported | relocalizations | APE t cm | APE r deg | FPS | LOST by reason |")
    print("|---|---|---:|---:|---:|---:|---:|---|")
    for site, name, k, n, rel, t, r, fps, why in rows:
        lost = ", ".join(f"{v} {w}" for w, v in sorted(why.items(), key=lambda kv: -kv[1]))
        print(f"| {site} | {name} | {k}/{n} ({100 * k / n:.1f} %) | {rel} | {t:.2f} | {r:.3f} | {fps:.1f} | {lost} |")


if __name__ == "__main__":
    main()
