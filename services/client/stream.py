"""Stream a sequence (folder, video, camera) through the service with on-device fallback (no torch).

Per frame: send it to the server with a deadline. A pose in time → use it (source ``server``)
and seed the local localizer with it. No live server, no reply before the deadline, or a
``lost`` reply → the local P&L localizer's pose is used **for that frame** (source ``local``).
The next frame tries the server again, so the client hands back as soon as a server answers.

Outputs: the TUM trajectory (frames with a pose from either source) and a side file
``<traj>.sources.txt``: ``stamp source status server rtt_ms`` per frame (``-`` where none). Both are written as the
frames come, to ``<file>.part`` beside them (flushed each frame: a crash, a power cut or a kill loses nothing
localized), and renamed into place when the stream ends, however it ends. A live camera runs for days: memory holds
only the last ``memory_frames`` frames (the statistics and the picture are theirs), the files hold every frame.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from protocol.messages import reason_kind
from services.client.client import LocalizationClient, reply_pose
from services.client.fallback import LocalFallback
from services.geometry.se3 import Pose
from services.io.atomic import fsync_dir
from services.io.trajectory import Trajectory, format_tum_line, relative_motions

__all__ = ["StreamStats", "stream_sequence", "sources_path"]

log = logging.getLogger("cristal.client")


def _since_last_sent(unsent: list, motion):
    """A frame's odometry motion since the last frame sent: the motions of the frames not sent between (each since the
    one before it) composed in front of its own; None when any of them is unknown."""
    for m in reversed(unsent):
        motion = None if m is None or motion is None else m @ motion
    return motion


def sources_path(traj_path: str | Path) -> Path:
    p = Path(traj_path)
    return p.with_name(p.stem + ".sources.txt")


@dataclass
class StreamStats:
    frames: int = 0
    server: int = 0
    local: int = 0
    none: int = 0
    missed: int = 0  # no reply before the deadline / no live server
    lost: int = 0  # server replied lost
    lost_reasons: dict[str, int] = field(default_factory=dict)  # those replies by the kind of their reason
    dropped: int = 0
    rejected: int = 0
    switches: int = 0
    rtt_ms: list[float] = field(default_factory=list)
    server_ms: list[float] = field(default_factory=list)  # the server's own arrival-to-reply time
    wall_s: float = 0.0
    rows: list[tuple] = field(default_factory=list)
    interrupted: bool = False  # ended by Ctrl-C (a live camera's usual end)
    forgotten: int = 0  # the oldest frames dropped from memory (``rows``, round trips) to bound it; the files keep them
    picture: Path | None = None  # TRAJ.png, the poses from above, once written

    def summary(self) -> dict:
        rtt = np.array(self.rtt_ms) if self.rtt_ms else np.array([np.nan])
        srv = np.array(self.server_ms) if self.server_ms else np.array([np.nan])

        def pct(a: np.ndarray, q: float) -> float:  # NaN, not a warning, when no frame had a reply
            return round(float(np.nanpercentile(a, q)), 2) if np.isfinite(a).any() else float("nan")

        return {"frames": self.frames, "server": self.server, "local": self.local, "no_pose": self.none,
                "missed": self.missed, "lost": self.lost, "lost_reasons": dict(self.lost_reasons),
                "dropped": self.dropped, "rejected": self.rejected,
                "switches": self.switches, "fps": round(self.frames / self.wall_s, 2) if self.wall_s else 0.0,
                "rtt_p50_ms": pct(rtt, 50), "rtt_p99_ms": pct(rtt, 99),
                "overhead_p50_ms": pct(rtt - srv, 50) if len(rtt) == len(srv) else None,
                **({"interrupted": True} if self.interrupted else {}),
                **({"frames_in_memory": self.frames - self.forgotten} if self.forgotten else {})}


def _frame_bytes(seq, i: int, image: np.ndarray):
    """The file's own bytes for a folder sequence (no re-encoding), else a JPEG of the frame."""
    from protocol.messages import ImageEncoding
    from services.client.client import encode_image

    files = getattr(seq, "files", None)
    if files is not None and i < len(files):
        suf = Path(files[i]).suffix.lower()
        if suf in (".jpg", ".jpeg"):
            return Path(files[i]).read_bytes(), ImageEncoding.JPEG
        if suf == ".png":
            return Path(files[i]).read_bytes(), ImageEncoding.PNG
    return encode_image(image)


def _seconds(seq, stamp: str) -> float | None:
    """A frame's capture time in seconds: a Sequence knows its stamps' unit (a recorder may count nanoseconds,
    services.io.stamps); a live source stamps in seconds."""
    if hasattr(seq, "seconds"):
        return seq.seconds(stamp)
    try:
        return float(stamp)
    except ValueError:
        return None


SOURCES_HEADER = "# stamp source status server rtt_ms"


class _Journal:
    """The trajectory and its sources written as the frames come: each line appended to ``<file>.part`` and flushed (a
    crash or a kill loses nothing localized; the page cache survives the process), renamed into place, fsynced, by
    :meth:`close` however the stream ends."""

    def __init__(self, out: str | Path):
        self.paths = [Path(out), sources_path(out)]
        self.paths[0].parent.mkdir(parents=True, exist_ok=True)
        self.files = [open(self._part(p), "w") for p in self.paths]
        self.files[1].write(SOURCES_HEADER + "\n")

    @staticmethod
    def _part(p: Path) -> Path:
        return p.with_name(p.name + ".part")

    def add(self, row: tuple, T: Pose | None) -> None:
        stamp, src, stt, srv, r = row
        if T is not None:
            self.files[0].write(format_tum_line(stamp, T) + "\n")
            self.files[0].flush()
        self.files[1].write(f"{stamp} {src} {stt} {srv} {r:.2f}\n")
        self.files[1].flush()

    def close(self) -> None:
        for f, p in zip(self.files, self.paths):
            f.flush()
            os.fsync(f.fileno())
            f.close()
            os.replace(self._part(p), p)
        with contextlib.suppress(OSError):
            fsync_dir(self.paths[0].parent)


def _forget_oldest(traj: Trajectory, st: StreamStats, keep: int) -> None:
    """Memory bounded for a stream of days: past 2 x ``keep`` frames in memory, the oldest are dropped down to ``keep``
    (amortised: a list's front is cut once in ``keep`` frames); the journal has written them."""
    if len(st.rows) <= 2 * keep:
        return
    cut = len(st.rows) - keep
    posed = sum(1 for r in st.rows[:cut] if r[1] != "-")  # (frames in order; a posed frame's source is named)
    del st.rows[:cut], traj.stamps[:posed], traj.poses[:posed]
    for lst in (st.rtt_ms, st.server_ms):
        del lst[:max(0, len(lst) - keep)]
    st.forgotten += cut


def stream_sequence(seq, client: LocalizationClient | None, fallback: LocalFallback | None, out: str | Path | None = None,
                    frames: int | None = None, fps: float = 0.0, deadline_ms: float | None = None,
                    on_frame=None, odometry: Trajectory | None = None,
                    readout_s: float | None = None, near=None,
                    memory_frames: int = 100_000) -> tuple[Trajectory, StreamStats]:
    """Stream ``seq`` (a services.io.sequence.Sequence, or anything with its ``camera``, ``stamps``, ``len`` and
    ``frames(tolerant=True)``) and write the trajectory + sources; a frame whose file is missing or broken gets no pose
    and the stream goes on. ``fps`` > 0 paces frames at that rate. ``odometry``: the
    device's own trajectory (any frame of its own): each frame is sent with its motion since the previous one.
    ``readout_s``: the camera's rolling-shutter readout (server and local fallback undo it; None: global shutter).
    ``near``: ((x, y, z), radius m) where the stream starts, roughly: sent with every frame until one has a pose (the
    server may be reached only later), and given to the local fallback. ``out``: written as the frames come (the module);
    ``memory_frames``: at most about twice this many frames are kept in memory (an hour at 30 FPS: 100 000), the
    returned trajectory and the statistics are those of the last ones."""
    from services.log import progress

    if memory_frames < 1:
        raise ValueError(f"memory_frames must be at least 1 (got {memory_frames})")

    traj = Trajectory()
    st = StreamStats()
    n = len(seq) if frames is None else min(len(seq), frames)
    t_start = time.perf_counter()
    period = 1.0 / fps if fps and fps > 0 else 0.0
    # a recording's motions up front; none for a live camera (its length is a bound, 10**9 frames: a list of that many
    # Nones took 8 GB and 17 s before the first frame)
    motions = relative_motions(odometry, seq.stamps[:n]) if odometry is not None else []

    def motion_of(i: int):
        return motions[i] if i < len(motions) else None
    unsent: list = []  # motions of frames not sent since the last one that was (unreadable): the next carries them
    journal = _Journal(out) if out is not None else None

    def record(row: tuple, T: Pose | None) -> None:
        st.rows.append(row)
        if T is not None:
            traj.append(row[0], T)
        if journal is not None:
            journal.add(row, T)
        _forget_oldest(traj, st, memory_frames)

    try:
        for i, frame in enumerate(progress(seq.frames(tolerant=True), desc="streaming", total=n, unit="frame")):
            if i >= n:
                break
            if frame.image is None:  # a missing or broken file (logged): no pose for it, the stream goes on
                unsent.append(motion_of(i))
                st.frames += 1
                st.none += 1
                record((frame.stamp, "-", "unreadable", "-", float("nan")), None)
                continue
            if period:
                wait = t_start + i * period - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
            cam = seq.camera
            T: Pose | None = None
            source, status, server, rtt = "-", "none", "-", float("nan")
            rep = None
            stamp_f = _seconds(seq, frame.stamp)
            stamp_f = float(i) if stamp_f is None else stamp_f
            motion, unsent = _since_last_sent(unsent, motion_of(i)), []
            if client is not None:
                data, enc = _frame_bytes(seq, i, frame.image)
                t0 = time.perf_counter()
                rep = client.localize(data, cam, stamp=stamp_f, stamp_text=frame.stamp, encoding=enc, deadline_ms=deadline_ms,
                                      motion=motion, readout_s=readout_s, near=near if not len(traj) else None)
                rtt = 1e3 * (time.perf_counter() - t0)
                if rep is None:
                    st.missed += 1
                    status = "missed"
                else:
                    status, server = rep.status.value, rep.server or "-"
                    if rep.status.value == "lost":
                        st.lost += 1
                        kind = reason_kind(rep.reason)
                        if kind not in st.lost_reasons:  # once per kind: a repetitive site's "ambiguous place" asks for a prior
                            log.info("frame %s lost: %s", frame.stamp, rep.reason)
                        st.lost_reasons[kind] = st.lost_reasons.get(kind, 0) + 1
                    elif rep.status.value == "dropped":
                        st.dropped += 1
                    elif rep.status.value == "rejected":
                        st.rejected += 1
                        log.warning("frame %s rejected: %s (%s)", frame.stamp, rep.reason, rep.error)
                    T = reply_pose(rep)
                    if T is not None:
                        st.rtt_ms.append(rtt)
                        st.server_ms.append(float(rep.timings.get("total_ms", np.nan)))
            if T is not None:
                source = "server"
                st.server += 1
                if fallback is not None:
                    fallback.seed(T, stamp=stamp_f)
            elif fallback is not None:
                lr = fallback.process(frame.image, cam, motion=motion, stamp=stamp_f, readout_s=readout_s,
                                      near=near if not len(traj) else None)
                if lr.T_wc is not None:
                    T, source = lr.T_wc, "local"
                    st.local += 1
                    status = f"{status}/{lr.status}"
            st.none += T is None
            st.frames += 1
            record((frame.stamp, source, status, server, rtt), T)
            if on_frame is not None:
                on_frame(i, frame, T, source, rep)
    except KeyboardInterrupt:  # Ctrl-C ends a live camera's stream: what was localized is still written
        st.interrupted = True
        log.warning("interrupted after %d frames: writing their poses", st.frames)
    finally:  # however the stream ends (a camera unplugged, the server's library raising), the frames done are kept
        if journal is not None:
            journal.close()
    st.wall_s = time.perf_counter() - t_start
    st.switches = client.switches if client is not None else 0
    if out is not None:
        st.picture = _picture(traj, st, seq, out, fallback)
    return traj, st


def _picture(traj: Trajectory, st: StreamStats, seq, out, fallback):
    """TRAJ.png: the stream's poses from above (services.eval.plots.plot_localization_topdown), the local
    fallback's marked, over its map's landmarks when it has one; None (logged) when it cannot be drawn (no matplotlib
    on a headset): the trajectory and sources are written either way."""
    from services.eval.plots import drawn, picture_path, plot_localization_topdown
    from services.io.frame_log import FrameRecord

    records = [FrameRecord(s, {"server": "TRACKING", "local": "LOCAL"}.get(src, "LOST")) for s, src, *_ in st.rows]
    last = f" (the last {len(st.rows)} of {st.frames})" if st.forgotten else ""
    idx = getattr(getattr(fallback, "loc", None), "idx", None)
    return drawn("the stream", plot_localization_topdown, traj, records, picture_path(out),
                 landmarks=getattr(idx, "pos", None), gt=getattr(seq, "groundtruth", None),
                 title=f"streamed (top view): {len(traj)}/{len(st.rows)} frames with a pose{last}")
