"""When a relocalization must be refused: another place fits the frame about as well.

Shared by Render & Match's database (services.relocalize.database) and the light P&L localizer
(services.localize.pnl); numpy only, so the client imports it without torch.

Repetitive sites are the reason: identical rack aisles, office floors. A cold frame in a warehouse aisle matched a
wrong aisle 12.8 m away with 39 coarse inliers, while six other places had 20-23 each. Rendering at the wrong aisle
confirmed it (89 inliers; the true place gives 78), and the wrong pose would have been reported. So a place is
refused when

- another place has ``ambiguity`` x its inliers (0.8: a second place fits about as well), or,
- with ``far_ambiguity`` (0.5, for frames with no recent pose to search near), ``FAR_RIVALS`` places more than
  ``FAR_M`` away have that share. One such place alone can be a chance solution (a small office: 28 inliers
  against 55, turned 180 degrees); several mean a repetitive site.

Rivals within ``FAR_M`` are mostly not places of their own: one view's coarse pose of the same place a metre off
(office: 39 inliers 1.0 m off, against 47) or a solution turned 90 degrees on the spot (32 against 38). A caller
that can check them (Render & Match renders there and matches again) passes ``verify``.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable

from services.geometry.se3 import Pose

__all__ = ["FAR_M", "FAR_RIVALS", "distinct", "rival"]

FAR_M = 2.0  # a rival this far away is another place, not a coarse pose of the same one (one view's PnP: <= 1.5 m off)
FAR_RIVALS = 2  # this many look-alike places (``far_ambiguity``) make a repetitive site


def distinct(a: Pose, b: Pose) -> bool:
    """Two poses at different places (more than 1 m or 20 degrees apart), not two estimates of one."""
    dt, dr = a.distance_to(b)
    return dt > 1.0 or dr > 20.0


def rival(best: Pose, support: int, others: Iterable[tuple[Pose, int, Any]], ambiguity: float = 0.8,
          far_ambiguity: float | None = None, verify: Callable[[Any], bool] | None = None,
          verify_far: Callable[[Any], bool] | None = None) -> str | None:
    """Why the place ``best`` (``support`` inliers) is ambiguous among ``others`` (pose, inliers, caller's tag),
    or None when it is not. ``verify(tag)`` decides for rivals within ``FAR_M`` that reach ``ambiguity``: True
    when the rival is a place of its own (see the module docstring); ``verify_far(tag)`` the same for rivals
    further away (without it they are refused unseen). A far place that a render there confirms is a look-alike
    (the warehouse's wrong aisle: 89 inliers against the true one's 78); one it does not confirm was a chance fit
    (office seed 90's cold frames: 56 coarse inliers 6.1 m / 92 deg away against 64)."""
    alike: list[Pose] = []
    for T, n, tag in others:
        if not distinct(best, T):
            continue
        dt, dr = best.distance_to(T)
        if n >= ambiguity * support:
            check = verify if dt <= FAR_M else verify_far
            if check is not None:
                if check(tag):
                    return f"a place {dt:.1f} m / {dr:.0f} deg away verified too"
                continue
            return f"{n} inliers at a place {dt:.1f} m / {dr:.0f} deg away, against {support}"
        far = far_ambiguity is not None and dt > FAR_M and n >= far_ambiguity * support
        if far and all(distinct(T, a) for a in alike):
            alike.append(T)
            if len(alike) >= FAR_RIVALS:
                m = sorted(best.distance_to(a)[0] for a in alike)
                return (f"{len(alike)} places {m[0]:.0f}-{m[-1]:.0f} m away have over {100 * far_ambiguity:.0f} % "
                        f"of its {support} inliers")
    return None
