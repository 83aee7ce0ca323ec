"""The client library: send frames to a cristal server over Zenoh, get poses back (no torch).

::

    from services.client import LocalizationClient
    with LocalizationClient(client_id="hmd-7", site="default", map_id="default") as cl:
        reply = cl.localize(jpeg_bytes, camera, stamp=t)        # a PoseReply, or None on deadline / no server
        if reply and reply.status.has_pose: T_wc = reply_pose(reply)

Worker choice: the client watches the servers' liveliness tokens
(``cristal/<site>/<map>/server/*``) and sticks to one worker, chosen by rendezvous hashing of
its id (so many clients spread over the workers and each keeps its own). When that worker's
token disappears (process died, network cut) or it answers ``overloaded``, the client moves to
another live worker and sends its last server pose as the prior, so the new worker tracks
instead of relocalizing.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
import uuid
from pathlib import Path

import numpy as np

from protocol import keys
from protocol.codec import DecodeError, decode, encode
from protocol.messages import (BundleChunk, ErrorCode, FrameRequest, Health, ImageEncoding, Intrinsics, MapBundleInfo,
                               NearMsg, PoseMsg, PoseReply, SiteInfo, Status)
from services.geometry.camera import Camera
from services.geometry.se3 import Pose

__all__ = ["LocalizationClient", "reply_pose", "encode_image", "intrinsics_of"]

log = logging.getLogger("cristal.client")


def reply_pose(rep: PoseReply | None) -> Pose | None:
    """The camera-to-world pose of a reply, or None."""
    if rep is None or rep.pose is None or not rep.status.has_pose:
        return None
    return Pose.from_tum(rep.pose.as_tum())


def intrinsics_of(camera: Camera) -> Intrinsics:
    return Intrinsics(**camera.to_dict())


def encode_image(image: np.ndarray, fmt: str = "jpeg", quality: int = 90) -> tuple[bytes, ImageEncoding]:
    """Compress a BGR or gray uint8 frame for the wire."""
    import cv2

    if fmt == "gray8":
        g = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return np.ascontiguousarray(g).tobytes(), ImageEncoding.GRAY8
    if fmt == "png":
        ok, buf = cv2.imencode(".png", image)
        return buf.tobytes(), ImageEncoding.PNG
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes(), ImageEncoding.JPEG


def _score(client: str, server: str) -> int:
    return int.from_bytes(hashlib.blake2b(f"{client}|{server}".encode(), digest_size=8).digest(), "big")


class LocalizationClient:
    """One device's connection to the service. Thread-safe enough for one streaming thread."""

    def __init__(self, zenoh_config=None, client_id: str | None = None, site: str = keys.DEFAULT_SITE,
                 map_id: str = keys.DEFAULT_MAP, deadline_ms: float = 200.0, session=None):
        from services.zconfig import make_config, open_session

        self.client_id = keys.check_id(client_id or "cl-" + uuid.uuid4().hex[:8], "client id")
        self.site = keys.check_id(site, "site")
        self.map_id = keys.check_id(map_id, "map id")
        self.deadline_ms = float(deadline_ms)
        self._own_session = session is None
        self.session = session if session is not None else open_session(zenoh_config if zenoh_config is not None else make_config())
        self.seq = 0
        self.servers: set[str] = set()
        self.server: str | None = None  # the worker this client sticks to
        self.avoid: dict[str, float] = {}  # server -> until (overloaded)
        self.T_last: Pose | None = None  # last pose a server gave (carried to a new worker as prior)
        self.switches = 0
        self._lock = threading.Lock()
        self._changed = threading.Event()
        import zenoh

        self._PUT = zenoh.SampleKind.PUT
        self._sub = self.session.liveliness().declare_subscriber(keys.server_tokens(self.site, self.map_id), self._on_token,
                                                                 history=True)

    # ---- discovery -----------------------------------------------------------------
    def _on_token(self, sample) -> None:
        sid = keys.parse_server_token(str(sample.key_expr))
        if sid is None:
            return
        with self._lock:
            if sample.kind == self._PUT:
                self.servers.add(sid)
            else:
                self.servers.discard(sid)
                if self.server == sid:
                    log.info("server %s went away", sid)
                    self.server = None
        self._changed.set()

    def wait_for_server(self, timeout: float = 5.0) -> bool:
        """Block until at least one worker is alive (True) or ``timeout`` passes (False)."""
        end = time.monotonic() + timeout
        while True:
            with self._lock:
                if self.servers:
                    return True
            left = end - time.monotonic()
            if left <= 0:
                return False
            self._changed.wait(min(left, 0.05))
            self._changed.clear()

    def pick_server(self) -> str | None:
        with self._lock:
            if self.server in self.servers and self.avoid.get(self.server, 0) <= time.monotonic():
                return self.server
            now = time.monotonic()
            live = [s for s in self.servers if self.avoid.get(s, 0) <= now] or sorted(self.servers)
            if not live:
                return None
            new = max(live, key=lambda s: _score(self.client_id, s))
            if self.server is not None or self.switches or self.seq:
                self.switches += 1
            log.info("client %s uses server %s", self.client_id, new)
            self.server = new
            self._fresh = True
            return new

    # ---- frames --------------------------------------------------------------------
    def localize(self, image: bytes | np.ndarray, camera: Camera, stamp: float | None = None, stamp_text: str | None = None,
                 prior: Pose | None = None, motion: Pose | None = None, reset: bool = False,
                 encoding: ImageEncoding | None = None, deadline_ms: float | None = None,
                 exposure_s: float | None = None, readout_s: float | None = None,
                 near: tuple[tuple[float, float, float], float] | None = None) -> PoseReply | None:
        """Send one frame and wait up to the deadline. None: no live server or no reply in time.

        ``stamp``: the frame's capture time in seconds (any clock, the same for all of a client's frames); None or 0: the
        time of this call, right for a live camera whose frames are sent as they are taken. The server's motion model
        and blur matching run on these times (without any, a 120-frame office walk ran at 5.5 instead of 14.6 FPS,
        0.054 instead of 0.037 deg): replaying a recording, pass its own.
        ``exposure_s``: the frame's exposure time when the camera reports it (the server matches motion blur with it).
        ``readout_s``: the camera's rolling-shutter readout, first row to last (phones; None: a global shutter).
        ``near``: ((x, y, z), radius m): where the camera is, roughly, while the server has no pose for it (a start
        among look-alike places; protocol.messages.NearMsg).
        """
        if not stamp:
            stamp = time.monotonic()
        if isinstance(image, np.ndarray):
            image, encoding = encode_image(image)
        encoding = encoding or ImageEncoding.JPEG
        deadline = float(deadline_ms or self.deadline_ms)
        t_end = time.monotonic() + deadline / 1e3
        for _attempt in range(3):  # another try only when a worker turned us away or vanished
            server = self.pick_server()
            if server is None:
                return None
            p = prior
            if p is None and getattr(self, "_fresh", False) and self.T_last is not None:
                p = self.T_last  # a new worker: carry the last pose over
            self._fresh = False
            left_ms = 1e3 * (t_end - time.monotonic())
            if left_ms <= 1:
                return None
            self.seq += 1
            req = FrameRequest(client=self.client_id, seq=self.seq, stamp=float(stamp), stamp_text=stamp_text, image=image,
                               encoding=encoding, intrinsics=intrinsics_of(camera),
                               prior=PoseMsg.from_tum(p.to_tum()) if p is not None else None,
                               motion=PoseMsg.from_tum(motion.to_tum()) if motion is not None else None,
                               exposure_s=exposure_s, readout_s=readout_s, reset=reset, map=self.map_id,
                               near=NearMsg(x=near[0][0], y=near[0][1], z=near[0][2], radius_m=near[1]) if near else None,
                               deadline_ms=left_ms)
            rep = self.request_raw(encode(req), server, left_ms / 1e3)
            if rep is None:
                # No reply. If the deadline is not spent, nobody answered at all: the worker is gone (its
                # liveliness token may take a moment to vanish). Try another live worker in this same frame.
                with self._lock:
                    others = [s for s in self.servers if s != server and self.avoid.get(s, 0) <= time.monotonic()]
                    if not others or t_end - time.monotonic() < 0.005:
                        return None
                    self.avoid[server] = time.monotonic() + 5.0
                    self.server = None
                log.info("server %s did not answer: trying another worker", server)
                continue
            if rep.status is Status.REJECTED and rep.error is ErrorCode.OVERLOADED:
                with self._lock:
                    self.avoid[server] = time.monotonic() + 10.0
                    self.server = None
                continue
            if rep.status.has_pose:
                self.T_last = reply_pose(rep)
            elif rep.status is Status.LOST:
                self.T_last = None
            return rep
        return None

    def request_raw(self, payload: bytes, server: str | None = None, timeout_s: float | None = None,
                    client_key: str | None = None) -> PoseReply | None:
        """Send raw bytes on this client's frame key (tests and tools); the decoded reply or None."""
        server = server or self.pick_server()
        if server is None:
            return None
        key = keys.frame(self.site, self.map_id, client_key or self.client_id, server)
        return self._get_one(key, payload, timeout_s if timeout_s is not None else self.deadline_ms / 1e3, PoseReply)

    def _get_one(self, key: str, payload: bytes | None, timeout_s: float, cls):
        try:
            replies = self.session.get(key, payload=payload, timeout=max(0.001, timeout_s))
            for r in replies:
                if r.ok is None:
                    continue
                try:
                    return decode(r.ok.payload.to_bytes(), cls)
                except DecodeError as e:
                    log.warning("undecodable %s from %s: %s", cls.__name__, key, e)
        except Exception as e:  # noqa: BLE001 - a closed session or a refused key (ACL): same as no reply
            log.debug("query %s failed: %s", key, e)
        return None

    # ---- site, health, bundle ----------------------------------------------------------
    def site_info(self, timeout_s: float = 2.0) -> SiteInfo | None:
        return self._get_one(keys.info(self.site, self.map_id), None, timeout_s, SiteInfo)

    def health(self, server: str, timeout_s: float = 2.0) -> Health | None:
        return self._get_one(keys.health(self.site, self.map_id, server), None, timeout_s, Health)

    def download_bundle(self, cache_dir: str | Path, timeout_s: float = 30.0) -> Path:
        """Fetch the P&L map bundle (chunk by chunk, each checksummed) into ``cache_dir/<map>-<version>/``."""
        from services.io.bundle import unpack_bundle

        end = time.monotonic() + timeout_s
        info = self._get_one(keys.bundle_info(self.site, self.map_id), None, min(5.0, timeout_s), MapBundleInfo)
        if info is None:
            raise ConnectionError(f"no server answers {keys.bundle_info(self.site, self.map_id)} (is one running with --map?)")
        out = Path(cache_dir) / f"{info.map}-{info.version}"
        if (out / "map.msg").is_file() and (out / ".sha256").is_file() and (out / ".sha256").read_text().strip() == info.sha256:
            return out  # already downloaded and verified
        buf = bytearray(info.size)
        for i in range(info.chunks):
            ch = None
            for _ in range(3):
                ch = self._get_one(keys.bundle_chunk(self.site, self.map_id, i), None, max(0.5, end - time.monotonic()),
                                   BundleChunk)
                if ch is not None and ch.version == info.version and hashlib.sha256(ch.data).hexdigest() == ch.sha256:
                    break
                ch = None
            if ch is None:
                raise ConnectionError(f"map bundle chunk {i}/{info.chunks} did not arrive intact")
            buf[ch.offset: ch.offset + len(ch.data)] = ch.data
        unpack_bundle(bytes(buf), info.sha256, out)
        (out / ".sha256").write_text(info.sha256 + "\n")
        return out

    # ---- lifecycle -----------------------------------------------------------------
    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:  # noqa: BLE001
            pass
        if self._own_session and self.session is not None:
            self.session.close()
            self.session = None

    def __enter__(self) -> "LocalizationClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
