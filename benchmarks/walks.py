"""Every benchmark walk, both methods, against the numbers recorded for them: a regression sweep.

    python benchmarks/walks.py [--root runs/bench-sim] [--sites office warehouse-dense] [--methods rm pnl]
                               [--baseline benchmarks/walks_baseline.json] [--update]

A change that helps one walk can break another that nobody reran (stop 24's crowded P&L retry gained 21 frames on
the occluded office and sent the survey-density warehouse 28.6 m into a look-alike bay). This runs `cristal
localize` over each site of ROOT that has a walk (SITE/seq_00) and the method's input: Render & Match with
SITE/reloc.npz (`--no-camera-check`), Prebuild & Localize with SITE/map. Images only, first frame cold. For each
it prints frames localized, APE with no alignment, the worst reported frame's translation and rotation errors
(not judged: a frame far beyond the 1 cm / 0.1 degree promise shows there before it counts as off), the frames
reported beyond 5 cm or 1 degree of the truth ("off", which must stay 0), the poses whose error exceeds 3 times
the 1-sigma they were reported with ("> 3σ", from the localizer's TRAJ.frames.csv: how honest its uncertainty is;
not judged), the rotation RMSE of the poses by what solved them ("by source": direct, features, fused, from the
same log: where the walk's error sits), and the change against the baseline file. A row is a regression when it
loses more than --tolerance frames, reports a frame off that the baseline did not, or its translation APE grows by
more than 15 % + 0.05 cm; the exit status is then 1. --update writes this run's numbers as the new baseline (commit it with
the change that moved them).

Sites come from `python benchmarks/sites.py` (their recipes: `cristal sim`, `cristal build-db`, `cristal prebuild`).
Each walk's numbers are stored with the fingerprint of the site it ran on (sites.py); a walk on a site that differs
from the baseline's is not judged (the same recipe built by older code can differ: rebuild the baseline on it).
A full sweep of the ten walks takes ~20 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from services.eval.ape import compute_ape, errors_by_source, uncertainty_check  # noqa: E402
from services.io.frame_log import frame_log_path, read_frame_log  # noqa: E402
from services.io.trajectory import read_tum  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sites import cristal, fingerprint  # noqa: E402

OFF_M, OFF_DEG = 0.05, 1.0


def inputs(site: Path, method: str) -> list[str] | None:
    """The `cristal localize` arguments for ``method`` on ``site``, or None when the site lacks its input. A camera
    simulated with a rolling shutter (site.json) is declared as such, as its owner would."""
    readout = 0.0
    if (site / "site.json").is_file():
        readout = json.loads((site / "site.json").read_text()).get("config", {}).get("sensor", {}).get("readout_s", 0.0)
    camera = ["--rolling-shutter", f"{1000 * readout:g}"] if readout else []
    if method == "rm" and (site / "reloc.npz").is_file():
        return [str(site / "scan.ply"), str(site / "seq_00"), "--method", "rm", "--db", str(site / "reloc.npz"),
                "--no-camera-check", *camera]
    if method == "pnl" and (site / "map" / "map.msg").is_file():
        return [str(site / "map"), str(site / "seq_00"), "--method", "pnl", "--map", str(site / "map"), *camera]
    return None


def run(site: Path, method: str, out: Path, extra: tuple[str, ...] = ()) -> dict:
    """One walk: the localizer's JSON summary plus the frames reported off (beyond OFF_M or OFF_DEG). ``extra``: more
    `cristal localize` arguments."""
    t0 = time.perf_counter()
    res = cristal("-q", "localize", *inputs(site, method), "--out", str(out), *extra)
    s = json.loads(res.stdout.strip().splitlines()[-1])
    a = compute_ape(read_tum(site / "seq_00" / "groundtruth.txt"), read_tum(out), "none", strict=False)
    log = read_frame_log(frame_log_path(out))
    check = uncertainty_check(a, log)  # each pose against its own predicted 1-sigma
    by = {src or "?": [g["n"], round(g["rot_rmse_deg"], 3)]  # where the walk's error sits
          for src, g in errors_by_source(a, log).items()} if len(a.stamps) else {}
    return {"frames": int(s["frames"]), "localized": int(s["localized"]),
            "ape_cm": round(100 * s["ape_none_trans_rmse_m"], 3), "ape_deg": round(s["ape_none_rot_rmse_deg"], 4),
            "off": int(((a.trans_err > OFF_M) | (a.rot_err_deg > OFF_DEG)).sum()),
            "max_cm": round(100 * float(a.trans_err.max(initial=0.0)), 2),
            "max_deg": round(float(a.rot_err_deg.max(initial=0.0)), 3),
            "beyond_3sigma": check["beyond_3sigma"], "by_source": by, "fps": round(s["fps"], 1), "wall_s": round(time.perf_counter() - t0, 1),
            "site": fingerprint(site, method)}


def verdict(now: dict, base: dict | None, tolerance: int) -> str:
    if base is None:
        return "new"
    if base.get("site") and now.get("site") != base["site"]:  # (sites.py: the same recipe built by other code)
        return "not judged: another site than the baseline's (sites.py fingerprint)"
    worse = []
    if now["localized"] < base["localized"] - tolerance:
        worse.append(f"{now['localized'] - base['localized']:+d} frames")
    if now["off"] > base["off"]:
        worse.append(f"{now['off'] - base['off']:+d} off")
    if now["ape_cm"] > 1.15 * base["ape_cm"] + 0.05:
        worse.append(f"APE {base['ape_cm']:.2f} -> {now['ape_cm']:.2f} cm")
    if worse:
        return "**REGRESSION**: " + ", ".join(worse)
    return "better" if now["localized"] > base["localized"] + tolerance else "same"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=Path("runs/bench-sim"), help="folder of simulated sites")
    ap.add_argument("--sites", nargs="+", help="site folder names under --root (default: every one with a walk)")
    ap.add_argument("--methods", nargs="+", default=["rm", "pnl"], choices=["rm", "pnl"])
    ap.add_argument("--baseline", type=Path, default=Path(__file__).with_name("walks_baseline.json"))
    ap.add_argument("--tolerance", type=int, default=2, help="frames a walk may lose before it counts as a regression")
    ap.add_argument("--update", action="store_true", help="write this run's numbers into --baseline")
    ap.add_argument("--localize-args", default="", metavar="ARGS",
                    help="more `cristal localize` arguments for every walk, one string (--localize-args='--max-side 360'); "
                         "compare against a baseline run with the same ones, not the committed one")
    ap.add_argument("--out", type=Path, default=Path("runs/walks"), help="trajectories are written here")
    args = ap.parse_args()
    extra = tuple(shlex.split(args.localize_args))  # the same for every walk
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    names = args.sites or sorted(p.name for p in args.root.iterdir() if (p / "seq_00" / "rgb.txt").is_file())
    base = json.loads(args.baseline.read_text()) if args.baseline.is_file() else {}
    args.out.mkdir(parents=True, exist_ok=True)
    now, bad = {}, 0
    print("| site | method | frames | APE cm / deg | worst cm / deg | off | > 3σ | by source: poses, deg | FPS | baseline | verdict |")
    print("|---|---|---:|---|---|---:|---:|---|---:|---|---|")
    for name in names:
        for method in args.methods:
            site = args.root / name
            if not (site / "seq_00").is_dir() or inputs(site, method) is None:
                continue
            key = f"{name}/{method}"
            r = now[key] = run(site, method, args.out / f"{name}-{method}.txt", extra)
            b = base.get(key)
            v = verdict(r, b, args.tolerance)
            bad += v.startswith("**REGRESSION")
            was = "-" if b is None else f"{b['localized']}, {b['ape_cm']:.2f} / {b['ape_deg']:.3f}, {b['off']} off"
            print(f"| {name} | {method} | {r['localized']}/{r['frames']} | {r['ape_cm']:.2f} / {r['ape_deg']:.3f} | "
                  f"{r['max_cm']:.2f} / {r['max_deg']:.3f} | {r['off']} | {r['beyond_3sigma']} | "
                  + ", ".join(f"{k} {n}, {d:.3f}" for k, (n, d) in r["by_source"].items())
                  + f" | {r['fps']:.1f} | {was} | {v} |", flush=True)
    if args.update:
        merged = {**base, **now}
        tmp = args.baseline.with_suffix(".tmp")
        tmp.write_text(json.dumps(dict(sorted(merged.items())), indent=1) + "\n")
        os.replace(tmp, args.baseline)
        print(f"baseline written: {args.baseline} ({len(now)} walks updated)")
    if bad:
        print(f"{bad} regression(s) against {args.baseline}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
