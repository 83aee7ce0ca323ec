"""Zenoh key expressions of the cristal service, scoped by site and map.

``<site>`` names an installation (a building, a campus), ``<map>`` one scan of it (its map id),
``<client>`` a device, ``<server>`` one server process (a worker; several serve the same map).
Ids are ``[A-Za-z0-9_-]`` (no ``/``, ``*``, ``$``, ``?``, ``#``).

==================================================== ============ ===================================================
key expression                                       kind         what
==================================================== ============ ===================================================
``cristal/<site>/<map>/frame/<client>/<server>``     queryable    :class:`FrameRequest` → :class:`PoseReply`;
                                                                  the query's timeout is the frame's deadline.
                                                                  Each server declares ``cristal/<site>/*/frame/*/<server>``
                                                                  (so a frame for a map it does not serve gets
                                                                  ``rejected/unknown_map`` instead of silence).
``cristal/<site>/<map>/pose/<client>``               publication  every :class:`PoseReply` that has a status other than
                                                                  rejected/dropped, for fleet managers and dashboards
                                                                  (subscribe to ``cristal/<site>/*/pose/*``).
``cristal/<site>/<map>/server/<server>``             liveliness   one token per server process; clients discover
                                                                  workers and notice their death through it.
``cristal/<site>/<map>/info``                        queryable    :class:`SiteInfo` (every server answers; take one).
``cristal/<site>/<map>/health/<server>``             queryable    :class:`Health` of one server.
``cristal/<site>/<map>/bundle/info``                 queryable    :class:`MapBundleInfo` of the P&L map bundle.
``cristal/<site>/<map>/bundle/chunk/<i>``            queryable    :class:`BundleChunk` ``i`` (0-based) of the bundle.
==================================================== ============ ===================================================

Access control (``deploy/zenoh/``) works on these keys: a client may query only
``cristal/<site>/*/frame/<its id>/*`` and subscribe only to ``cristal/<site>/*/pose/<its id>``;
the server rejects a frame whose body names another client than its key (``client_mismatch``), so
a key-level rule is a message-level guarantee. A fleet role subscribes to ``cristal/<site>/*/pose/*``.

Default endpoint: a server (or ``cristal router``) listens on :data:`DEFAULT_ENDPOINT`; a client
with no configuration connects there.
"""

from __future__ import annotations

import re

__all__ = ["PREFIX", "DEFAULT_ENDPOINT", "DEFAULT_SITE", "DEFAULT_MAP", "check_id", "frame", "frame_queryable",
           "pose", "poses", "server_token", "server_tokens", "info", "health", "bundle_info", "bundle_chunk",
           "bundle_queryable", "parse_frame_key", "parse_server_token"]

PREFIX = "cristal"
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
DEFAULT_SITE = "default"
DEFAULT_MAP = "default"
_ID = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def check_id(value: str, what: str = "id") -> str:
    """``value`` if it is a valid key chunk, else ValueError naming ``what``."""
    if not isinstance(value, str) or not _ID.match(value):
        raise ValueError(f"{what} {value!r} must be 1-64 characters of [A-Za-z0-9_-]")
    return value


def frame(site: str, map_id: str, client: str, server: str) -> str:
    return f"{PREFIX}/{site}/{map_id}/frame/{client}/{server}"


def frame_queryable(site: str, server: str) -> str:
    return f"{PREFIX}/{site}/*/frame/*/{server}"


def parse_frame_key(key: str) -> tuple[str, str, str, str] | None:
    """``(site, map, client, server)`` of a frame key, or None."""
    p = str(key).split("/")
    if len(p) != 6 or p[0] != PREFIX or p[3] != "frame":
        return None
    return p[1], p[2], p[4], p[5]


def pose(site: str, map_id: str, client: str) -> str:
    return f"{PREFIX}/{site}/{map_id}/pose/{client}"


def poses(site: str, map_id: str = "*") -> str:
    """Every client's poses on one map (or all maps of the site)."""
    return f"{PREFIX}/{site}/{map_id}/pose/*"


def server_token(site: str, map_id: str, server: str) -> str:
    return f"{PREFIX}/{site}/{map_id}/server/{server}"


def server_tokens(site: str, map_id: str) -> str:
    return f"{PREFIX}/{site}/{map_id}/server/*"


def parse_server_token(key: str) -> str | None:
    p = str(key).split("/")
    return p[4] if len(p) == 5 and p[0] == PREFIX and p[3] == "server" else None


def info(site: str, map_id: str) -> str:
    return f"{PREFIX}/{site}/{map_id}/info"


def health(site: str, map_id: str, server: str) -> str:
    return f"{PREFIX}/{site}/{map_id}/health/{server}"


def bundle_info(site: str, map_id: str) -> str:
    return f"{PREFIX}/{site}/{map_id}/bundle/info"


def bundle_chunk(site: str, map_id: str, index: int) -> str:
    return f"{PREFIX}/{site}/{map_id}/bundle/chunk/{int(index)}"


def bundle_queryable(site: str, map_id: str) -> str:
    return f"{PREFIX}/{site}/{map_id}/bundle/**"
