"""The cristal client library: stream frames to the service over Zenoh, fall back to the local P&L map.

Imports without torch (a headset or robot installs only the base package)."""

from services.client.client import LocalizationClient, encode_image, reply_pose

__all__ = ["LocalizationClient", "encode_image", "reply_pose"]
