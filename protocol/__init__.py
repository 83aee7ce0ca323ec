"""The wire contract between cristal clients and servers: no torch, tiny dependencies.

Issue 6 grows this into the full message set; for now it carries the protocol version.
"""

PROTOCOL_VERSION = 1
