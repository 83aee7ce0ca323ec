"""Evaluation plots: trajectories seen from above (over the scan), errors over time, errors against the predicted
uncertainty.

Rendered with matplotlib's Agg canvas (no display, no pyplot global state) and written
atomically as PNG.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from services.io.atomic import atomic_write_bytes
from services.io.stamps import seconds_per_unit
from services.io.trajectory import Trajectory

if TYPE_CHECKING:  # pragma: no cover
    from services.eval.ape import ApeResult
    from services.io.scan import Scan

__all__ = ["plot_trajectory_topdown", "plot_errors", "plot_uncertainty"]

log = logging.getLogger(__name__)

GT_COLOR, EST_COLOR, LOST_COLOR = "#1f77b4", "#d62728", "#7f7f7f"


def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)  # Agg explicitly: works headless, never touches pyplot's backend
    return fig


def _save(fig, out_png: str | Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write_bytes(out_png, buf.getvalue())
    log.info("wrote %s", out_png)
    return Path(out_png)


def _scan_points(scan: "Scan", lo: np.ndarray, hi: np.ndarray, z_max: float, max_points: int, seed: int = 0):
    """World xy and rgb of a random subsample of the scan inside the x-y box [lo, hi] and below z_max (ceiling cut)."""
    lo_l = (lo - scan.origin[:2]).astype(np.float32)
    hi_l = (hi - scan.origin[:2]).astype(np.float32)
    x, y, z = scan.xyz[:, 0], scan.xyz[:, 1], scan.xyz[:, 2]
    mask = (x >= lo_l[0]) & (x <= hi_l[0]) & (y >= lo_l[1]) & (y <= hi_l[1]) & (z <= np.float32(z_max - scan.origin[2]))
    idx = np.flatnonzero(mask)
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    pts = scan.world_xyz(idx)
    order = np.argsort(pts[:, 2])  # higher points drawn last, as seen from above
    return pts[order, :2], scan.rgb[idx][order] / 255.0


def plot_trajectory_topdown(gt: Trajectory, est: Trajectory, out_png: str | Path, scan: "Scan | None" = None,
                            title: str = "ground truth vs estimate (top view)", max_points: int = 200_000) -> Path:
    """Ground truth and estimate in the world x-y plane (z is up), equal aspect, over the scan if given.

    The estimate is drawn in ground-truth frame order and breaks where frames got no pose;
    those frames are marked on the ground truth. Scan points above the highest camera
    + 0.5 m are left out (ceilings would hide the floor plan).
    """
    P = gt.positions()
    est_by_stamp = est.as_dict()
    E = np.full_like(P, np.nan)
    for i, s in enumerate(gt.stamps):
        if s in est_by_stamp:
            E[i] = est_by_stamp[s].t
    lost = np.isnan(E[:, 0])
    both = np.vstack([P, E[~lost]]) if len(P) else est.positions()

    fig = _figure(8, 7)
    ax = fig.add_subplot()
    if len(both):
        lo, hi = both[:, :2].min(axis=0), both[:, :2].max(axis=0)
        pad = max(3.0, 0.5 * float(np.max(hi - lo)))  # scan context around the walk (a whole room or site)
        lo, hi = lo - pad, hi + pad
        if scan is not None and len(scan):
            xy, rgb = _scan_points(scan, lo, hi, float(both[:, 2].max()) + 0.5, max_points)
            ax.scatter(xy[:, 0], xy[:, 1], c=rgb, s=0.5, alpha=0.35, linewidths=0, rasterized=True, zorder=0)
            log.debug("top view: %d scan points", len(xy))
    ax.plot(P[:, 0], P[:, 1], "-", color=GT_COLOR, lw=1.6, label=f"ground truth ({len(gt)} frames)", zorder=2)
    n_est = int((~lost).sum())
    ax.plot(E[:, 0], E[:, 1], "-", color=EST_COLOR, lw=1.2, label=f"estimate ({n_est} frames with a pose)", zorder=3)
    if lost.any():
        ax.plot(P[lost, 0], P[lost, 1], "x", color=LOST_COLOR, ms=4, mew=1,
                label=f"no pose ({int(lost.sum())} frames)", zorder=4)
    if len(P):
        ax.plot(*P[0, :2], "o", color=GT_COLOR, ms=9, mfc="none", mew=2, label="start", zorder=5)
    if n_est:
        first = E[~lost][0]
        ax.plot(*first[:2], "o", color=EST_COLOR, ms=6, zorder=5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(loc="best", fontsize=8, framealpha=0.85)
    return _save(fig, out_png)


def plot_errors(result: "ApeResult", out_png: str | Path, title: str | None = None) -> Path:
    """Translation (cm) and rotation (deg) error over time with RMSE lines; frames without a pose marked."""
    scale, _ = seconds_per_unit(sorted(result.stamps + result.lost_stamps, key=float))  # stamps in ns: the axis in s
    t_all = np.concatenate([result.times, result.lost_times]) * scale
    t0 = float(t_all.min()) if len(t_all) else 0.0
    # one series over all ground-truth frames, NaN (a gap) where a frame got no pose
    order = np.argsort(t_all, kind="stable")
    tt = t_all[order] - t0
    te = np.concatenate([result.trans_err * 100.0, np.full(len(result.lost_times), np.nan)])[order]
    re = np.concatenate([result.rot_err_deg, np.full(len(result.lost_times), np.nan)])[order]

    fig = _figure(9, 5.5)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    for ax, y, rmse, unit, name in ((ax1, te, result.trans_rmse * 100.0, "cm", "translation error"),
                                    (ax2, re, result.rot_rmse_deg, "deg", "rotation error")):
        ax.plot(tt, y, "-", color=EST_COLOR, lw=1.0, marker=".", ms=2.5, label=name)
        ax.axhline(rmse, color="k", ls="--", lw=1.0, label=f"RMSE {rmse:.3g} {unit}")
        if len(result.lost_times):
            ax.vlines(result.lost_times * scale - t0, 0, 1, transform=ax.get_xaxis_transform(), color=LOST_COLOR,
                      alpha=0.35, lw=1.0, label=f"no pose ({len(result.lost_times)} frames)")
        ax.set_ylabel(f"{name} ({unit})")
        ax.set_ylim(bottom=0)
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.set_ylim(top=1.3 * max(float(np.nanmax(y)) if np.isfinite(y).any() else 0.0, rmse, 1e-3))  # room for the legend
        ax.legend(loc="upper right", ncols=3, fontsize=8, framealpha=0.85)
    ax2.set_xlabel("time since first ground-truth frame (s)")
    ax1.set_title(title or f"APE, alignment {result.align}: {result.n_matched}/{result.n_gt} frames "
                  f"({100 * result.fraction:.1f} %) with a pose")
    return _save(fig, out_png)


def plot_uncertainty(check: dict, out_png: str | Path, gates: tuple[float, float] = (0.01, 0.1),
                     title: str | None = None) -> Path:
    """Each pose's error against the 1-sigma it was reported with (services.eval.ape.uncertainty_check), translation
    and rotation, log-log: an honest localizer keeps its points under the 3-sigma line; the dotted line is the gate
    a pose's sigma must pass to be reported (``gates``: metres, degrees)."""
    fig = _figure(10, 4.6)
    axes = fig.subplots(1, 2)
    beyond = check["beyond"]
    for ax, err, sig, gate, scale, unit, name in (
            (axes[0], check["t_err_m"], check["sigma_m"], gates[0], 100.0, "cm", "camera centre"),
            (axes[1], check["r_err_deg"], check["sigma_deg"], gates[1], 1.0, "deg", "orientation")):
        e, s = np.maximum(err * scale, 1e-4 * scale), sig * scale
        ax.scatter(s[~beyond], e[~beyond], s=8, color=GT_COLOR, alpha=0.6, label="within 3 sigma (both)")
        ax.scatter(s[beyond], e[beyond], s=14, color=EST_COLOR, label=f"beyond 3 sigma ({int(beyond.sum())})")
        if len(s):
            lo = max(min(float(s.min()), float(e.min())) / 2, 1e-4 * scale)
            hi = max(float(s.max()), float(e.max()), gate * scale) * 2
            x = np.array([lo, hi])
            ax.plot(x, x, "k-", lw=0.8, label="error = 1 sigma")
            ax.plot(x, 3 * x, "k--", lw=0.8, label="3 sigma")
            ax.set_xlim(lo, hi)
            ax.set_ylim(lo, hi)
        ax.axvline(gate * scale, color=LOST_COLOR, ls=":", lw=1.0, label=f"reporting gate {gate * scale:g} {unit}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"predicted 1-sigma, {name} ({unit})")
        ax.set_ylabel(f"error, {name} ({unit})")
        ax.grid(True, which="both", lw=0.3, alpha=0.5)
        ax.legend(loc="upper left", fontsize=8, framealpha=0.85)
    fig.suptitle(title or f"error against predicted uncertainty: {check['n']} poses, {int(beyond.sum())} beyond 3 sigma")
    return _save(fig, out_png)
