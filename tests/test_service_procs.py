"""Faults with real processes on loopback: a router, server processes that die, a client that copes.

- two workers behind one router: the client sticks to one; killed, it moves to the other carrying its last pose;
- the only server killed mid-stream: the client uses its local pose from the next frame (within one deadline)
  and hands back to the server as soon as one serves again.
"""

import time

import pytest
from _zenoh import config, cristal, endpoint, free_port, stop, wait_until
from _pictures import pixels_of, red_pixels

from services.eval.plots import LOCAL_COLOR

pytestmark = [pytest.mark.timeout(300), pytest.mark.slow]


class GroundTruthLocal:
    """Stands in for the on-device P&L localizer in these tests: the policy under test is the client's."""

    def __init__(self, seq):
        self.poses = dict(zip(seq.stamps, seq.groundtruth.poses))
        self.by_shape = {}
        self.seq = seq
        self.calls = 0
        self.seeds = 0

    def seed(self, T):
        self.seeds += 1

    def process(self, image, camera, prior, motion=None, stamp=None):
        self.calls += 1
        i = self.i  # set by the stream loop's on_frame hook below
        from services.client.fallback import LocalResult

        return type("R", (), {"status": "tracking", "T_wc": self.seq.groundtruth.poses[i], "inliers": 100})()


@pytest.fixture
def router():
    port = free_port()
    p = cristal("router", "--listen", endpoint(port))
    try:
        assert wait_until(lambda: _connectable(port), 15), stop(p)
        yield port
    finally:
        stop(p)


def _connectable(port):
    import socket

    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _serve(small_site, db, port, sid):
    return cristal("-v", "serve", small_site[0] / "scan.ply", "--db", db, "--connect", endpoint(port), "--site", "lab",
                   "--map-id", "office", "--server-id", sid, "--device", "cpu")


class _Seq:
    """The first n frames of a sequence, repeated so the stream lasts long enough to kill things in it."""

    def __init__(self, seq, n):
        import itertools

        self.camera, self.groundtruth, self.files = seq.camera, seq.groundtruth, None
        self.base = seq
        self.idx = [i for _, i in zip(range(n), itertools.cycle(list(range(len(seq))) + list(range(len(seq) - 2, 0, -1))))]
        self.stamps = [f"{k:06d}" for k in range(n)]

    def __len__(self):
        return len(self.idx)

    def frames(self, tolerant=False):
        from services.io.sequence import Frame

        for k, i in enumerate(self.idx):
            yield Frame(self.stamps[k], self.base.read(i).image)

    __iter__ = frames


def test_failover_between_two_workers(small_site, small_site_db, router):
    from services.client.client import LocalizationClient
    from services.client.stream import stream_sequence
    from services.io.sequence import open_sequence

    seq = open_sequence(small_site[0] / "seq_00")
    procs = {sid: _serve(small_site, small_site_db, router, sid) for sid in ("wA", "wB")}
    try:
        with LocalizationClient(config(connect=[endpoint(router)]), client_id="robot-1", site="lab", map_id="office",
                                deadline_ms=3000) as cl:
            assert wait_until(lambda: len(cl.servers) == 2, 60), {k: stop(p) for k, p in procs.items()}
            first = cl.pick_server()
            killed = {}

            def on_frame(i, frame, T, source, rep):
                if i == 3:
                    procs[first].kill()  # SIGKILL: no goodbye, the router notices the closed link
                    killed["t"] = time.monotonic()

            s = _Seq(seq, 10)
            traj, st = stream_sequence(s, cl, None, None, on_frame=on_frame)
            servers = [r[3] for r in st.rows]
            other = "wB" if first == "wA" else "wA"
            assert servers[:4] == [first] * 4, st.rows
            assert set(servers[5:]) == {other}, st.rows  # moved to the live worker and stayed there
            assert cl.switches == 1
            statuses = [r[2] for r in st.rows]
            # the new worker got the last pose as prior: it tracks on, no relocalization needed
            assert statuses[5] == "tracking" or statuses[4] == "tracking", st.rows
            assert st.server >= 8, st.rows
    finally:
        for p in procs.values():
            stop(p, kill=True)


def test_killed_server_falls_back_within_a_deadline_and_hands_back(small_site, small_site_db, router, tmp_path):
    from services.client.client import LocalizationClient
    from services.client.fallback import LocalFallback
    from services.client.stream import sources_path, stream_sequence
    from services.io.sequence import open_sequence
    from services.io.trajectory import read_tum

    seq = open_sequence(small_site[0] / "seq_00")
    s = _Seq(seq, 24)
    local = GroundTruthLocal(seq)
    fb = LocalFallback(local)
    deadline = 2500.0
    srv = {"p": _serve(small_site, small_site_db, router, "w1")}
    events = {}
    try:
        with LocalizationClient(config(connect=[endpoint(router)]), client_id="hmd-1", site="lab", map_id="office",
                                deadline_ms=deadline) as cl:
            assert wait_until(lambda: len(cl.servers) == 1, 60), stop(srv["p"])

            def on_frame(i, frame, T, source, rep):
                local.i = s.idx[min(i + 1, len(s.idx) - 1)]
                if i == 4:
                    srv["p"].kill()
                    events["killed"] = i
                if i == 10:
                    srv["p"] = _serve(small_site, small_site_db, router, "w2")  # a server returns
                if i >= 11 and "back" not in events:
                    assert wait_until(lambda: "w2" in cl.servers, 60)
                    events["back"] = i

            local.i = s.idx[0]
            out = tmp_path / "traj.txt"
            traj, st = stream_sequence(s, cl, fb, out, on_frame=on_frame)
    finally:
        stop(srv["p"], kill=True)
    src = [r[1] for r in st.rows]
    rtt = [r[4] for r in st.rows]
    assert src[:5] == ["server"] * 5, st.rows
    assert src[5] == "local" and rtt[5] < deadline + 300, st.rows  # the very next frame: local, within one deadline
    assert all(x == "local" for x in src[5:11]), st.rows
    assert src[-1] == "server" and "server" in src[12:], st.rows  # handed back to the returned server
    assert len(traj) == len(s) and local.seeds >= 6
    lines = sources_path(out).read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == len(s) + 1 and lines[6].split()[1] == "local"
    assert len(read_tum(out)) == len(s)
    picture = out.with_suffix(".png")  # the poses from above, the local fallback's marked
    assert st.picture == picture and red_pixels(picture) > 100 and pixels_of(picture, LOCAL_COLOR) > 20


def test_serve_and_stream_commands(small_site, small_site_db, tmp_path):
    """`cristal serve` listening itself (no router) and `cristal stream` writing the trajectory and the sources."""
    from _zenoh import summary

    from services.io.trajectory import read_tum

    port = free_port()
    p = cristal("serve", small_site[0] / "scan.ply", "--db", small_site_db, "--listen", endpoint(port), "--server-id", "solo",
                "--device", "cpu")
    try:
        out = tmp_path / "t.txt"
        s = cristal("stream", small_site[0] / "seq_00", "--out", out, "--connect", endpoint(port), "--frames", "5",
                    "--deadline", "3000", "--wait", "60")
        o, e = s.communicate(timeout=120)
        assert s.returncode == 0, e
        sm = summary(o)
        assert sm["frames"] == 5 and sm["server"] >= 4 and sm["poses"] == len(read_tum(out))
        rows = [line.split() for line in (tmp_path / "t.sources.txt").read_text().splitlines()[1:]]
        assert len(rows) == 5 and rows[0][1] == "server" and rows[0][3] == "solo"
    finally:
        o, e = stop(p)
    assert summary(o)["frames"] >= 5
