"""Prebuild & Localize on a simulated site: map build time and size, localization rate, APE and FPS on one core.

    python benchmarks/pnl.py [--site runs/bench-sim/office] [--variants full:1.0 full:0.1 splat:1.0] [--spacing 1.0]
    python benchmarks/pnl.py --site runs/bench-sim/office-s6-wide --map runs/bench-sim/office-s6-wide/map

Each variant is STAGE:FRACTION: the renderer stage the map is built from ("full" = neural, "splat" =
plain point splats, the paper's ablation) and the fraction of the scan's points kept (random
decimation). Maps are built with ``cristal -j 1 prebuild`` into SITE/pnl-maps/<variant>/ (reused when
present; --rebuild to redo), then the light localizer runs over SITE/seq_00 with every thread pinned
to one (OpenCV, OpenMP): the first frame relocalizes with no prior. APE is against groundtruth.txt,
with no alignment. "tracking": direct (the default: patch alignment from the prediction, keypoints when it
fails), keypoints+align (ORB, then patch alignment) and keypoints (ORB only, as for a map without patches).
"track ms" = median CPU time (``time.thread_time``, so other processes on a shared
machine do not count) of a frame that tracked; "track FPS" = 1000 / its mean; "FPS all" = all frames
(relocalizations included) over their total CPU time. "cold reloc": 40 random frames, each given to a fresh
localizer with no pose (``--cold N --cold-seed S``); counted when RELOCALIZED within 5 cm / 1 degree of the ground
truth, and "k off" when RELOCALIZED further from it (a wrong pose reported). ``--map DIR``:
measure a map already built (``cristal prebuild``) instead of building the variants.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_v] = "1"
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)


def build(site: Path, stage: str, fraction: float, spacing: float, rebuild: bool) -> tuple[Path, dict]:
    out = site / "pnl-maps" / f"{stage}-{int(round(fraction * 100))}pct-{spacing:g}m"
    meta = out / "build.json"
    if meta.exists() and not rebuild:
        return out, json.loads(meta.read_text())
    cmd = [sys.executable, "-m", "services.cli", "-q", "-j", "1", "prebuild", str(site / "scan.ply"), "--camera",
           str(site / "seq_00" / "camera.json"), "--out", str(out), "--stage", stage, "--spacing", str(spacing)]
    if fraction < 1:
        cmd += ["--decimate", str(fraction)]
    r = subprocess.run(cmd, capture_output=True, text=True, check=True)
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    meta.write_text(json.dumps(summary, indent=2) + "\n")
    return out, summary


MODES = {  # tracking modes (see services/localize/pnl.py): the default, then the paths it falls back to
    "direct": {},
    "keypoints+align": {"direct_landmarks": 0},
    "keypoints": {"align": False},
}


def localize(map_dir: Path, seq_dir: Path, mode: str = "direct", cold: int = 40, cold_seed: int = 0) -> dict:
    from services.eval.ape import compute_ape
    from services.io.sequence import open_sequence
    from services.io.trajectory import Trajectory
    from services.localize.pnl import PnlConfig, PnlLocalizer
    from services.localize.status import Status

    seq = open_sequence(seq_dir)
    t0 = time.perf_counter()
    loc = PnlLocalizer.load(map_dir, PnlConfig(**MODES[mode]))
    load_s = time.perf_counter() - t0
    traj = Trajectory()
    track_ms, all_ms, counts = [], [], {s: 0 for s in Status}
    first = None
    t0 = time.perf_counter()
    for i, f in enumerate(seq):
        r = loc.process(f.image, seq.camera)
        counts[r.status] += 1
        if i == 0:
            first = r.status.value
        all_ms.append(r.timings["cpu_ms"])
        if r.status == Status.TRACKING:
            track_ms.append(r.timings["cpu_ms"])
        if r.T_wc is not None:
            traj.append(f.stamp, r.T_wc)
    wall = time.perf_counter() - t0
    # cold relocalization: random frames, each with a fresh localizer (no pose), RELOCALIZED within 5 cm / 1 deg
    import copy

    rng = np.random.default_rng(cold_seed)
    cold_ok, cold_n, cold_off = 0, 0, 0
    for i in rng.choice(len(seq), min(cold, len(seq)), replace=False):
        fresh = copy.copy(loc)
        f = seq.read(int(i))
        r = fresh.process(f.image, seq.camera)
        cold_n += 1
        if r.status == Status.RELOCALIZED:
            dt, dr = seq.groundtruth_pose(f.stamp).distance_to(r.T_wc)
            hit = dt < 0.05 and dr < 1.0
            cold_ok, cold_off = cold_ok + hit, cold_off + (not hit)
    a = compute_ape(seq.groundtruth, traj, "none") if len(traj) else None
    return {"frames": len(seq), "localized": len(traj), "first": first, "relocalizations": counts[Status.RELOCALIZED],
            "ape_cm": 100 * a.trans_rmse if a else float("nan"), "ape_deg": a.rot_rmse_deg if a else float("nan"),
            "ape_median_cm": 100 * a.trans_median if a else float("nan"),
            "ape_median_deg": a.rot_median_deg if a else float("nan"),
            "track_fps": 1000 / np.mean(track_ms) if track_ms else 0.0,
            "track_ms_median": float(np.median(track_ms)) if track_ms else float("nan"),
            "fps": 1000 * len(all_ms) / sum(all_ms), "wall_fps": len(seq) / wall, "load_s": load_s,
            "cold": f"{cold_ok}/{cold_n}" + (f", {cold_off} off" if cold_off else "")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/office")
    ap.add_argument("--variants", nargs="+", default=["full:1.0", "full:0.1", "splat:1.0"])
    ap.add_argument("--spacing", type=float, default=1.0)
    ap.add_argument("--rebuild", action="store_true")
    ap.add_argument("--map", type=Path, help="an existing map folder to measure (the variants are not built)")
    ap.add_argument("--cold", type=int, default=40, help="random frames tried cold (each with a fresh localizer)")
    ap.add_argument("--cold-seed", type=int, default=0, help="which random frames")
    args = ap.parse_args()
    site = Path(args.site)
    if not (site / "site.json").exists():
        sys.exit(f"{site}: no simulated site (cristal sim --preset office --seed 1 --out {site})")
    from services.prebuild.patches import alignment_backend

    print(f"P&L kernels: {alignment_backend()} (set CRISTAL_KERNELS=numpy for a light client's path without numba)\n")
    print("| site | map from | points | keyframes | landmarks | map MB (+ patches) | build s | tracking | localized | 1st frame "
          "| APE RMSE cm / deg (none) | APE median cm / deg | track CPU ms (median) | track FPS | FPS all | cold reloc |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for v in ([None] if args.map else args.variants):
        if v is None:  # a given map: its own counts, no build
            from services.prebuild.stella_map import MAP_FILE, read_map

            out, m = args.map, read_map(args.map)
            stage, where, built = args.map.name, "given", "-"
            b = {"keyframes": m.n_keyframes, "landmarks": m.n_landmarks, "bytes": (out / MAP_FILE).stat().st_size}
        else:
            stage, frac = v.split(":")
            out, b = build(site, stage, float(frac), args.spacing, args.rebuild)
            where, built = f"{b['points'] / 1e6:.2f} M ({float(frac):.0%})", f"{b['total_s']:.0f}"
        patches = out / "patches.npz"
        extra = f" (+ {patches.stat().st_size / 1e6:.1f})" if patches.exists() else ""
        for mode in (list(MODES) if patches.exists() else ["keypoints"]):
            r = localize(out, site / "seq_00", mode, args.cold, args.cold_seed)
            print(f"| {site.name} | {stage} | {where} | {b['keyframes']} | {b['landmarks']:,} "
                  f"| {b['bytes'] / 1e6:.1f}{extra} | {built} | {mode} "
                  f"| {r['localized']}/{r['frames']} = {r['localized'] / r['frames']:.1%} | {r['first']} "
                  f"| {r['ape_cm']:.2f} / {r['ape_deg']:.3f} | {r['ape_median_cm']:.2f} / {r['ape_median_deg']:.3f} "
                  f"| {r['track_ms_median']:.1f} | {r['track_fps']:.0f} | {r['fps']:.0f} | {r['cold']} |", flush=True)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    main()
