"""The largest consistent arc of a candidate segment (ours, issue 11): the numpy pipeline's
arc candidates.

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
step); the arc's final circle is the detector's own fit. The search itself is compiled
(:mod:`stemmap.scan._fast_arcs`) and shared with the compiled detector, which judges the arc
with the same tests (tests/scan/test_detect_fast.py compares the two paths).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtri

from stemmap.scan._fast_arcs import ARC_WORK_ROWS, arc_run
from stemmap.scan._fast_arcs import largest_arc as _largest_arc
from stemmap.scan._kernel_params import kernel_params
from stemmap.scan._refit import Refitted, fit_passes
from stemmap.scan.features import footprint_correct, segment_features, segment_sum
from stemmap.scan.plausibility import segment_reasons, segment_sigma
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan._segment_fits import _Fitted
    from stemmap.scan.config import DetectorConfig
    from stemmap.scan.detect import ScanTrunkDetector

__all__ = ["arc_pieces", "arc_tests", "consensus_arcs", "largest_arc", "piece_passes"]


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
    one circle explains (:func:`stemmap.scan._fast_arcs.largest_arc`, the compiled search
    both detector paths run): grown from every ``seed``-return window whose circle has a
    radius in [r_min, r_max] and lies beyond the returns (convex towards the sensor); a
    neighbour joins when its residual is within ``max(k x 1.4826 MAD, floor)`` of the arc's
    current circle. ``ends_only``: only arcs that reach the first or the last return count.
    None when no seed window qualifies."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    n = x.shape[0]
    work = np.empty((ARC_WORK_ROWS, max(n, 9)))
    lo, hi = _largest_arc(x, y, 0, n, floor, k, seed, r_min, r_max, ends_only, work)
    return None if lo < 0 else (int(lo), int(hi))


def consensus_arcs(segs: Segments, cfg: DetectorConfig) -> NDArray[np.bool_]:
    """Per return of ``segs``, whether it lies on its segment's largest consistent arc
    (:func:`largest_arc`, seed ``max(min_points, 4)`` returns, ``arc_sigmas``, floor the RMS
    ``arc_floor_sigmas`` x the segment's range noise), holding at least ``min_points_partial``
    returns (with ``arc_short_steps``: ``min_points`` when a range step sets the arc off at
    every cut end) and a quarter of the segment's (:func:`stemmap.scan._fast_arcs.arc_run`,
    which the compiled path calls too)."""
    p = segs.points
    keep = np.zeros(len(p), dtype=bool)
    if len(segs) == 0:
        return keep
    mean_r = segment_sum(p.r, segs) / segs.counts
    sigma = segment_sigma(cfg, segs, mean_r)
    # the arc's parameters as the kernel reads them (the scan layout does not matter here)
    prm = kernel_params(cfg, 0.0, math.inf, 1.0, -1, len(p), False)
    px = np.ascontiguousarray(p.x)
    py = np.ascontiguousarray(p.y)
    pr = np.ascontiguousarray(p.r)
    work = np.empty((ARC_WORK_ROWS, max(int(segs.counts.max()), 9)))
    for j, (a, b) in enumerate(zip(segs.start, segs.stop, strict=True)):
        lo, hi = arc_run(px, py, pr, int(a), int(b), float(sigma[j]), prm, work)
        if lo >= 0:
            keep[a + lo : a + hi] = True
    return keep


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
    return Refitted(pieces, refit, piece_passes(cfg, pieces, refit), parent.astype(np.int64))


def piece_passes(cfg: DetectorConfig, pieces: Segments, fitted: _Fitted) -> NDArray[np.bool_]:
    """Whether each piece of a merged candidate (an arc of ``arc_refit``, a piece of
    ``split_search``; fitted: ``fitted``) passes the tests of a piece: the fit plausibility
    tests without the bark allowance (the piece holds the returns that lie on one circle
    within the noise; with it, round pieces of the simulator's bushes at 2-3 sigma passed)
    and :func:`arc_tests` (tangent range, chi-square)."""
    ok: NDArray[np.bool_] = fit_passes(replace(cfg, bark_roughness=0.0), fitted)
    return ok & arc_tests(cfg, pieces, fitted)


def arc_tests(cfg: DetectorConfig, pieces: Segments, fitted: _Fitted) -> NDArray[np.bool_]:
    """Whether each arc of ``pieces`` (fitted: ``fitted``) passes the fifteenth round's
    tests (:func:`stemmap.scan._fast_arcs.arc_consistent`, the same arithmetic): with
    ``arc_chi2`` its residuals are the range noise (``n x RMS^2 <= chi2_0.99(n - 3) x
    sigma^2`` over its n returns); with a finite ``arc_tangent_sigmas`` k none of its returns
    lies farther than the circle's tangent range ``sqrt(d^2 - r^2)`` (centre at range d) by
    more than ``k sqrt(sigma^2 + (bark_roughness x r)^2)``: a first return of a convex trunk
    comes from its visible half."""
    ok = np.ones(len(pieces), dtype=bool)
    if len(pieces) == 0:
        return ok
    n = pieces.counts
    sig, rms, r = fitted.sigma, fitted.rms, fitted.radii
    if cfg.arc_chi2:
        dof = n - 3
        limit = chdtri(np.maximum(dof, 1).astype(np.float64), 0.01)
        ok &= ~((n > 3) & (n * rms * rms > limit * sig * sig))
    k = cfg.arc_tangent_sigmas
    if math.isfinite(k):
        cx, cy = fitted.centers[:, 0], fitted.centers[:, 1]
        d2 = cx * cx + cy * cy - r * r
        far = np.maximum.reduceat(pieces.points.r, pieces.start)
        br = cfg.bark_roughness * r
        with np.errstate(invalid="ignore"):
            ok &= (d2 > 0.0) & ~(far - np.sqrt(d2) > k * np.sqrt(sig * sig + br * br))
    return ok
