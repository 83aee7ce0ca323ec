"""On-device fallback: the light P&L localizer behind a small interface (no torch).

The client needs three things from a local localizer: ``seed(T_wc)`` with each server pose (so
it is warm when needed; ``seed(T_wc, stamp=)`` when it takes the capture time, to learn the motion), ``process(image, camera)`` for a frame the server did not localize, and
``reset()``. :func:`load_local` wraps :class:`services.localize.pnl.PnlLocalizer` (issue 5); any
object with ``process(image, camera, prior, motion=, stamp=) -> result`` (``.status``, ``.T_wc``, ``.inliers``;
``motion``: the device's odometry since the previous frame or None, ``stamp``: capture time in seconds or None)
and optionally ``seed``/``reset`` fits :class:`LocalFallback`.
"""

from __future__ import annotations

import inspect
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.geometry.camera import Camera
from services.geometry.se3 import Pose

__all__ = ["LocalFallback", "LocalResult", "load_local"]

log = logging.getLogger("cristal.client")


@dataclass
class LocalResult:
    status: str  # "tracking" | "relocalized" | "lost" | "unavailable" | "error"
    T_wc: Pose | None
    inliers: int = 0
    ms: float = 0.0


class LocalFallback:
    """Keeps a local localizer warm with server poses; localizes the frames the server did not."""

    def __init__(self, localizer):
        self.loc = localizer
        self.T_seed: Pose | None = None
        self.seeded_fresh = False
        self.errors = 0
        self._seeds = hasattr(localizer, "seed")
        self._seeds_with_stamp = self._seeds and _takes(localizer.seed, "stamp")  # (checked once, not per frame)

    def seed(self, T_wc: Pose, stamp: float | None = None) -> None:
        """A trusted pose (from the server) for the current frame, captured at ``stamp`` (s): a localizer whose
        ``seed`` takes the capture time learns the motion from consecutive seeds and predicts the first frame it
        is handed with it (P&L: a hand-over in a fast turn)."""
        self.T_seed = T_wc
        self.seeded_fresh = True
        if self._seeds:
            try:
                if stamp is not None and self._seeds_with_stamp:
                    self.loc.seed(T_wc, stamp=stamp)
                else:
                    self.loc.seed(T_wc)
            except Exception as e:  # noqa: BLE001 - the fallback must never break the stream
                self.errors += 1
                log.warning("local localizer rejected a seed: %s", e)

    def reset(self) -> None:
        self.T_seed = None
        if hasattr(self.loc, "reset"):
            self.loc.reset()

    def process(self, image: np.ndarray, camera: Camera, prior: Pose | None = None, motion: Pose | None = None,
                stamp: float | None = None, readout_s: float | None = None, near=None) -> LocalResult:
        """``motion``: the device's odometry since the previous frame (the localizer predicts from its last pose
        with it, and carries that pose on through LOST frames); ``stamp``: capture time (s)."""
        t0 = time.perf_counter()
        if prior is None and self.seeded_fresh and motion is None and not self._seeds:
            prior = self.T_seed  # the last server pose: one frame old at most while handing over (a seeded localizer
            #                      already tracks from it, with the motion its seeds showed)
        self.seeded_fresh = False
        try:
            kw = {"readout_s": readout_s} if readout_s else {}  # (a rolling shutter, undone by the P&L localizer)
            if near is not None:  # (where the device is, roughly, until it has a pose)
                kw["near"] = near
            r = self.loc.process(image, camera, prior, motion=motion, stamp=stamp, **kw)
        except Exception as e:  # noqa: BLE001
            self.errors += 1
            log.warning("local localizer failed on a frame: %s: %s", type(e).__name__, e)
            return LocalResult("error", None, 0, 1e3 * (time.perf_counter() - t0))
        status = str(getattr(r.status, "value", r.status))
        T = r.T_wc if status in ("tracking", "relocalized") else None
        if T is not None:
            self.T_seed = T
        return LocalResult(status, T, int(getattr(r, "inliers", 0) or 0), 1e3 * (time.perf_counter() - t0))


def _takes(fn, name: str) -> bool:
    """Whether callable ``fn`` accepts a keyword argument ``name``."""
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return name in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def load_local(map_dir: str | Path, scan_sigma_m: float | None = None) -> LocalFallback | None:
    """The P&L localizer for ``map_dir`` behind :class:`LocalFallback`; None (with a warning) if unavailable.
    ``scan_sigma_m``: the scan's registration error, counted in each reported 1-sigma (as the server's
    ``--scan-sigma-mm``); None: what prebuild recorded beside the map (0 if nothing), and where on the site it lies."""
    try:
        from services.localize.pnl import PnlConfig, PnlLocalizer
    except ImportError as e:
        log.warning("the local P&L localizer is not available (%s): frames the server misses get no pose", e)
        return None
    grid = None
    if scan_sigma_m is None:  # what prebuild measured: the scan's error, and each station's (where the camera looks)
        from services.localize.scan_error import grid_arg, read_accuracy

        record = read_accuracy(map_dir)
        scan_sigma_m = 0.0 if record is None else record["scan_sigma_mm"] / 1000.0
        grid = grid_arg(record) if scan_sigma_m else None
    return LocalFallback(PnlLocalizer.load(Path(map_dir), PnlConfig(scan_sigma_m=scan_sigma_m, scan_grid=grid)))
