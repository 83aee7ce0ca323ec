"""The wire contract between cristal clients and servers: no torch, tiny dependencies.

Everything that crosses the network is defined here and nowhere else:

- :mod:`protocol.messages` — the pydantic models (frame request, pose reply, site info, map bundle,
  health) and the error codes; read it as the API document.
- :mod:`protocol.codec` — msgpack encoding with a protocol version and size limits; every decode
  failure is a typed :class:`protocol.codec.DecodeError` carrying an error code.
- :mod:`protocol.keys` — the Zenoh key expressions, scoped by site and map.

Dependencies: pydantic, msgpack (and numpy nowhere on the hot path). A headset or robot client
imports this package without torch.
"""

PROTOCOL_VERSION = 1
