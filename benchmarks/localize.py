"""Render & Match on a simulated site: the cold relocalization rate.

    python benchmarks/localize.py [--site runs/bench-sim/office] [--cold 40] [--seed 0] [--set reloc_px_ratio=1.8]

Builds the relocalization database if missing (site/reloc.npz), then tries --cold randomly chosen frames,
each with a fresh tracker and no prior (--seed picks which); success = RELOCALIZED within 5 cm and 1 degree of
ground truth, and a RELOCALIZED frame further off is counted as reported off (a wrong pose).
Tracking accuracy and speed over the whole sequence: `cristal localize` (it prints APE when ground truth exists).
"""

from __future__ import annotations

import argparse
import ast
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _site import ensure_site  # noqa: E402

from services.features.xfeat import XFeatExtractor  # noqa: E402
from services.io.scans import load_scan  # noqa: E402
from services.io.sequence import open_sequence  # noqa: E402
from services.localize.render_match import RenderMatchTracker, RMConfig, Status  # noqa: E402
from services.relocalize.database import RelocDB, build_database  # noqa: E402
from services.relocalize.roi import sample_positions  # noqa: E402
from services.render.renderer import Renderer  # noqa: E402


def _setting(kv: str) -> tuple[str, object]:
    """``NAME=VALUE`` as an RMConfig field and a Python literal (2.5, True, (12, 3)); a clear error otherwise."""
    name, _, value = kv.partition("=")
    if not hasattr(RMConfig(), name):
        raise SystemExit(f"--set {kv}: RMConfig has no field {name!r}")
    try:
        return name, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        raise SystemExit(f"--set {kv}: {value!r} is not a Python literal") from None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/office")
    ap.add_argument("--cold", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0, help="which random frames")
    ap.add_argument("--max-side", type=int, default=480)
    ap.add_argument("--db", help="relocalization database (default: SITE/reloc.npz, built if missing)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="an RMConfig field for this run (repeatable): a variant measured against the default")
    args = ap.parse_args()
    cfg = RMConfig(**dict(_setting(kv) for kv in args.set))
    torch.set_num_threads(1)
    site = ensure_site(args.site)
    scan = load_scan(site / "scan.ply")
    renderer = Renderer(scan)
    ext = XFeatExtractor(device="cpu", top_k=1024, max_side=args.max_side)
    db_path = Path(args.db) if args.db else site / "reloc.npz"
    if not db_path.exists():
        build_database(renderer, sample_positions(scan), ext).save(db_path)
    db = RelocDB.load(db_path)
    seq = open_sequence(site / "seq_00")
    rng = np.random.default_rng(args.seed)
    idx = rng.choice(len(seq), min(args.cold, len(seq)), replace=False)
    ok, wrong, times, missed = 0, 0, [], []
    for i in idx:
        tr = RenderMatchTracker(renderer, ext, db, cfg)
        t0 = time.perf_counter()
        r = tr.process(seq.read(int(i)).image, seq.camera)
        times.append(time.perf_counter() - t0)
        if r.status == Status.RELOCALIZED:
            dt, dr = seq.groundtruth.poses[int(i)].distance_to(r.T_wc)
            ok += dt < 0.05 and dr < 1.0
            if not (dt < 0.05 and dr < 1.0):
                wrong += 1
                missed.append(f"{i} ({100 * dt:.0f} cm / {dr:.1f} deg off)")
        else:
            missed.append(f"{i} ({r.reason})")
    print(f"| cold relocalization | {ok}/{len(idx)} = {ok / len(idx):.0%} of random frames within 5 cm / 1 deg; "
          f"{wrong} reported further off; median {1e3 * np.median(times):.0f} ms each |")
    print("not relocalized:\n  " + "\n  ".join(missed[i] for i in np.argsort([int(m.split()[0]) for m in missed])))


if __name__ == "__main__":
    main()
