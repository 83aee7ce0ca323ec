"""How honest is a reported pose's 1-sigma, by how blurred its frame was? Against the simulator's poses.

    python benchmarks/walks.py --methods rm --out runs/walks        # the walks first (their TRAJ and frames.csv)
    python benchmarks/sigma_by_blur.py --walks runs/walks [--root runs/bench-sim] [--method rm] [--sites office ...]

Every localizer reports each pose with a predicted 1-sigma (``TRAJ.frames.csv``: sigma_cm, sigma_deg), which the gate
judges and a client fuses by. This pools the reported frames of the walks in --walks (``SITE-METHOD.txt`` and
``.frames.csv``, as ``benchmarks/walks.py --out`` writes them) and bins them by the frame's motion blur: the image
motion over the simulator's exposure (``site.json``), from the true poses of the frame and the one before, at 640 px
wide. Per bin it prints the frames, the rotation error RMS, the median reported 1-sigma, the RMS of error / 1-sigma
(rotation and translation) and how many frames lie beyond 3-sigma. A 1-sigma that is honest gives about the same
ratio in every bin (the norm of a 3-D error over its per-axis sigma has an RMS of ~1.7); a bin far above the others
is where the uncertainty model under-predicts (benchmarks/RESULTS.md, stop 45: ~1.5x above 10 px of blur).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from services.eval.ape import compute_ape  # noqa: E402
from services.geometry.blur import blur_length_px  # noqa: E402
from services.io.frame_log import frame_log_path, read_frame_log  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402
from services.io.trajectory import read_tum  # noqa: E402

BINS = ((0, 3), (3, 6), (6, 10), (10, 15), (15, 20), (20, 1000))


def frames_of(site: Path, walks: Path, method: str) -> list[tuple[float, float, float, float, float]]:
    """(blur px at 640, translation error cm, rotation error deg, sigma cm, sigma deg) per reported frame."""
    traj = walks / f"{site.name}-{method}.txt"
    if not (traj.exists() and frame_log_path(traj).exists() and (site / "site.json").exists()):
        return []
    cfg = json.loads((site / "site.json").read_text())["config"]
    exposure_frames = cfg["sensor"]["exposure_time_s"] * cfg["fps"]  # exposure as a fraction of the frame interval
    seq = open_sequence(site / "seq_00")
    ape = compute_ape(seq.groundtruth, read_tum(traj), "none", strict=False)
    records = read_frame_log(frame_log_path(traj))
    index = {s: i for i, s in enumerate(seq.groundtruth.stamps)}
    out = []
    for s, te, re in zip(ape.stamps, ape.trans_err, ape.rot_err_deg):
        i, rec = index[s], records.get(s)
        if i == 0 or rec is None or not (np.isfinite(rec.sigma_m) and np.isfinite(rec.sigma_deg)):
            continue
        before, gt = seq.groundtruth.poses[i - 1], seq.groundtruth.poses[i]
        blur = blur_length_px(seq.camera, before, gt) * exposure_frames * 640.0 / seq.camera.width
        out.append((blur, 100 * te, re, 100 * rec.sigma_m, rec.sigma_deg))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--walks", type=Path, required=True, help="benchmarks/walks.py --out folder")
    ap.add_argument("--root", type=Path, default=Path("runs/bench-sim"), help="folder of simulated sites")
    ap.add_argument("--method", choices=["rm", "pnl"], default="rm")
    ap.add_argument("--sites", nargs="+", help="site names (default: every site with a walk in --walks)")
    args = ap.parse_args()
    sites = [args.root / n for n in args.sites] if args.sites else sorted(p for p in args.root.iterdir() if p.is_dir())
    used, rows = [], []
    for site in sites:
        got = frames_of(site, args.walks, args.method)
        if got:
            used.append(f"{site.name} ({len(got)})")
            rows += got
    if not rows:
        print(f"no walks of {args.method} with sites under {args.root} in {args.walks}", file=sys.stderr)
        return 1
    a = np.array(rows)
    print(f"reported frames of {', '.join(used)}: {len(a)}")
    print("| blur (px at 640) | frames | rotation error RMS | median 1σ | error / 1σ RMS, rotation | translation | > 3σ (rotation) |")
    print("|---|---|---|---|---|---|---|")
    for lo, hi in BINS:
        m = (a[:, 0] >= lo) & (a[:, 0] < hi)
        if not m.any():
            continue
        zr, zt = a[m, 2] / a[m, 4], a[m, 1] / a[m, 3]
        rms = lambda x: float(np.sqrt(np.mean(x ** 2)))  # noqa: E731
        label = f"{lo}–{hi}" if hi < 1000 else f"≥ {lo}"
        print(f"| {label} | {m.sum()} | {rms(a[m, 2]):.3f}° | {np.median(a[m, 4]):.3f}° | {rms(zr):.2f} | {rms(zt):.2f} | "
              f"{int((zr > 3).sum())} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
