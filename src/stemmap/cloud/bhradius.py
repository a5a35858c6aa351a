"""The radius at the measurement height from the slices about it, not from the line through the
whole band (``StemConfig.dbh_from``; docs/algorithms/cloud.md "Breast-height DBH, stage by
stage: the line through a flared profile").

Before Dec 6 the DBH was the Theil-Sen line through the kept slices' radii (0.8-2.0 m) evaluated
at breast height (:func:`~stemmap.cloud.slicestem._stem_at`). A stem's profile in that band is
not a line: the root flare widens the lowest slices and fades by about breast height, so the
profile is convex and a line through it passes above the stem in the band's middle. On treels
pine_plot.laz the ten full-ring stems' slice fits agree with a plain least-squares ring of the
same slice within 0.13 cm RMS (bias -0.02 cm), while the line at 1.3 m is 0.40 cm above the ring
on average (0.76 cm RMSE), and the same line through the plain rings is too (+0.40 cm): the
line, not the fits, makes the bias (``benchmarks/cloud_dbh_trace.py``).

``dbh_from`` values: ``"line"`` (the default until Dec 6), ``"slice"`` (the kept slice that
holds the measurement height, as ``thick_dbh_slice`` does for a sparse plot's thick slices:
:func:`~stemmap.cloud.slicestem._stem_at` with ``at_slice``), ``"median"`` (this module: the
median of the kept slices within one slice thickness of the measurement height -- the slice
holding it and its neighbours -- when there are at least three; a branch stub or a knot in
one of them does not move it; the default since Dec 6, docs "The median at breast height is
the default"). Both keep the line's centre, lean correction and taper test.
"""

from __future__ import annotations

import math

import numpy as np

from stemmap.cloud.dbhsd import dbh_variance
from stemmap.cloud.slicefit import _theil_sen
from stemmap.types import FloatArray

__all__ = ["DBH_FROM", "MIN_NEAR_SLICES", "near_median_radius"]

#: the values of ``StemConfig.dbh_from``
DBH_FROM = ("line", "slice", "median")
#: kept slices about the measurement height the median needs (fewer: the line stands)
MIN_NEAR_SLICES = 3


def near_median_radius(
    radii: FloatArray,
    centers: FloatArray,
    var_r: FloatArray,
    hh: FloatArray,
    thickness: float,
) -> tuple[float, float] | None:
    """The lean-corrected median radius of the kept slices within ``thickness`` (one slice
    step) of the measurement height, and its variance; None with fewer than
    :data:`MIN_NEAR_SLICES` of them.

    ``radii`` (S,), ``centers`` (S, 2), ``var_r`` (S,: each slice radius's variance from its
    fit) and ``hh`` (S,: heights relative to the measurement height) of the kept slices. The
    lean correction is :func:`~stemmap.cloud.slicestem._stem_at`'s (the Theil-Sen lines
    through all kept slices' centres: a horizontal section of a stem leaning by theta has a
    circle fit of about (1 + 1 / cos theta) / 2 of its diameter across the axis). The
    variance is the fit noise's part of :func:`~stemmap.cloud.dbhsd.dbh_variance`: the median
    of the near slices about the Theil-Sen line through all of them, against the slice that
    holds the measurement height (the section term is added by the caller)."""
    near = np.abs(hh) <= thickness + 1e-9
    if int(near.sum()) < MIN_NEAR_SLICES:
        return None
    slope_x = _theil_sen(hh, centers[:, 0])[1]
    slope_y = _theil_sen(hh, centers[:, 1])[1]
    cos_t = 1.0 / math.sqrt(1.0 + slope_x**2 + slope_y**2)
    r = float(np.median(radii[near])) * 2 * cos_t / (1 + cos_t)
    var = dbh_variance(math.nan, radii, var_r, hh, "median", thickness, 0.0)
    return r, var
