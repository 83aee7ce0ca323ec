"""The Zenoh sessions every command opens (services.zconfig), measured as a long-running server sees them."""

import subprocess
import sys
import textwrap
import time
from pathlib import Path

from _zenoh import config, endpoint, free_port

ROOT = Path(__file__).resolve().parents[1]


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def test_a_server_keeps_no_memory_of_clients_that_came_and_went():
    """Clients on the server's host that each send a few frame-sized requests and leave: zenoh's shared-memory
    transport (on by default) gave every such client a 16 MiB pool that the server kept mapped after it left, +16 MB of
    server memory per client, without end (benchmarks/soak.py). The sessions make_config opens do not use it."""
    import zenoh

    port = free_port()
    server = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(ROOT)!r})
        from services.zconfig import make_config, open_session
        s = open_session(make_config(listen=[{endpoint(port)!r}], default_role="server"))
        q = s.declare_queryable("cristal-test/**", lambda q: q.reply(q.key_expr, b"ok"))
        print("ready", flush=True)
        time.sleep(120)
        """)], stdout=subprocess.PIPE, text=True)
    try:
        assert server.stdout.readline().strip() == "ready"
        frame = bytes(range(256)) * 160  # 40 KB, a JPEG frame's size
        rss = []
        for _ in range(8):
            with zenoh.open(config(connect=[endpoint(port)])) as s:
                time.sleep(0.2)
                replies = [r for _ in range(5) for r in s.get("cristal-test/frame", payload=frame, timeout=5) if r.ok]
                assert len(replies) == 5
            time.sleep(0.2)
            rss.append(_rss_mb(server.pid))
        assert rss[-1] - rss[0] < 30, f"server memory grew {rss[-1] - rss[0]:.0f} MB over 7 departed clients: {rss}"
    finally:
        server.kill()
        server.wait(10)


_FRAGMENTED_HEAP = """
import os
from services.server.service import _heap_trimmer

def rss_mb():
    return next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmRSS")) / 1024

big, pins = [], []
for i in range(20000):  # 320 MB of 16 KB blocks, each followed by a small block that stays: freed, they cannot shrink
    big.append(os.urandom(16) * 1000)  # the heap's top, so free() keeps their pages
    pins.append(os.urandom(16) * 40)
del big
held = rss_mb()
_heap_trimmer()(0)
print(held, rss_mb())
"""


def test_the_server_can_hand_freed_heap_back_to_the_system():
    """The server's janitor trims the C heap every ServerConfig.trim_every_s (glibc's malloc_trim): a long-running
    server's RSS then follows what it holds, not what it once held. Checked on a heap fragmented on purpose, in a
    process of its own: the freed blocks' pages go back to the system only when trimmed (379 -> 150 MB here)."""
    import platform

    from services.server.service import ServerConfig, _heap_trimmer

    assert ServerConfig().trim_every_s > 0
    trim = _heap_trimmer()
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert trim is not None
        out = subprocess.run([sys.executable, "-c", _FRAGMENTED_HEAP], capture_output=True, text=True, timeout=120,
                             cwd=Path(__file__).resolve().parents[1], check=True).stdout.split()
        held, trimmed = float(out[0]), float(out[1])
        assert held - trimmed > 150, f"RSS {held:.0f} MB with 320 MB freed, {trimmed:.0f} MB trimmed"
