"""Evaluation plots: trajectories seen from above (over the scan), errors over time, errors against the predicted
uncertainty; and what a run did, for a recording with no ground truth: the poses of a localization seen from above,
the positions a database or map was built from.

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

__all__ = ["plot_trajectory_topdown", "plot_localization_topdown", "plot_positions_topdown", "plot_errors",
           "plot_uncertainty", "picture_path", "drawn"]

log = logging.getLogger(__name__)

GT_COLOR, EST_COLOR, LOST_COLOR = "#1f77b4", "#d62728", "#7f7f7f"
RELOC_COLOR, BACKFILL_COLOR, LOCAL_COLOR = "#2ca02c", "#ff7f0e", "#9467bd"


def picture_path(path: str | Path) -> Path:
    """``run/traj.txt`` -> ``run/traj.png``; ``site/reloc.npz`` -> ``site/reloc.png``."""
    p = Path(path)
    return p.with_name(p.stem + ".png")


def drawn(what: str, plot, *args, **kw) -> Path | None:
    """``plot(*args, **kw)``'s picture, or None with a warning naming ``what``: a picture never costs the run it shows
    (matplotlib missing on a device, a full disk), so the callers draw after writing their outputs."""
    try:
        return plot(*args, **kw)
    except Exception as e:  # noqa: BLE001
        log.warning("no picture of %s: %s", what, e)
        return None


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
    pool = None
    if len(scan) > 20 * max_points:  # a survey scan (100 M+ points): look among a random few million, not all of them
        pool = np.sort(np.random.default_rng(seed).integers(0, len(scan), 20 * max_points))  # (a repeat is harmless)
    xyz = scan.xyz if pool is None else scan.xyz[pool]
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    mask = (x >= lo_l[0]) & (x <= hi_l[0]) & (y >= lo_l[1]) & (y <= hi_l[1]) & (z <= np.float32(z_max - scan.origin[2]))
    idx = np.flatnonzero(mask) if pool is None else pool[mask]
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    pts = scan.world_xyz(idx)
    order = np.argsort(pts[:, 2])  # higher points drawn last, as seen from above
    return pts[order, :2], scan.rgb[idx][order] / 255.0


def _box(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The x-y box around ``xyz`` with the scan around it (a whole room or site)."""
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    pad = max(3.0, 0.5 * float(np.max(hi - lo)))
    return lo - pad, hi + pad


def _background(ax, lo: np.ndarray, hi: np.ndarray, z_max: float, scan: "Scan | None", landmarks: np.ndarray | None,
                max_points: int = 200_000, seed: int = 0) -> None:
    """Under the plot, inside the x-y box [lo, hi] and below ``z_max`` (ceilings would hide the floor plan): the
    scan's points in their colours, or else a map's landmarks (world xyz), grey by height."""
    if scan is not None and len(scan):
        xy, rgb = _scan_points(scan, lo, hi, z_max, max_points, seed)
        ax.scatter(xy[:, 0], xy[:, 1], c=rgb, s=0.5, alpha=0.35, linewidths=0, rasterized=True, zorder=0)
        log.debug("top view: %d scan points", len(xy))
    elif landmarks is not None and len(landmarks):
        P = np.asarray(landmarks, np.float64).reshape(-1, 3)
        P = P[np.all((P[:, :2] >= lo) & (P[:, :2] <= hi), axis=1) & (P[:, 2] <= z_max)]
        if len(P) > max_points:
            P = P[np.random.default_rng(seed).choice(len(P), max_points, replace=False)]
        P = P[np.argsort(P[:, 2])]
        z0, z1 = (float(P[:, 2].min()), float(P[:, 2].max())) if len(P) else (0.0, 1.0)
        ax.scatter(P[:, 0], P[:, 1], c=P[:, 2], cmap="Greys", vmin=2 * z0 - z1 - 0.1, vmax=z1, s=0.8, alpha=0.6,
                   linewidths=0, rasterized=True, zorder=0)  # (mid-grey at the lowest: the floor must show)


def plot_trajectory_topdown(gt: Trajectory, est: Trajectory, out_png: str | Path, scan: "Scan | None" = None,
                            title: str = "ground truth vs estimate (top view)", max_points: int = 200_000,
                            frame_log: dict | None = None) -> Path:
    """Ground truth and estimate from above, over the scan if given: :func:`plot_localization_topdown` over the
    ground truth's frames. A frame's status comes from ``frame_log`` (stamp -> FrameRecord, the run's
    TRAJ.frames.csv) where it has the frame, else TRACKING where the estimate has a pose and LOST where not."""
    from services.io.frame_log import FrameRecord

    poses, frame_log = est.as_dict(), frame_log or {}
    records = [frame_log.get(s) or FrameRecord(s, "TRACKING" if s in poses else "LOST") for s in gt.stamps]
    return plot_localization_topdown(est, records, out_png, scan=scan, gt=gt, title=title, max_points=max_points)


def plot_localization_topdown(est: Trajectory, records: list, out_png: str | Path, scan: "Scan | None" = None,
                              landmarks: np.ndarray | None = None, gt: Trajectory | None = None,
                              title: str | None = None, max_points: int = 200_000) -> Path:
    """What a localization did, seen from above over the scan (or a map's landmarks): the poses reported, joined
    frame to frame and broken where frames got none; the camera's heading every few poses; the relocalizations;
    each LOST stretch as a dashed line from the pose before it to the pose after it, with its length in frames;
    the ground truth of the frames the run covered when there is one. ``records``: the run's services.io.frame_log.FrameRecord, every frame in
    order (status RELOCALIZED, BACKFILLED and, from a streaming client, LOCAL are marked). For a recording with no
    ground truth this is the picture to look at first."""
    poses = est.as_dict()
    status = [r.status for r in records]
    T = [poses.get(r.stamp) for r in records]
    has = np.array([t is not None for t in T], bool)
    P = np.array([t.t if t is not None else (np.nan, np.nan, np.nan) for t in T], float).reshape(-1, 3)
    seen = {r.stamp for r in records}  # the ground truth of the frames the run covered
    G = np.array([T.t for s, T in gt if s in seen]).reshape(-1, 3) if gt is not None else np.zeros((0, 3))
    both = np.vstack([P[has], G])
    lo, hi = _box(both) if len(both) else (np.zeros(2), np.ones(2))
    fig = _figure(9, float(np.clip(9 * (hi[1] - lo[1]) / (hi[0] - lo[0]) + 0.8, 4.5, 10)))  # the site's shape
    ax = fig.add_subplot()
    if len(both):
        _background(ax, lo, hi, float(both[:, 2].max()) + 0.5, scan, landmarks, max_points)
        ax.set_xlim(lo[0], hi[0])  # the walk with the site around it, background or none
        ax.set_ylim(lo[1], hi[1])
        step = 0.025 * float(np.max(hi - lo))  # heading ticks a few percent of the view long
    if len(G):
        ax.plot(G[:, 0], G[:, 1], "-", color=GT_COLOR, lw=1.0, alpha=0.7, zorder=2,
                label=f"ground truth ({len(G)} frames)")
    # the reported poses: NaN between runs breaks the line where frames got none
    if has.any():
        ax.plot(P[:, 0], P[:, 1], "-", color=EST_COLOR, lw=1.4, zorder=3,
                label=f"pose reported ({int(has.sum())} of {len(records)} frames)")
    idx = np.flatnonzero(has)
    gaps = [(a, b) for a, b in zip(idx[:-1], idx[1:]) if b - a > 1]  # a LOST stretch between two poses
    min_label = max(3, len(records) // 60)
    for k, (a, b) in enumerate(gaps):
        ax.plot(P[[a, b], 0], P[[a, b], 1], "--", color=LOST_COLOR, lw=1.0, zorder=2,
                label="LOST stretch (pose before to pose after)" if k == 0 else None)
        if b - a - 1 >= min_label:
            m = (P[a] + P[b]) / 2
            ax.annotate(f"{b - a - 1} LOST", m[:2], fontsize=7, color="#444444", ha="center", va="bottom", zorder=6)
    if len(idx):
        heads = idx[:: max(1, len(idx) // 30)]
        d = np.array([T[i].R[:2, 2] for i in heads])  # the viewing direction (camera z) in the floor plane
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        ax.quiver(P[heads, 0], P[heads, 1], d[:, 0] * step, d[:, 1] * step, angles="xy", scale_units="xy", scale=1,
                  color=EST_COLOR, width=0.0025, headwidth=3, headlength=4, alpha=0.7, zorder=4,
                  label="viewing direction")
        ax.plot(*P[idx[0], :2], "o", color=EST_COLOR, ms=8, mfc="none", mew=2,
                label=f"first pose (frame {idx[0] + 1})", zorder=5)
        tail = len(records) - 1 - idx[-1]
        if tail:  # LOST from the last pose to the end of the sequence
            ax.plot(*P[idx[-1], :2], "X", color="k", ms=8, zorder=6, label=f"last pose (frame {idx[-1] + 1}); "
                    f"the {tail} frames after it LOST")
    for name, color, marker, label in (("RELOCALIZED", RELOC_COLOR, "^", "relocalized"),
                                       ("BACKFILLED", BACKFILL_COLOR, ".", "backfilled"),
                                       ("LOCAL", LOCAL_COLOR, ".", "from the local P&L fallback")):
        sel = np.array([s == name for s in status], bool) & has
        if sel.any():
            ax.plot(P[sel, 0], P[sel, 1], marker, color=color, ms=6 if marker == "^" else 4, ls="none", zorder=5,
                    label=f"{label} ({int(sel.sum())})")
    ax.set_aspect("equal", adjustable="box")  # (the limits are the box above)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    lost = len(records) - int(has.sum())
    ax.set_title(title or f"localization (top view): {int(has.sum())}/{len(records)} frames with a pose, {lost} LOST")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(loc="best", fontsize=8, framealpha=0.85)
    return _save(fig, out_png)


def plot_positions_topdown(positions: np.ndarray, out_png: str | Path, scan: "Scan | None" = None,
                           landmarks: np.ndarray | None = None, label: str = "positions", title: str | None = None,
                           max_points: int = 200_000) -> Path:
    """Where a relocalization database or a map was rendered from (world xyz), seen from above over the scan (or
    the map's landmarks): is the region of interest where cameras go?"""
    X = np.asarray(positions, float).reshape(-1, 3)
    fig = _figure(8, 7)
    ax = fig.add_subplot()
    if len(X):
        lo, hi = _box(X)
        _background(ax, lo, hi, float(X[:, 2].max()) + 0.5, scan, landmarks, max_points)
        ax.plot(X[:, 0], X[:, 1], "o", color=EST_COLOR, ms=4.5, mfc="none", mew=1.2, ls="none", zorder=3,
                label=f"{label} ({len(X)})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{len(X)} {label} (top view)")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.legend(loc="best", fontsize=8, framealpha=0.85)
    return _save(fig, out_png)


def plot_station_agreement(agreement, scan: "Scan", out_png: str | Path, max_points: int = 200_000) -> Path:
    """``cristal scan check --plot``: the stations seen from above over the scan, each pair that shares surfaces
    joined by a line coloured by how far they disagree (services.io.registration; the worse direction of the two),
    each station labelled with its own share (mm), the loose ones ringed."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    C = np.array([s.t for s in scan.stations], float).reshape(-1, 3)
    worst: dict[tuple[int, int], float] = {}
    for p in agreement.pairs:
        key = (min(p.a, p.b), max(p.a, p.b))
        worst[key] = max(worst.get(key, 0.0), 1e3 * p.registration_m)
    top = max(10.0, max(worst.values(), default=0.0))
    norm, cmap = Normalize(0.0, top), colormaps["RdYlGn_r"]
    fig = _figure(8, 7)
    ax = fig.add_subplot()
    lo, hi = _box(C)
    _background(ax, lo, hi, float(C[:, 2].max()) + 0.5, scan, None, max_points)
    for (a, b), mm in sorted(worst.items(), key=lambda kv: kv[1]):
        ax.plot(C[[a, b], 0], C[[a, b], 1], "-", color=cmap(norm(mm)), lw=2.5, zorder=2)
        ax.annotate(f"{mm:.1f}", C[[a, b], :2].mean(axis=0), fontsize=7, ha="center", va="center", zorder=4,
                    bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8})
    ax.plot(C[:, 0], C[:, 1], "o", color=EST_COLOR, ms=6, ls="none", zorder=3, label=f"stations ({len(C)})")
    own_m = agreement.station_sigmas_m()
    own, loose = 1e3 * own_m, agreement.loose_stations(own_m)
    if loose:
        ax.plot(C[loose, 0], C[loose, 1], "o", mfc="none", mec="red", mew=2, ms=14, ls="none", zorder=3,
                label="loose: off its neighbours well beyond the rest")
    for k, c in enumerate(C):
        label = str(k) if not np.isfinite(own[k]) else f"{k}: {own[k]:.1f}"
        ax.annotate(label, c[:2], xytext=(4, 4), textcoords="offset points", fontsize=7, zorder=4,
                    color="red" if k in loose else "black")
    fig.colorbar(ScalarMappable(norm, cmap), ax=ax, shrink=0.7, label="registration error between the two (mm)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"how far the stations disagree: {1e3 * agreement.registration_m:.1f} mm overall (top view)")
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
