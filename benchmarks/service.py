"""The localization service under load on loopback: N clients streaming at a fixed rate.

A ``cristal serve`` process (Render & Match) and, in this process, N clients, each with its own
Zenoh session, sending the frames of a sequence (played forwards, then backwards) at ``--fps`` without
waiting for replies (as a headset does): replies arrive asynchronously, the server drops stale frames
(latest frame wins). ``--warmup S``: each set of N clients first streams N x S seconds that do not count (a new
client's first relocalization and its exposure calibration, 8 frames of 8 blurred renders matched, take
~6 s of a 2-core CPU: in a 10 s window they are most of what is measured). Per N: round-trip latency p50/p99 of frames that got a pose, the server's own time for them
(arrival to reply) and the difference (what Zenoh + encoding add), throughput in poses/s,
dropped frames, and the server's resident memory at start and end.

    python benchmarks/service.py --site runs/bench-sim/office --clients 1 2 4 8 --seconds 10 [--warmup 10]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol import keys  # noqa: E402
from protocol.codec import decode, encode  # noqa: E402
from protocol.messages import FrameRequest, ImageEncoding, Intrinsics, PoseMsg, PoseReply  # noqa: E402


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


_LAST_SEQ: dict[str, int] = {}  # per client id, over the runs of one server


def _ping_pong(i: int, n: int) -> int:
    """Frame index ``i`` of a clip of ``n`` frames played forwards, then backwards, and so on: the camera turns back
    instead of jumping from the clip's end to its start (a jump is a relocalization, not tracking, on every lap)."""
    if n < 2:
        return 0
    k = i % (2 * (n - 1))
    return k if k < n else 2 * (n - 1) - k


def run_clients(port: int, n: int, seconds: float, fps: float, frames: list[bytes], intr: Intrinsics, server: str,
                poses: list | None = None) -> dict:
    """N clients streaming ``frames`` (ping-pong) at ``fps`` for ``seconds``; ``poses``: the frames' true camera-to-world
    poses, to send each frame's motion since the one before as a device's odometry would."""
    import zenoh

    from services.zconfig import make_config

    sessions = [zenoh.open(make_config(connect=[f"tcp/127.0.0.1:{port}"])) for _ in range(n)]
    lock = threading.Lock()
    rec = {"sent": 0, "pose": 0, "lost": 0, "dropped": 0, "rejected": 0, "none": 0, "rtt": [], "srv": [], "loc": []}
    time.sleep(0.5)

    def client(k: int) -> None:
        s = sessions[k]
        cid = f"bench-{k}"
        key = keys.frame("default", "default", cid, server)
        t_next = time.perf_counter() + k * (1.0 / fps / max(n, 1))
        t_end = time.perf_counter() + seconds
        seq = _LAST_SEQ.get(cid, 0)  # a client's frames stay newer than its last run's (the server drops older ones)
        while t_next < t_end:
            time.sleep(max(0.0, t_next - time.perf_counter()))
            seq += 1
            i = _ping_pong(seq, len(frames))
            img = frames[i]
            motion = None
            if poses is not None:
                m = poses[_ping_pong(seq - 1, len(frames))].inverse() @ poses[i]
                motion = PoseMsg.from_tum(m.to_tum())
            payload = encode(FrameRequest(client=cid, seq=seq, stamp=time.time(), image=img, encoding=ImageEncoding.JPEG,
                                          motion=motion,
                                          intrinsics=intr, deadline_ms=1000))
            t0 = time.perf_counter()
            got = {"r": False}

            def on_reply(reply, t0=t0, got=got):
                if reply.ok is None:
                    return
                got["r"] = True
                r = decode(reply.ok.payload.to_bytes(), PoseReply)
                dt = 1e3 * (time.perf_counter() - t0)
                with lock:
                    if r.status.has_pose:
                        rec["pose"] += 1
                        rec["rtt"].append(dt)
                        rec["srv"].append(r.timings.get("total_ms", np.nan))
                        rec["loc"].append(r.timings.get("localize_ms", np.nan))
                    else:
                        rec[r.status.value] += 1

            s.get(key, on_reply, payload=payload, timeout=1.5)
            with lock:
                rec["sent"] += 1
            t_next += 1.0 / fps
        _LAST_SEQ[cid] = seq

    threads = [threading.Thread(target=client, args=(k,)) for k in range(n)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    time.sleep(1.6)  # outstanding replies
    wall = time.perf_counter() - t0 - 1.6
    for s in sessions:
        s.close()
    rtt, srv, loc = (np.array(rec[k]) if rec[k] else np.array([np.nan]) for k in ("rtt", "srv", "loc"))
    return {"clients": n, "sent": rec["sent"], "poses": rec["pose"], "lost": rec["lost"], "dropped": rec["dropped"],
            "rejected": rec["rejected"], "throughput": rec["pose"] / wall,
            "rtt_p50": float(np.nanpercentile(rtt, 50)), "rtt_p99": float(np.nanpercentile(rtt, 99)),
            "server_p50": float(np.nanpercentile(srv, 50)), "localize_p50": float(np.nanpercentile(loc, 50)),
            "overhead_p50": float(np.nanpercentile(rtt - srv, 50)), "overhead_p99": float(np.nanpercentile(rtt - srv, 99))}


def sequential(port: int, frames: list[bytes], intr: Intrinsics, server: str, n: int = 20) -> dict:
    """One client sending the next frame only after the reply: round trip minus the server's localization time."""
    import zenoh

    from services.zconfig import make_config

    s = zenoh.open(make_config(connect=[f"tcp/127.0.0.1:{port}"]))
    rtt, loc, srv = [], [], []
    try:
        time.sleep(0.5)
        for i in range(n):
            payload = encode(FrameRequest(client="seq-0", seq=i + 1, image=frames[i % len(frames)], intrinsics=intr))
            t0 = time.perf_counter()
            r = [x for x in s.get(keys.frame("default", "default", "seq-0", server), payload=payload, timeout=5) if x.ok]
            dt = 1e3 * (time.perf_counter() - t0)
            rep = decode(r[0].ok.payload.to_bytes(), PoseReply)
            if rep.status.has_pose:
                rtt.append(dt)
                loc.append(rep.timings["localize_ms"])
                srv.append(rep.timings["total_ms"])
    finally:
        s.close()
    rtt, loc, srv = map(np.array, (rtt, loc, srv))
    return {"poses": len(rtt), "rtt_p50": float(np.median(rtt)), "localize_p50": float(np.median(loc)),
            "added_p50": float(np.median(rtt - loc)), "added_p99": float(np.percentile(rtt - loc, 99)),
            "transport_p50": float(np.median(rtt - srv))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/office", help="folder with scan.ply, reloc.npz and seq_00")
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--warmup", type=float, default=0.0,
                    help="seconds per client that each set of N clients streams before the measured window (default 0: a new "
                         "client's "
                         "first relocalization and exposure calibration, ~6 s of CPU, count)")
    ap.add_argument("--frames", type=int, default=60, help="frames of seq_00 cycled through")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--workers", type=int, default=1, help="the server's worker threads (frames of different clients in parallel)")
    ap.add_argument("--odometry", action="store_true",
                    help="send each frame's motion since the one before (from the ground truth), as a headset's VIO would")
    ap.add_argument("--json", help="write the rows here too")
    a = ap.parse_args()
    from services.io.sequence import open_sequence

    site = Path(a.site)
    seq = open_sequence(site / "seq_00")
    frames = [seq.files[i].read_bytes() for i in range(min(a.frames, len(seq)))]
    intr = Intrinsics(**seq.camera.to_dict())
    poses = seq.groundtruth.poses[:len(frames)] if a.odometry else None
    port = _free_port()
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE")
    srv = subprocess.Popen([sys.executable, "-m", "services.cli", "serve", str(site / "scan.ply"), "--db", str(site / "reloc.npz"),
                            "--listen", f"tcp/127.0.0.1:{port}", "--server-id", "bench", "--device", a.device,
                            "--max-clients", "64", "--workers", str(a.workers)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    try:
        line = srv.stdout.readline()  # stdout's first line, "serving ...", once it answers (logs go to stderr)
        if not line.startswith("serving"):
            raise SystemExit(f"server did not start: {line!r}")
        threading.Thread(target=srv.stdout.read, daemon=True).start()  # keep the pipe drained
        # warm-up: the first frames compile kernels and relocalize
        run_clients(port, 1, 3.0, 5.0, frames, intr, "bench")
        rss0 = _rss_mb(srv.pid)
        sq = sequential(port, frames, intr, "bench")
        print(json.dumps(sq), file=sys.stderr, flush=True)
        rows = []
        for n in a.clients:
            if a.warmup > 0:  # every client relocalized and its exposure calibrated before the window that counts
                run_clients(port, n, a.warmup * n, a.fps, frames, intr, "bench", poses)
            r = run_clients(port, n, a.seconds, a.fps, frames, intr, "bench", poses)
            r["rss_mb"] = _rss_mb(srv.pid)
            rows.append(r)
            print(json.dumps(r), file=sys.stderr, flush=True)
    finally:
        srv.terminate()
        srv.wait(10)
    print(f"one client, next frame after the reply ({sq['poses']} poses): round trip p50 {sq['rtt_p50']:.1f} ms, "
          f"localization p50 {sq['localize_p50']:.1f} ms -> the service adds p50 {sq['added_p50']:.2f} ms, "
          f"p99 {sq['added_p99']:.2f} ms (of which Zenoh + msgpack, outside the server: p50 {sq['transport_p50']:.2f} ms)")
    print(f"server RSS after warm-up {rss0:.0f} MB; {a.fps:.0f} FPS per client for {a.seconds:.0f} s after N x {a.warmup:.0f} s "
          f"unmeasured; {a.workers} worker(s); odometry {'sent' if a.odometry else 'none'}; "
          f"device {a.device}; site {site}")
    print("| clients | sent | poses | poses/s | lost | dropped | RTT p50 ms | RTT p99 ms | server p50 ms | localize p50 ms "
          "| overhead p50 ms | overhead p99 ms | server RSS MB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['clients']} | {r['sent']} | {r['poses']} | {r['throughput']:.1f} | {r['lost']} | {r['dropped']} | "
              f"{r['rtt_p50']:.1f} | {r['rtt_p99']:.1f} | {r['server_p50']:.1f} | {r['localize_p50']:.1f} | "
              f"{r['overhead_p50']:.2f} | {r['overhead_p99']:.2f} | {r['rss_mb']:.0f} |")
    if a.json:
        Path(a.json).write_text(json.dumps({"rss_start_mb": rss0, "sequential": sq, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
