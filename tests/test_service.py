"""The localization service over real Zenoh sessions on loopback, with Render & Match on a small site.

Request/reply, publication, site info, health, metrics, map bundle download, latest-frame-wins,
and malformed input (a hypothesis fuzz against the live server)."""

import contextlib
import math
import threading
import time
import urllib.request

import msgpack
import numpy as np
import pytest
from _zenoh import config, endpoint, free_port, wait_until

from protocol import PROTOCOL_VERSION, keys
from protocol.codec import decode, encode
from protocol.messages import ErrorCode, FrameRequest, ImageEncoding, Intrinsics, PoseMsg, PoseReply, Status
from services.io.frame_log import SOURCES

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def rm_backend(small_site, small_site_db):
    import torch

    from services.server.backend import RMBackend

    torch.set_num_threads(1)
    return RMBackend.load(small_site[0] / "scan.ply", small_site_db, device="cpu")


@pytest.fixture(scope="module")
def map_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("pnl")
    (d / "map.msg").write_bytes(np.random.default_rng(1).integers(0, 255, 1_300_000, dtype=np.uint8).tobytes())
    (d / "config.yaml").write_text("Camera:\n  name: test\n")
    return d


@pytest.fixture(scope="module")
def service(rm_backend, map_dir):
    from services.client.client import LocalizationClient
    from services.server.service import LocalizationServer, ServerConfig

    port, mport = free_port(), free_port()
    cfg = ServerConfig(site="lab", map_id="office", server_id="w0", metrics_port=mport, idle_s=30)
    srv = LocalizationServer(rm_backend, cfg, config(listen=[endpoint(port)]), bundle_dir=map_dir).start()
    cl = LocalizationClient(config(connect=[endpoint(port)]), client_id="dev-1", site="lab", map_id="office",
                            deadline_ms=5000)
    try:
        assert cl.wait_for_server(10)
        yield srv, cl, port, mport
    finally:
        cl.close()
        srv.close()


def test_every_client_tracker_shares_the_scan_s_floor_plan(rm_backend):
    """Built once when the backend warms up, not on a client's first relocalization near a recent pose (a 1.3 s
    stall on a 6 M-point scan), and not once per client."""
    assert rm_backend.plan is not None and rm_backend.plan.blocked.any()
    a, b = rm_backend.new_tracker(), rm_backend.new_tracker()
    assert a.t._plan is rm_backend.plan and b.t._plan is rm_backend.plan


def test_request_reply_and_publication(service, small_site):
    from services.client.client import LocalizationClient
    from services.io.sequence import open_sequence

    srv, cl, port, _ = service
    seq = open_sequence(small_site[0] / "seq_00")
    got = []
    sub_sess = __import__("zenoh").open(config(connect=[endpoint(port)]))
    try:
        sub = sub_sess.declare_subscriber(keys.poses("lab"), lambda s: got.append(decode(s.payload.to_bytes(), PoseReply)))
        time.sleep(0.3)
        replies = []
        for i in range(4):
            f = seq.read(i)  # the file's own JPEG bytes, as `cristal stream` sends them
            rep = cl.localize(seq.files[i].read_bytes(), seq.camera, stamp=float(f.stamp), stamp_text=f.stamp)
            replies.append(rep)
        assert replies[0].status is Status.RELOCALIZED  # the first frame has no prior
        assert all(r.status.has_pose for r in replies) and [r.seq for r in replies] == [1, 2, 3, 4]
        for i, r in enumerate(replies):
            dt, dr = seq.groundtruth.poses[i].distance_to(__import__("services.client", fromlist=["x"]).reply_pose(r))
            assert dt < 0.15 and dr < 2.0, (i, dt, dr)  # service test: convention errors would be metres
            assert r.server == "w0" and r.map == "office" and r.inliers >= 40 and r.stamp_text == seq.stamps[i]
            assert r.source in SOURCES, r  # what solved the pose travels with it
            assert r.timings["total_ms"] > 0 and ("features_ms" in r.timings or "direct_ms" in r.timings) and "queue_ms" in r.timings
        assert wait_until(lambda: len(got) == 4, 5), got
        assert [g.seq for g in got] == [1, 2, 3, 4] and got[0].client == "dev-1"
        sub.undeclare()
        # gray8 raw frames and a resolution change between frames (intrinsics travel with each frame)
        g = np.ascontiguousarray(seq.read(4).image.mean(axis=2).astype(np.uint8))
        rep = cl.localize(g.tobytes(), seq.camera, encoding=ImageEncoding.GRAY8)
        assert rep.status.has_pose, rep
        assert rep.stamp > 0  # sent without a stamp: the call's time, so the server's motion model has a clock
        half = seq.camera.scaled(0.5) if hasattr(seq.camera, "scaled") else None
        small = __import__("cv2").resize(seq.read(5).image, (half.width, half.height))
        rep = cl.localize(small, half)
        assert rep.status in (Status.TRACKING, Status.RELOCALIZED, Status.LOST)
        # a second client gets its own state: it relocalizes, it does not inherit dev-1's track
        with LocalizationClient(config(connect=[endpoint(port)]), client_id="dev-2", site="lab", map_id="office",
                                deadline_ms=5000) as c2:
            assert c2.wait_for_server(5)
            assert c2.localize(seq.files[6].read_bytes(), seq.camera).status is Status.RELOCALIZED
        # garbage pixels: lost, not a guess, and the reply says why
        noise = np.random.default_rng(0).integers(0, 255, seq.read(0).image.shape, dtype=np.uint8)
        lost = cl.localize(noise, seq.camera)
        assert lost.status is Status.LOST and lost.pose is None and lost.reason, lost
    finally:
        sub_sess.close()


def test_info_health_metrics_and_bundle(service, map_dir, tmp_path):
    srv, cl, port, mport = service
    info = cl.site_info()
    assert info.site == "lab" and info.map == "office" and info.protocol == PROTOCOL_VERSION and info.backend == "rm"
    assert info.bundle.chunks == 3 and len(info.bounds_min) == 3
    h = cl.health("w0")
    assert h.ok and h.server == "w0" and h.clients >= 1
    d = cl.download_bundle(tmp_path / "cache")
    assert (d / "map.msg").read_bytes() == (map_dir / "map.msg").read_bytes()
    assert (d / "config.yaml").read_text() == (map_dir / "config.yaml").read_text()
    assert cl.download_bundle(tmp_path / "cache") == d  # cached, verified by checksum
    text = urllib.request.urlopen(f"http://127.0.0.1:{mport}/metrics", timeout=5).read().decode()
    assert 'cristal_frames_total{map="office",server="w0",site="lab",status=' in text
    assert "cristal_stage_seconds_bucket" in text and "cristal_clients" in text


@contextlib.contextmanager
def _seen_by_tracker(srv, client: str):
    """The (stamp, prior, motion) each frame of ``client`` reaches its real tracker with, while in the block (the
    tracker is only wrapped to see its arguments)."""
    seen: list = []
    t = srv.clients[client].tracker
    real = t.process

    def spy(image, camera, prior, motion, **kw):
        seen.append((kw.get("stamp"), prior, motion))
        return real(image, camera, prior, motion, **kw)

    t.process = spy
    try:
        yield seen
    finally:
        t.process = real


def _req(client="dev-1", seq=1, **kw):
    d = dict(client=client, seq=seq, image=b"", encoding=ImageEncoding.JPEG,
             intrinsics=Intrinsics(width=200, height=150, fx=150, fy=150, cx=99.5, cy=74.5))
    d.update(kw)
    return FrameRequest(**d)


def test_bad_input_gets_reasoned_rejections(service, small_site):
    import cv2

    from services.io.sequence import open_sequence

    srv, cl, port, _ = service
    seq = open_sequence(small_site[0] / "seq_00")
    jpg = cv2.imencode(".jpg", seq.read(0).image)[1].tobytes()
    good = msgpack.unpackb(encode(_req(client="bad-1", image=jpg)))

    def send(payload, client_key="bad-1"):
        r = cl.request_raw(payload, "w0", 10.0, client_key=client_key)
        assert r is not None, payload[:40]
        return r

    cases = [
        (b"\x00\x01garbage", ErrorCode.MALFORMED),
        (msgpack.packb(dict(good, v=PROTOCOL_VERSION + 1)), ErrorCode.VERSION),
        (b"\x00" * (9 * 1024 * 1024), ErrorCode.TOO_LARGE),
        (msgpack.packb(dict(good, image=b"\xff\xd8\xff not a jpeg")), ErrorCode.BAD_IMAGE),
        (msgpack.packb(dict(good, intrinsics=dict(good["intrinsics"], fx=0.0))), ErrorCode.BAD_INTRINSICS),
        (msgpack.packb(dict(good, intrinsics=dict(good["intrinsics"], fy=-150.0))), ErrorCode.BAD_INTRINSICS),
        (msgpack.packb(dict(good, intrinsics=dict(good["intrinsics"], fx=math.nan))), ErrorCode.BAD_INTRINSICS),
        (msgpack.packb(dict(good, intrinsics=dict(good["intrinsics"], cx=1e6))), ErrorCode.BAD_INTRINSICS),
        (msgpack.packb(dict(good, intrinsics=dict(good["intrinsics"], width=400, height=300))), ErrorCode.BAD_IMAGE),
        (msgpack.packb(dict(good, encoding="gray8", image=b"\x00" * 100)), ErrorCode.BAD_IMAGE),
        (msgpack.packb(dict(good, map="warehouse")), ErrorCode.UNKNOWN_MAP),
    ]
    for k, (payload, code) in enumerate(cases):
        d = msgpack.unpackb(payload) if payload[:1] not in (b"\x00",) else None
        if isinstance(d, dict) and "seq" in d:  # each frame newer than the last (a reused seq is dropped as stale)
            payload = msgpack.packb(dict(d, seq=10 + k))
        r = send(payload)
        assert r.status is Status.REJECTED and r.error is code and r.reason, (k, r)
    # another client's id in the body of my key: refused
    r = send(encode(_req(client="someone-else", seq=50, image=jpg)))
    assert r.error is ErrorCode.CLIENT_MISMATCH
    # a map this server does not serve, in the key
    from services.client.client import LocalizationClient

    with LocalizationClient(config(connect=[endpoint(port)]), client_id="x1", site="lab", map_id="warehouse",
                            deadline_ms=3000) as other:
        r = other.request_raw(encode(_req(client="x1", image=jpg)), "w0", 5.0)
        assert r.status is Status.REJECTED and r.error is ErrorCode.UNKNOWN_MAP
    # and the server still serves a good frame
    assert cl.localize(seq.files[1].read_bytes(), seq.camera, reset=True, prior=seq.groundtruth.poses[1]).status.has_pose


def test_latest_frame_wins(service, small_site):
    """A client sending faster than the server serves gets stale frames dropped, never a backlog."""
    from services.io.sequence import open_sequence

    srv, cl, port, _ = service
    seq = open_sequence(small_site[0] / "seq_00")
    import cv2

    frames = [cv2.imencode(".jpg", seq.read(i).image)[1].tobytes() for i in range(8)]
    results = {}

    def fire(i):
        req = _req(client="burst", seq=i + 1, image=frames[i], intrinsics=Intrinsics(**seq.camera.to_dict()))
        results[i] = cl.request_raw(encode(req), "w0", 20.0, client_key="burst")

    threads = []
    for i in range(8):
        t = threading.Thread(target=fire, args=(i,))
        t.start()
        threads.append(t)
        time.sleep(0.005)
    for t in threads:
        t.join(30)
    st = [results[i].status for i in range(8)]
    assert all(r is not None for r in results.values())
    assert st.count(Status.DROPPED) >= 4, st  # frames 2..7 arrive while 1 is being localized: only the latest survives
    assert results[7].status is not Status.DROPPED  # the newest frame is always served
    assert all(results[i].error is ErrorCode.SUPERSEDED for i in range(8) if st[i] is Status.DROPPED)
    # deadline: a frame that could not start in time is dropped with that reason
    req = _req(client="burst", seq=100, image=frames[0], intrinsics=Intrinsics(**seq.camera.to_dict()), deadline_ms=0.001)
    r = cl.request_raw(encode(req), "w0", 5.0, client_key="burst")
    assert r.status is Status.DROPPED and r.error is ErrorCode.DEADLINE


def test_fuzz_malformed_messages_against_live_server(service, small_site):
    """Thousands of malformed messages: each gets a rejection, then the server still localizes."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    srv, cl, port, _ = service
    base = msgpack.unpackb(encode(_req(client="fz", image=b"\xff\xd8\xff\xe0")))
    field_values = st.none() | st.booleans() | st.integers(-2 ** 63, 2 ** 63 - 1) | st.floats() | st.text(max_size=12) \
        | st.binary(max_size=64) | st.lists(st.floats(), max_size=6)
    intr = st.fixed_dictionaries({}, optional={k: field_values for k in ("width", "height", "fx", "fy", "cx", "cy", "distortion")})
    mutated = st.builds(lambda upd, drop: msgpack.packb({k: v for k, v in {**base, **upd}.items() if k not in drop}),
                        st.dictionaries(st.sampled_from(sorted(base) + ["intrinsics", "prior", "motion"]),
                                        field_values | intr, max_size=4),
                        st.sets(st.sampled_from(sorted(base)), max_size=2))
    payloads = st.binary(max_size=200) | mutated
    n = {"sent": 0}

    @settings(max_examples=1500, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    @given(payloads)
    def run(p):
        r = cl.request_raw(p, "w0", 5.0, client_key="fz")
        n["sent"] += 1
        assert r is not None and r.status in (Status.REJECTED, Status.DROPPED, Status.LOST), r

    run()
    assert n["sent"] >= 1000
    from services.io.sequence import open_sequence

    seq = open_sequence(small_site[0] / "seq_00")
    assert cl.localize(seq.files[2].read_bytes(), seq.camera, reset=True, prior=seq.groundtruth.poses[2]).status.has_pose
    assert srv.health().ok


def test_a_rolling_shutter_declared_per_frame_reaches_the_tracker(service, small_site):
    """``FrameRequest.readout_s`` (a phone's rolling shutter): the server re-samples such frames into their middle
    row's view from the tracked motion and reports poses only once that motion comes from frames it undid, so a new
    client's first frames are answered LOST with that reason, then tracked (here a global-shutter walk, so the poses
    that follow are as good as ever)."""
    from services.client import reply_pose
    from services.client.client import LocalizationClient
    from services.io.sequence import open_sequence

    srv, cl, port, _ = service
    seq = open_sequence(small_site[0] / "seq_00")
    with LocalizationClient(config(connect=[endpoint(port)]), client_id="phone-1", site="lab", map_id="office",
                            deadline_ms=5000) as phone:
        assert phone.wait_for_server(5)
        reps = [phone.localize(seq.files[i].read_bytes(), seq.camera, stamp=float(seq.stamps[i]), readout_s=0.02)
                for i in range(6)]
    assert reps[0].status is Status.LOST and reps[0].reason.startswith("rolling shutter not undone yet"), reps[0]
    assert reps[-1].status.has_pose, reps[-1]
    dt, dr = seq.groundtruth.poses[5].distance_to(reply_pose(reps[-1]))
    assert dt < 0.05 and dr < 1.0, (dt, dr)


def test_a_hint_of_where_the_client_starts_reaches_the_tracker(service, small_site):
    """``FrameRequest.near``: a client that says it starts 30 m from anywhere the frame fits gets LOST, not the place
    the database would give; without the hint the same frame relocalizes; a hint with no radius is rejected."""
    from services.client import reply_pose
    from services.client.client import LocalizationClient
    from services.io.sequence import open_sequence

    srv, cl, port, _ = service
    seq = open_sequence(small_site[0] / "seq_00")
    G = seq.groundtruth.poses[3]
    with LocalizationClient(config(connect=[endpoint(port)]), client_id="robot-1", site="lab", map_id="office",
                            deadline_ms=5000) as robot:
        assert robot.wait_for_server(5)
        frame = seq.files[3].read_bytes()
        far = robot.localize(frame, seq.camera, stamp=1.0, near=((G.t[0] + 30.0, G.t[1], G.t[2]), 1.0))
        assert far.status is Status.LOST and far.reason, far
        ok = robot.localize(frame, seq.camera, stamp=2.0, reset=True, near=(tuple(G.t), 2.0))
        assert ok.status.has_pose and G.distance_to(reply_pose(ok))[0] < 0.05, ok
        with pytest.raises(ValueError, match="radius_m"):
            robot.localize(frame, seq.camera, near=(tuple(G.t), 0.0))


def test_the_odometry_of_frames_the_server_skipped_reaches_the_next_tracked_frame(service, small_site):
    """A frame's ``motion`` is since the frame sent before it. Under load the server skips frames (latest frame wins,
    deadlines): the next frame it tracks must get the motion from the last tracked frame, the skipped ones' composed
    in front of its own, or the tracker predicts from a fraction of the motion and its odometry check turns it off.
    Real server and tracker; the client's tracker is wrapped only to see the motion it is given."""
    import cv2

    from protocol.messages import PoseMsg
    from services.io.sequence import open_sequence

    srv, cl, port, _ = service
    seq = open_sequence(small_site[0] / "seq_00")
    gt = seq.groundtruth.poses
    intr = Intrinsics(**seq.camera.to_dict())
    jpg = [cv2.imencode(".jpg", seq.read(i).image)[1].tobytes() for i in range(12)]

    def req(i, **kw):  # frame i with the true motion since frame i-1, as a device's odometry gives it
        m = gt[i - 1].inverse() @ gt[i]
        return _req(client="odo", seq=i, image=jpg[i], intrinsics=intr, stamp=float(seq.stamps[i]),
                    motion=PoseMsg.from_tum(m.to_tum()), **kw)

    assert cl.request_raw(encode(req(1)), "w0", 20.0, client_key="odo").status.has_pose
    results = {}
    with _seen_by_tracker(srv, "odo") as seen:

        def fire(i, **kw):
            results[i] = cl.request_raw(encode(req(i, **kw)), "w0", 20.0, client_key="odo")

        def other():  # another client's first frame (a cold relocalization) keeps the server's one worker busy
            results["other"] = cl.request_raw(encode(_req(client="other", seq=1, image=jpg[0], intrinsics=intr)), "w0",
                                              20.0, client_key="other")

        threads = [threading.Thread(target=other)]
        threads[0].start()
        time.sleep(0.02)
        for i in range(2, 9):  # 2..7 arrive while the worker is busy: superseded, in order, by 8
            threads.append(threading.Thread(target=fire, args=(i,)))
            threads[-1].start()
            time.sleep(0.002)
        for th in threads:
            th.join(30)
        fire(9, deadline_ms=0.001)  # taken, but past its deadline
        fire(10)
    assert results.pop("other").status is not Status.DROPPED
    st = {i: results[i].status for i in results}
    assert st[9] is Status.DROPPED and results[9].error is ErrorCode.DEADLINE, st
    assert sum(s is Status.DROPPED and results[i].error is ErrorCode.SUPERSEDED for i, s in st.items()) >= 3, st
    tracked = [i for i in sorted(results) if st[i] is not Status.DROPPED]
    assert tracked[-1] == 10 and len(seen) == len(tracked), (tracked, seen)
    stamp_to_i = {float(seq.stamps[i]): i for i in range(12)}
    prev = 1
    for stamp, _, motion in seen:
        i = stamp_to_i[stamp]
        want = gt[prev].inverse() @ gt[i]  # from the last tracked frame, whatever was skipped between
        assert motion is not None, i
        dt, dr = want.distance_to(motion)
        assert dt < 1e-6 and dr < 1e-4, (prev, i, dt, dr)
        prev = i
    assert prev == 10


def test_the_odometry_of_a_frame_overtaken_on_the_way_reaches_the_next_tracked_frame(service, small_site):
    """Frames 3, 2, 4 arrive in that order while the worker is busy (a client's threads, the network): 2 is older than
    the waiting 3 and is dropped, but its motion (since 1, the last tracked) is what 3's and 4's are composed after, so
    frame 4 is tracked with the motion since frame 1. Dropped with it, 4 would be predicted a frame's motion short.
    Frame 2 also carries a prior (where the device knows it was): it reaches frame 4 moved on by 3's and 4's motions."""
    import cv2

    from protocol.messages import PoseMsg
    from services.io.sequence import open_sequence

    srv, cl, port, _ = service
    seq = open_sequence(small_site[0] / "seq_00")
    gt = seq.groundtruth.poses
    intr = Intrinsics(**seq.camera.to_dict())
    jpg = [cv2.imencode(".jpg", seq.read(i).image)[1].tobytes() for i in range(6)]

    def req(i):
        return _req(client="late", seq=i, image=jpg[i], intrinsics=intr, stamp=float(seq.stamps[i]),
                    motion=PoseMsg.from_tum((gt[i - 1].inverse() @ gt[i]).to_tum()),
                    prior=PoseMsg.from_tum(gt[i].to_tum()) if i == 2 else None)

    assert cl.request_raw(encode(req(1)), "w0", 20.0, client_key="late").status.has_pose
    results = {}
    with _seen_by_tracker(srv, "late") as seen:

        def fire(i):
            results[i] = cl.request_raw(encode(req(i)), "w0", 20.0, client_key="late")

        def other(k):  # cold relocalizations of three other clients, queued first, keep the one worker busy meanwhile
            results[f"other{k}"] = cl.request_raw(encode(_req(client=f"late-other{k}", seq=1, image=jpg[k],
                                                              intrinsics=intr)), "w0", 20.0, client_key=f"late-other{k}")

        threads = []
        for k in range(3):
            threads.append(threading.Thread(target=other, args=(k,)))
            threads[-1].start()
            time.sleep(0.01)
        for i in (3, 2, 4):
            threads.append(threading.Thread(target=fire, args=(i,)))
            threads[-1].start()
            time.sleep(0.04)
        for th in threads:
            th.join(30)
    for k in range(3):
        results.pop(f"other{k}")
    assert results[2].status is Status.DROPPED and results[3].status is Status.DROPPED, results
    assert results[4].status is not Status.DROPPED and len(seen) == 1, (results, seen)
    dt, dr = (gt[1].inverse() @ gt[4]).distance_to(seen[0][2])
    assert dt < 1e-6 and dr < 1e-4, (dt, dr)
    assert seen[0][1] is not None, "frame 2's prior was lost with it"
    dt, dr = gt[4].distance_to(seen[0][1])
    assert dt < 1e-6 and dr < 1e-4, (dt, dr)


def test_a_streamed_frame_after_unreadable_ones_carries_their_odometry(small_site):
    """`cristal stream` does not send a frame whose file is missing or broken: the next frame's motion is since the
    last frame sent (the unsent ones' composed in front of its own), unknown if any of them had none."""
    from services.client.stream import _since_last_sent
    from services.io.sequence import open_sequence

    gt = open_sequence(small_site[0] / "seq_00").groundtruth.poses
    m = [gt[i - 1].inverse() @ gt[i] for i in range(1, 5)]  # motions into frames 1..4
    dt, dr = (gt[0].inverse() @ gt[4]).distance_to(_since_last_sent(m[:3], m[3]))  # frames 1-3 unsent
    assert dt < 1e-9 and dr < 1e-6
    assert _since_last_sent([], m[3]) is m[3]
    assert _since_last_sent([m[0], None], m[3]) is None and _since_last_sent([m[0]], None) is None


def test_a_reset_asked_by_a_frame_the_server_skipped_is_done_by_the_next(service, small_site):
    """A client that asks for a reset (it was moved, its odometry restarted) must get one even when the server, busy,
    supersedes that frame with the next: the next frame starts from the database, not from the old track."""
    import cv2

    from services.io.sequence import open_sequence

    srv, cl, port, _ = service
    seq = open_sequence(small_site[0] / "seq_00")
    intr = Intrinsics(**seq.camera.to_dict())
    jpg = [cv2.imencode(".jpg", seq.read(i).image)[1].tobytes() for i in range(6)]

    def send(cid, i, **kw):
        return cl.request_raw(encode(_req(client=cid, seq=i, image=jpg[i], intrinsics=intr, stamp=float(seq.stamps[i]), **kw)),
                              "w0", 20.0, client_key=cid)

    for i in (1, 2):
        assert send("rst", i).status.has_pose
    assert send("rst", 3).status is Status.TRACKING  # the track holds without a reset
    results = {}
    busy = threading.Thread(target=lambda: results.update(other=send("other-cold", 0)))  # a cold frame keeps the worker busy
    busy.start()
    time.sleep(0.02)
    t4 = threading.Thread(target=lambda: results.update({4: send("rst", 4, reset=True)}))
    t4.start()
    time.sleep(0.005)
    results[5] = send("rst", 5)
    t4.join(30)
    busy.join(30)
    assert results[4].status is Status.DROPPED and results[4].error is ErrorCode.SUPERSEDED, results[4]
    assert results[5].status is Status.RELOCALIZED, results[5]  # the reset was done: a relocalization, not tracking


def test_a_prior_sent_with_a_frame_the_server_skipped_reaches_the_next_tracked_frame(service, small_site):
    """A client moving to another worker (or told where it is) sends a prior once: if the busy server supersedes that
    frame, the next frame it tracks starts from the prior, carried on by the odometry since, not from the database."""
    import cv2

    from protocol.messages import PoseMsg
    from services.io.sequence import open_sequence

    srv, cl, port, _ = service
    seq = open_sequence(small_site[0] / "seq_00")
    gt = seq.groundtruth.poses
    intr = Intrinsics(**seq.camera.to_dict())
    jpg = [cv2.imencode(".jpg", seq.read(i).image)[1].tobytes() for i in range(8)]

    def send(cid, i, **kw):
        m = PoseMsg.from_tum((gt[i - 1].inverse() @ gt[i]).to_tum()) if i else None
        return cl.request_raw(encode(_req(client=cid, seq=i, image=jpg[i], intrinsics=intr, stamp=float(seq.stamps[i]),
                                          motion=m, **kw)), "w0", 20.0, client_key=cid)

    assert send("pri", 1).status.has_pose
    results = {}
    with _seen_by_tracker(srv, "pri") as seen:
        busy = threading.Thread(target=lambda: results.update(other=send("other-cold-2", 0)))
        busy.start()
        time.sleep(0.02)
        th = [threading.Thread(target=lambda i=i, kw=kw: results.update({i: send("pri", i, **kw)}))
              for i, kw in ((2, {"reset": True, "prior": PoseMsg.from_tum(gt[2].to_tum())}), (3, {}), (4, {}))]
        for x in th:
            x.start()
            time.sleep(0.003)
        for x in th + [busy]:
            x.join(30)
    assert [results[i].status for i in (2, 3)] == [Status.DROPPED, Status.DROPPED], results
    assert len(seen) == 1 and seen[0][0] == float(seq.stamps[4]) and seen[0][1] is not None, seen
    dt, dr = gt[4].distance_to(seen[0][1])  # frame 2's prior, moved by the motions of frames 3 and 4
    assert dt < 1e-6 and dr < 1e-4, (dt, dr)
    assert results[4].status is Status.TRACKING, results[4]  # from the prior: no relocalization


def test_a_full_server_gives_a_long_silent_client_s_place_to_a_newcomer(rm_backend, small_site):
    """max_clients held: a newcomer is refused while every client is streaming, and takes the place of the one
    silent longest once it has been silent evict_silent_s (a device that restarted under a new id, a headset put
    down), instead of waiting idle_s for it to expire."""
    from services.client.client import LocalizationClient
    from services.io.sequence import open_sequence
    from services.server.service import LocalizationServer, ServerConfig

    seq = open_sequence(small_site[0] / "seq_00")
    jpg, intr = seq.files[0].read_bytes(), Intrinsics(**seq.camera.to_dict())
    port = free_port()
    cfg = ServerConfig(site="lab", map_id="office", server_id="full", max_clients=2, idle_s=60, evict_silent_s=4.0)
    srv = LocalizationServer(rm_backend, cfg, config(listen=[endpoint(port)])).start()
    clients = {cid: LocalizationClient(config(connect=[endpoint(port)]), client_id=cid, site="lab", map_id="office",
                                       deadline_ms=10000) for cid in ("a", "b", "c")}
    seqs = dict.fromkeys(clients, 0)
    prior = PoseMsg.from_tum(seq.groundtruth.poses[0].to_tum())  # (tracked, not relocalized: quick)

    def send(cid):
        seqs[cid] += 1
        req = FrameRequest(client=cid, seq=seqs[cid], image=jpg, intrinsics=intr, prior=prior, reset=True)
        return clients[cid].request_raw(encode(req), "full", 20.0)

    try:
        assert all(cl.wait_for_server(10) for cl in clients.values())
        assert send("a").error is None and send("b").error is None
        r = send("c")  # both just spoke
        assert r.status is Status.REJECTED and r.error is ErrorCode.OVERLOADED and "2 clients" in r.reason
        time.sleep(2.5)
        assert send("b").error is None  # b speaks again: a is now the one silent longest
        time.sleep(2.0)
        r = send("c")  # a silent over 4 s (b maybe too, if the box is slow, but a longer): a's place
        assert r.error is None, r
        assert set(srv.clients) == {"b", "c"}
        assert clients["a"].health("full").clients == 2
    finally:
        for cl in clients.values():
            cl.close()
        srv.close()
