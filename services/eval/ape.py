"""Absolute pose error (APE) of an estimated trajectory against ground truth, as ``evo_ape`` computes it.

Frames are matched by their exact timestamp text (``"1.50"`` and ``"1.5"`` are different
frames, see ``docs/CONVENTIONS.md``). The estimate is optionally aligned to the ground
truth first (Umeyama on the camera centres): ``none`` (the product claims poses in the
scan frame), ``se3`` (rigid) or ``sim3`` (rigid + scale). Per matched frame:

* translation error = ``|t_gt - t_est_aligned|`` in metres,
* rotation error = angle of ``R_gt^T R_est_aligned`` in degrees.

``fraction`` is the share of ground-truth frames that got a pose.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, fields

import numpy as np

from services.geometry.se3 import Pose
from services.io.trajectory import Trajectory

__all__ = ["ALIGNMENTS", "ApeResult", "DegenerateAlignment", "umeyama", "associate", "compute_ape", "evaluate",
           "errors_by_source", "uncertainty_check"]

log = logging.getLogger(__name__)

ALIGNMENTS = ("none", "se3", "sim3")


class DegenerateAlignment(ValueError):
    """The matched camera centres do not fix an alignment (fewer than 3, or collinear)."""


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares ``(R, t, s)`` with ``dst ≈ s R src + t`` (Umeyama 1991), points as rows (N, 3).

    Raises DegenerateAlignment (a ValueError) when the points do not fix a rotation (fewer than 3, or collinear).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama needs two (N, 3) arrays of the same shape, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = np.mean(np.sum(xs * xs, axis=1))
    cov = xd.T @ xs / len(src)
    U, d, Vt = np.linalg.svd(cov)
    if len(src) < 3 or d[1] <= 1e-12 * max(d[0], 1e-300):
        raise DegenerateAlignment(f"alignment is degenerate: {len(src)} positions, collinear or fewer than 3")
    if d[1] < 1e-2 * d[0]:  # d ~ variances: the second axis spans < 10 % of the first
        log.warning("alignment is poorly conditioned: the camera centres lie almost on a line, so the rotation "
                    "about it is arbitrary (as in evo); trust the unaligned numbers")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(d) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


def associate(gt: Trajectory, est: Trajectory, strict: bool = True) -> tuple[Trajectory, Trajectory]:
    """Pairs of (ground truth, estimate) with the same timestamp text, in ground-truth order.

    With ``strict`` an estimated stamp that the ground truth lacks is a ValueError (usually a
    reformatted timestamp); otherwise such frames are ignored with a warning.
    """
    est_by_stamp = est.as_dict()
    known = set(gt.stamps)
    unknown = [s for s in est.stamps if s not in known]
    if unknown:
        msg = (f"{len(unknown)} of {len(est)} estimated timestamps are not in the ground truth, e.g. {unknown[0]!r} "
               "(timestamps are matched as exact text)")
        if strict:
            raise ValueError(msg)
        log.warning("%s; ignoring them", msg)
    g, e = Trajectory(), Trajectory()
    for stamp, T_wc in gt:
        if stamp in est_by_stamp:
            g.append(stamp, T_wc)
            e.append(stamp, est_by_stamp[stamp])
    return g, e


@dataclass(frozen=True, eq=False)
class ApeResult:
    """APE of one alignment. Errors in metres and degrees; arrays are per matched frame in ground-truth order."""

    align: str
    n_gt: int
    n_est: int
    n_matched: int
    fraction: float
    trans_rmse: float
    trans_mean: float
    trans_median: float
    trans_max: float
    rot_rmse_deg: float
    rot_mean_deg: float
    rot_median_deg: float
    rot_max_deg: float
    alignment: Pose  # applied to the estimate: T_est_aligned = alignment @ (estimate with translations scaled)
    scale: float
    stamps: tuple[str, ...]
    times: np.ndarray  # float(stamp) of matched frames
    trans_err: np.ndarray
    rot_err_deg: np.ndarray
    lost_stamps: tuple[str, ...]  # ground-truth frames without an estimate
    lost_times: np.ndarray

    def summary(self) -> dict:
        """The scalar fields (JSON-ready)."""
        return {f.name: getattr(self, f.name) for f in fields(self)
                if isinstance(getattr(self, f.name), (str, int, float))}


def _stats(x: np.ndarray) -> tuple[float, float, float, float]:
    return (float(np.sqrt(np.mean(x * x))), float(np.mean(x)), float(np.median(x)), float(np.max(x)))


def _rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    """Angles of a stack of rotations (N, 3, 3), accurate near 0 and 180 degrees."""
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    tr = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    return np.degrees(np.arctan2(np.linalg.norm(v, axis=1), tr - 1.0))


def _ro(a) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    a.setflags(write=False)
    return a


def compute_ape(gt: Trajectory, est: Trajectory, align: str = "none", strict: bool = True) -> ApeResult:
    """APE of ``est`` against ``gt`` after ``align`` ("none", "se3" or "sim3"). See the module docstring."""
    if align not in ALIGNMENTS:
        raise ValueError(f"unknown alignment {align!r}; choose one of {', '.join(ALIGNMENTS)}")
    g, e = associate(gt, est, strict=strict)
    if len(g) == 0:
        raise ValueError(f"no estimated pose matches a ground-truth timestamp ({len(gt)} ground-truth, "
                         f"{len(est)} estimated frames; timestamps are matched as exact text)")
    p_gt, p_est = g.positions(), e.positions()
    R_gt = np.stack([p.R for p in g.poses])
    R_est = np.stack([p.R for p in e.poses])
    if align == "none":
        R_a, t_a, s = np.eye(3), np.zeros(3), 1.0
    else:
        R_a, t_a, s = umeyama(p_est, p_gt, with_scale=align == "sim3")
    p_al = s * p_est @ R_a.T + t_a
    R_al = R_a @ R_est  # broadcasts over the stack
    trans_err = np.linalg.norm(p_gt - p_al, axis=1)
    rot_err = _rotation_angles_deg(np.transpose(R_gt, (0, 2, 1)) @ R_al)
    matched = set(g.stamps)
    lost = tuple(s_ for s_ in gt.stamps if s_ not in matched)
    return ApeResult(
        align, len(gt), len(est), len(g), len(g) / len(gt),
        *_stats(trans_err), *_stats(rot_err),
        alignment=Pose(R_a, t_a), scale=float(s),
        stamps=tuple(g.stamps), times=_ro(g.times()), trans_err=_ro(trans_err), rot_err_deg=_ro(rot_err),
        lost_stamps=lost, lost_times=_ro([float(x) for x in lost]),
    )


def evaluate(gt: Trajectory, est: Trajectory, aligns: tuple[str, ...] = ALIGNMENTS,
             strict: bool = True) -> dict[str, ApeResult]:
    """APE for each alignment (default none, se3, sim3), keyed by alignment name.

    An alignment that is degenerate (fewer than three matched frames, collinear camera centres)
    is left out with a warning; ``none`` never is. Other errors (no match, unknown stamps) raise.
    """
    out: dict[str, ApeResult] = {}
    for a in aligns:
        try:
            out[a] = compute_ape(gt, est, a, strict=strict)
        except DegenerateAlignment as exc:
            log.warning("APE with %s alignment skipped: %s", a, exc)
    return out


def ape_first_frames(gt: Trajectory, est: Trajectory, n: int) -> tuple[str, dict]:
    """APE with no alignment of ``est`` against the first ``n`` ground-truth poses, as the localize/stream
    commands report it: a human line and the summary fields."""
    a = compute_ape(Trajectory(gt.stamps[:n], gt.poses[:n]), est, "none")
    line = (f"APE (no alignment): translation RMSE {100 * a.trans_rmse:.2f} cm, rotation RMSE {a.rot_rmse_deg:.3f} deg, "
            f"{a.fraction:.1%} of frames")
    return line, {"ape_none_trans_rmse_m": a.trans_rmse, "ape_none_rot_rmse_deg": a.rot_rmse_deg, "fraction": a.fraction}


def errors_by_source(result: ApeResult, records: dict) -> dict[str, dict]:
    """The errors of ``result``'s poses grouped by what solved each (``records``' ``source``: "features", "direct",
    "fused"; "" where the log has none): {source: {"n", "trans_rmse_m", "rot_rmse_deg", "trans_max_m",
    "rot_max_deg"}}, most poses first. A walk's error usually sits with one of them (Render & Match: the poses XFeat
    alone solved, where too few patches aligned)."""
    groups: dict[str, list[int]] = {}
    for i, s in enumerate(result.stamps):
        groups.setdefault(records[s].source if s in records else "", []).append(i)
    out = {}
    for src, idx in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        te, re = result.trans_err[idx], result.rot_err_deg[idx]
        out[src] = {"n": len(idx), "trans_rmse_m": float(np.sqrt(np.mean(te ** 2))),
                    "rot_rmse_deg": float(np.sqrt(np.mean(re ** 2))), "trans_max_m": float(te.max()),
                    "rot_max_deg": float(re.max())}
    return out


def uncertainty_check(result: ApeResult, records: dict) -> dict:
    """How the errors of ``result`` (alignment "none": the scan frame the poses claim) compare with the 1-sigma each
    pose was reported with (``records``: services.io.frame_log.read_frame_log). The 1-sigmas are the largest axis's,
    the errors 3-D: Gaussian errors as predicted put at most 2.9 % of the poses beyond 3 sigma in translation (the
    chi-square of 3 degrees of freedom beyond 9; less for an elongated covariance), as many in rotation, so at most
    ~6 % in either.
    Returns {"n": poses with a predicted sigma, "beyond_3sigma": how many exceed 3 sigma in either,
    "t_ratio_median" / "r_ratio_median": median error / sigma, and per pose the arrays "t_err_m", "r_err_deg",
    "sigma_m", "sigma_deg" and "beyond" (a mask: for the plot)}."""
    if result.align != "none":
        raise ValueError("the predicted uncertainty is in the scan frame: use the 'none' alignment's result")
    keep = [i for i, s in enumerate(result.stamps)
            if s in records and np.isfinite(records[s].sigma_m) and np.isfinite(records[s].sigma_deg)]
    sm = np.array([records[result.stamps[i]].sigma_m for i in keep], float)
    sd = np.array([records[result.stamps[i]].sigma_deg for i in keep], float)
    te, re = result.trans_err[keep], result.rot_err_deg[keep]
    beyond = (te > 3 * sm) | (re > 3 * sd)
    return {"n": len(keep), "beyond_3sigma": int(beyond.sum()), "beyond": beyond,
            "t_ratio_median": float(np.median(te / np.maximum(sm, 1e-12))) if keep else float("nan"),
            "r_ratio_median": float(np.median(re / np.maximum(sd, 1e-12))) if keep else float("nan"),
            "t_err_m": te, "r_err_deg": re, "sigma_m": sm, "sigma_deg": sd}
