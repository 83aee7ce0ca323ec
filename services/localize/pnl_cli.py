"""``cristal localize --method pnl``: Prebuild & Localize over a sequence (no torch; the same output contract as rm)."""

from __future__ import annotations

import logging
from pathlib import Path


log = logging.getLogger(__name__)


def pnl_config(args):
    """The localizer's settings from ``cristal localize``'s arguments. The report gates are Render & Match's
    (--max-sigma-cm / --max-sigma-deg); a keypoint-only pose's looser gates (a map without patches) move by the same
    ratio."""
    from services.localize.cli import scan_grid, scan_sigma_m
    from services.localize.pnl import PnlConfig

    d = PnlConfig()
    gate_m = getattr(args, "max_sigma_cm", 100 * d.max_sigma_m) / 100
    gate_deg = getattr(args, "max_sigma_deg", d.max_sigma_deg)
    return PnlConfig(align=not getattr(args, "no_align", False),
                     direct_landmarks=0 if getattr(args, "no_direct", False) else d.direct_landmarks,
                     readout_s=getattr(args, "rolling_shutter", 0.0) / 1000.0,
                     max_sigma_m=gate_m, max_sigma_deg=gate_deg,
                     kp_max_sigma_m=d.kp_max_sigma_m * gate_m / d.max_sigma_m,
                     kp_max_sigma_deg=d.kp_max_sigma_deg * gate_deg / d.max_sigma_deg,
                     scan_sigma_m=scan_sigma_m(args), scan_grid=scan_grid(args))


def run_localize_pnl(args) -> int:
    from services.cli import CliError
    from services.geometry.camera import Camera
    from services.io.sequence import open_sequence
    from services.io.trajectory import read_odometry
    from services.localize.cli import resolve_scan_sigma
    from services.localize.pnl import PnlLocalizer
    from services.localize.runner import localize_and_report
    from services.prebuild.stella_map import MAP_FILE

    map_dir = Path(args.map or args.scan)
    if not (map_dir / MAP_FILE).exists() and not (map_dir.is_file() and map_dir.suffix == ".msg"):
        raise CliError(f"--method pnl needs --map MAPDIR (a folder with {MAP_FILE} from 'cristal prebuild'); {map_dir} has none")
    if getattr(args, "threads", None):
        import cv2

        cv2.setNumThreads(int(args.threads))  # -j 1: the one-core figure of benchmarks/RESULTS.md
    seq = open_sequence(args.sequence, camera=Camera.load(args.camera) if getattr(args, "camera", None) else None)
    odometry = read_odometry(args.odometry, seq.stamps, axes=args.odometry_axes) if getattr(args, "odometry", None) else None
    resolve_scan_sigma(args, map_dir=map_dir if map_dir.is_dir() else map_dir.parent)
    loc = PnlLocalizer.load(map_dir, pnl_config(args))
    if loc.patches is None:
        log.info("%s has no landmark patches (a map from before them, or from stella_vslam): keypoint measurements only", map_dir)
    # capture times: the frame interval (a 10 fps camera's blur is a tenth of its motion per frame, not 0.3 of it),
    # the odometry's and the rolling shutter's clock, and a start hint's widening
    return localize_and_report(loc, seq, args, "pnl", stamped=True, odometry=odometry,
                               background={"landmarks": loc.idx.pos})
