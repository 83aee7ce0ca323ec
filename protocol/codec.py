"""msgpack encoding of :mod:`protocol.messages`, with a protocol version, a type tag and size limits.

On the wire every message is one msgpack map::

    {"v": 1, "t": "frame", ...the model's fields...}

``v`` is :data:`protocol.PROTOCOL_VERSION`; ``t`` one of :data:`protocol.messages.MESSAGE_TYPES`.
Bytes fields (images, bundle chunks) are msgpack ``bin``; there is no base64 anywhere.

Decoding never raises anything but :class:`DecodeError`, whose ``code`` is the
:class:`~protocol.messages.ErrorCode` a server puts in its ``rejected`` reply and whose message is
the human-readable reason. Limits: :data:`MAX_REQUEST_BYTES` for a frame request (a 4K JPEG fits
easily; raw gray8 up to 8 MP), :data:`MAX_MESSAGE_BYTES` for anything else.
"""

from __future__ import annotations

from typing import TypeVar

import msgpack
from pydantic import BaseModel, ValidationError

from protocol import PROTOCOL_VERSION
from protocol.messages import MESSAGE_TYPES, ErrorCode

__all__ = ["encode", "decode", "peek", "DecodeError", "MAX_REQUEST_BYTES", "MAX_MESSAGE_BYTES"]

MAX_REQUEST_BYTES = 8 * 1024 * 1024
MAX_MESSAGE_BYTES = 16 * 1024 * 1024

M = TypeVar("M", bound=BaseModel)
_TYPE_OF = {cls: name for name, cls in MESSAGE_TYPES.items()}


class DecodeError(ValueError):
    """A message that cannot be decoded; ``code`` says which rule it broke, the message why."""

    def __init__(self, code: ErrorCode, reason: str, fields: dict | None = None):
        super().__init__(reason)
        self.code = code
        self.reason = reason
        self.fields = fields or {}  # whatever could be read (client, seq) so a rejection can still be addressed


def encode(msg: BaseModel) -> bytes:
    """One message as msgpack bytes (``v`` and ``t`` added)."""
    d = msg.model_dump(mode="python", exclude_none=True)
    for k, v in list(d.items()):
        if hasattr(v, "value") and not isinstance(v, (bytes, str)):  # enums
            d[k] = v.value
    out = {"v": PROTOCOL_VERSION, "t": _TYPE_OF[type(msg)], **d}
    return msgpack.packb(out, use_bin_type=True, default=_default)


def _default(o):
    if hasattr(o, "value"):
        return o.value
    raise TypeError(f"cannot encode {type(o).__name__}")


def peek(data: bytes) -> dict:
    """The raw map (no validation) or {} — used to address a rejection to the right client/seq."""
    try:
        d = msgpack.unpackb(data, raw=False, strict_map_key=True, max_bin_len=MAX_MESSAGE_BYTES)
        return d if isinstance(d, dict) else {}
    except Exception:  # noqa: BLE001 - peeking is best effort by design
        return {}


def decode(data: bytes | bytearray | memoryview, expect: type[M], max_bytes: int | None = None) -> M:
    """Decode ``data`` as a message of type ``expect``; raises :class:`DecodeError` and nothing else."""
    limit = max_bytes if max_bytes is not None else MAX_MESSAGE_BYTES
    if data is None:
        raise DecodeError(ErrorCode.MALFORMED, "empty payload")
    n = len(data)
    if n > limit:
        raise DecodeError(ErrorCode.TOO_LARGE, f"payload of {n} bytes is over the limit of {limit}")
    if n == 0:
        raise DecodeError(ErrorCode.MALFORMED, "empty payload")
    try:
        d = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, max_bin_len=limit, max_str_len=limit,
                            max_array_len=100_000, max_map_len=10_000)
    except Exception as e:  # noqa: BLE001 - msgpack raises many types (ExtraData, ValueError, UnicodeDecodeError, ...)
        raise DecodeError(ErrorCode.MALFORMED, f"not a msgpack message: {type(e).__name__}") from None
    if not isinstance(d, dict):
        raise DecodeError(ErrorCode.MALFORMED, f"a message is a msgpack map, got {type(d).__name__}")
    fields = {k: d[k] for k in ("client", "seq") if k in d and isinstance(d[k], (str, int)) and not isinstance(d[k], bool)}
    v = d.get("v")
    if v != PROTOCOL_VERSION:
        raise DecodeError(ErrorCode.VERSION, f"protocol version {v!r} is not supported (this side speaks {PROTOCOL_VERSION})",
                          fields)
    want = _TYPE_OF[expect]
    if d.get("t") != want:
        raise DecodeError(ErrorCode.MALFORMED, f"expected a {want!r} message, got {d.get('t')!r}", fields)
    try:
        return expect.model_validate(d)
    except ValidationError as e:
        errs = e.errors(include_url=False, include_input=False)
        first = errs[0] if errs else {}
        loc = ".".join(str(x) for x in first.get("loc", ())) or "message"
        code = ErrorCode.BAD_INTRINSICS if loc.startswith("intrinsics") else ErrorCode.MALFORMED
        reason = f"{loc}: {first.get('msg', 'invalid')}"
        if len(errs) > 1:
            reason += f" (and {len(errs) - 1} more)"
        raise DecodeError(code, reason, fields) from None
    except Exception as e:  # noqa: BLE001 - anything else pydantic may raise on hostile input
        raise DecodeError(ErrorCode.MALFORMED, f"invalid message: {type(e).__name__}", fields) from None
