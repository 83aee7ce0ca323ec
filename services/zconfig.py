"""Zenoh session configuration shared by ``cristal router``, ``serve`` and ``stream`` (no torch).

With no file and no endpoints: a server (or router) listens on ``tcp/127.0.0.1:7447`` and a
client connects there, so the commands work on one machine out of the box. A ``--zenoh-config``
JSON5 file (zenoh 1.x format, examples in ``deploy/zenoh/``) is taken as is; explicit
``listen``/``connect`` endpoints are added on top of it. Without a file, multicast scouting is off
(sessions find each other through the endpoints, never by surprise on a LAN) and so is zenoh's
shared-memory transport (see ``make_config``); every file in ``deploy/zenoh/`` turns both off, and a
file that leaves shared memory on is taken as is, with a warning.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from protocol.keys import DEFAULT_ENDPOINT

log = logging.getLogger(__name__)

__all__ = ["make_config", "open_session"]


def make_config(path: str | Path | None = None, mode: str | None = None, listen: list[str] | None = None,
                connect: list[str] | None = None, default_role: str = "client"):
    """A ``zenoh.Config``. ``default_role``: "client" connects to the default endpoint, "server" listens on it."""
    import zenoh

    if path:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such zenoh configuration file")
        try:
            cfg = zenoh.Config.from_file(str(p))
        except Exception as e:  # zenoh raises ZError with the parser's message
            raise ValueError(f"{p}: not a valid zenoh configuration ({e})") from None
        if cfg.get_json("transport/shared_memory/enabled") == "true":
            log.warning("%s leaves zenoh's shared-memory transport on (its default): a long-running process then keeps "
                        "16 MiB and an open file for every same-host peer that came and went; deploy/zenoh/ turns it off "
                        "(transport: { shared_memory: { enabled: false } })", p)
    else:
        cfg = zenoh.Config()
        cfg.insert_json5("scouting/multicast/enabled", "false")
        # zenoh 1.x sends payloads over 3 KB between processes on one host through a 16 MiB shared-memory pool per
        # session, and the receiving side keeps each departed peer's pool mapped: a server took 16 MB more with every
        # client that came and went (benchmarks/soak.py, RESULTS.md stop 54). Frames are ~40 KB JPEGs; copying is free
        cfg.insert_json5("transport/shared_memory/enabled", "false")
        if not listen and not connect:
            if default_role == "client":
                connect = [DEFAULT_ENDPOINT]
            else:
                listen = [DEFAULT_ENDPOINT]
        if mode is None:
            # A client is a *peer* with no listener: unlike zenoh's client mode it opens even when the
            # server is down and keeps reconnecting in the background (what on-device fallback needs).
            mode = "peer"
        if default_role == "client":
            cfg.insert_json5("listen/endpoints", "[]")
            cfg.insert_json5("connect/retry", json.dumps({"period_init_ms": 200, "period_max_ms": 1000,
                                                          "period_increase_factor": 1.5}))
    if mode:
        cfg.insert_json5("mode", json.dumps(mode))
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return cfg


def open_session(cfg):
    """``zenoh.open`` with its error turned into a ConnectionError that names the endpoints."""
    import zenoh

    try:
        return zenoh.open(cfg)
    except Exception as e:
        try:
            eps = cfg.get_json("connect/endpoints") or cfg.get_json("listen/endpoints")
        except Exception:  # noqa: BLE001
            eps = "?"
        raise ConnectionError(f"cannot open a zenoh session ({eps}): {e}") from None
