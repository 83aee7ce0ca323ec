"""Messages of the cristal localization service (protocol version 1): the API document.

Every message is a pydantic model, encoded as a msgpack map by :mod:`protocol.codec` (which adds
``"v"``, the protocol version, and ``"t"``, the message type). Field names are short enough to
read in a capture and stable: new optional fields may be added within a version; renaming or
removing one bumps :data:`protocol.PROTOCOL_VERSION`.

Conventions (``docs/CONVENTIONS.md``):

- A pose is **camera-to-world** ``T_wc`` in the scan's metric frame, as ``tx ty tz qx qy qz qw``
  (Hamilton quaternion, scalar last): :class:`PoseMsg`. ``t`` is the camera centre in the world.
- Intrinsics are OpenCV pinhole + ``[k1, k2, p1, p2, k3]`` distortion, pixel centres at integer
  coordinates: :class:`Intrinsics`. They travel with **every** frame; a client may change
  resolution or zoom between frames.

Request/reply (key ``cristal/<site>/<map>/frame/<client>/<server>``, see :mod:`protocol.keys`)::

    client ── FrameRequest ──► server
    client ◄── PoseReply ───── server     (also published on cristal/<site>/<map>/pose/<client>)

:class:`FrameRequest`: client id, sequence number, capture time, the image (JPEG, PNG, or raw
8-bit grayscale), intrinsics, an optional pose prior, an optional relative motion from the
device's own odometry, a reset flag and a deadline.

:class:`PoseReply`: the frame's sequence number and a :class:`Status`:

========== ==============================================================================
tracking    pose from tracking against the scan
relocalized pose from relocalization (first frame, after lost, after reset)
lost        the frame was processed but no pose passed the quality gates; ``pose`` is None and ``reason``
            says why when the server knows (e.g. "ambiguous place: ...": a repetitive site, where a
            ``prior`` lets it track; "pose too uncertain to report ...": a blurred or feature-poor frame)
dropped     the server skipped this frame: a newer frame of the same client superseded it
            (latest frame wins) or its deadline had passed; ``error`` says which. Not a fault.
rejected    the request was invalid (``error`` + ``reason`` say why); the client must fix it
========== ==============================================================================

Quality: ``inliers``, ``rmse_px`` (inlier reprojection RMSE), ``sigma_m`` / ``sigma_deg`` (predicted
1-sigma camera-centre and orientation uncertainty from the inlier geometry, scaled up with the frame's
motion blur, under which matches err more than their scatter shows), ``source`` (what solved a reported pose:
``features``, matched keypoints; ``direct``, image patches aligned to the render or map; ``fused``, both), ``timings`` (ms per
server stage that ran for the frame: ``decode_ms``, ``queue_ms``, ``direct_ms`` (tracked by patch alignment, no
features on the frame), ``features_ms``, ``render_ms``, ``match_ms``, ``pose_ms``, ``relocalize_ms``,
``total_ms``), ``server_id`` and ``map_id``.
"""

from __future__ import annotations

import math
from enum import Enum

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

__all__ = ["ImageEncoding", "Status", "ErrorCode", "Intrinsics", "PoseMsg", "FrameRequest", "PoseReply",
           "MapBundleInfo", "BundleChunk", "SiteInfo", "Health", "MESSAGE_TYPES", "MAX_IMAGE_SIDE", "reason_kind"]

MAX_IMAGE_SIDE = 8192  # pixels; bigger frames are rejected (intrinsics and decoded images alike)


class _Msg(BaseModel):
    model_config = ConfigDict(extra="ignore", frozen=True, ser_json_inf_nan="constants")


class ImageEncoding(str, Enum):
    JPEG = "jpeg"
    PNG = "png"
    GRAY8 = "gray8"  # raw 8-bit grayscale, row-major, exactly width*height bytes (width/height from intrinsics)


class Status(str, Enum):
    TRACKING = "tracking"
    RELOCALIZED = "relocalized"
    LOST = "lost"
    DROPPED = "dropped"
    REJECTED = "rejected"

    @property
    def has_pose(self) -> bool:
        return self in (Status.TRACKING, Status.RELOCALIZED)


class ErrorCode(str, Enum):
    """Why a frame was rejected (or dropped). ``reason`` in the reply is the human-readable detail."""

    MALFORMED = "malformed"  # not msgpack, not a map, or fields of the wrong type
    VERSION = "version"  # protocol version the server does not speak
    TOO_LARGE = "too_large"  # payload over the size limit
    BAD_IMAGE = "bad_image"  # image bytes that do not decode, or whose size disagrees with the intrinsics
    BAD_INTRINSICS = "bad_intrinsics"  # zero/negative/NaN focal length, absurd principal point, ...
    UNKNOWN_MAP = "unknown_map"  # the frame names a map this server does not serve
    CLIENT_MISMATCH = "client_mismatch"  # client id in the message differs from the one in the key
    OVERLOADED = "overloaded"  # too many clients on this server; try another worker
    SUPERSEDED = "superseded"  # (dropped) a newer frame of the same client arrived before this one started
    DEADLINE = "deadline"  # (dropped) the frame's deadline passed before the server could start it
    INTERNAL = "internal"  # a server fault; the server logged it and keeps serving


class Intrinsics(_Msg):
    """OpenCV pinhole intrinsics of one frame (the ``camera.json`` fields)."""

    width: int = Field(gt=0, le=MAX_IMAGE_SIDE)
    height: int = Field(gt=0, le=MAX_IMAGE_SIDE)
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: list[float] = Field(default_factory=lambda: [0.0] * 5, max_length=5)

    @model_validator(mode="after")
    def _sane(self) -> "Intrinsics":
        vals = (self.fx, self.fy, self.cx, self.cy, *self.distortion)
        if not all(math.isfinite(v) for v in vals):
            raise ValueError("intrinsics must be finite numbers")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        return self

    def to_camera_dict(self) -> dict:
        d = self.model_dump()
        d["distortion"] = list(self.distortion) + [0.0] * (5 - len(self.distortion))
        return d


class PoseMsg(_Msg):
    """A rigid transform ``tx ty tz qx qy qz qw`` (Hamilton, scalar last). Camera-to-world unless stated."""

    tx: float
    ty: float
    tz: float
    qx: float
    qy: float
    qz: float
    qw: float

    @model_validator(mode="after")
    def _finite_unit(self) -> "PoseMsg":
        v = (self.tx, self.ty, self.tz, self.qx, self.qy, self.qz, self.qw)
        if not all(math.isfinite(x) for x in v):
            raise ValueError("pose must be finite numbers")
        n = math.sqrt(self.qx ** 2 + self.qy ** 2 + self.qz ** 2 + self.qw ** 2)
        if not 0.9 < n < 1.1:
            raise ValueError(f"pose quaternion must be unit, has norm {n:.3g}")
        return self

    def as_tum(self) -> list[float]:
        return [self.tx, self.ty, self.tz, self.qx, self.qy, self.qz, self.qw]

    @classmethod
    def from_tum(cls, v) -> "PoseMsg":
        v = [float(x) for x in v]
        return cls(tx=v[0], ty=v[1], tz=v[2], qx=v[3], qy=v[4], qz=v[5], qw=v[6])


class NearMsg(_Msg):
    """Where a camera is, roughly: within ``radius_m`` of world (``x``, ``y``, ``z``) (a dock, an entrance, a robot's
    own estimate)."""

    x: float
    y: float
    z: float
    radius_m: float = Field(gt=0.0, le=10_000.0)

    @model_validator(mode="after")
    def _finite(self) -> "NearMsg":
        if not all(math.isfinite(v) for v in (self.x, self.y, self.z)):
            raise ValueError("near: position must be finite numbers")
        return self


class FrameRequest(_Msg):
    """One camera frame to localize.

    - ``client``: the client's id (``[A-Za-z0-9_-]``, also the last-but-one chunk of the key; they must agree).
    - ``seq``: strictly increasing per client; replies carry it back.
    - ``stamp``: capture time in seconds (device clock); ``stamp_text`` the exact text (e.g. from rgb.txt), echoed.
    - ``image`` + ``encoding``: JPEG or PNG bytes (colour or gray), or raw gray8 of ``intrinsics.width*height`` bytes.
    - ``intrinsics``: of this frame (must match the decoded image's size).
    - ``prior``: optional camera-to-world pose hint (e.g. the client's own last pose when it moves to a new worker).
      A frame the server skips hands its prior to the next frame it tracks (moved on by the motions sent since).
    - ``motion``: optional relative motion since the previous frame from the device's odometry, as
      ``T_prev_cur`` (the current camera in the previous camera's frame). The server predicts
      ``T_wc = T_wc_prev @ motion`` when it has a previous pose, and after a LOST frame carries that pose on
      with it for a few seconds (unreported), so tracking resumes without a relocalization. Send every frame's
      motion since the frame sent before it, whatever the server answered: the server composes the motions of the
      frames it skips (latest frame wins, deadlines) in front of the next one it tracks.
    - ``exposure_s``: optional exposure time of this frame (seconds), when the camera reports it. Fast
      frames are blurred; the server blurs its render to match, with this time if given (otherwise it
      calibrates one per client from the first fast frames).
    - ``readout_s``: optional rolling-shutter readout of the camera (seconds from its first row to its last; phones
      10-30 ms). The server re-samples the frame into its middle row's view from the tracked motion, and reports
      poses (of the middle row, at ``stamp``) once that motion comes from frames it has undone. None or 0: a global
      shutter.
    - ``near``: optional rough position of the camera (:class:`NearMsg`) for when the server has no pose for this
      client: until one is reported, relocalization searches only as far from it as the camera can have moved since
      (3 m/s), so a look-alike place elsewhere (an aisle of identical racks) does not leave the start ambiguous.
      Ignored while the client is tracked.
    - ``reset``: forget this client's state (tracking starts over, by relocalization unless ``prior`` is given). A
      frame the server skips (superseded, past its deadline) hands its reset to the next frame it tracks.
    - ``map``: optional map id the client expects; a server serving another map rejects with ``unknown_map``.
    - ``deadline_ms``: how long the client will wait for the reply; the server drops the frame (``dropped/deadline``)
      if it cannot start it within that budget.
    """

    client: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_\-]+$")
    seq: int = Field(ge=0, lt=2 ** 63)
    stamp: float = 0.0
    stamp_text: str | None = Field(default=None, max_length=64)
    image: bytes = Field(repr=False)
    encoding: ImageEncoding = ImageEncoding.JPEG
    intrinsics: Intrinsics
    prior: PoseMsg | None = None
    motion: PoseMsg | None = None
    exposure_s: float | None = Field(default=None, ge=0.0, le=1.0)
    readout_s: float | None = Field(default=None, ge=0.0, le=0.2)
    near: NearMsg | None = None
    reset: bool = False
    map: str | None = Field(default=None, max_length=64)
    deadline_ms: float | None = Field(default=None, gt=0, le=600_000)

    @field_validator("stamp")
    @classmethod
    def _finite_stamp(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError("stamp must be finite")
        return v


def reason_kind(reason: str | None) -> str:
    """The kind of a LOST reply's ``reason``, for counting: "ambiguous place: 2 places ..." -> "ambiguous place",
    "pose too uncertain to report (0.7 cm ...)" -> "pose too uncertain to report". Reasons keep their numbers
    after the kind, never in it."""
    return (reason or "no reason given").split(":")[0].split(" (")[0]


class PoseReply(_Msg):
    """The answer to one :class:`FrameRequest` (also published for subscribers)."""

    client: str
    seq: int
    status: Status
    stamp: float = 0.0
    stamp_text: str | None = None
    pose: PoseMsg | None = None  # camera-to-world; only with tracking / relocalized
    inliers: int = 0
    rmse_px: float | None = None
    sigma_m: float | None = None
    sigma_deg: float | None = None
    timings: dict[str, float] = Field(default_factory=dict)
    server: str = ""
    map: str = ""
    error: ErrorCode | None = None
    reason: str | None = None
    source: str | None = None  # what solved the pose (only with one): "features", "direct", "fused"

    @model_validator(mode="after")
    def _consistent(self) -> "PoseReply":
        if self.status.has_pose and self.pose is None:
            raise ValueError(f"status {self.status.value} needs a pose")
        if self.status in (Status.REJECTED, Status.DROPPED) and self.error is None:
            raise ValueError(f"status {self.status.value} needs an error code")
        return self


class MapBundleInfo(_Msg):
    """The P&L map bundle a client downloads for its on-device fallback.

    The bundle is an uncompressed tar of the map directory (``map.msg`` + ``config.yaml``), served in
    ``chunk_size`` pieces on ``cristal/<site>/<map>/bundle/chunk/<i>``; ``sha256`` covers the whole
    bundle, each :class:`BundleChunk` carries its own. ``version`` changes whenever the map does.
    """

    map: str
    version: str
    size: int = Field(ge=0)
    sha256: str
    chunk_size: int = Field(gt=0)
    chunks: int = Field(ge=0)
    files: list[str] = Field(default_factory=list)


class BundleChunk(_Msg):
    map: str
    version: str
    index: int = Field(ge=0)
    offset: int = Field(ge=0)
    sha256: str
    data: bytes = Field(repr=False)


class SiteInfo(_Msg):
    """What a server serves: site, map, scan origin (survey offset), bounds, the bundle, limits."""

    site: str
    map: str
    server: str
    protocol: int
    origin: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    bounds_min: list[float] = Field(default_factory=list)
    bounds_max: list[float] = Field(default_factory=list)
    bundle: MapBundleInfo | None = None
    max_request_bytes: int = 0
    backend: str = ""


class Health(_Msg):
    server: str
    site: str
    map: str
    ok: bool
    uptime_s: float
    clients: int
    frames: int
    dropped: int
    rejected: int
    lost: int
    busy: bool = False


MESSAGE_TYPES: dict[str, type[_Msg]] = {
    "frame": FrameRequest,
    "pose": PoseReply,
    "bundle_info": MapBundleInfo,
    "bundle_chunk": BundleChunk,
    "site": SiteInfo,
    "health": Health,
}
