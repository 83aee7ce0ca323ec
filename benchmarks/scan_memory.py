"""Peak memory and time of ``load_scan`` on a large binary PLY: parse, cold cache write, warm cache reload.

    python benchmarks/scan_memory.py --points 50000000

Writes a binary little-endian PLY (float32 xyz, uchar rgb: 15 bytes a point) of random points
in chunks, then loads it in a fresh subprocess per case, each reporting its own peak RSS
(``VmHWM``; ``ru_maxrss`` is also recorded but Linux carries the parent's peak over fork+exec) and its current RSS after loading and after one pass over every point (a
memory-mapped cache is only resident once read). The loader's output is 15 bytes a point
(float32 xyz + uint8 rgb): the floor for the parse cases.
Files are deleted afterwards unless ``--keep``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHILD = r"""
import json, resource, sys, time
import numpy as np
from services.io.scans import load_scan

def rss_kb(field="VmRSS"):  # current (VmRSS) or peak (VmHWM) resident set, file-backed mapped pages included
    return int(next(l for l in open("/proc/self/status") if l.startswith(field)).split()[1])

base = rss_kb()
t0 = time.perf_counter()
scan = load_scan(sys.argv[1], cache=sys.argv[2] == "1")
dt = time.perf_counter() - t0
after = rss_kb()
t1 = time.perf_counter()
total = float(scan.xyz.sum(dtype=np.float64)) + float(scan.rgb.sum(dtype=np.uint64))  # touch every point
touch = time.perf_counter() - t1
print(json.dumps({"points": len(scan), "seconds": dt, "from_cache": scan.meta["from_cache"], "base_kb": base,
                  "after_load_kb": after, "touch_seconds": touch, "after_touch_kb": rss_kb(),
                  "peak_kb": rss_kb("VmHWM"), "ru_maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))
"""


def write_ply(path: Path, n: int, chunk: int = 5_000_000, seed: int = 0) -> None:
    """A binary PLY of ``n`` random points (a 100 m cube, random colours), written chunk by chunk."""
    rng = np.random.default_rng(seed)
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {n}\n" + "".join(f"property float {a}\n" for a in "xyz")
              + "".join(f"property uchar {c}\n" for c in ("red", "green", "blue")) + "end_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        for i in range(0, n, chunk):
            m = min(chunk, n - i)
            rec = np.empty(m, dtype)
            for a in "xyz":
                rec[a] = rng.uniform(0, 100, m).astype(np.float32)
            for c in ("red", "green", "blue"):
                rec[c] = rng.integers(0, 256, m, dtype=np.uint8)
            f.write(rec.data)


def run_child(path: Path, cache: bool) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, str(path), "1" if cache else "0"], check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--points", type=int, default=50_000_000, help="points in the test PLY (default 50 M)")
    p.add_argument("--dir", help="folder for the PLY and its cache (default: a new folder in the temp dir)")
    p.add_argument("--keep", action="store_true", help="keep the files")
    args = p.parse_args(argv)

    folder = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="cristal-scanbench-"))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "bench.ply"
    try:
        t0 = time.perf_counter()
        write_ply(path, args.points)
        size_gb = path.stat().st_size / 1e9
        print(f"wrote {path}: {args.points:,} points, {size_gb:.2f} GB in {time.perf_counter() - t0:.1f} s", flush=True)
        rows = []
        for name, cache in (("parse (cache=False)", False), ("parse + write cache (cold)", True),
                            ("reload from cache (warm)", True)):
            r = run_child(path, cache)
            rows.append((name, r))
            print(f"  {name}: {r['seconds']:.1f} s", flush=True)
        floor_mb = args.points * 15 / 1e6
        print(f"\n{'case':<28} {'load s':>7} {'peak RSS MB':>12} {'RSS after load MB':>18} {'full pass s':>12} "
              f"{'RSS after pass MB':>18}")
        for name, r in rows:
            print(f"{name:<28} {r['seconds']:>7.2f} {r['peak_kb'] / 1e3:>12.0f} {r['after_load_kb'] / 1e3:>18.0f} "
                  f"{r['touch_seconds']:>12.2f} {r['after_touch_kb'] / 1e3:>18.0f}")
        print(f"(RSS before loading, interpreter + numpy + cristal: {rows[0][1]['base_kb'] / 1e3:.0f} MB; "
              f"the loaded arrays alone are {floor_mb:.0f} MB; 'full pass' sums every point once)")
        print(json.dumps({"points": args.points, "file_gb": round(size_gb, 3),
                          **{name: {k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()} for name, r in rows}}))
    finally:
        if not args.keep:
            path.unlink(missing_ok=True)
            shutil.rmtree(folder / "bench.ply.cristal-cache", ignore_errors=True)
            if not args.dir:
                shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
