"""Re-fit the pieces of candidates that fail the RMS test (ours, issue 11).

A real trunk's segment often holds more than the trunk: the fillet where a branch leaves the
bark (returns 2-10 cm outside the circle over several beams), a stub, a thin stem touching it.
The circle fit follows them and the RMS test rejects the whole candidate although most of its
returns lie on a circle. :func:`refit_pieces` drops the returns that are outliers of the failed
fit (farther than ``refit_sigmas`` robust residual scales from the median residual, and beyond
the RMS limit), splits the segment there and fits every piece again; the pieces then pass the
same segment filters and plausibility tests as any candidate. One pass only: a piece that
fails again is dropped.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from stemmap.scan.features import segment_features
from stemmap.scan.plausibility import REASONS, fitted_reasons, rms_limit, segment_reasons
from stemmap.scan.segment import Segments, split_largest_gap
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig
    from stemmap.scan.detect import ScanTrunkDetector, _Fitted

__all__ = ["Refitted", "fit_passes", "outlier_returns", "refit_pieces"]

_RMS = REASONS.index("rms")


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
    returns (:func:`outlier_returns`), fitted again; None when there is nothing to re-fit."""
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
    good = segment_reasons(pieces, segment_features(pieces), cfg) == 0
    if not np.any(good):
        return None
    pieces, parent = pieces.select(good), parent[good]
    refit = detector._fit_candidates(pieces, grid, wrap)
    return Refitted(pieces, refit, fit_passes(cfg, refit), parent.astype(np.int64))


def fit_passes(cfg: DetectorConfig, fitted: _Fitted) -> NDArray[np.bool_]:
    """Whether each fitted candidate passes every fit plausibility test of ``cfg``."""
    out: NDArray[np.bool_] = fitted_reasons(cfg, fitted) == 0
    return out
