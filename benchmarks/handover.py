"""The client's hand-over to its local P&L, frame by frame: a server pose for frame k, then frame k+1 alone.

    python benchmarks/handover.py [--site runs/bench-sim/office-hd] [--mode seeds|seed|prior] [--step 1] [--start 0]

For every STEP-th frame k of SITE/seq_00 (with SITE/map from `cristal prebuild`), the P&L localizer is reset and
handed the simulator's true pose of frame k as the client hands it a server pose, then asked for frame k+1 with
nothing else, as the client does when the server misses a frame:

- ``seeds`` (the client now): ``seed()`` with the truths of frames k-1 and k and their capture times (the velocity
  between consecutive server poses predicts frame k+1);
- ``seed``: ``seed()`` with frame k's truth only (no motion known);
- ``prior``: frame k localized with its truth as a prior (the client before stop 36: the last server pose, no motion).

Prints each hand-over and a summary: frames reported, reported beyond 2 cm or 0.3 degrees of the truth, and beyond
5 cm or 1 degree (a wrong pose); RMS error of the reported ones.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from services.io.sequence import open_sequence  # noqa: E402
from services.localize.pnl import PnlConfig, PnlLocalizer  # noqa: E402
from services.localize.runner import _seconds  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--site", default="runs/bench-sim/office-hd")
    ap.add_argument("--mode", choices=["seeds", "seed", "prior"], default="seeds")
    ap.add_argument("--step", type=int, default=1)
    ap.add_argument("--start", type=int, default=1)
    args = ap.parse_args()
    site = Path(args.site)
    seq = open_sequence(site / "seq_00")
    if seq.groundtruth is None:
        raise SystemExit(f"{site}/seq_00 has no groundtruth.txt")
    gt = seq.groundtruth.as_dict()
    loc = PnlLocalizer.load(site / "map", PnlConfig())
    rows = []
    for k in range(max(args.start, 1), len(seq) - 1, args.step):
        loc.reset()
        f0, f1 = seq.read(k), seq.read(k + 1)
        if args.mode == "seeds":
            fp = seq.read(k - 1)
            loc.seed(gt[fp.stamp], stamp=_seconds(fp.stamp))
        if args.mode in ("seeds", "seed"):
            loc.seed(gt[f0.stamp], stamp=_seconds(f0.stamp))
        else:
            loc.process(f0.image, seq.camera, prior=gt[f0.stamp], stamp=_seconds(f0.stamp))
        r = loc.process(f1.image, seq.camera, stamp=_seconds(f1.stamp))
        turn = gt[f0.stamp].distance_to(gt[f1.stamp])[1]
        if r.T_wc is None:
            rows.append((np.nan, np.nan))
            print(f"{k:4d} -> {k + 1}: LOST ({r.reason}); turn {turn:.2f} deg", flush=True)
            continue
        dt, dr = gt[f1.stamp].distance_to(r.T_wc)
        rows.append((100 * dt, dr))
        print(f"{k:4d} -> {k + 1}: {r.status.name.lower():11s} {100 * dt:5.2f} cm {dr:6.3f} deg ({r.inliers} inliers, "
              f"1-sigma {100 * r.sigma_m:.2f} cm {r.sigma_deg:.3f} deg); turn {turn:.2f} deg", flush=True)
    e = np.array(rows).reshape(-1, 2)
    rep = e[np.isfinite(e[:, 0])]
    print(f"\n{site} ({args.mode}): {len(rep)}/{len(e)} hand-overs reported; beyond 2 cm or 0.3 deg: "
          f"{int(((rep[:, 0] > 2) | (rep[:, 1] > 0.3)).sum())}; beyond 5 cm or 1 deg: {int(((rep[:, 0] > 5) | (rep[:, 1] > 1)).sum())}"
          + (f"; RMS {np.sqrt((rep[:, 0] ** 2).mean()):.2f} cm / {np.sqrt((rep[:, 1] ** 2).mean()):.3f} deg" if len(rep) else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
