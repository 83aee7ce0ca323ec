"""The wire contract: round trips, versions, limits, typed decode errors (no network)."""

import math

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import PROTOCOL_VERSION, keys
from protocol.codec import MAX_REQUEST_BYTES, DecodeError, decode, encode
from protocol.messages import (ErrorCode, FrameRequest, ImageEncoding, Intrinsics, MapBundleInfo, PoseMsg, PoseReply,
                               Status)

INTR = Intrinsics(width=64, height=48, fx=50, fy=50, cx=31.5, cy=23.5, distortion=[-0.1, 0.01, 0, 0, 0])


def _req(**kw):
    base = dict(client="dev-1", seq=3, stamp=12.5, stamp_text="12.500000", image=b"\xff\xd8jpeg", intrinsics=INTR,
                prior=PoseMsg.from_tum([1, 2, 3, 0, 0, 0, 1]))
    base.update(kw)
    return FrameRequest(**base)


def test_frame_and_reply_round_trip():
    r = _req(encoding=ImageEncoding.GRAY8, reset=True, deadline_ms=80, exposure_s=0.012)
    back = decode(encode(r), FrameRequest)
    assert back == r and back.encoding is ImageEncoding.GRAY8 and back.prior.as_tum() == [1, 2, 3, 0, 0, 0, 1]
    assert back.exposure_s == 0.012 and _req().exposure_s is None
    with pytest.raises(ValueError):
        _req(exposure_s=-0.001)  # an exposure time is never negative (nor over a second)
    rep = PoseReply(client="dev-1", seq=3, status=Status.TRACKING, pose=PoseMsg.from_tum([0, 0, 1, 0, 0, 0, 1]),
                    inliers=120, rmse_px=0.7, timings={"total_ms": 31.0}, server="s1", map="office")
    assert decode(encode(rep), PoseReply) == rep
    rej = PoseReply(client="dev-1", seq=4, status=Status.REJECTED, error=ErrorCode.BAD_IMAGE, reason="no")
    assert decode(encode(rej), PoseReply).error is ErrorCode.BAD_IMAGE
    wire = msgpack.unpackb(encode(rep))
    assert wire["v"] == PROTOCOL_VERSION and wire["t"] == "pose" and wire["status"] == "tracking"


def test_reply_invariants():
    with pytest.raises(ValueError):
        PoseReply(client="a", seq=0, status=Status.TRACKING)  # a pose status without a pose
    with pytest.raises(ValueError):
        PoseReply(client="a", seq=0, status=Status.REJECTED)  # rejected without a code


@pytest.mark.parametrize("data,code", [
    (b"", ErrorCode.MALFORMED),
    (b"\xc1garbage", ErrorCode.MALFORMED),
    (msgpack.packb([1, 2, 3]), ErrorCode.MALFORMED),
    (msgpack.packb({"v": 99, "t": "frame"}), ErrorCode.VERSION),
    (msgpack.packb({"t": "frame", "client": "x"}), ErrorCode.VERSION),
    (msgpack.packb({"v": PROTOCOL_VERSION, "t": "pose"}), ErrorCode.MALFORMED),
    (msgpack.packb({"v": PROTOCOL_VERSION, "t": "frame", "client": "x", "seq": 1}), ErrorCode.MALFORMED),
])
def test_decode_errors_are_typed(data, code):
    with pytest.raises(DecodeError) as e:
        decode(data, FrameRequest)
    assert e.value.code is code and e.value.reason


def test_absurd_intrinsics_and_oversize():
    d = msgpack.unpackb(encode(_req()))
    for bad in ({"fx": 0.0}, {"fy": -3.0}, {"fx": math.nan}, {"width": 0}, {"cx": math.inf}):
        dd = dict(d, intrinsics=dict(d["intrinsics"], **bad))
        with pytest.raises(DecodeError) as e:
            decode(msgpack.packb(dd), FrameRequest)
        assert e.value.code is ErrorCode.BAD_INTRINSICS, bad
        assert e.value.fields == {"client": "dev-1", "seq": 3}
    with pytest.raises(DecodeError) as e:
        decode(encode(_req(image=b"x" * (MAX_REQUEST_BYTES + 1))), FrameRequest, max_bytes=MAX_REQUEST_BYTES)
    assert e.value.code is ErrorCode.TOO_LARGE
    with pytest.raises(DecodeError) as e:
        decode(msgpack.packb(dict(d, client="a/*")), FrameRequest)
    assert e.value.code is ErrorCode.MALFORMED


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=256) | st.builds(lambda d: msgpack.packb(d), st.dictionaries(
    st.sampled_from(["v", "t", "client", "seq", "image", "intrinsics", "prior", "encoding", "stamp"]),
    st.none() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=8) | st.binary(max_size=8)
    | st.dictionaries(st.sampled_from(["width", "height", "fx", "fy", "cx", "cy", "distortion"]),
                      st.integers(-2**63, 2**63 - 1) | st.floats() | st.lists(st.floats(), max_size=6)), max_size=9)))
def test_decoder_only_raises_decode_error(data):
    try:
        m = decode(data, FrameRequest)
    except DecodeError as e:
        assert isinstance(e.code, ErrorCode)
    else:
        assert isinstance(m, FrameRequest)


def test_keys_are_scoped_and_parse():
    k = keys.frame("siteA", "office", "dev-1", "srv0")
    assert k == "cristal/siteA/office/frame/dev-1/srv0"
    assert keys.parse_frame_key(k) == ("siteA", "office", "dev-1", "srv0")
    assert keys.parse_frame_key("cristal/x/frame") is None
    assert keys.parse_server_token(keys.server_token("s", "m", "w1")) == "w1"
    with pytest.raises(ValueError):
        keys.check_id("a/b", "client")
    info = MapBundleInfo(map="m", version="v", size=10, sha256="00", chunk_size=4, chunks=3)
    assert decode(encode(info), MapBundleInfo) == info


def test_reason_kinds_count_alike_reasons_together():
    """LOST reasons are counted by kind (the summaries' lost_reasons): the numbers follow the kind, never sit in it."""
    from protocol.messages import reason_kind

    assert reason_kind("too few inliers in the database: the best place has 22, a pose needs 30") == \
        reason_kind("too few inliers in the database: the best place has 27, a pose needs 12") == "too few inliers in the database"
    assert reason_kind("pose too uncertain to report (0.7 cm / 0.11 deg 1-sigma)") == "pose too uncertain to report"
    assert reason_kind("place out of reach: found 3.1 m from where the camera can be (1.2 m)") == "place out of reach"
    assert reason_kind("ambiguous place: verified at places 2.0 m apart") == "ambiguous place"
    assert reason_kind(None) == "no reason given"
