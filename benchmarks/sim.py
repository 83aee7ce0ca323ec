"""How long each simulator preset takes to generate (scan + sequences), and what it produces.

    python benchmarks/sim.py [--presets office warehouse] [--out runs/bench-sim]

Prints one row per preset: points, stations, frames, seconds for the scene, the scan and each sequence.
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

from services.sim.site import config_for, generate_site


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["office", "warehouse"])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default="runs/bench-sim")
    args = ap.parse_args()
    print(f"{os.cpu_count()} CPUs\n")
    print("| preset | points | stations | frames | scene s | scan s | sequence s | total s |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for preset in args.presets:
        out = Path(args.out) / preset
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        s = generate_site(config_for(preset, seed=args.seed), out)
        total = time.perf_counter() - t0
        tm = s["timings"]
        seq_s = sum(v for k, v in tm.items() if k.startswith("seq_"))
        print(f"| {preset} | {s['points']:,} | {len(s['stations'])} | {sum(q['frames'] for q in s['sequences'])} | "
              f"{tm['scene_s']:.1f} | {tm['scan_s']:.1f} | {seq_s:.1f} | {total:.1f} |", flush=True)


if __name__ == "__main__":
    main()
