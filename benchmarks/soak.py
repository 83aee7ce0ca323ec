"""Clients that come and go, round after round: does the server's memory settle (days of uptime, compressed)?

A fleet's robots and headsets connect, walk a while and vanish (battery, network, shift change), each with a new
client id; the server holds a tracker per client until it has been idle ``--idle`` seconds. This starts a
``cristal serve`` process (Render & Match) and, per round, ``--clients`` new clients (the real client library, each its
own Zenoh session), each sending ``--frames`` consecutive frames of the site's walk from its own starting frame and
waiting for every reply (a cold relocalization first, then tracking). After each round it waits for the idle expiry
and reads the server's health (client states still held), resident memory (VmRSS), threads and open files. A
leak shows as memory, threads or files that grow round after round, or client states that are never let go; the
last line fits the memory's growth per round over the rounds after the first (which includes the server's warm-up).

    python benchmarks/soak.py --site runs/bench-sim/office --rounds 12 --clients 3 --frames 15 --idle 3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service import _free_port, _rss_mb  # noqa: E402  (benchmarks/service.py: the same server, N steady clients)


def _threads_fds(pid: int) -> tuple[int, int]:
    threads = next(int(x.split()[1]) for x in Path(f"/proc/{pid}/status").read_text().splitlines() if x.startswith("Threads:"))
    return threads, len(os.listdir(f"/proc/{pid}/fd"))


def _walk(port: int, cid: str, seq, start: int, n: int, out: dict, lock: threading.Lock) -> None:
    """One client: ``n`` frames from ``start``, each sent after the last reply, then gone."""
    from services.client import LocalizationClient
    from services.zconfig import make_config

    with LocalizationClient(make_config(connect=[f"tcp/127.0.0.1:{port}"]), client_id=cid, deadline_ms=5000) as cl:
        if not cl.wait_for_server(10.0):
            with lock:
                out["no_server"] += 1
            return
        for i in range(start, start + n):
            rep = cl.localize(seq.files[i].read_bytes(), seq.camera, stamp=seq.seconds(seq.stamps[i]))
            with lock:
                out["sent"] += 1
                if rep is None:
                    out["no_reply"] += 1
                elif rep.status.has_pose:
                    out["poses"] += 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--site", default="runs/bench-sim/office", help="folder with scan.ply, reloc.npz and seq_00")
    ap.add_argument("--rounds", type=int, default=12, help="rounds of new clients (default 12)")
    ap.add_argument("--clients", type=int, default=3, help="new clients per round, streaming at once (default 3)")
    ap.add_argument("--frames", type=int, default=15, help="frames each client sends (default 15)")
    ap.add_argument("--idle", type=float, default=3.0, help="the server's --idle: seconds before a silent client's state goes")
    ap.add_argument("--device", default="auto", help="the server's device: cpu, cuda or auto")
    ap.add_argument("--backend", choices=["rm", "pnl"], default="rm",
                    help="the server's localizer: rm (Render & Match, SITE/reloc.npz) or pnl (SITE/map)")
    ap.add_argument("--router", action="store_true",
                    help="the production topology: a 'cristal router' that the server and every client connect to (its "
                         "memory is reported too), instead of clients connecting to the server directly")
    ap.add_argument("--seed", type=int, default=0, help="draw of the clients' starting frames")
    ap.add_argument("--json", help="write the rows here too")
    a = ap.parse_args()
    from services.client import LocalizationClient
    from services.io.sequence import open_sequence
    from services.zconfig import make_config

    site = Path(a.site)
    seq = open_sequence(site / "seq_00")
    rng = np.random.default_rng(a.seed)
    port = _free_port()
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE")
    inputs = ["--db", str(site / "reloc.npz")] if a.backend == "rm" else ["--backend", "pnl", "--map", str(site / "map")]
    ep = f"tcp/127.0.0.1:{port}"
    router = None
    if a.router:  # (its first stdout line says it listens)
        router = subprocess.Popen([sys.executable, "-m", "services.cli", "router", "--listen", ep],
                                  stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
        router.stdout.readline()
        threading.Thread(target=router.stdout.read, daemon=True).start()
    srv = subprocess.Popen([sys.executable, "-m", "services.cli", "serve", str(site / "scan.ply"), *inputs,
                            "--connect" if a.router else "--listen", ep, "--server-id", "soak", "--device", a.device,
                            "--idle", str(a.idle), "--max-clients", "64"],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    rows, t_start = [], time.perf_counter()
    try:
        line = srv.stdout.readline()  # "serving ..." once it answers (logs go to stderr)
        if not line.startswith("serving"):
            raise SystemExit(f"server did not start: {line!r}")
        threading.Thread(target=srv.stdout.read, daemon=True).start()  # keep the pipe drained
        rss_start = _rss_mb(srv.pid)
        probe = LocalizationClient(make_config(connect=[f"tcp/127.0.0.1:{port}"]), client_id="soak-probe")
        try:
            for r in range(a.rounds):
                out = {"sent": 0, "poses": 0, "no_reply": 0, "no_server": 0}
                lock = threading.Lock()
                starts = rng.integers(0, len(seq) - a.frames, a.clients)
                t0 = time.perf_counter()
                threads = [threading.Thread(target=_walk, args=(port, f"soak-{r}-{k}", seq, int(s), a.frames, out, lock))
                           for k, s in enumerate(starts)]
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
                busy_s = time.perf_counter() - t0
                time.sleep(a.idle + 1.5)  # the janitor runs every idle/4 s
                h = probe.health("soak", timeout_s=5.0)
                row = {"round": r + 1, "clients_so_far": (r + 1) * a.clients, **out, "round_s": round(busy_s, 1),
                       "held_after_idle": None if h is None else h.clients, "rss_mb": round(_rss_mb(srv.pid), 1)}
                row["threads"], row["fds"] = _threads_fds(srv.pid)
                if router is not None:
                    row["router_rss_mb"] = round(_rss_mb(router.pid), 1)
                    row["router_threads"], row["router_fds"] = _threads_fds(router.pid)
                rows.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
        finally:
            probe.close()
    finally:
        srv.terminate()
        srv.wait(10)
        if router is not None:
            router.terminate()
            router.wait(10)
    wall = time.perf_counter() - t_start
    print(f"{a.rounds} rounds x {a.clients} new clients x {a.frames} frames, idle expiry {a.idle:g} s, backend {a.backend}, device {a.device}, "
          f"{'through a router, ' if a.router else ''}"
          f"site {site}; {wall:.0f} s; server RSS once serving {rss_start:.0f} MB")
    extra = " router RSS MB | router threads | router open files |" if a.router else ""
    print("| round | clients so far | frames sent | poses | no reply | round s | client states held after idle | server RSS MB "
          "| threads | open files |" + extra)
    print("|---:" * (10 + 3 * a.router) + "|")
    for w in rows:
        more = f" {w['router_rss_mb']:.0f} | {w['router_threads']} | {w['router_fds']} |" if a.router else ""
        print(f"| {w['round']} | {w['clients_so_far']} | {w['sent']} | {w['poses']} | {w['no_reply']} | {w['round_s']} | "
              f"{w['held_after_idle']} | {w['rss_mb']:.0f} | {w['threads']} | {w['fds']} |" + more)
    if len(rows) >= 3:
        x = np.array([w["round"] for w in rows[1:]], float)
        y = np.array([w["rss_mb"] for w in rows[1:]], float)
        slope = float(np.polyfit(x, y, 1)[0])
        print(f"RSS growth after the first round: {slope:+.1f} MB a round ({slope / a.clients:+.2f} MB a client); "
              f"rounds 2-{len(rows)}: {y.min():.0f}-{y.max():.0f} MB")
    if a.json:
        Path(a.json).write_text(json.dumps({"rss_start_mb": rss_start, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
