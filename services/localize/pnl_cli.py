"""``cristal localize --method pnl``: Prebuild & Localize over a sequence (no torch; the same output contract as rm)."""

from __future__ import annotations

import logging
from pathlib import Path


log = logging.getLogger(__name__)


def localize_sequence(loc, seq, n: int, progress_desc: str = "localizing"):
    """Run a localizer over the first ``n`` frames. Returns (trajectory, status counts, mean ms per stage, seconds)."""
    import time

    from services.io.trajectory import Trajectory
    from services.localize.status import Status
    from services.log import progress

    traj = Trajectory()
    counts = {s: 0 for s in Status}
    stage: dict[str, float] = {}
    t0 = time.perf_counter()
    for i, frame in enumerate(progress(seq, desc=progress_desc, total=n, unit="frame")):
        if i >= n:
            break
        r = loc.process(frame.image, seq.camera)
        counts[r.status] += 1
        for k, v in r.timings.items():
            stage[k] = stage.get(k, 0.0) + v / n
        if r.T_wc is not None:
            traj.append(frame.stamp, r.T_wc)
    return traj, counts, stage, time.perf_counter() - t0


def run_localize_pnl(args) -> int:
    from services.cli import CliError, emit_summary
    from services.io.sequence import open_sequence
    from services.io.trajectory import Trajectory, write_tum
    from services.localize.pnl import PnlConfig, PnlLocalizer
    from services.localize.status import Status
    from services.prebuild.stella_map import MAP_FILE

    map_dir = Path(args.map or args.scan)
    if not (map_dir / MAP_FILE).exists() and not (map_dir.is_file() and map_dir.suffix == ".msg"):
        raise CliError(f"--method pnl needs --map MAPDIR (a folder with {MAP_FILE} from 'cristal prebuild'); {map_dir} has none")
    if getattr(args, "threads", None):
        import cv2

        cv2.setNumThreads(int(args.threads))  # -j 1: the one-core figure of benchmarks/RESULTS.md
    seq = open_sequence(args.sequence)
    loc = PnlLocalizer.load(map_dir, PnlConfig(align=not getattr(args, "no_align", False)))
    if loc.patches is None:
        log.info("%s has no landmark patches (a map from before them, or from stella_vslam): keypoint measurements only", map_dir)
    n = min(len(seq), args.frames or len(seq))
    traj, counts, stage, dt = localize_sequence(loc, seq, n)
    write_tum(args.out, traj, header="cristal localize --method pnl: camera-to-world in the scan frame")
    print(f"{len(traj)}/{n} frames localized ({counts[Status.RELOCALIZED]} relocalizations, {counts[Status.LOST]} lost), "
          f"{n / dt:.1f} FPS; mean ms per frame: " + ", ".join(f"{k[:-3]} {v:.1f}" for k, v in stage.items()))
    summary = {"out": args.out, "method": "pnl", "frames": n, "localized": len(traj),
               "relocalizations": counts[Status.RELOCALIZED], "lost": counts[Status.LOST], "fps": round(n / dt, 2),
               **{k: round(v, 2) for k, v in stage.items()}}
    if seq.groundtruth is not None and len(traj):
        from services.eval.ape import ape_first_frames

        line, fields = ape_first_frames(seq.groundtruth, traj, n)
        print(line)
        summary.update(fields)
    emit_summary(summary)
    return 0 if len(traj) else 1
