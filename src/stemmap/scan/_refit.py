"""Re-fit the pieces of candidates that fail the RMS test (ours, issue 11).

A real trunk's segment often holds more than the trunk: the fillet where a branch leaves the
bark (returns 2-10 cm outside the circle over several beams), a stub, a thin stem touching it.
The circle fit follows them and the RMS test rejects the whole candidate although most of its
returns lie on a circle. :func:`refit_pieces` drops the returns that are outliers of the failed
fit (farther than ``refit_sigmas`` robust residual scales from the median residual, and beyond
the RMS limit), splits the segment there and fits every piece again; the pieces then pass the
same segment filters and plausibility tests as any candidate. One pass only: a piece that
fails again is dropped.

``refit_split="corners"`` cuts a candidate rejected as not convex (``depth``) or by the RMS
test at its concave corners (:func:`corner_cut_pieces`, the rule of ``split_corners``), the
junctions where a trunk touches a stem, branch or bush. With ``refit_validate`` a cut counts
only when it explains the whole candidate (:func:`validate_pieces`): every piece with enough
returns to be judged passes every test and the pieces' circles are disjoint; otherwise the
candidate keeps its verdict (rejected). ``split_corners`` cuts every candidate before the fit
and keeps whichever piece passes, so a bush or wall cut into pieces can pass as trunks
(scan-detection-history.md, ninth round).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from stemmap.scan.features import (
    footprint_correct,
    sagitta_depth,
    segment_features,
    segment_sum,
)
from stemmap.scan.plausibility import (
    REASONS,
    fitted_reasons,
    rms_limit,
    segment_reasons,
    segment_sigma,
)
from stemmap.scan.segment import Segments, concave_corners, split_largest_gap
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig
    from stemmap.scan.detect import ScanTrunkDetector, _Fitted

__all__ = [
    "Refitted",
    "corner_cut_pieces",
    "fit_passes",
    "judge_pieces",
    "outlier_returns",
    "refit_pieces",
    "split_refit",
    "validate_pieces",
]

_RMS = REASONS.index("rms")
_DEPTH = REASONS.index("depth")


class Refitted(NamedTuple):
    """The re-fitted pieces (``segs``, ``fitted``), which of them pass every test (``ok``) and
    the candidate each piece came from (``parent``, an index into the first pass)."""

    segs: Segments
    fitted: _Fitted
    ok: NDArray[np.bool_]
    parent: NDArray[np.int64]


def outlier_returns(
    segs: Segments,
    centers: FloatArray,
    radii: FloatArray,
    floor: FloatArray,
    k: float,
    *,
    ends_only: bool = False,
) -> NDArray[np.bool_]:
    """Per return, whether it is an outlier of its segment's circle: ``|e_i - median(e)| >
    max(k x 1.4826 MAD(e), floor)`` with ``e_i = |p_i - c| - r`` (medians: the mean of the two
    middle values for an even count)."""
    p = segs.points
    out = np.zeros(len(p), dtype=bool)
    for j, (a, b) in enumerate(zip(segs.start, segs.stop, strict=True)):
        e = np.hypot(p.x[a:b] - centers[j, 0], p.y[a:b] - centers[j, 1]) - radii[j]
        dev = np.abs(e - np.median(e))
        scale = 1.4826 * float(np.median(dev))
        bad = dev > max(k * scale, floor[j])
        if ends_only:  # only the runs of outliers at either end (a fillet, a stub)
            lo = int(np.argmin(bad)) if not bad.all() else bad.shape[0]
            hi = int(np.argmin(bad[::-1])) if not bad.all() else bad.shape[0]
            bad[:] = False
            bad[:lo] = True
            bad[bad.shape[0] - hi :] = True
        out[a:b] = bad
    return out


def corner_cut_pieces(
    segs: Segments, cfg: DetectorConfig, *, min_points: int | None = None
) -> tuple[Segments, NDArray[np.int64]]:
    """Cut trunks merged with a branch, bush or second stem at the junctions (ours, issue 11):
    at the concave corners (:func:`~stemmap.scan.segment.concave_corners`) deeper than
    ``corner_depth`` in a segment that is not a convex arc (sagitta below ``max(min_depth,
    0)``), deeper than ``corner_depth_convex`` in a convex one (the dents of rough bark on a
    trunk's own arc are not junctions), and at least ``corner_sigmas`` range-noise sigmas deep
    (noise alone makes no corner); the corner return is dropped and pieces with fewer than
    ``min_points`` (default ``cfg.min_points``) returns go. Returns the pieces and the segment
    of ``segs`` each came from."""
    keep_min = cfg.min_points if min_points is None else min_points
    thr = np.where(
        sagitta_depth(segs) < max(cfg.min_depth, 0.0), cfg.corner_depth, cfg.corner_depth_convex
    )
    sigma = segment_sigma(cfg, segs, segment_sum(segs.points.r, segs) / segs.counts)
    thr = np.maximum(thr, cfg.corner_sigmas * sigma)
    cuts = concave_corners(segs, cfg.corner_span, thr[segs.labels])
    if not np.any(cuts):
        big = segs.counts >= keep_min
        return segs.select(big), np.flatnonzero(big).astype(np.int64)
    # the junction return itself belongs to neither piece (the same cut in either beam order)
    pieces = segs.cut(np.cumsum(cuts) % 2 == 1).drop(~cuts)
    parent = segs.labels[np.flatnonzero(~cuts)[pieces.start]].astype(np.int64)
    big = pieces.counts >= keep_min
    return pieces.select(big), parent[big]


def validate_pieces(
    parent: NDArray[np.int64],
    seg_codes: NDArray[np.int8],
    fit_ok: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """Per piece, whether its cut is accepted (``refit_validate``; ours, issue 11): the piece
    passes the segment filters and the fit tests (``fit_ok``), every other piece of the same
    parent that passed the segment filters (a circle-like piece) passes the fit tests too,
    and it is the only passing piece of its parent. A parent that breaks either keeps its own
    verdict: none of its pieces is accepted. The merges of the real slices are one trunk
    and a piece that is no trunk (2-3 returns of a stem, a branch leaving the bark); two
    passing arcs meeting at a concave corner were the faces of one rock or bush on the
    simulator (scan-detection-history.md, ninth round)."""
    shaped = seg_codes == 0
    passed = shaped & fit_ok
    n_par = int(parent.max()) + 1 if parent.size else 0
    veto = np.zeros(n_par, dtype=bool)
    veto[parent[shaped & ~fit_ok]] = True
    veto |= np.bincount(parent[passed], minlength=n_par) > 1
    ok: NDArray[np.bool_] = passed & ~veto[parent]
    return ok


def _returns_inside(
    parent_segs: Segments, parent: NDArray[np.int64], fitted: _Fitted, ok: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """Per piece, whether a return of its parent segment lies inside the piece's circle by
    more than 3 noise sigmas: a trunk hides what is behind it and nothing stands inside it,
    so such a piece is an arc of something larger (a rock or bush face), not a trunk."""
    out = np.zeros(parent.shape[0], dtype=bool)
    p = parent_segs.points
    for i in np.flatnonzero(ok):
        a, b = parent_segs.start[parent[i]], parent_segs.stop[parent[i]]
        d = np.hypot(p.x[a:b] - fitted.centers[i, 0], p.y[a:b] - fitted.centers[i, 1])
        out[i] = bool(np.any(d < fitted.radii[i] - 3.0 * fitted.sigma[i]))
    return out


def split_refit(
    detector: ScanTrunkDetector,
    every: Segments,
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
) -> Refitted | None:
    """``refit_split="corners"``: the candidates of ``every`` (before footprint correction)
    flagged by ``which`` cut at their concave corners (:func:`corner_cut_pieces`), every
    piece with ``min_points`` returns judged by the segment filters and fitted; with
    ``refit_validate`` a candidate's pieces are accepted only together
    (:func:`validate_pieces`). ``parent`` indexes ``every``; None when nothing was cut."""
    cfg = detector.config
    if not np.any(which):
        return None
    sub = every.select(which)
    pieces, local = corner_cut_pieces(sub, cfg, min_points=1)
    # only the candidates that were cut: an uncut one is its own rejected candidate
    cut = np.bincount(local, minlength=len(sub)) > 1
    cut |= np.bincount(local, weights=pieces.counts, minlength=len(sub)) < sub.counts
    sel = cut[local]
    if not np.any(sel):
        return None
    return judge_pieces(
        detector, sub, pieces.select(sel), local[sel], which, grid, wrap, cfg.refit_validate
    )


def judge_pieces(
    detector: ScanTrunkDetector,
    sub: Segments,
    pieces: Segments,
    local: NDArray[np.int64],
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
    validate: bool,
    tests: Callable[[DetectorConfig, Segments, _Fitted], NDArray[np.bool_]] | None = None,
) -> Refitted | None:
    """The pieces of the candidates ``sub`` (= ``every.select(which)``; ``local`` indexes
    ``sub``) judged as any candidate: segment filters, fit, fit tests; with ``validate`` a
    candidate's pieces are accepted only together (:func:`validate_pieces`) and a piece whose
    circle holds a return of its parent more than 3 sigma inside is rejected. ``parent`` of
    the result indexes ``every``; None when no piece passed the segment filters. ``tests``
    (config, fitted pieces, fit): the fit tests
    a piece must pass (default :func:`fit_passes`; ``split_search`` passes
    :func:`~stemmap.scan._arcs.piece_passes`, the arcs' tests)."""
    cfg = detector.config
    codes = segment_reasons(pieces, segment_features(pieces), cfg)
    good = codes == 0
    if not np.any(good):
        return None
    if cfg.beam_footprint_deg > 0:
        pieces = footprint_correct(pieces, math.radians(cfg.beam_footprint_deg))
    fitted = detector._fit_candidates(pieces.select(good), grid, wrap)
    fit_ok = np.zeros(len(pieces), dtype=bool)
    fit_ok[good] = (
        fit_passes(cfg, fitted) if tests is None else tests(cfg, pieces.select(good), fitted)
    )
    if validate:
        ok = validate_pieces(local, codes, fit_ok)[good]
        ok &= ~_returns_inside(sub, local[good], fitted, ok)
    else:
        ok = fit_ok[good]
    parent = np.flatnonzero(which)[local[good]].astype(np.int64)
    return Refitted(pieces.select(good), fitted, ok, parent)


def refit_pieces(
    detector: ScanTrunkDetector,
    segs: Segments,
    fitted: _Fitted,
    codes: NDArray[np.int8],
    grid: FloatArray,
    wrap: bool,
) -> Refitted | None:
    """Pieces of the candidates of ``segs`` whose fit failed only the RMS test (``codes``),
    cut at their largest gap (``refit_split="gap"``) or without the failed fit's outlier
    returns (:func:`outlier_returns`), fitted again (with ``refit_validate``: accepted only
    together, :func:`validate_pieces`); None when there is nothing to re-fit.
    ``refit_split="corners"`` goes through :func:`split_refit` instead."""
    cfg = detector.config
    fail = codes == _RMS
    if not np.any(fail):
        return None
    sub = segs.select(fail)
    lim = rms_limit(cfg, fitted.sigma[fail], fitted.radii[fail])
    if cfg.refit_split == "gap":
        # every failed segment: cut at its largest gap; no return is dropped
        pieces = split_largest_gap(
            sub,
            sub.counts >= 2,
            cfg.occlusion_margin,
            cfg.gap_ratio,
            cfg.gap_sigmas * fitted.sigma[fail],
        )
        keep = np.ones(len(sub.points), dtype=bool)
    else:
        out = outlier_returns(
            sub,
            fitted.centers[fail],
            fitted.radii[fail],
            lim,
            cfg.refit_sigmas,
            ends_only=cfg.refit_split == "outlier_ends",
        )
        if not np.any(out):
            return None
        keep = ~out
        pieces = sub.split(keep)
    idx = np.flatnonzero(keep)
    parent = np.flatnonzero(fail)[sub.labels[idx[pieces.start]]]
    # a piece is a new candidate: the same segment filters as the first pass
    codes_p = segment_reasons(pieces, segment_features(pieces), cfg)
    good = codes_p == 0
    if not np.any(good):
        return None
    refit = detector._fit_candidates(pieces.select(good), grid, wrap)
    ok = fit_passes(cfg, refit)
    if cfg.refit_validate:
        fit_ok = np.zeros(len(pieces), dtype=bool)
        fit_ok[good] = ok
        ok = validate_pieces(parent, codes_p, fit_ok)[good]
    return Refitted(pieces.select(good), refit, ok, parent[good].astype(np.int64))


def fit_passes(cfg: DetectorConfig, fitted: _Fitted) -> NDArray[np.bool_]:
    """Whether each fitted candidate passes every fit plausibility test of ``cfg``."""
    out: NDArray[np.bool_] = fitted_reasons(cfg, fitted) == 0
    return out
