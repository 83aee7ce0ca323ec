"""The simulated sites the benchmarks walk, as recipes: build the missing ones, and fingerprint what is there.

    python benchmarks/sites.py [--root runs/bench-sim] [--sites office office-s13] [--maps] [--list]

Each site is `cristal sim` with fixed arguments, its relocalization database (`cristal build-db`) and, with --maps,
its Prebuild & Localize map (`cristal prebuild` for the walk's own camera). A site folder that already has a file is
kept as it is; delete the folder to build it again. --list prints each recipe and the fingerprint of what ROOT holds.

Why fingerprints: stop 48 found the committed baseline's office walk (280/300) measured with a database built by
other code; the same recipe built afresh gives 271/300 with the same tracker (after the whip pan the look-around's
best view gets 24-29 inliers where a pose needs 30). `benchmarks/walks.py` stores each walk's fingerprint with its
numbers and does not judge a walk on a site that differs from the baseline's: rebuild the baseline on that site.
Another machine builds another database from the same recipe (stop 56: scan, sequence and P&L map the same to the
byte, the database not: XFeat's convolutions round differently on another CPU), so there compare two commits on the
same sites instead, the old one checked out with `git worktree add /tmp/old REV` and run as
`cd /tmp/old && python benchmarks/walks.py --root /path/to/runs/bench-sim ...` (it imports its own code; its first
walk compiles its numba kernels, ~20 s, so time the walks after one).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

log = logging.getLogger("sites")

# name -> (cristal sim arguments, cristal build-db arguments, cristal prebuild arguments)
SITES: dict[str, tuple[list[str], list[str], list[str]]] = {
    "office": (["--preset", "office", "--seed", "1"], [], []),
    "office-s2": (["--preset", "office", "--seed", "2"], [], []),
    "office-s8": (["--preset", "office", "--seed", "8"], [], []),
    "office-s13": (["--preset", "office", "--seed", "13"], [], []),
    "office-hd": (["--preset", "office", "--seed", "4", "--frames", "150", "--width", "960", "--height", "540",
                   "--hfov", "75", "--distortion", "-0.12", "0.03", "0", "0", "0"], [], []),
    "office-s6-wide": (["--preset", "office", "--seed", "6", "--hfov", "90", "--distortion", "-0.25", "0.06", "0",
                        "0", "0", "--fps", "24"], [], []),
    "office-rs20": (["--preset", "office", "--rolling-shutter", "20"], [], []),
    # a narrow 52-degree lens (stop 50): through a doorway at a wall 7.4 m off, a sideways step looks like a turn
    "office-s21-narrow": (["--preset", "office", "--seed", "21", "--hfov", "52"], [], []),
    # other cameras on the office path (stops 26-27 probed them by hand; recipes since stop 55): a phone held upright, a
    # robot's QVGA camera
    "office-portrait": (["--preset", "office", "--seed", "1", "--frames", "150", "--width", "480", "--height", "640",
                         "--hfov", "50"], [], []),
    "office-qvga": (["--preset", "office", "--seed", "1", "--frames", "150", "--width", "320", "--height", "240"], [], []),
    # sites no stop had seen before stop 55: a 60-degree lens with mild barrel distortion; the default camera
    "office-s37-60": (["--preset", "office", "--seed", "37", "--hfov", "60", "--distortion", "-0.08", "0.02", "0", "0",
                       "0"], [], []),
    "office-s44": (["--preset", "office", "--seed", "44"], [], []),
    # a site no stop had seen before stop 57: a sparser scan (0.3-degree step, ~45 % of the points) through a 75-degree
    # lens with barrel distortion
    "office-s61-sparse": (["--preset", "office", "--seed", "61", "--lidar-step", "0.3", "--hfov", "75", "--distortion",
                           "-0.1", "0.02", "0", "0", "0"], [], []),
    # a site no stop had seen before stop 61: the default camera on another layout
    "office-s90": (["--preset", "office", "--seed", "90"], [], []),
    # the default office walk through a scan with a real registration's flaws (stop 61): stations a few mm and
    # hundredths of a degree off, panoramas exposed apart, mixed pixels along silhouettes (services/sim/lidar.py)
    "office-survey": (["--preset", "office", "--seed", "1", "--scan-flaws", "survey"], [], []),
    "office-poor": (["--preset", "office", "--seed", "1", "--scan-flaws", "poor"], [], []),
    # the survey's registration alone (stop 62): what the scan's own error does to the reported 1-sigma
    # (benchmarks/scan_error.py), on the default walk and on another layout
    "office-reg": (["--preset", "office", "--seed", "1", "--scan-flaws", "registration"], [], []),
    "office-s8-reg": (["--preset", "office", "--seed", "8", "--scan-flaws", "registration"], [], []),
    # a millimetre registration but for one loose station, 1 cm off (stop 63): where on the site the error lies
    "office-loose": (["--preset", "office", "--seed", "1", "--scan-flaws", "loose"], [], []),
    # a scanner that took no pictures (stop 65): every point has the laser's intensity, no colour, on the default walk
    "office-nir": (["--preset", "office", "--seed", "1", "--scan-colour", "intensity"], [], []),
    "office-s8-nir": (["--preset", "office", "--seed", "8", "--scan-colour", "intensity"], [], []),
    "warehouse-s3-nir": (["--preset", "warehouse", "--seed", "3", "--scan-colour", "intensity"], ["--spacing", "2"],
                         ["--spacing", "2"]),
    # the default walk filmed after the site changed (stop 67, services/sim/changes.py): 30 % / 60 % of the movable
    # objects (desks, chairs, shelf boxes) moved or taken away, new boxes on the floor; the scan is the office's
    "office-chg30": (["--preset", "office", "--seed", "1", "--changes", "0.3"], [], []),
    "office-chg60": (["--preset", "office", "--seed", "1", "--changes", "0.6"], [], []),
    "office-s8-chg30": (["--preset", "office", "--seed", "8", "--changes", "0.3"], [], []),
    "office-s2-chg30": (["--preset", "office", "--seed", "2", "--changes", "0.3"], [], []),
    "office-s13-chg30": (["--preset", "office", "--seed", "13", "--changes", "0.3"], [], []),
    "office-s44-chg30": (["--preset", "office", "--seed", "44", "--changes", "0.3"], [], []),
    # the warehouse after 30 % of its pallets moved or were picked (stop 67; no P&L map: ~45 min)
    "warehouse-s3-chg30": (["--preset", "warehouse", "--seed", "3", "--changes", "0.3"], ["--spacing", "2"],
                           ["--spacing", "2"]),
    # its map takes ~45 min on 2 cores (RESULTS stop 33): --maps builds it only when --sites names it
    "warehouse-s3": (["--preset", "warehouse", "--seed", "3"], ["--spacing", "2"], ["--spacing", "2"]),
}
DEFAULT = ["office", "office-s2", "office-s8", "office-s13", "office-hd", "warehouse-s3"]  # the regression sweep's six
SLOW_MAPS = {"warehouse-s3", "warehouse-s3-nir"}


def cristal(*args: str) -> subprocess.CompletedProcess:
    """Run `cristal ARGS` with this interpreter from the repository root (walks.py's localizations too); its output
    captured, RuntimeError with the tail of stderr when it fails."""
    cmd = [sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main(sys.argv[1:]))", *args]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
    if res.returncode != 0:
        raise RuntimeError(f"cristal {' '.join(args)} failed:\n{res.stderr[-2000:]}")
    return res


def build(root: Path, name: str, maps: bool) -> None:
    """Build what ``root/name`` lacks of its recipe: the site, its database, and with ``maps`` its map."""
    sim, db, pre = SITES[name]
    site = root / name
    steps = []
    if not (site / "site.json").is_file():
        steps.append(("sim", ["sim", *sim, "--out", str(site)]))
    if not (site / "reloc.npz").is_file():
        steps.append(("build-db", ["build-db", str(site / "scan.ply"), "--out", str(site / "reloc.npz"), *db]))
    if maps and not (site / "map" / "map.msg").is_file():
        steps.append(("prebuild", ["prebuild", str(site / "scan.ply"), "--camera", str(site / "seq_00" / "camera.json"),
                                   "--out", str(site / "map"), *pre]))
    for what, args in steps:
        t0 = time.perf_counter()
        cristal(*args)
        log.info("%s: %s in %.0f s", name, what, time.perf_counter() - t0)


def _hash_file(h, path: Path, skip_header: bytes | None = None) -> None:
    """The file's bytes; with ``skip_header``, a PLY header's lines that start with it left out."""
    with open(path, "rb") as f:
        if skip_header is not None:
            while (line := f.readline()) and line.strip() != b"end_header":
                if not line.startswith(skip_header):
                    h.update(line)
            h.update(line)
        while chunk := f.read(1 << 22):
            h.update(chunk)


def fingerprint(site: Path, method: str) -> str | None:
    """12 hex digits of what a walk of ``method`` on ``site`` reads: the scan, the sequence (its stamps, truth, camera
    and first and last images) and the database's arrays (rm) or the map file (pnl); None when something is missing."""
    import numpy as np

    seq = site / "seq_00"
    h = hashlib.sha1()
    try:
        # (less the station point counts written since stop 62: the same points, the same walks, the same fingerprint)
        _hash_file(h, site / "scan.ply", skip_header=b"comment cristal_station_points")
        for f in ("rgb.txt", "groundtruth.txt", "camera.json"):
            _hash_file(h, seq / f)
        images = sorted((seq / "rgb").iterdir())
        for f in (images[0], images[-1]):
            _hash_file(h, f)
        if method == "rm":
            with np.load(site / "reloc.npz") as z:  # (its meta holds the build time: not hashed)
                for k in sorted(z.files):
                    if k != "meta":
                        h.update(np.ascontiguousarray(z[k]).tobytes())
        else:
            _hash_file(h, site / "map" / "map.msg")
    except (OSError, IndexError, ValueError):
        return None
    return h.hexdigest()[:12]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=Path("runs/bench-sim"), help="folder of simulated sites")
    ap.add_argument("--sites", nargs="+", choices=sorted(SITES),
                    help=f"sites to build (default: {' '.join(DEFAULT)})")
    ap.add_argument("--maps", action="store_true",
                    help=f"also each site's P&L map (~1.5 min each; {', '.join(sorted(SLOW_MAPS))}: ~45 min, only when "
                         "--sites names it)")
    ap.add_argument("--list", action="store_true", help="print the recipes and fingerprints; build nothing")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    for name in args.sites or DEFAULT:
        if not args.list:
            build(args.root, name, args.maps and (name not in SLOW_MAPS or args.sites is not None))
        site = args.root / name
        sim, db, pre = SITES[name]
        print(json.dumps({"site": name, "sim": " ".join(sim), "build_db": " ".join(db),
                          "prebuild": " ".join(pre),
                          "rm": fingerprint(site, "rm"), "pnl": fingerprint(site, "pnl")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
