"""How well a scan's stations agree: its registration error, measured from the scan itself.

Where two stations saw the same surface their points should lie on it together. A registration off by ``s`` leaves
one station's points off the other's surface along its normal. For a sample of each station's points on flat
surfaces this measures the distance to the *other* station's local plane (``between``) and to the station's *own*
local plane, the point left out (``own``: the scanner's range noise, which ``between`` holds as well), each an RMS
over the nearest 95 % (a plane fitted across an edge or to clutter is no surface's). The
registration's share of a pair is ``sqrt(between² - own²)``; the scan's error is its RMS over the pairs, weighted by
how many points they share: what a registration report's cloud-to-cloud error says, and the number
``cristal localize/serve --scan-sigma-mm`` takes (``services/localize/scan_error.py``).

Needs each point's station: ``meta["station_points"]`` (E57 files, simulated scans, PLY written by cristal). Only
each station's ``neighbours`` nearest stations are compared, and each k-d tree holds at most ``max_tree_points``
points, so a 300 M-point survey costs one tree at a time.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from services.io.scan import Scan
from services.io.scans import station_points
from services.log import progress

__all__ = ["PairAgreement", "StationAgreement", "station_agreement"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairAgreement:
    a: int  # the station whose points were sampled ...
    b: int  # ... against this one's surfaces
    n: int  # sampled points of a on a flat surface of b
    between_m: float  # RMS distance of those points to b's local plane
    own_m: float  # RMS distance of the same points to a's own local plane (range noise)

    @property
    def registration_m(self) -> float:
        return math.sqrt(max(0.0, self.between_m ** 2 - self.own_m ** 2))


@dataclass
class StationAgreement:
    stations: int
    pairs: list[PairAgreement] = field(default_factory=list)

    def _pooled(self, value) -> float:
        """RMS of ``value(pair)`` over the pairs, weighted by their shared points (NaN when no two share a surface)."""
        w = sum(p.n for p in self.pairs)
        return math.sqrt(sum(p.n * value(p) ** 2 for p in self.pairs) / w) if w else float("nan")

    @property
    def registration_m(self) -> float:
        """The scan's registration error: the pairs' registration share, pooled."""
        return self._pooled(lambda p: p.registration_m)

    @property
    def noise_m(self) -> float:
        """The range noise, pooled the same way."""
        return self._pooled(lambda p: p.own_m)

    def station_sigmas_m(self, prior_weight: float = 0.001) -> np.ndarray:
        """Each station's own registration error (m; NaN for a station that shares no surface): a pair's
        disagreement is both stations' errors, ``registration² = s_a² + s_b²``, solved over all pairs by least squares
        weighted by their shared points (non-negative). A station's error is told from its neighbours' only where it
        has two or more that do not share one another's error; ``prior_weight`` (relative to a pair's mean weight)
        draws each towards half the pooled pair (what they are when all are alike: two stations alone split it)."""
        from scipy.optimize import lsq_linear

        out = np.full(self.stations, np.nan)
        if not self.pairs:
            return out
        seen = sorted({p.a for p in self.pairs} | {p.b for p in self.pairs})
        col = {s: k for k, s in enumerate(seen)}
        n = np.array([p.n for p in self.pairs], float)
        w = np.sqrt(n / n.mean())
        A = np.zeros((len(self.pairs) + len(seen), len(seen)))
        b = np.zeros(len(A))
        for r, p in enumerate(self.pairs):
            A[r, col[p.a]] = A[r, col[p.b]] = w[r]
            b[r] = w[r] * (1e3 * p.registration_m) ** 2  # (mm²: the solver's tolerances are absolute)
        lam = math.sqrt(prior_weight)
        A[len(self.pairs):] = lam * np.eye(len(seen))
        b[len(self.pairs):] = lam * 0.5 * (1e3 * self.registration_m) ** 2
        x = lsq_linear(A, b, bounds=(0.0, np.inf)).x
        out[seen] = 1e-3 * np.sqrt(x)
        return out

    def loose_stations(self, own_m: np.ndarray | None = None, factor: float = 3.0, min_m: float = 0.002) -> list[int]:
        """The stations whose own error (``own_m``, :meth:`station_sigmas_m` when not given) is ``factor`` times the
        stations' median and at least ``min_m``: a setup the registration held weakly (few targets, a corridor). Needs
        three stations that share."""
        s = self.station_sigmas_m() if own_m is None else np.asarray(own_m, float)
        ok = np.isfinite(s)
        if ok.sum() < 3:
            return []
        return [int(k) for k in np.flatnonzero(ok & (s >= max(factor * float(np.median(s[ok])), min_m)))]


def _plane_distances(tree, pts: np.ndarray, k: int, radius_m: float, skip_self: bool) -> np.ndarray:
    """Distance of each of ``pts`` to the plane through its ``k`` nearest tree points within ``radius_m`` (NaN where
    they are fewer or not flat: an edge, a corner, clutter)."""
    kk = k + int(skip_self)
    d, i = tree.query(pts, k=kk, distance_upper_bound=radius_m)
    if skip_self:
        d, i = d[:, 1:], i[:, 1:]
    ok = np.isfinite(d).all(axis=1)
    out = np.full(len(pts), np.nan)
    if not ok.any():
        return out
    P = tree.data[i[ok]]  # (M, k, 3)
    c = P.mean(axis=1)
    Q = P - c[:, None]
    w, v = np.linalg.eigh(np.einsum("mki,mkj->mij", Q, Q))
    flat = w[:, 0] < 0.05 * w[:, 1]
    dist = np.abs(np.einsum("mi,mi->m", pts[ok] - c, v[:, :, 0]))
    out[np.flatnonzero(ok)[flat]] = dist[flat]
    return out


def _rms(x: np.ndarray, keep: float = 0.95) -> float:
    """RMS of the smallest ``keep`` of ``x``: a plane fitted across an edge or to clutter is no surface's."""
    if not len(x):
        return float("nan")
    x = np.sort(np.abs(x))[:max(1, int(np.ceil(keep * len(x))))]
    return float(np.sqrt(np.mean(x ** 2)))


def station_agreement(scan: Scan, sample: int = 20_000, k: int = 10, radius_m: float = 0.1, max_offset_m: float = 0.05,
                      neighbours: int = 6, max_tree_points: int = 2_000_000, min_shared: int = 200,
                      seed: int = 0) -> StationAgreement | None:
    """The stations' agreement (see the module); None when the scan does not say which points each station has, or
    has fewer than two stations. A plane is fitted to ``k`` neighbours within ``radius_m``; a point farther than
    ``max_offset_m`` from the other station's plane is taken to lie on another surface (so a registration off by
    more than a few centimetres reads low: it is broken, not imprecise)."""
    from scipy.spatial import cKDTree

    counts = station_points(scan)
    if counts is None or len(counts) < 2:
        return None
    edges = np.concatenate([[0], np.cumsum(counts)])
    centres = np.array([s.t for s in scan.stations]) - scan.origin
    rng = np.random.default_rng(seed)

    def points(s: int, m: int) -> np.ndarray:
        a, b = int(edges[s]), int(edges[s + 1])
        idx = np.arange(a, b) if b - a <= m else np.sort(rng.choice(np.arange(a, b), m, replace=False))
        return np.asarray(scan.xyz[idx], np.float64)

    S = len(counts)
    order = np.argsort(np.linalg.norm(centres[:, None] - centres[None], axis=2), axis=1)[:, 1:neighbours + 1]
    samples = [points(s, sample) for s in range(S)]
    against = {b: [a for a in range(S) if b in order[a]] for b in range(S)}
    own: dict[int, np.ndarray] = {}
    between: dict[tuple[int, int], np.ndarray] = {}
    for b in progress(range(S), desc="station agreement", total=S, unit="station"):
        if counts[b] < k + 1:
            continue
        tree = cKDTree(points(b, max_tree_points))
        own[b] = _plane_distances(tree, samples[b], k, radius_m, skip_self=True)
        for a in against[b]:
            between[(a, b)] = _plane_distances(tree, samples[a], k, radius_m, skip_self=False)
    out = StationAgreement(S)
    for (a, b), d in sorted(between.items()):
        if a not in own:
            continue
        both = np.isfinite(d) & np.isfinite(own[a]) & (d < max_offset_m)  # (farther: another surface)
        if both.sum() >= min_shared:
            out.pairs.append(PairAgreement(a, b, int(both.sum()), _rms(d[both]), _rms(own[a][both])))
    log.info("station agreement: %d stations, %d pairs sharing surfaces, registration %.1f mm (range noise %.1f mm)",
             S, len(out.pairs), 1e3 * out.registration_m, 1e3 * out.noise_m)
    return out
