"""The scan's own error in the reported 1-sigma: is a pose beyond 3 sigma rare on a scan registered a few mm off?

    python benchmarks/sites.py --sites office-reg office-s8-reg office-loose [--maps]     # the sites (3-5 min each)
    python benchmarks/scan_error.py [--sites runs/bench-sim/office-reg runs/bench-sim/office-s8-reg ...]

For each site: `cristal scan check` (how far its stations disagree), then `cristal localize` with
`--scan-sigma-mm 0` (each 1-sigma the frame's own), with the check's pooled number (that error everywhere on the
site) and `auto` (the default: what build-db / prebuild recorded, where on the site it lies),
Render & Match always, Prebuild & Localize where SITE/map exists. The same frames get the same poses each way (the
gates do not look at the scan's error); what changes is how many poses err beyond 3 x their reported 1-sigma, the
median error / 1-sigma at the centre and in orientation (about 1 is honest; far above: the 1-sigma lies), and how
many poses are 10 x better at the centre than their 1-sigma says (a 1-sigma that cries wolf: a loose station's error
told where the camera sees none of its points).
A table prints; --json writes the rows.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from services.eval.ape import compute_ape, uncertainty_check  # noqa: E402
from services.io.frame_log import frame_log_path, read_frame_log  # noqa: E402
from services.io.trajectory import read_tum  # noqa: E402

CRISTAL = [sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main(sys.argv[1:]))"]


def _run(*args) -> dict:
    r = subprocess.run([*CRISTAL, *map(str, args)], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[1])
    if r.returncode != 0:
        raise SystemExit(f"cristal {' '.join(map(str, args))} failed:\n{r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def honesty(gt_path: Path, est_path: Path) -> dict:
    """Frames, APE RMSE and how the errors compare with each pose's reported 1-sigma (TRAJ.frames.csv), as
    ``cristal eval`` compares them (services.eval.ape.uncertainty_check)."""
    a = compute_ape(read_tum(gt_path), read_tum(est_path), "none")
    u = uncertainty_check(a, read_frame_log(frame_log_path(est_path)))
    return {"frames": len(a.stamps), "rmse_cm": round(100 * a.trans_rmse, 2), "rmse_deg": round(a.rot_rmse_deg, 3),
            "sigma_cm": round(100 * float(np.median(u["sigma_m"])), 2),
            "sigma_deg": round(float(np.median(u["sigma_deg"])), 3), "beyond_3sigma": u["beyond_3sigma"],
            "tenfold": int((u["sigma_m"] > 10 * u["t_err_m"]).sum()),
            "ratio_centre": round(u["t_ratio_median"], 2), "ratio_deg": round(u["r_ratio_median"], 2)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sites", nargs="+", type=Path,
                    default=[Path("runs/bench-sim/office-reg"), Path("runs/bench-sim/office-s8-reg"),
                             Path("runs/bench-sim/office-loose")])
    ap.add_argument("--out", type=Path, default=Path("runs/scan_error"))
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args()
    rows = []
    for site in args.sites:
        check = _run("scan", "check", site / "scan.ply")
        out = args.out / site.name
        out.mkdir(parents=True, exist_ok=True)
        runs = [("rm", [site / "scan.ply", site / "seq_00", "--method", "rm", "--db", site / "reloc.npz",
                        "--no-camera-check"])]
        if (site / "map" / "map.msg").exists():
            runs.append(("pnl", [site / "map", site / "seq_00", "--method", "pnl", "--map", site / "map"]))
        for method, base in runs:
            for sigma in ("0", str(check["registration_mm"] or 0), "auto"):
                est = out / f"{method}-{sigma}.txt"
                _run("localize", *base, "--out", est, "--scan-sigma-mm", sigma)
                row = {"site": site.name, "check_mm": check["registration_mm"], "method": method,
                       "scan_sigma_mm": sigma, **honesty(site / "seq_00" / "groundtruth.txt", est)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    print()
    print("| site | scan check | method | --scan-sigma-mm | frames | APE cm / deg | median 1σ cm / deg "
          "| beyond 3σ | error/1σ centre, orientation (median) | 1σ > 10× error |")
    print("|---|---:|---|---|---:|---|---|---:|---|---:|")
    for r in rows:
        print(f"| {r['site']} | {r['check_mm']} mm | {r['method']} | {r['scan_sigma_mm']} | {r['frames']} | "
              f"{r['rmse_cm']} / {r['rmse_deg']} | {r['sigma_cm']} / {r['sigma_deg']} | {r['beyond_3sigma']} | "
              f"{r['ratio_centre']}, {r['ratio_deg']} | {r['tenfold']} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
