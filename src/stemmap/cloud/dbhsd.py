"""A cloud stem's stated DBH variance from its parts (``CloudStems.diameter_std``;
``StemConfig.dbh_sd_scatter``; docs/algorithms/cloud.md "The stated DBH std of a cloud stem"
and "The DBH std from its parts").

The DBH is read from the stem's kept slices (0.2 m thick, 0.9-1.9 m): the median of the slices
within one slice thickness of the measurement height (``dbh_from = "median"``,
:func:`~stemmap.cloud.bhradius.near_median_radius`), the one slice holding it (``"slice"``, a
sparse plot's thick slices), the Theil-Sen line through all of them (``"line"``), or -- a
pre-cut slice cloud cut into at most three sub-slices spanning less than 0.3 m -- their
weighted mean (``"mean"``, :func:`~stemmap.cloud.uncertainty._mean_uncertainty`). What it
should match is the stem's section at the measurement height (a tape there; the benchmarks'
ring fit of the points about it). Its error has three parts:

* *fit noise* ``sigma_i^2``: each slice fit's ``s^2 (J^T J)^-1``
  (:func:`~stemmap.cloud.slicefit._segment_covariances`), the points' scatter about that
  slice's circle;
* *the section's change* ``tau^2``: a real stem's section differs from one slice to the next
  by more than its fits say (bark, knots, an out-of-round or flaring section). Each slice's
  radius is the profile (the Theil-Sen line ``a + b h`` through the kept slices) plus a section
  term ``S_i`` of variance ``tau^2`` plus its fit noise. ``tau^2`` is read from the slices
  themselves: their robust scatter about the line minus their mean fit variance
  (:func:`section_variance`; about their mean for a pre-cut slice's sub-slices). The target
  is ``a + b h_j + S_j`` of the slice ``j`` that holds the measurement height: an estimator
  that averages neighbours misses that slice's own section term, and its covariance with
  ``S_j`` is what it shares;
* *the median's sampling error*: the median of n slices is not their mean. Of n independent
  normal values of equal variance it has n x variance / n = :data:`MEDIAN_FACTOR` [n] (1.346
  at n = 3, not the large-n pi / 2), and of values along a taper it is mostly the middle
  slice (three slices whose means step by more than their noise: the middle one's whole
  variance, 3 / 1.346 = 2.2 x the iid value). :func:`median_error_variance` takes both from
  fixed normal draws (:data:`N_DRAWS`, common to every stem, deterministic).

``dbh_sd_scatter`` = k scales the section term (``k^2 tau^2``); k = 0 is the fit noise alone
(the median: through the exact median of the slices about the line; the mean, the slice and
the line: as their fits state it). The DBH is never changed.
"""

from __future__ import annotations

import math

import numpy as np

from stemmap.cloud.slicefit import _theil_sen
from stemmap.types import FloatArray

__all__ = [
    "DBH_PATHS",
    "MEDIAN_FACTOR",
    "N_DRAWS",
    "dbh_variance",
    "local_scatter_variance",
    "median_error_variance",
    "median_factor",
    "section_variance",
    "slice_scatter_variance",
]

#: n x the variance of the median of n independent standard normal values (numerical
#: integration of the order statistics' densities; an even count's median is the mean of the
#: middle two); pi / 2 = 1.571 is the large-n limit (:func:`median_factor`)
MEDIAN_FACTOR = {
    1: 1.0,
    2: 1.0,
    3: 1.346,
    4: 1.193,
    5: 1.434,
    6: 1.289,
    7: 1.473,
    8: 1.345,
    9: 1.495,
    10: 1.383,
    11: 1.509,
}
#: how a stem's radius at the measurement height was taken from its kept slices
DBH_PATHS = ("median", "slice", "line", "mean")
#: normal draws per slice of :func:`median_error_variance` (half of them antithetic): the
#: variance to about 2 % (1 % in sd)
N_DRAWS = 4096
#: most slices :func:`median_error_variance` draws for (more: the iid factor)
MAX_DRAWN = 12
_DRAWS: FloatArray | None = None


def median_factor(n: int) -> float:
    """n x the variance of the median of n iid standard normals (:data:`MEDIAN_FACTOR`; pi / 2
    beyond it)."""
    return MEDIAN_FACTOR.get(int(n), math.pi / 2)


def _draws() -> FloatArray:
    """The fixed standard normal draws (2, N_DRAWS, MAX_DRAWN + 1): section and fit noise
    (the last section column: a target section of its own)."""
    global _DRAWS
    if _DRAWS is None:
        z = np.random.default_rng(20261206).standard_normal((2, N_DRAWS // 2, MAX_DRAWN + 1))
        _DRAWS = np.concatenate((z, -z), axis=1)
    return _DRAWS


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


def local_scatter_variance(radii: FloatArray, hh: FloatArray) -> float:
    """The variance of one slice's radius about the stem's *local* profile: each kept slice's
    deviation ``d`` from the straight line through its two neighbours (sorted by height),
    ``d^2 / (1 + w_a^2 + w_b^2)`` (``w``: the neighbours' interpolation weights; for
    independent slices of variance v its mean is v), averaged over the slices that have
    two neighbours. A taper and a smooth flare bend the profile by well under a slice's
    scatter over 0.4 m; the line through all slices (:func:`slice_scatter_variance`) reads
    the flare's curvature as scatter. NaN with fewer than 3 slices."""
    h = np.asarray(hh, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    if r.size < 3:
        return math.nan
    o = np.argsort(h, kind="stable")
    h, r = h[o], r[o]
    span = h[2:] - h[:-2]
    ok = span > 1e-9
    if not ok.any():
        return math.nan
    wa = (h[2:] - h[1:-1])[ok] / span[ok]
    wb = 1.0 - wa
    d = r[1:-1][ok] - (wa * r[:-2][ok] + wb * r[2:][ok])
    return float(np.mean(d**2 / (1.0 + wa**2 + wb**2)))


def section_variance(radii: FloatArray, fit_var: FloatArray, hh: FloatArray, path: str) -> float:
    """``tau^2``: the variance of a slice's section about the stem's local profile beyond its
    fit noise -- the slices' local scatter (:func:`local_scatter_variance`; for the sub-slices
    of a pre-cut slice, ``path = "mean"``, the sample variance about their mean, n - 1
    degrees of freedom) minus their mean fit variance, at least 0. NaN when the slices cannot
    tell (fewer than 3, or 2 about a mean)."""
    r = np.asarray(radii, dtype=np.float64)
    v = np.asarray(fit_var, dtype=np.float64)
    if path == "mean":
        sc = float(np.var(r, ddof=1)) if r.size >= 2 else math.nan
    else:
        sc = local_scatter_variance(r, hh)
    if not math.isfinite(sc):
        return math.nan
    fit = float(np.mean(v[np.isfinite(v)])) if np.isfinite(v).any() else 0.0
    return max(sc - fit, 0.0)


def _target(hh: FloatArray, thickness: float) -> int:
    """Index of the slice that holds the measurement height (within half a slice), or -1."""
    j = int(np.argmin(np.abs(hh)))
    return j if abs(float(hh[j])) <= thickness / 2 + 1e-9 else -1


def median_error_variance(mu: FloatArray, fit_var: FloatArray, tau2: float, target: int) -> float:
    """``E[(median(Y) - T)^2]`` for slices ``Y_i = mu_i + S_i + e_i`` (section terms ``S_i``
    of variance ``tau2``, fit noise ``e_i`` of variance ``fit_var[i]``, all independent) and
    the target ``T = mu_j + S_j`` of slice ``j = target`` (-1: a section of its own, ``mu``
    0). From :data:`N_DRAWS` fixed draws (n <= :data:`MAX_DRAWN`; more slices: the iid value
    ``MEDIAN_FACTOR / n`` x the mean variance, plus ``tau2 (1 - 2 / n)``)."""
    mu = np.asarray(mu, dtype=np.float64)
    n = mu.size
    v = np.asarray(fit_var, dtype=np.float64)
    v = np.where(np.isfinite(v), v, float(np.nanmean(v)) if np.isfinite(v).any() else 0.0)
    if n > MAX_DRAWN:
        own = 1.0 - 2.0 / n if target >= 0 else 1.0
        return median_factor(n) / n * (float(np.mean(v)) + tau2) + tau2 * own
    z = _draws()
    sec = math.sqrt(max(tau2, 0.0)) * z[0, :, :n]
    y = mu + sec + np.sqrt(v) * z[1, :, :n]
    t = mu[target] + sec[:, target] if target >= 0 else math.sqrt(max(tau2, 0.0)) * z[0, :, n]
    return float(np.mean((np.median(y, axis=1) - t) ** 2))


def _linear_section(w: FloatArray, target: int, tau2: float) -> float:
    """The section term of an estimator ``sum w_i Y_i`` (``sum w = 1``) against the target's
    section: ``tau2 (sum w^2 + 1 - 2 w_j)``."""
    own = float(w[target]) if target >= 0 else 0.0
    return tau2 * (float(np.sum(w**2)) + 1.0 - 2.0 * own)


def dbh_variance(
    var_r: float,
    radii: FloatArray,
    fit_var: FloatArray,
    hh: FloatArray,
    path: str,
    thickness: float,
    scatter: float,
    weights: FloatArray | None = None,
) -> float:
    """A stem's radius variance at the measurement height from its parts.

    ``var_r``: the variance as the path's own fits state it (median: unused); ``radii``,
    ``fit_var``, ``hh``: the kept slices' radii, fit variances and heights relative to the
    measurement height; ``path``: :data:`DBH_PATHS`; ``thickness``: the slice thickness;
    ``scatter`` = k, the weight of the section term (``k^2 tau^2``, :func:`section_variance`;
    0: the fit noise alone); ``weights``: the ``"mean"`` path's slice weights.

    * median (of the slices within ``thickness`` of the measurement height):
      :func:`median_error_variance` about the Theil-Sen line through all kept slices;
    * slice: ``var_r`` + the section term of that slice against the target (0 when it holds
      the measurement height);
    * line: the larger of ``var_r`` (which already reads the scatter about the line) and fit
      noise / n + the section term, with the least-squares intercept's weights;
    * mean (a pre-cut slice's sub-slices): ``var_r`` + the section term of the weighted mean.

    ``var_r`` unchanged for another path, or when k > 0 is asked but ``tau^2`` is undefined
    and the path is not the median."""
    h = np.asarray(hh, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    v = np.asarray(fit_var, dtype=np.float64)
    if path not in DBH_PATHS or r.size == 0:
        return var_r
    tau2 = section_variance(r, v, h, path) if scatter > 0 else 0.0
    tau2 = scatter**2 * tau2 if math.isfinite(tau2) else 0.0
    if path == "median":
        near = np.abs(h) <= thickness + 1e-9
        hn = h[near]
        b = _theil_sen(h, r)[1] if r.size >= 2 else 0.0
        j = _target(hn, thickness)
        fit = median_error_variance(b * hn, v[near], 0.0, j)
        # a section term never lowers the variance; the draws' noise (~1 %) could
        return max(fit, median_error_variance(b * hn, v[near], tau2, j)) if tau2 > 0 else fit
    if tau2 <= 0:
        return var_r
    j = _target(h, thickness)
    if path == "slice":
        k = int(np.argmin(np.abs(h)))
        w = np.zeros(h.size)
        w[k] = 1.0
        return var_r + _linear_section(w, j, tau2)
    if path == "mean":
        w = np.ones(h.size) if weights is None else np.asarray(weights, dtype=np.float64)
        w = w / w.sum()
        return var_r + _linear_section(w, j, tau2)
    dh = h - h.mean()
    sxx = float(np.sum(dh**2))
    w = 1.0 / h.size + (0.0 - h.mean()) * dh / sxx if sxx > 0 else np.full(h.size, 1.0 / h.size)
    fit = float(np.sum(w**2 * np.where(np.isfinite(v), v, 0.0)))
    return max(var_r, fit + _linear_section(w, j, tau2))
