"""Drop a candidate's end returns that lie outside its own circle: branch stubs on the stem's
flank (ours, issue 11, seventeenth round; numpy path).

A branch stub that leaves the stem near its silhouette edge returns from a surface *outside*
the stem's circle, nearer than the tangent range (so :mod:`stemmap.scan._behind` keeps it),
and the segmentation joins it to the stem's arc (the step is a few millimetres). Fitted with
the arc it pulls the circle outwards: on lidR's single tree (0.5 deg nearest-return, no
noise; docs/algorithms/scan-detection.md, "Branch stubs at the arc end") one to nine such
returns end five of the eleven detected views, 11-97 mm outside the reference circle, and
those views read +1.9 to +10.5 cm of diameter.

:func:`outward_ends` is a deletion test on each end of every accepted candidate (Cook and
Weisberg 1982, ch. 2: an outlier's own pull on the fit masks it, so the end is judged
against the circle fitted without it). That circle is fitted with the end taken as occluded
(whether the end return is the stem's edge is what is asked, so the fit may not assume a
silhouette there); the end goes when the circle passes every fit test, its residuals are
the range noise (the upper 1 % chi-square test of ``arc_chi2``: on a lobed outline, aRchi's
polygonal trunk, the rest's circle is itself off and every end looks outward in turn), and
the end return lies outside it by more than ``stub_sigmas`` times the deletion residual's
standard deviation ``sqrt(s^2 + g' C g)`` -- ``s = sqrt(sigma^2 + (bark_roughness r)^2)`` the
RMS test's noise scale, ``C`` the circle's covariance and ``g`` the gradient of ``|p - c| - r``
in ``(cx, cy, r)``: the circle's own uncertainty where it is extrapolated to the end (without
it a 2-sigma test trimmed 10-14 % of clean simulated arcs with 1 cm noise and shrank them).
The test is one-sided: a stem's own first-echo returns scatter on both sides of its circle, a
stub's lie outside it. With the averaging edge model (:func:`first_echo` False) an edge return
is a mixed pixel that lies outside the circle by construction, so nothing is trimmed.
:func:`~stemmap.scan._behind.trim_behind` repeats the test on the new ends down to
``max(min_points, min_points_partial)`` returns, fits the trimmed candidate again with the
trimmed end as a silhouette edge (as a trimmed end behind the circle: the stub's beam is the
first that left the stem; taking it as occluded instead read lidR 4.02 cm RMSE against 3.54
with the plain 2-sigma test)
and keeps the trim only when that fit passes every test.

References: R. D. Cook and S. Weisberg, *Residuals and Influence in Regression*, Chapman and
Hall, 1982.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtri

from stemmap.scan._behind import trim_behind
from stemmap.scan._refit import fit_passes
from stemmap.scan.segment import Segments
from stemmap.types import FloatArray

if TYPE_CHECKING:
    from stemmap.scan.config import DetectorConfig
    from stemmap.scan.detect import ScanTrunkDetector, _Fitted

__all__ = ["first_echo", "outward_ends", "trim_stubs"]


def outward_ends(
    detector: ScanTrunkDetector, segs: Segments, grid: FloatArray, wrap: bool
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Per segment of ``segs`` (each with >= 2 returns), whether its first / its last return
    lies outside the circle the detector fits to the other returns (that end occluded) by
    more than ``stub_sigmas`` noise scales (module docstring)."""
    cfg = detector.config
    p = segs.points
    out = []
    none = np.zeros(len(segs), dtype=bool)
    for first, end in ((True, segs.start), (False, segs.stop - 1)):
        keep = np.ones(len(p), dtype=bool)
        keep[end] = False
        rest = segs.drop(keep)
        rest = Segments(
            rest.points,
            rest.start,
            rest.stop,
            rest.scan,
            rest.occluded_start | (~none if first else none),
            rest.occluded_end | (none if first else ~none),
            rest.truncated_start,
            rest.truncated_end,
        )
        f = detector._fit_candidates(rest, grid, wrap)
        # only a circle that is a trunk by every test, and whose residuals are the range noise
        # (upper 1 % chi-square test, as arc_chi2), says what lies outside it: on a lobed
        # outline the rest's circle is itself off and every end looks outward in turn
        n = rest.counts.astype(np.float64)
        limit = chdtri(np.maximum(n - 3.0, 1.0), 0.01)
        with np.errstate(invalid="ignore"):
            good = fit_passes(cfg, f) & (n * f.rms * f.rms <= limit * f.sigma * f.sigma)
        br = cfg.bark_roughness * f.radii
        scale = np.sqrt(f.sigma * f.sigma + br * br)
        dx = p.x[end] - f.centers[:, 0]
        dy = p.y[end] - f.centers[:, 1]
        dist = np.hypot(dx, dy)
        with np.errstate(invalid="ignore", divide="ignore"):
            # the deletion residual's variance: the noise scale plus the prediction variance
            # of the circle at the end return, g' C g with g = d(|p - c| - r)/d(cx, cy, r)
            g = np.stack((-dx / dist, -dy / dist, -np.ones_like(dist)), axis=1)
            pred = np.einsum("ki,kij,kj->k", g, f.covs, g)
            bound = cfg.stub_sigmas * np.sqrt(scale * scale + np.maximum(pred, 0.0))
            out.append(good & np.isfinite(bound) & (dist - f.radii > bound))
    return out[0], out[1]


def first_echo(cfg: DetectorConfig) -> bool:
    """Whether the fit of ``cfg`` takes each return as a point of the surface (first-echo or
    thin beams: ``beam_footprint_deg`` > 0 or ``beam_divergence_deg`` 0), so that a stem's
    own returns scatter on both sides of its circle. With the averaging edge model an edge
    return is a mixed pixel, outside the circle by up to the background's range: nothing to
    tell a stub by, and :func:`trim_stubs` leaves the candidates as they are."""
    return cfg.beam_footprint_deg > 0 or cfg.beam_divergence_deg == 0


def trim_stubs(
    detector: ScanTrunkDetector,
    segs: Segments,
    fitted: _Fitted,
    which: NDArray[np.bool_],
    grid: FloatArray,
    wrap: bool,
) -> tuple[Segments, _Fitted]:
    """``segs`` without the end returns of the candidates ``which`` that lie outside their
    circle (:func:`outward_ends`), and the fits of the trimmed candidates
    (:func:`~stemmap.scan._behind.trim_behind`: a trimmed end is a silhouette edge); the
    same segments and fits unless :func:`first_echo`."""
    if not first_echo(detector.config):
        return segs, fitted
    return trim_behind(detector, segs, fitted, which, grid, wrap, ends=outward_ends)
