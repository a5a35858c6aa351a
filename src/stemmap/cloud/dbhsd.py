"""The slices' scatter as a term of a cloud stem's DBH variance (``StemConfig.dbh_sd_scatter``,
default 0: off; docs/algorithms/cloud.md "The stated DBH std of a cloud stem").

A stem's stated DBH variance (``CloudStems.diameter_std``) comes from the slice fits about the
measurement height: for the median of the slices about it (``dbh_from = "median"``,
:func:`~stemmap.cloud.bhradius.near_median_radius`) pi / 2 x their mean fit variance / n, for
the slice holding it (``at_slice``: a sparse plot's thick slices) that slice's fit variance --
each fit's ``s^2 (J^T J)^-1`` (:func:`~stemmap.cloud.slicefit._segment_covariances`): the
points' scatter about that slice's circle, nothing else. Slices of a real stem differ by more
than their fits say -- bark, knots, an out-of-round section, the flare: the section changes
from one 0.2 m slice to the next, and which slice is the median, or which one holds breast
height, changes with it when the cloud is thinned or noisier. Only the Theil-Sen line's
variance (:func:`~stemmap.cloud.uncertainty._line_uncertainty`) already reads that scatter.

The scatter term measures it from the stem's own kept slices: their radii's robust spread about
the Theil-Sen line through them (:func:`slice_scatter_variance`), which holds each slice's fit
noise and the section's changes alike, carried to the estimate by the number of slices it uses
(the median of n: the small-sample factor of a median of n normal values,
:data:`MEDIAN_FACTOR`; one slice: 1; the line: 1 / n). The variance is the larger of the stated
one and k^2 x that term (as the line's variance takes the larger of its two estimates). k = 0
leaves the variance as it was; the DBH is never changed.
"""

from __future__ import annotations

import math

import numpy as np

from stemmap.cloud.slicefit import _theil_sen
from stemmap.types import FloatArray

__all__ = ["DBH_PATHS", "MEDIAN_FACTOR", "scatter_dbh_variance", "slice_scatter_variance"]

#: n x the variance of the median of n standard normal values (Monte Carlo, 4e5 draws; the
#: median of an even count is the mean of the middle two); pi / 2 beyond
MEDIAN_FACTOR = {1: 1.0, 2: 1.0, 3: 1.344, 4: 1.192, 5: 1.439, 6: 1.287}
#: how a stem's radius at the measurement height was taken from its kept slices
DBH_PATHS = ("median", "slice", "line")


def slice_scatter_variance(radii: FloatArray, hh: FloatArray) -> float:
    """The variance of one slice's radius about the stem's profile: the robust scatter of the
    kept slices' ``radii`` about the Theil-Sen line through them over ``hh`` (their heights),
    ``(1.4826 MAD)^2 x n / (n - 2)`` (two line parameters); NaN with fewer than 3 slices."""
    r = np.asarray(radii, dtype=np.float64)
    h = np.asarray(hh, dtype=np.float64)
    n = r.size
    if n < 3:
        return math.nan
    a, b = _theil_sen(h, r)
    res = r - (a + b * h)
    return (1.4826 * float(np.median(np.abs(res)))) ** 2 * n / (n - 2)


def scatter_dbh_variance(
    var_r: float,
    radii: FloatArray,
    hh: FloatArray,
    path: str,
    thickness: float,
    scatter: float,
) -> float:
    """The radius variance ``var_r`` with the slices' scatter term ``scatter`` = k.

    ``radii``, ``hh``: the stem's kept slices' radii and heights relative to the measurement
    height; ``path``: how the radius was taken (:data:`DBH_PATHS`: the median of the slices
    within ``thickness`` of the measurement height, the one slice holding it, the line through
    all). Returns the larger of ``var_r`` and k^2 x :func:`slice_scatter_variance` x the
    path's factor (median of n: ``MEDIAN_FACTOR[n] / n``; slice: 1; line: 1 / n); ``var_r``
    unchanged when k = 0 or the scatter is not defined (fewer than 3 slices)."""
    if scatter <= 0 or path not in DBH_PATHS:
        return var_r
    h = np.asarray(hh, dtype=np.float64)
    sc = slice_scatter_variance(radii, h)
    if not math.isfinite(sc):
        return var_r
    if path == "median":
        n = int(np.sum(np.abs(h) <= thickness + 1e-9))
        factor = MEDIAN_FACTOR.get(n, math.pi / 2) / max(n, 1)
    elif path == "slice":
        factor = 1.0
    else:
        factor = 1.0 / h.size
    term = scatter**2 * factor * sc
    return max(var_r, term) if math.isfinite(var_r) else term
