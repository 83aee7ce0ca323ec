"""The localization server: Zenoh queryables in front of a backend, per-client state, latest frame wins.

One :class:`LocalizationServer` is one worker process's service (several may serve the same site
and map; clients pick one through the liveliness tokens, see :mod:`protocol.keys`).

Flow of a frame::

    zenoh thread: query ─► decode + key checks ─(bad)─► reply rejected (immediately)
                                  │ ok
                                  ▼
                  client slot: at most ONE pending frame; a newer one replaces it and the
                  replaced frame is answered dropped/superseded (latest frame wins)
                                  │
    worker threads: take a client whose slot is full and which no other worker holds
                  ─► deadline passed? ─► reply dropped/deadline
                  ─► decode image, check intrinsics ─(bad)─► reply rejected
                  ─► backend tracker (per client) ─► reply pose/lost, publish on pose/<client>

Work is bounded: per client one frame in flight and one waiting, at most ``max_clients``
clients (a newcomer takes the place of one silent for ``evict_silent_s``, else it is rejected
``overloaded`` so it moves to another worker), and a client idle for ``idle_s`` loses its state.
Errors are values: every request gets exactly one reply and an exception in one client's frame
becomes ``rejected/internal`` for that frame only.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from protocol import PROTOCOL_VERSION, keys
from protocol.codec import MAX_REQUEST_BYTES, DecodeError, decode, encode
from protocol.messages import (MAX_IMAGE_SIDE, BundleChunk, ErrorCode, FrameRequest, Health, ImageEncoding,
                               MapBundleInfo, PoseMsg, PoseReply, SiteInfo, Status)
from services.geometry.camera import Camera, CameraError
from services.geometry.se3 import Pose

__all__ = ["ServerConfig", "LocalizationServer", "decode_image"]

log = logging.getLogger("cristal.server")


def _event(level: int, event: str, **fields) -> None:
    """Structured log line: one JSON object per event (greppable, parseable)."""
    if log.isEnabledFor(level):
        log.log(level, "%s", json.dumps({"event": event, **fields}, default=str, sort_keys=True))


@dataclass
class ServerConfig:
    site: str = keys.DEFAULT_SITE
    map_id: str = keys.DEFAULT_MAP
    server_id: str = ""
    workers: int = 1  # frames processed in parallel (different clients); 1 on a CPU box, more on a GPU
    max_clients: int = 64
    idle_s: float = 60.0  # client state expires after this long without a frame
    evict_silent_s: float = 5.0  # when full, a new client takes the place of the one silent longest, if this long
    #                              (a streaming client sends several frames a second; apps that restart under a new id
    #                              would otherwise lock newcomers out until idle_s). 0: never, newcomers are refused
    max_request_bytes: int = MAX_REQUEST_BYTES
    metrics_port: int = 0  # Prometheus exporter (0: off)
    metrics_addr: str = "127.0.0.1"
    trim_every_s: float = 60.0  # hand the C heap's freed memory back to the system this often (0: never; glibc only)

    def __post_init__(self) -> None:
        if not self.server_id:
            self.server_id = "srv-" + uuid.uuid4().hex[:8]
        for v, what in ((self.site, "site"), (self.map_id, "map id"), (self.server_id, "server id")):
            keys.check_id(v, what)


def _heap_trimmer():
    """``malloc_trim(0)`` of the C library when it is glibc's, else None. A server's images, renders and feature maps
    come and go in many sizes; glibc keeps what they freed, and a tracker fed 3000 frames held 784 MB, 697 MB once
    trimmed (below its size after 300 frames; no Python object grew: benchmarks/RESULTS.md, stop 54). ~0.2 ms a call."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return libc.malloc_trim if hasattr(libc, "malloc_trim") else None
    except OSError:
        return None


class _Rejected(Exception):
    def __init__(self, code: ErrorCode, reason: str):
        super().__init__(reason)
        self.code, self.reason = code, reason


def decode_image(req: FrameRequest) -> np.ndarray:
    """The frame's pixels (gray HxW or BGR HxWx3 uint8), checked against its intrinsics; raises _Rejected."""
    w, h = req.intrinsics.width, req.intrinsics.height
    if req.encoding is ImageEncoding.GRAY8:
        if len(req.image) != w * h:
            raise _Rejected(ErrorCode.BAD_IMAGE, f"gray8 image has {len(req.image)} bytes, intrinsics say {w}x{h} = {w * h}")
        return np.frombuffer(req.image, np.uint8).reshape(h, w)
    buf = np.frombuffer(req.image, np.uint8)
    img = None
    if len(buf) >= 8:
        # refuse decompression bombs before decoding: read the header size first
        ok = _header_size_ok(req.image)
        if not ok:
            raise _Rejected(ErrorCode.BAD_IMAGE, f"image is larger than {MAX_IMAGE_SIDE} pixels on a side")
        try:
            img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        except cv2.error:
            img = None
    if img is None:
        raise _Rejected(ErrorCode.BAD_IMAGE, f"{req.encoding.value} bytes do not decode to an image")
    if img.dtype != np.uint8:
        img = (img / 257).astype(np.uint8) if img.dtype == np.uint16 else img.astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.shape[1] != w or img.shape[0] != h:
        raise _Rejected(ErrorCode.BAD_IMAGE, f"image is {img.shape[1]}x{img.shape[0]} but the intrinsics say {w}x{h}")
    return img


def _header_size_ok(data: bytes) -> bool:
    """Cheap JPEG/PNG header check of the image size (OpenCV would allocate first and ask later)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        w, h = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        return 0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE
    return True  # JPEG: OpenCV's reader limits itself (CV_IO_MAX_IMAGE_PIXELS); other formats are tiny here


def _finite(x) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def _pose(msg) -> Pose | None:
    return Pose.from_tum(msg.as_tum()) if msg is not None else None


@dataclass
class _Carry:
    """What a client's frames that were not tracked (superseded, past their deadline, undecodable) hand to the next
    frame that is. A frame's ``motion`` is since the frame sent before it, so the next tracked frame gets the skipped
    ones' composed in front of its own, in the order they were sent (their ``seq``: a frame may arrive after a newer
    one overtook it on the way); one without a motion breaks the chain (None then). A skipped reset is done, a skipped
    prior is used, carried on by the motions after it. A frame rejected on arrival, before it could be pending
    (bad intrinsics, an undecodable message), hands on nothing. Used under the server's lock."""

    skipped: list = field(default_factory=list)  # (seq, motion | None, reset, prior | None) of each frame not tracked

    def add(self, seq: int, motion: Pose | None, reset: bool, prior: Pose | None) -> None:
        """A frame not tracked (or, from :meth:`take`'s result, a taken one given back: its motion is then since the
        last tracked frame, and every frame skipped before it is in it)."""
        self.skipped.append((seq, motion, reset, prior))

    def take(self, req: FrameRequest) -> tuple[Pose | None, bool, Pose | None]:
        """(motion since the last tracked frame, reset, prior) for ``req``, taken to be tracked; empties the carry."""
        motion, unknown, reset, prior = None, False, False, None
        for _, m, r, p in sorted(self.skipped, key=lambda e: e[0]):
            reset |= r
            if m is None:
                motion, unknown = None, True
            elif not unknown:
                motion = m if motion is None else motion @ m
            if p is not None:
                prior = p
            elif prior is not None and m is not None:
                prior = prior @ m
        self.skipped = []
        own = _pose(req.motion)
        reset = req.reset or reset
        motion = None if unknown or reset or own is None else (own if motion is None else motion @ own)
        if req.prior is not None:
            prior = _pose(req.prior)
        elif prior is not None and own is not None:
            prior = prior @ own
        return motion, reset, prior


@dataclass
class _Client:
    cid: str
    tracker: object
    last_seen: float
    pending: tuple | None = None  # (query, request, camera, t_arrival, decode_ms)
    busy: bool = False
    queued: bool = False
    last_seq: int = -1
    T_last: Pose | None = None
    frames: int = 0
    carry: _Carry = field(default_factory=_Carry)  # what frames not tracked hand to the next that is
    untimed: bool = False  # whether the log has said that its frames come without capture times

    def silent_for(self, now: float) -> float:
        """Seconds since its last frame arrived; -inf while it has a frame in hand (being tracked or waiting)."""
        return float("-inf") if self.busy or self.pending is not None else now - self.last_seen


class LocalizationServer:
    """Serve ``backend`` over a Zenoh session. ``start()`` / ``close()`` (also a context manager)."""

    def __init__(self, backend, cfg: ServerConfig, zenoh_config, bundle_dir: str | Path | None = None):
        self.backend = backend
        self.cfg = cfg
        self.zconf = zenoh_config
        self.bundle = None
        if bundle_dir is not None:
            from services.io.bundle import pack_map_dir

            self.bundle = pack_map_dir(bundle_dir)
        self.clients: dict[str, _Client] = {}
        self.lock = threading.Lock()
        self.ready: queue.Queue = queue.Queue()
        self.stop_evt = threading.Event()
        self.t_start = time.time()
        self.counts = {"frames": 0, "dropped": 0, "rejected": 0, "lost": 0}
        self.session = None
        self._decl: list = []
        self._threads: list[threading.Thread] = []
        self._metrics_http = None
        self._init_metrics()

    # ---- metrics ---------------------------------------------------------------
    def _init_metrics(self) -> None:
        try:
            from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
        except ImportError:  # pragma: no cover - the server extra installs it
            self.m = None
            return
        r = self.registry = CollectorRegistry()
        lbl = ["site", "map", "server"]
        buckets = (0.002, 0.005, 0.01, 0.02, 0.035, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5)
        self.m = {
            "frames": Counter("cristal_frames_total", "frames answered, by status", lbl + ["status"], registry=r),
            "rejected": Counter("cristal_rejected_total", "rejected or dropped frames, by error code", lbl + ["code"], registry=r),
            "latency": Histogram("cristal_frame_seconds", "arrival to reply, per frame", lbl, buckets=buckets, registry=r),
            "stage": Histogram("cristal_stage_seconds", "time per server stage", lbl + ["stage"], buckets=buckets, registry=r),
            "clients": Gauge("cristal_clients", "clients with state on this server", lbl, registry=r),
        }
        self._lbl = dict(site=self.cfg.site, map=self.cfg.map_id, server=self.cfg.server_id)

    def _count(self, status: Status, code: ErrorCode | None = None) -> None:
        with self.lock:
            if status in (Status.DROPPED,):
                self.counts["dropped"] += 1
            elif status is Status.REJECTED:
                self.counts["rejected"] += 1
            else:
                self.counts["frames"] += 1
                if status is Status.LOST:
                    self.counts["lost"] += 1
        if self.m:
            self.m["frames"].labels(**self._lbl, status=status.value).inc()
            if code is not None:
                self.m["rejected"].labels(**self._lbl, code=code.value).inc()

    # ---- lifecycle ---------------------------------------------------------------
    def start(self) -> "LocalizationServer":
        import zenoh

        from services.zconfig import open_session

        c, s = self.cfg, None
        self.session = s = open_session(self.zconf)
        self._decl.append(s.declare_queryable(keys.frame_queryable(c.site, c.server_id), self._on_frame))
        self._decl.append(s.declare_queryable(keys.info(c.site, c.map_id), self._on_info))
        self._decl.append(s.declare_queryable(keys.health(c.site, c.map_id, c.server_id), self._on_health))
        if self.bundle is not None:
            self._decl.append(s.declare_queryable(keys.bundle_queryable(c.site, c.map_id), self._on_bundle))
        for i in range(max(1, c.workers)):
            t = threading.Thread(target=self._worker, name=f"cristal-worker-{i}", daemon=True)
            t.start()
            self._threads.append(t)
        t = threading.Thread(target=self._janitor, name="cristal-janitor", daemon=True)
        t.start()
        self._threads.append(t)
        if c.metrics_port and self.m:
            from prometheus_client import start_http_server

            self._metrics_http = start_http_server(c.metrics_port, addr=c.metrics_addr, registry=self.registry)
        # the liveliness token last: clients discover a worker only once it can answer
        self._decl.append(s.liveliness().declare_token(keys.server_token(c.site, c.map_id, c.server_id)))
        _event(logging.INFO, "server_started", site=c.site, map=c.map_id, server=c.server_id, backend=self.backend.name,
               workers=c.workers, zid=str(s.zid()), metrics_port=c.metrics_port or None,
               bundle=None if self.bundle is None else {"bytes": len(self.bundle.data), "version": self.bundle.version})
        _ = zenoh  # imported for its side effect of failing early when the binding is missing
        return self

    def close(self) -> None:
        self.stop_evt.set()
        for _ in self._threads:
            self.ready.put(None)
        for t in self._threads:
            t.join(timeout=5)
        for d in reversed(self._decl):
            try:
                d.undeclare()
            except Exception:  # noqa: BLE001 - already gone with the session
                pass
        self._decl.clear()
        if self.session is not None:
            self.session.close()
            self.session = None
        if self._metrics_http is not None:
            srv, th = self._metrics_http
            srv.shutdown()
            srv.server_close()
            self._metrics_http = None
        _event(logging.INFO, "server_stopped", server=self.cfg.server_id, **self.counts)

    def __enter__(self) -> "LocalizationServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- replies ---------------------------------------------------------------
    def _reply(self, query, rep: PoseReply, publish: bool = False) -> None:
        data = encode(rep)
        try:
            query.reply(query.key_expr, data)
        except Exception as e:  # noqa: BLE001 - the querier may be gone (timeout); nothing to do
            _event(logging.DEBUG, "reply_failed", client=rep.client, seq=rep.seq, error=str(e))
        finally:
            try:
                query.drop()
            except Exception:  # noqa: BLE001
                pass
        if publish and self.session is not None and rep.client:
            try:
                self.session.put(keys.pose(self.cfg.site, self.cfg.map_id, rep.client), data)
            except Exception as e:  # noqa: BLE001
                _event(logging.WARNING, "publish_failed", client=rep.client, error=str(e))

    def _reject(self, query, client: str, seq: int, status: Status, code: ErrorCode, reason: str,
                stamp: float = 0.0, stamp_text: str | None = None, timings: dict | None = None) -> None:
        rep = PoseReply(client=client, seq=seq, status=status, stamp=stamp, stamp_text=stamp_text, server=self.cfg.server_id,
                        map=self.cfg.map_id, error=code, reason=reason[:500], timings=timings or {})
        self._count(status, code)
        _event(logging.INFO if status is Status.REJECTED else logging.DEBUG, status.value, client=client, seq=seq,
               code=code.value, reason=reason[:200])
        self._reply(query, rep)

    # ---- the frame queryable (zenoh thread: cheap work only) ------------------------
    def _on_frame(self, query) -> None:
        t0 = time.perf_counter()
        try:
            self._admit(query, t0)
        except Exception as e:  # noqa: BLE001 - never let one request take the queryable down
            log.exception("admitting a frame failed")
            self._reject(query, "", 0, Status.REJECTED, ErrorCode.INTERNAL, f"server error: {type(e).__name__}")

    def _admit(self, query, t0: float) -> None:
        parts = keys.parse_frame_key(query.key_expr)
        payload = query.payload
        data = payload.to_bytes() if payload is not None else b""
        key_client = parts[2] if parts else ""
        try:
            req = decode(data, FrameRequest, max_bytes=self.cfg.max_request_bytes)
        except DecodeError as e:
            f = e.fields
            cid = f.get("client") if isinstance(f.get("client"), str) and len(f["client"]) <= 64 else key_client
            seq = f.get("seq") if isinstance(f.get("seq"), int) and 0 <= f["seq"] < 2 ** 63 else 0
            self._reject(query, cid or key_client, seq, Status.REJECTED, e.code, e.reason)
            return
        if parts is None or parts[2] != req.client:
            self._reject(query, req.client, req.seq, Status.REJECTED, ErrorCode.CLIENT_MISMATCH,
                         f"the message is from client {req.client!r} but was sent on key {query.key_expr}")
            return
        map_id = parts[1]
        if map_id != self.cfg.map_id or (req.map is not None and req.map != self.cfg.map_id):
            self._reject(query, req.client, req.seq, Status.REJECTED, ErrorCode.UNKNOWN_MAP,
                         f"map {req.map or map_id!r} is not served here (this server serves {self.cfg.map_id!r})")
            return
        try:
            cam = Camera.from_dict(req.intrinsics.to_camera_dict())
        except CameraError as e:
            self._reject(query, req.client, req.seq, Status.REJECTED, ErrorCode.BAD_INTRINSICS, str(e), req.stamp, req.stamp_text)
            return
        decode_ms = 1e3 * (time.perf_counter() - t0)
        old = None
        with self.lock:
            c = self.clients.get(req.client)
            evicted = None
            if c is None:
                if len(self.clients) >= self.cfg.max_clients:
                    evicted = self._silent_longest(time.time())
                    if evicted is not None:
                        del self.clients[evicted]
                if len(self.clients) >= self.cfg.max_clients:
                    c = None
                else:
                    c = self.clients[req.client] = _Client(req.client, None, time.time())
                    _event(logging.INFO, "client_joined", client=req.client, clients=len(self.clients))
            if c is not None:
                c.last_seen = time.time()
                newest = max(c.last_seq, c.pending[1].seq if c.pending is not None else -1)
                if req.seq <= newest and not req.reset:
                    old = (query, req)  # (out of order: older than a frame tracked or waiting)
                    if req.seq > c.last_seq:
                        # newer than the last tracked frame, overtaken by the waiting one on the way (a client's
                        # threads, the network): its motion belongs in front of those carried to the waiting frame, and
                        # its prior is moved on by them (a reset frame is never overtaken: it always waits)
                        c.carry.add(req.seq, _pose(req.motion), False, _pose(req.prior))
                else:
                    old = c.pending[:2] if c.pending is not None else None
                    if old is not None:
                        c.carry.add(old[1].seq, _pose(old[1].motion), old[1].reset, _pose(old[1].prior))
                    c.pending = (query, req, cam, t0, decode_ms)
                    if not c.busy and not c.queued:
                        c.queued = True
                        self.ready.put(req.client)
        if evicted is not None:
            _event(logging.INFO, "client_evicted", client=evicted, by=req.client,
                   why=f"server full ({self.cfg.max_clients} clients) and it was silent longest")
        if c is None:
            self._reject(query, req.client, req.seq, Status.REJECTED, ErrorCode.OVERLOADED,
                         f"this server already serves {self.cfg.max_clients} clients"
                         + (f", none silent for {self.cfg.evict_silent_s:g} s" if self.cfg.evict_silent_s > 0 else "")
                         + "; use another worker")
            return
        if old is not None:
            q_old, r_old = old
            why = "a newer frame of this client arrived first" if r_old is not req else \
                f"frame {req.seq} is not newer than frame {newest}, already taken or waiting"
            self._reject(q_old, r_old.client, r_old.seq, Status.DROPPED, ErrorCode.SUPERSEDED, why,
                         r_old.stamp, r_old.stamp_text)

    # ---- workers -----------------------------------------------------------------
    def _worker(self) -> None:
        while not self.stop_evt.is_set():
            cid = self.ready.get()
            if cid is None:
                return
            with self.lock:
                c = self.clients.get(cid)
                if c is None or c.pending is None:
                    if c is not None:
                        c.queued = False
                    continue
                query, req, cam, t0, decode_ms = c.pending
                c.pending, c.queued, c.busy = None, False, True
                c.last_seq = max(c.last_seq, req.seq)
                motion, reset, prior = c.carry.take(req)
            try:
                self._process(c, query, req, cam, t0, decode_ms, motion, reset, prior)
            except Exception as e:  # noqa: BLE001 - one bad frame must not stop the worker
                log.exception("frame %s/%s failed", cid, req.seq)
                self._reject(query, req.client, req.seq, Status.REJECTED, ErrorCode.INTERNAL,
                             f"server error while localizing: {type(e).__name__}: {e}")
            finally:
                with self.lock:
                    c.busy = False
                    if c.pending is not None and not c.queued:
                        c.queued = True
                        self.ready.put(cid)

    def _process(self, c: _Client, query, req: FrameRequest, cam: Camera, t0: float, decode_ms: float,
                 motion: Pose | None = None, reset: bool = False, prior: Pose | None = None) -> None:
        """Track one frame of client ``c``; ``motion``, ``reset``, ``prior``: the frame's own with what frames skipped
        before it handed on (:class:`_Carry`)."""
        t_start = time.perf_counter()
        queue_ms = 1e3 * (t_start - t0)
        tm = {"decode_ms": decode_ms, "queue_ms": queue_ms}
        if req.deadline_ms is not None and queue_ms > req.deadline_ms:
            with self.lock:
                c.carry.add(req.seq, motion, reset, prior)
            self._reject(query, req.client, req.seq, Status.DROPPED, ErrorCode.DEADLINE,
                         f"waited {queue_ms:.0f} ms, over the frame's deadline of {req.deadline_ms:.0f} ms",
                         req.stamp, req.stamp_text, tm)
            return
        try:
            t1 = time.perf_counter()
            img = decode_image(req)
            tm["image_ms"] = 1e3 * (time.perf_counter() - t1)
        except _Rejected as e:
            with self.lock:
                c.carry.add(req.seq, motion, reset, prior)
            self._reject(query, req.client, req.seq, Status.REJECTED, e.code, e.reason, req.stamp, req.stamp_text)
            return
        if c.tracker is None:
            c.tracker = self.backend.new_tracker()
        if reset:
            c.tracker.reset()
            c.T_last = None
        if req.stamp <= 0 and not c.untimed:  # (the Python client stamps every frame; another may not)
            c.untimed = True
            _event(logging.WARNING, "no_capture_time", client=req.client,
                   why="frames without a stamp are tracked without a motion model: slower and less sure in fast motion")
        extra = {"readout_s": req.readout_s} if req.readout_s else {}  # (backends from before them need not take them)
        if req.near is not None:
            extra["near"] = ((req.near.x, req.near.y, req.near.z), req.near.radius_m)
        r = c.tracker.process(img, cam, prior, motion, stamp=req.stamp if req.stamp > 0 else None, exposure_s=req.exposure_s,
                              **extra)
        c.T_last = r.T_wc
        c.frames += 1
        tm.update({k: float(v) for k, v in r.timings.items() if k != "total_ms"})
        total = time.perf_counter() - t0
        tm["localize_ms"] = float(r.timings.get("total_ms", 1e3 * (time.perf_counter() - t_start)))
        tm["total_ms"] = 1e3 * total
        status = Status(r.status)
        rep = PoseReply(client=req.client, seq=req.seq, status=status, stamp=req.stamp, stamp_text=req.stamp_text,
                        pose=PoseMsg.from_tum(r.T_wc.to_tum()) if (r.T_wc is not None and status.has_pose) else None,
                        inliers=int(r.inliers), rmse_px=_finite(r.rmse_px), sigma_m=_finite(r.sigma_m),
                        sigma_deg=_finite(r.sigma_deg), timings={k: round(v, 3) for k, v in tm.items()},
                        server=self.cfg.server_id, map=self.cfg.map_id,
                        reason=(getattr(r, "reason", None) or None) if status is Status.LOST else None,
                        source=r.source if status.has_pose else None)
        self._count(status)
        if self.m:
            self.m["latency"].labels(**self._lbl).observe(total)
            for k, v in tm.items():
                if k.endswith("_ms") and k != "total_ms":
                    self.m["stage"].labels(**self._lbl, stage=k[:-3]).observe(v / 1e3)
        self._reply(query, rep, publish=True)
        if status is Status.LOST or c.frames == 1 or status is Status.RELOCALIZED:
            _event(logging.INFO, "frame", client=req.client, seq=req.seq, status=status.value, inliers=rep.inliers,
                   total_ms=round(tm["total_ms"], 1))

    def _silent_longest(self, now: float) -> str | None:
        """The client silent longest, if for at least ``evict_silent_s`` and with no frame in hand (under the lock)."""
        if self.cfg.evict_silent_s <= 0:
            return None
        idle = [(c.last_seen, cid) for cid, c in self.clients.items() if c.silent_for(now) >= self.cfg.evict_silent_s]
        return min(idle)[1] if idle else None

    def _janitor(self) -> None:
        trim = _heap_trimmer() if self.cfg.trim_every_s > 0 else None
        trimmed = time.monotonic()
        while not self.stop_evt.wait(min(1.0, self.cfg.idle_s / 4)):
            now = time.time()
            if trim is not None and time.monotonic() - trimmed >= self.cfg.trim_every_s:
                trim(0)
                trimmed = time.monotonic()
            with self.lock:
                gone = [cid for cid, c in self.clients.items() if c.silent_for(now) > self.cfg.idle_s]
                for cid in gone:
                    del self.clients[cid]
                n = len(self.clients)
            for cid in gone:
                _event(logging.INFO, "client_expired", client=cid, clients=n)
            if self.m:
                self.m["clients"].labels(**self._lbl).set(n)

    # ---- info, health, bundle ------------------------------------------------------
    def site_info(self) -> SiteInfo:
        meta = self.backend.site_meta() if hasattr(self.backend, "site_meta") else {}
        return SiteInfo(site=self.cfg.site, map=self.cfg.map_id, server=self.cfg.server_id, protocol=PROTOCOL_VERSION,
                        bundle=self.bundle_info(), max_request_bytes=self.cfg.max_request_bytes,
                        backend=self.backend.name, **meta)

    def bundle_info(self) -> MapBundleInfo | None:
        b = self.bundle
        if b is None:
            return None
        return MapBundleInfo(map=self.cfg.map_id, version=b.version, size=len(b.data), sha256=b.sha256,
                             chunk_size=b.chunk_size, chunks=b.chunks, files=list(b.files))

    def health(self) -> Health:
        with self.lock:
            n = len(self.clients)
            busy = any(c.busy for c in self.clients.values())
            counts = dict(self.counts)
        return Health(server=self.cfg.server_id, site=self.cfg.site, map=self.cfg.map_id, ok=not self.stop_evt.is_set(),
                      uptime_s=round(time.time() - self.t_start, 3), clients=n, busy=busy, **counts)

    def _answer(self, query, msg) -> None:
        try:
            query.reply(query.key_expr, encode(msg))
        except Exception as e:  # noqa: BLE001
            _event(logging.DEBUG, "reply_failed", key=str(query.key_expr), error=str(e))

    def _on_info(self, query) -> None:
        self._answer(query, self.site_info())

    def _on_health(self, query) -> None:
        self._answer(query, self.health())

    def _on_bundle(self, query) -> None:
        k = str(query.key_expr)
        tail = k.split("/bundle/", 1)[-1]
        if tail == "info":
            self._answer(query, self.bundle_info())
            return
        if tail.startswith("chunk/"):
            try:
                i = int(tail.split("/", 1)[1])
                off, data = self.bundle.chunk(i)
            except (ValueError, IndexError) as e:
                query.reply_err(str(e).encode())
                return
            import hashlib

            self._answer(query, BundleChunk(map=self.cfg.map_id, version=self.bundle.version, index=i, offset=off,
                                            sha256=hashlib.sha256(data).hexdigest(), data=data))
            return
        query.reply_err(f"unknown bundle key {k}".encode())
