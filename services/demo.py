"""``cristal demo``: the main job on the embedded simulated site, end to end.

Today: simulate the default office site, produce a trajectory for its sequence and score
it against ground truth with plots. The trajectory comes from a drifting visual-odometry
stand-in (ground-truth relative motion with noise, integrated), which shows exactly the
drift that localizing in the scan removes; Render & Match replaces it as it lands.
"""

from __future__ import annotations

import argparse

EPILOG = """\
example:
  cristal demo --out runs/demo           simulate the office site, write a trajectory, score it, draw plots
  cristal demo --out runs/demo --frames 60 --lidar-step 0.4     a faster, smaller run

writes runs/demo/site/ (the simulated site), runs/demo/estimate.txt (TUM), runs/demo/plots/*.png,
and ends with a one-line JSON summary.
"""


def register(sub) -> None:
    p = sub.add_parser("demo", help="the main job on the embedded simulated site (no download)",
                       description=__doc__, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    p.add_argument("--preset", default="office", choices=["office", "warehouse"])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--frames", type=int, help="frames in the sequence (preset default)")
    p.add_argument("--lidar-step", type=float, dest="lidar_step_deg", help="scanner angular step in degrees")
    p.add_argument("--regenerate", action="store_true", help="simulate again even if the site folder matches")
    p.set_defaults(func=run)


def drifting_odometry(gt, seed: int = 0, trans_noise: float = 0.004, rot_noise_deg: float = 0.15):
    """Integrate noisy ground-truth frame-to-frame motion from the first ground-truth pose: a drift baseline."""
    import numpy as np

    from services.geometry.se3 import Pose
    from services.io.trajectory import Trajectory

    rng = np.random.default_rng(seed)
    out = Trajectory()
    T = gt.poses[0]
    out.append(gt.stamps[0], T)
    for s, a, b in zip(gt.stamps[1:], gt.poses[:-1], gt.poses[1:]):
        d = a.inverse() @ b
        noise = Pose.from_rotvec_t(np.deg2rad(rng.normal(0, rot_noise_deg, 3)), rng.normal(0, trans_noise, 3))
        T = T @ d @ noise
        out.append(s, T)
    return out


def run(args) -> int:
    import json
    import time
    from pathlib import Path

    from services.cli import emit_summary
    from services.eval.ape import evaluate
    from services.eval.plots import plot_errors, plot_trajectory_topdown
    from services.io.scans import load_scan
    from services.io.trajectory import read_tum, write_tum
    from services.sim.site import _jsonable, config_for, generate_site
    from dataclasses import asdict

    out = Path(args.out)
    site = out / "site"
    cfg = config_for(args.preset, seed=args.seed, frames=args.frames, lidar_step_deg=args.lidar_step_deg)
    t0 = time.perf_counter()
    meta = site / "site.json"
    if not args.regenerate and meta.exists() and json.loads(meta.read_text()).get("config") == _jsonable(asdict(cfg)):
        print(f"[1/3] simulated site {site} is up to date (use --regenerate to rebuild)")
    else:
        print(f"[1/3] simulating the {args.preset} site (seed {args.seed}) into {site} ...", flush=True)
        generate_site(cfg, site)
    t_sim = time.perf_counter() - t0

    seq = site / "seq_00"
    gt = read_tum(seq / "groundtruth.txt")
    print("[2/3] trajectory: drifting-odometry stand-in (Render & Match will replace it)", flush=True)
    est = drifting_odometry(gt, seed=args.seed)
    write_tum(out / "estimate.txt", est, header="drifting visual-odometry stand-in, camera-to-world")

    print("[3/3] scoring against ground truth", flush=True)
    results = evaluate(gt, est)
    scan = load_scan(site / "scan.ply")
    plots = out / "plots"
    plot_trajectory_topdown(gt, est, plots / "trajectory.png", scan=scan, title=f"{args.preset} seq_00: ground truth vs estimate")
    plot_errors(results["se3"] if "se3" in results else results["none"], plots / "errors.png")
    for name, r in results.items():
        print(f"  APE ({name:>4}): {r.n_matched}/{r.n_gt} frames, translation RMSE {100 * r.trans_rmse:.2f} cm, "
              f"rotation RMSE {r.rot_rmse_deg:.3f} deg")
    print(f"  plots: {plots / 'trajectory.png'}, {plots / 'errors.png'}")
    summary = {"site": str(site), "points": len(scan), "frames": len(gt), "sim_seconds": round(t_sim, 1),
               "estimate": str(out / "estimate.txt"), "method": "odometry-stand-in"}
    for name, r in results.items():
        summary[f"ape_{name}_trans_rmse_m"] = r.trans_rmse
        summary[f"ape_{name}_rot_rmse_deg"] = r.rot_rmse_deg
    summary["fraction"] = results["none"].fraction
    emit_summary(summary)
    return 0
