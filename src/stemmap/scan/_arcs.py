"""The largest consistent arc of a candidate segment (ours, issue 11; numpy path only).

A real trunk's segment often runs on into a branch, its fillet or a stem touching it (lidR's
single tree: 7 of 9 trunks at 0.5 deg merged with a branch into one 85-98 cm segment that is
not convex and fails the ``depth`` filter). The circle fit of the whole segment follows the
branch; :func:`consensus_arcs` instead grows a circle from a short convex seed window and adds
the neighbouring returns one at a time while each new return lies within the tolerance of the
circle fitted so far (``arc_sigmas`` robust residual scales of the arc so far, at least
``arc_floor_sigmas`` range-noise sigmas), re-fitting after every addition. Every seed window is
grown; the arc with the most returns wins (ties: the smaller residual RMS). The arc then
becomes a candidate of its own (:func:`arc_pieces`): the same segment filters, fit and
plausibility tests as any candidate.

The growing fit is Kasa's (1976) algebraic circle, updated from running sums (one 3x3 solve per
step); the arc's final circle is the detector's own fit.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.scan._refit import Refitted, fit_passes
from stemmap.scan.features import footprint_correct, segment_features, segment_sum
from stemmap.scan.plausibility import segment_reasons, segment_sigma
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig
    from stemmap.scan.detect import ScanTrunkDetector

__all__ = ["arc_pieces", "consensus_arcs", "largest_arc"]

#: At most this many seed windows per segment (evenly spaced): bounds the cost of long segments.
_MAX_SEEDS = 24
#: An arc must hold at least this share of its segment's returns: a trunk that runs on into a
#: branch fills a third or more of the segment (lidR at 0.25-1 deg: 26 of 78 returns at 1.3 m,
#: 5-8 of 11-20 at 5-9 m); a 2 cm bark ridge or stub at the end of a 150-return trunk does not
#: (aRchi at 2 m, 0.25 deg: 6 of ~150 returns fitted as a 5 cm stem inside the 55 cm trunk).
_MIN_SHARE = 0.25


def _kasa(s: FloatArray) -> tuple[float, float, float] | None:
    """Kasa circle from the running sums ``s`` = (n, Sx, Sy, Sxx, Syy, Sxy, Sz, Sxz, Syz) with
    z = x^2 + y^2 (coordinates relative to a local origin); None when degenerate."""
    n, sx, sy, sxx, syy, sxy, sz, sxz, syz = s
    a = np.array([[sxx, sxy, sx], [sxy, syy, sy], [sx, sy, n]])
    rhs = np.array([sxz, syz, sz])
    try:
        u, v, w = np.linalg.solve(a, rhs)
    except np.linalg.LinAlgError:
        return None
    cx, cy = 0.5 * u, 0.5 * v
    r2 = w + cx * cx + cy * cy
    if not (r2 > 0 and math.isfinite(r2)):
        return None
    return float(cx), float(cy), math.sqrt(r2)


def _terms(x: FloatArray, y: FloatArray) -> FloatArray:
    z = x * x + y * y
    return np.stack((np.ones_like(x), x, y, x * x, y * y, x * y, z, x * z, y * z), axis=1)


def largest_arc(
    x: FloatArray,
    y: FloatArray,
    floor: float,
    k: float,
    seed: int,
    r_min: float,
    r_max: float,
    *,
    ends_only: bool = True,
) -> tuple[int, int] | None:
    """The largest run ``[a, b)`` of consecutive returns (sensor frame, origin = sensor) that
    one circle explains: grown from every ``seed``-return window whose circle has a radius in
    [r_min, r_max] and lies beyond the returns (convex towards the sensor); a neighbour joins
    when its residual is within ``max(k x 1.4826 MAD, floor)`` of the arc's current circle.
    ``ends_only``: only arcs that reach the first or the last return count (a trunk whose
    segment runs on into a branch or stem on one side; a run in the middle of a long segment
    is far more often a piece of a bush or wall that happens to be round -- on the simulator's
    clutter, 178 of 179 passing arcs were). None when no seed window qualifies."""
    n = x.shape[0]
    if n < seed:
        return None
    ox, oy = float(x.mean()), float(y.mean())
    lx, ly = x - ox, y - oy
    t = _terms(lx, ly)
    starts = range(n - seed + 1)
    if len(starts) > _MAX_SEEDS:
        starts = range(0, n - seed + 1, math.ceil((n - seed + 1) / _MAX_SEEDS))
    best: tuple[int, float, int, int] | None = None
    for a0 in starts:
        a, b = a0, a0 + seed
        s = t[a:b].sum(axis=0)
        c = _kasa(s)
        if c is None or not (r_min <= c[2] <= r_max):
            continue
        if math.hypot(c[0] + ox, c[1] + oy) <= math.hypot(lx[a:b].mean() + ox, ly[a:b].mean() + oy):
            continue  # centre not beyond the returns: concave towards the sensor
        while True:
            e = np.hypot(lx[a:b] - c[0], ly[a:b] - c[1]) - c[2]
            dev = np.abs(e - np.median(e))
            tol = max(k * 1.4826 * float(np.median(dev)), floor)
            cand = []
            for i in (a - 1, b):
                if 0 <= i < n:
                    ei = abs(math.hypot(lx[i] - c[0], ly[i] - c[1]) - c[2])
                    if ei <= tol:
                        cand.append((ei, i))
            if not cand:
                break
            _, i = min(cand)
            s2 = s + t[i]
            c2 = _kasa(s2)
            if c2 is None or not (r_min <= c2[2] <= r_max):
                break
            s, c = s2, c2
            a, b = (i, b) if i < a else (a, i + 1)
        if ends_only and a > 0 and b < n:
            continue  # not at an end: a trunk runs on into a branch on one side
        e = np.hypot(lx[a:b] - c[0], ly[a:b] - c[1]) - c[2]
        rms = float(np.sqrt(np.mean(e * e)))
        key = (b - a, -rms)
        if best is None or key > (best[0], -best[1]):
            best = (b - a, rms, a, b)
    return None if best is None else (best[2], best[3])


def consensus_arcs(segs: Segments, cfg: DetectorConfig) -> NDArray[np.bool_]:
    """Per return of ``segs``, whether it lies on its segment's largest consistent arc
    (:func:`largest_arc`, seed ``max(min_points, 4)`` returns, ``arc_sigmas``, floor the RMS
    ``arc_floor_sigmas`` x the segment's range noise), holding at least ``min_points_partial``
    returns (with ``arc_short_steps``: ``min_points`` when a range step sets the arc off at
    every cut end) and a quarter of the segment's."""
    p = segs.points
    keep = np.zeros(len(p), dtype=bool)
    if len(segs) == 0:
        return keep
    mean_r = segment_sum(p.r, segs) / segs.counts
    sigma = segment_sigma(cfg, segs, mean_r)
    seed = max(cfg.min_points, 4)
    # arc_short_steps: a shorter arc counts when a range step sets it off (_stepped)
    least = cfg.min_points if cfg.arc_short_steps else cfg.min_points_partial
    for j, (a, b) in enumerate(zip(segs.start, segs.stop, strict=True)):
        # the noise only, not the bark allowance of the RMS test: a fillet leaves the circle
        # gradually and its first returns lie within a few cm of it
        floor = cfg.arc_floor_sigmas * float(sigma[j])
        got = largest_arc(
            p.x[a:b], p.y[a:b], floor, cfg.arc_sigmas, seed, cfg.min_radius, cfg.max_radius
        )
        if got is None:
            continue
        lo, hi = got
        if max(least, _MIN_SHARE * (b - a)) <= hi - lo < b - a and (
            hi - lo >= cfg.min_points_partial or _stepped(p.r[a:b], lo, hi, cfg.max_jump)
        ):
            keep[a + lo : a + hi] = True
    return keep


def _stepped(r: FloatArray, lo: int, hi: int, step: float) -> bool:
    """Whether the run ``[lo, hi)`` of a segment's ranges ``r`` is separated from the rest of
    the segment by a range step larger than ``step`` at every cut end (``arc_short_steps``)."""
    cuts = []
    if lo > 0:
        cuts.append(abs(float(r[lo - 1] - r[lo])))
    if hi < r.shape[0]:
        cuts.append(abs(float(r[hi] - r[hi - 1])))
    return bool(cuts) and min(cuts) > step


def _cut_flags(sub: Segments, pieces: Segments, idx: NDArray[np.int64], margin: float) -> Segments:
    """Occlusion at a piece's cut ends by the rule of ``build_segments``: occluded only when
    the return across the cut is nearer by more than ``margin`` (a branch going on at the
    trunk's range does not make the trunk partial)."""
    r = sub.points.r
    lab = sub.labels
    first = idx[pieces.start]
    last = idx[pieces.stop - 1]
    seg = lab[first]
    cut_s = first > sub.start[seg]
    cut_e = last < sub.stop[seg] - 1
    occ_s = np.where(
        cut_s, r[np.maximum(first - 1, 0)] < r[first] - margin, sub.occluded_start[seg]
    )
    occ_e = np.where(
        cut_e, r[np.minimum(last + 1, len(r) - 1)] < r[last] - margin, sub.occluded_end[seg]
    )
    return Segments(
        pieces.points,
        pieces.start,
        pieces.stop,
        pieces.scan,
        occ_s,
        occ_e,
        pieces.truncated_start,
        pieces.truncated_end,
    )


def arc_pieces(
    detector: ScanTrunkDetector,
    segs: Segments,
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
    *,
    corrected: bool,
) -> Refitted | None:
    """The largest consistent arcs of the segments ``which`` of ``segs``, as new candidates:
    segment filters, footprint correction (unless the returns are ``corrected`` already), the
    detector's fit and its plausibility tests. ``parent`` indexes ``segs``."""
    cfg = detector.config
    if not np.any(which):
        return None
    sub = segs.select(which)
    keep = consensus_arcs(sub, cfg)
    if not np.any(keep):
        return None
    idx = np.flatnonzero(keep)
    pieces = _cut_flags(sub, sub.split(keep), idx, cfg.occlusion_margin)
    parent = np.flatnonzero(which)[sub.labels[idx[pieces.start]]]
    good = segment_reasons(pieces, segment_features(pieces), cfg) == 0
    if not np.any(good):
        return None
    pieces, parent = pieces.select(good), parent[good]
    if not corrected and cfg.beam_footprint_deg > 0:
        pieces = footprint_correct(pieces, math.radians(cfg.beam_footprint_deg))
    refit = detector._fit_candidates(pieces, grid, wrap)
    # the arc holds the returns that lie on one circle within the noise: the RMS test without
    # the bark allowance (with it, round pieces of the simulator's bushes at 2-3 sigma passed)
    ok = fit_passes(replace(cfg, bark_roughness=0.0), refit)
    return Refitted(pieces, refit, ok, parent.astype(np.int64))
