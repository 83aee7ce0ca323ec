"""One loop for ``cristal localize`` (both methods) and the benchmarks: run a localizer over a sequence,
write the TUM trajectory, print frames / FPS / per-stage times and APE, end with the JSON summary. No torch."""

from __future__ import annotations

import logging
import time

__all__ = ["localize_sequence", "localize_and_report"]

log = logging.getLogger(__name__)


def _png(image) -> bytes:
    import cv2

    return cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])[1].tobytes()


def localize_sequence(loc, seq, n: int, progress_desc: str = "localizing", stamped: bool = False, odometry=None,
                      backfill=None, near=None, records: list | None = None):
    """Run a localizer over the first ``n`` frames (``stamped``: pass each frame's capture time, which
    Render & Match uses for constant velocity and motion blur; ``odometry``: the device's own trajectory
    (services.io.trajectory.Trajectory, any world frame), passed as each frame's ``motion`` since the previous
    frame where both have one; ``backfill``: a services.localize.backfill.BackfillStats to run the offline backward
    pass and count into; ``near``: (position, radius m) where the first frame was taken, roughly, passed to the
    localizer with it; ``records``: a list to append each frame's services.io.frame_log.FrameRecord to). Returns
    (trajectory, status counts of the forward pass, mean ms per stage of the forward pass, seconds of both passes,
    LOST frames per reason in the forward pass, interrupted): Ctrl-C ends the pass early and keeps the frames
    localized so far (no backward pass then)."""
    import cv2
    import numpy as np

    from protocol.messages import reason_kind
    from services.io.frame_log import FrameRecord
    from services.io.trajectory import Trajectory, relative_motions
    from services.localize.status import Status
    from services.log import progress, progress_bar

    counts = {s: 0 for s in Status}
    stage: dict[str, float] = {}
    why: dict[str, int] = {}
    motions = relative_motions(odometry, seq.stamps[:n]) if odometry is not None else None
    # the capture time: constant velocity and blur (R&M), the odometry's clock
    stamps = [seq.seconds(s) if (stamped or motions is not None) else None for s in seq.stamps[:n]]
    poses: list = [None] * n
    kept: dict[int, bytes] = {}  # a video's frames the backward pass needs (LOST ones and those around them), as PNG
    prev = None
    t0 = time.perf_counter()
    unreadable: set[int] = set()  # frames whose image is missing or broken: LOST, and the run goes on
    done, interrupted = 0, False
    try:
        for i, frame in enumerate(progress(seq.frames(tolerant=True), desc=progress_desc, total=n, unit="frame")):
            if i >= n:
                break
            done = i + 1
            if frame.image is None:
                counts[Status.LOST] += 1
                why["unreadable image"] = why.get("unreadable image", 0) + 1
                unreadable.add(i)
                if records is not None:
                    records.append(FrameRecord(frame.stamp, Status.LOST.name, reason=f"unreadable image: {frame.problem}"))
                continue
            hint = {"near": near} if near is not None and i == 0 else {}
            r = loc.process(frame.image, seq.camera, stamp=stamps[i], motion=None if motions is None else motions[i],
                            **hint)
            counts[r.status] += 1
            reason = getattr(r, "reason", None) if r.status == Status.LOST else None
            if reason:
                why[reason_kind(reason)] = why.get(reason_kind(reason), 0) + 1
            for k, v in r.timings.items():
                stage[k] = stage.get(k, 0.0) + v
            poses[i] = r.T_wc
            if records is not None:
                records.append(FrameRecord(frame.stamp, r.status.name, int(r.inliers), float(r.rmse_px),
                                           float(r.sigma_m), float(r.sigma_deg), reason or "", r.source or ""))
            if backfill is not None and seq.files is None:  # a video: no going back to its frames
                if i > 0 and (poses[i] is None) != (poses[i - 1] is None) and i - 1 not in kept:
                    kept[i - 1] = _png(prev)
                if poses[i] is None or (i > 0 and poses[i - 1] is None):
                    kept[i] = _png(frame.image)
                prev = frame.image
    except KeyboardInterrupt:  # Ctrl-C on a long recording: keep what was localized (the caller writes it)
        done = sum(counts.values())
        log.warning("interrupted after %d of %d frames: keeping their poses%s", done, n,
                    ", no backward pass" if backfill is not None else "")
        backfill, interrupted = None, True
    stage = {k: v / max(done, 1) for k, v in stage.items()}
    poses = poses[:done]
    if backfill is not None:
        from services.localize.backfill import backfill as backward

        def image(i: int):
            if i in unreadable:
                return None
            return seq.read(i).image if seq.files is not None else cv2.imdecode(np.frombuffer(kept[i], np.uint8),
                                                                                 cv2.IMREAD_COLOR)

        with progress_bar("backward pass", total=sum(p is None for p in poses), unit="frame") as bar:
            backward(loc, image, seq.camera, poses, stamps, motions, progress=bar.update, stats=backfill)
        if records is not None:  # (records and poses are both in frame order, one each)
            base = len(records) - len(poses)
            for i, T in enumerate(poses):
                if T is not None and records[base + i].status == Status.LOST.name:
                    records[base + i] = FrameRecord(records[base + i].stamp, "BACKFILLED")
    traj = Trajectory()
    for stamp, T in zip(seq.stamps, poses):
        if T is not None:
            traj.append(stamp, T)
    return traj, counts, stage, time.perf_counter() - t0, why, interrupted


def localize_and_report(loc, seq, args, method: str, stamped: bool = False, after=None, odometry=None,
                        background: dict | None = None) -> int:
    """``cristal localize``'s output contract for either method; exit code 0 when any frame got a pose.
    ``after(traj) -> dict``: a check run on the trajectory once timed (its fields join the summary);
    ``background``: what the run's top-view picture is drawn over (``scan=`` a Scan, or ``landmarks=`` world xyz)."""
    from services.cli import emit_summary, near_arg
    from services.io.frame_log import frame_log_path, write_frame_log
    from services.io.trajectory import write_tum
    from services.localize.backfill import BackfillStats
    from services.localize.status import Status

    n = min(len(seq), args.frames or len(seq))
    back = BackfillStats() if getattr(args, "backfill", False) else None
    near = near_arg(getattr(args, "near", None))
    records: list = []
    traj, counts, stage, dt, why, interrupted = localize_sequence(loc, seq, n, stamped=stamped, odometry=odometry,
                                                                  backfill=back, near=near, records=records)
    if interrupted:
        print(f"interrupted: the first {sum(counts.values())} of {n} frames only")
        n = sum(counts.values())
    write_tum(args.out, traj, header=f"cristal localize --method {method}: camera-to-world in the scan frame")
    write_frame_log(frame_log_path(args.out), records)  # every frame: status, inliers, predicted 1-sigma, reason
    from services.eval.plots import drawn, picture_path, plot_localization_topdown

    picture = drawn("the run", plot_localization_topdown, traj, records, picture_path(args.out), gt=seq.groundtruth,
                    **(background or {}))  # TRAJ.png, after the outputs: a picture never costs the poses
    print(f"{len(traj)}/{n} frames localized ({counts[Status.RELOCALIZED]} relocalizations, {n - len(traj)} lost), "
          f"{n / dt:.1f} FPS; mean ms per frame: " + ", ".join(f"{k[:-3]} {v:.1f}" for k, v in stage.items()))
    if picture is not None:
        over = "scan" if "scan" in (background or {}) else "map"
        print(f"picture: {picture} (the poses seen from above over the {over})")
    summary = {"out": args.out, "frame_log": str(frame_log_path(args.out)), "picture": picture and str(picture),
               "method": method, "frames": n, "localized": len(traj), "odometry": odometry is not None,
               **({"interrupted": True} if interrupted else {}),
               "relocalizations": counts[Status.RELOCALIZED], "lost": n - len(traj), "fps": round(n / dt, 2),
               **{k: round(v, 2) for k, v in stage.items()}}
    if back is not None:
        print(f"backward pass: {back.filled} more frames from {back.stretches} LOST stretches"
              + (f" ({back.rejected} dropped: their track back missed the pose before them)" if back.rejected else ""))
        summary.update(backfilled=back.filled, backfill_rejected=back.rejected)
    unused = getattr(getattr(loc, "odometry", None), "unused", 0) if odometry is not None else 0
    if unused:
        print(f"the odometry disagreed with the tracked motion and was set aside on {unused} frames: check its axes "
              f"(--odometry-axes) and that its clock is the frames'")
        summary["odometry_unused_frames"] = unused
    if why:
        head = "lost in the pass in time order: " if back is not None else "lost: "
        print(head + ", ".join(f"{v} {k}" for k, v in sorted(why.items(), key=lambda kv: -kv[1]))
              + " (what each means and what helps: docs/TROUBLESHOOTING.md)")
        summary["lost_reasons"] = why
    if seq.groundtruth is not None and len(traj):
        from services.eval.ape import ape_first_frames

        line, fields = ape_first_frames(seq.groundtruth, traj, n)
        print(line)
        summary.update(fields)
    if after is not None and len(traj):
        summary.update(after(traj))
    emit_summary(summary)
    return 130 if interrupted else 0 if len(traj) else 1  # (130: ended by Ctrl-C, as a shell reports it)

