"""The per-frame status every localizer reports (light: no torch; shared by Render & Match and Prebuild & Localize)."""

from __future__ import annotations

from enum import Enum

__all__ = ["Status"]


class Status(str, Enum):
    TRACKING = "tracking"
    RELOCALIZED = "relocalized"
    LOST = "lost"
