"""One loop for ``cristal localize`` (both methods) and the benchmarks: run a localizer over a sequence,
write the TUM trajectory, print frames / FPS / per-stage times and APE, end with the JSON summary. No torch."""

from __future__ import annotations

import time

__all__ = ["localize_sequence", "localize_and_report"]


def _seconds(stamp: str) -> float | None:
    try:
        return float(stamp)
    except ValueError:
        return None


def localize_sequence(loc, seq, n: int, progress_desc: str = "localizing", stamped: bool = False, odometry=None):
    """Run a localizer over the first ``n`` frames (``stamped``: pass each frame's capture time, which
    Render & Match uses for constant velocity and motion blur; ``odometry``: the device's own trajectory
    (services.io.trajectory.Trajectory, any world frame), passed as each frame's ``motion`` since the previous
    frame where both have one). Returns (trajectory, status counts, mean ms per stage, seconds, LOST frames
    per reason)."""
    from protocol.messages import reason_kind
    from services.io.trajectory import Trajectory, relative_motions
    from services.localize.status import Status
    from services.log import progress

    traj = Trajectory()
    counts = {s: 0 for s in Status}
    stage: dict[str, float] = {}
    why: dict[str, int] = {}
    motions = relative_motions(odometry, seq.stamps[:n]) if odometry is not None else None
    t0 = time.perf_counter()
    for i, frame in enumerate(progress(seq, desc=progress_desc, total=n, unit="frame")):
        if i >= n:
            break
        kw = {} if motions is None else {"motion": motions[i]}
        if stamped or motions is not None:  # the capture time: constant velocity and blur (R&M), the odometry's clock
            kw["stamp"] = _seconds(frame.stamp)
        r = loc.process(frame.image, seq.camera, **kw)
        counts[r.status] += 1
        reason = getattr(r, "reason", None) if r.status == Status.LOST else None
        if reason:
            why[reason_kind(reason)] = why.get(reason_kind(reason), 0) + 1
        for k, v in r.timings.items():
            stage[k] = stage.get(k, 0.0) + v / n
        if r.T_wc is not None:
            traj.append(frame.stamp, r.T_wc)
    return traj, counts, stage, time.perf_counter() - t0, why


def localize_and_report(loc, seq, args, method: str, stamped: bool = False, after=None, odometry=None) -> int:
    """``cristal localize``'s output contract for either method; exit code 0 when any frame got a pose.
    ``after(traj) -> dict``: a check run on the trajectory once timed (its fields join the summary)."""
    from services.cli import emit_summary
    from services.io.trajectory import write_tum
    from services.localize.status import Status

    n = min(len(seq), args.frames or len(seq))
    traj, counts, stage, dt, why = localize_sequence(loc, seq, n, stamped=stamped, odometry=odometry)
    write_tum(args.out, traj, header=f"cristal localize --method {method}: camera-to-world in the scan frame")
    print(f"{len(traj)}/{n} frames localized ({counts[Status.RELOCALIZED]} relocalizations, {counts[Status.LOST]} lost), "
          f"{n / dt:.1f} FPS; mean ms per frame: " + ", ".join(f"{k[:-3]} {v:.1f}" for k, v in stage.items()))
    summary = {"out": args.out, "method": method, "frames": n, "localized": len(traj), "odometry": odometry is not None,
               "relocalizations": counts[Status.RELOCALIZED], "lost": counts[Status.LOST], "fps": round(n / dt, 2),
               **{k: round(v, 2) for k, v in stage.items()}}
    unused = getattr(getattr(loc, "odometry", None), "unused", 0) if odometry is not None else 0
    if unused:
        print(f"the odometry disagreed with the tracked motion and was set aside on {unused} frames: check its axes "
              f"(--odometry-axes) and that its clock is the frames'")
        summary["odometry_unused_frames"] = unused
    if why:
        print("lost: " + ", ".join(f"{v} {k}" for k, v in sorted(why.items(), key=lambda kv: -kv[1])))
        summary["lost_reasons"] = why
    if seq.groundtruth is not None and len(traj):
        from services.eval.ape import ape_first_frames

        line, fields = ape_first_frames(seq.groundtruth, traj, n)
        print(line)
        summary.update(fields)
    if after is not None and len(traj):
        summary.update(after(traj))
    emit_summary(summary)
    return 0 if len(traj) else 1
