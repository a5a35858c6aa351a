"""Drop a candidate's end returns that lie behind its own circle (ours, issue 11; numpy path).

A circle of radius ``r`` whose centre lies ``d`` from the sensor shows the sensor only the
returns between its nearest point (range ``d - r``) and its two tangent points, at range
``sqrt(d^2 - r^2)``: nothing a beam returns from the trunk lies farther than that. A
first-echo (nearest-return) beam reports the nearest surface in its cell, so a trunk's own
edge return is nearer than the tangent range even when the footprint shifts it sideways by
up to a cell (the tangential offset that makes an edge return and a stub's return look alike
to a residual test, scan-detection-history.md tenth round). A return *farther* than the
tangent range is something behind the trunk's silhouette: on lidR's single tree
(scan-detection-history.md, thirteenth round) the Y branch running away from the sensor
behind the stem and a stub on the stem's far flank, which the range-adaptive segmentation
joins to the trunk because the range step is below its threshold at that range (8-35 cm at
5-9 m) and which pull the fit by +5 to +10 cm in diameter.

:func:`trim_behind` tests each end of every fitted candidate against the circle fitted
*without* that end return (a deletion test: the circle fitted with it is pulled towards it):
the end goes when that circle passes every fit test (only a credible trunk says what lies
behind it) and the end's range exceeds its tangent range by more than ``behind_sigmas`` noise
scales ``sqrt(sigma^2 + (bark_roughness r)^2)`` (the RMS test's scale); the test repeats on
the new ends until no end is behind or the candidate is down to ``max(min_points,
min_points_partial)`` returns. A trimmed end is a true silhouette edge (what was next to it is
farther), so it is marked neither occluded nor truncated. The trimmed candidates are fitted
again and judged by the usual tests; one that fails keeps its returns and fit. Only accepted
candidates are trimmed (the detector's main fit and the validated corner split's pieces): the
trimmed remainder of a rejected one passed as a false trunk (aRchi's lobed trunk, 0.5 deg: a
7-return bark ridge trimmed to a 6 cm "stem").

The rule is one-sided: a return *nearer* than the tangent range may be the trunk's own, so
the fillet of a branch coming towards the sensor is not cut by it (``arc_replace`` is the
tool for that).

Cost: two extra fits per candidate and trimming step (numpy path only; the compiled kernel
fits each candidate once).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from stemmap.scan._refit import fit_passes
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.detect import ScanTrunkDetector, _Fitted

__all__ = ["behind_ends", "tangent_range", "trim_behind"]


def tangent_range(centers: FloatArray, radii: FloatArray) -> FloatArray:
    """Range ``sqrt(d^2 - r^2)`` of the tangent points of circles (sensor at the origin),
    shape (K,); NaN where the sensor is inside the circle."""
    d2 = centers[:, 0] ** 2 + centers[:, 1] ** 2
    r2 = radii * radii
    with np.errstate(invalid="ignore"):
        out: FloatArray = np.where(d2 > r2, np.sqrt(d2 - r2), np.nan)
    return out


def behind_ends(
    detector: ScanTrunkDetector, segs: Segments, grid: FloatArray, wrap: bool
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Per segment of ``segs`` (each with >= 2 returns), whether its first / its last return
    lies farther than the tangent range of the circle the detector fits to the other returns,
    by more than ``behind_sigmas`` noise scales (module docstring)."""
    cfg = detector.config
    r = segs.points.r
    out = []
    for end in (segs.start, segs.stop - 1):
        keep = np.ones(len(segs.points), dtype=bool)
        keep[end] = False
        f = detector._fit_candidates(segs.drop(keep), grid, wrap)
        # only a circle that is a trunk by every test says what lies behind it
        good = fit_passes(cfg, f)
        br = cfg.bark_roughness * f.radii
        scale = np.sqrt(f.sigma * f.sigma + br * br)
        t = tangent_range(f.centers, f.radii)
        with np.errstate(invalid="ignore"):
            out.append(good & np.isfinite(t) & (r[end] > t + cfg.behind_sigmas * scale))
    return out[0], out[1]


def _merge(fitted: _Fitted, rows: NDArray[np.int64], new: _Fitted) -> _Fitted:
    """``fitted`` with its rows ``rows`` replaced by the rows of ``new`` (same order)."""
    vals: list[np.ndarray | None] = []
    for old, upd in zip(fitted, new, strict=True):
        if old is None or upd is None:
            vals.append(old)
            continue
        a = old.copy()
        a[rows] = upd
        vals.append(a)
    return type(fitted)._make(vals)


#: An end test: per segment, whether its first / its last return goes (:func:`behind_ends`).
EndTest = Callable[
    ["ScanTrunkDetector", Segments, FloatArray, bool],
    tuple[NDArray[np.bool_], NDArray[np.bool_]],
]


def trim_behind(
    detector: ScanTrunkDetector,
    segs: Segments,
    fitted: _Fitted,
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
    *,
    ends: EndTest = behind_ends,
) -> tuple[Segments, _Fitted]:
    """``segs`` without the end returns that lie behind their candidate's circle, for the
    candidates ``which`` (module docstring), and the fits of the trimmed candidates; a
    trimmed candidate that fails a test keeps its returns and fit. The same segments in the
    same order. ``ends`` replaces the test (:func:`stemmap.scan._stubs.outward_ends`: returns
    outside the circle)."""
    cfg = detector.config
    least = max(cfg.min_points, cfg.min_points_partial)
    keep = np.ones(len(segs.points), dtype=bool)
    cut_start = np.zeros(len(segs), dtype=bool)
    cut_end = np.zeros(len(segs), dtype=bool)
    act = (segs.counts > least) & which
    while np.any(act):
        cur = segs.drop(keep)  # every segment keeps >= least returns: same indexing
        ids = np.flatnonzero(act)
        sub = cur.select(act)
        first, last = ends(detector, sub, grid, wrap)
        n = sub.counts
        # both ends behind but room for one: the first goes now, the last is tested again
        last &= ~first | (n - 2 >= least)
        alive = np.flatnonzero(keep)
        keep[alive[cur.start[ids[first]]]] = False
        keep[alive[cur.stop[ids[last]] - 1]] = False
        cut_start[ids[first]] = True
        cut_end[ids[last]] = True
        act = np.zeros(len(segs), dtype=bool)
        act[ids[(first | last) & (n - first - last > least)]] = True
    rows = np.flatnonzero(cut_start | cut_end)
    if rows.size == 0:
        return segs, fitted
    sel = np.zeros(len(segs), dtype=bool)
    sel[rows] = True
    trimmed = _flagged(segs.drop(keep), cut_start, cut_end)
    refit = detector._fit_candidates(trimmed.select(sel), grid, wrap)
    passed = fit_passes(cfg, refit)
    if not np.any(passed):
        return segs, fitted
    # a trimmed candidate that fails a test keeps its returns (and its verdict)
    undo = np.zeros(len(segs), dtype=bool)
    undo[rows[~passed]] = True
    keep |= undo[segs.labels]
    cut_start &= ~undo
    cut_end &= ~undo
    out = _flagged(segs.drop(keep), cut_start, cut_end)
    return out, _merge(fitted, rows[passed], _take(refit, passed))


def _flagged(segs: Segments, cut_start: NDArray[np.bool_], cut_end: NDArray[np.bool_]) -> Segments:
    """A trimmed end is a true silhouette edge: neither occluded nor truncated."""
    return Segments(
        segs.points,
        segs.start,
        segs.stop,
        segs.scan,
        segs.occluded_start & ~cut_start,
        segs.occluded_end & ~cut_end,
        segs.truncated_start & ~cut_start,
        segs.truncated_end & ~cut_end,
    )


def _take(fitted: _Fitted, rows: NDArray[np.bool_]) -> _Fitted:
    """The rows ``rows`` of ``fitted``."""
    return type(fitted)._make(None if v is None else v[rows] for v in fitted)
