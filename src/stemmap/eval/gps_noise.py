"""How far is a GPS reference from the truth? Its own error, estimated without the truth (ours).

A trajectory scored against GPS fixes without any alignment (the GNSS-fused run on the fixes it
did not use, docs/algorithms/slam.md "GNSS fusion") cannot score better than the GPS's own
error, ``e_i = g_i - x(t_i)`` (fix minus the true antenna position), unless it copies that
error. Two estimates of ``E|e|²`` that need only a *locally* right path ``p`` (dead reckoning or
a SLAM path: its displacements over a short time or between two visits of one place, never its
absolute position):

* **Fix-to-fix consistency** (:func:`gps_variogram`): the semivariogram of the GPS error along
  time, ``gamma(tau) = ½ E|(g_j - g_i) - (p_j - p_i)|²`` over fix pairs ``tau`` apart (per axis:
  half again). At short lags it is the white fix noise; if the error is stationary its sill
  ``2 gamma(inf)`` is ``E|e - ē|²`` (2-D). Valid where the path's own drift over ``tau`` is
  small next to it (compare the same curve with dead reckoning and with the SLAM path).
* **Revisits** (:func:`gps_revisit_error`): pairs of fixes far apart in time where the path
  passes the same place (within ``radius``): there the path's relative position is right (the
  same trees are seen; docs/algorithms/slam.md "Where the iSAM2 error against the GPS comes
  from": they overlay to ~0.1 m on Victoria Park), so ``(g_j - g_i) - (p_j - p_i) = e_j - e_i``
  and, for independent visits, ``E|e|² = ½ E|e_j - e_i|²``.

Its time structure (:func:`gps_autocorrelation`, :func:`fit_gauss_markov`): the correlation of
the error with itself over a lag, and a first-order Gauss-Markov model of it (white fix noise
plus a bias with an exponential autocovariance, the usual GNSS error model of loosely coupled
GNSS/INS fusion, e.g. Groves, *Principles of GNSS, Inertial, and Multisensor Integrated
Navigation Systems*, 2nd ed. 2013, its Kalman-filter system models) fitted to the
semivariogram: it says how much of an unused fix's error a fused fix ``tau`` away shares.

Both are the usual geostatistical / GNSS-noise estimates (e.g. the Allan-variance view of a
GNSS position error: white noise plus a slowly varying bias); the decision to score against
them is ours.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from stemmap.errors import InputError
from stemmap.types import FloatArray

__all__ = [
    "GaussMarkovFit",
    "GpsErrorEstimate",
    "GpsVariogram",
    "fit_gauss_markov",
    "gps_autocorrelation",
    "gps_revisit_error",
    "gps_variogram",
]


def _inputs(
    gps_times: ArrayLike, gps_xy: ArrayLike, path_xy: ArrayLike, name: str
) -> tuple[FloatArray, FloatArray, FloatArray]:
    t = np.asarray(gps_times, dtype=np.float64).reshape(-1)
    g = np.asarray(gps_xy, dtype=np.float64).reshape(-1, 2)
    p = np.asarray(path_xy, dtype=np.float64).reshape(-1, 2)
    if not (t.shape[0] == g.shape[0] == p.shape[0]):
        raise InputError(
            f"{name}: {t.shape[0]} times, {g.shape[0]} fixes and {p.shape[0]} path positions "
            "must all match (the path at the fix times)."
        )
    if t.shape[0] > 1 and np.any(np.diff(t) < 0):
        raise InputError(f"{name}: fix times must not decrease.")
    return t, g, p


@dataclass(frozen=True, eq=False)
class GpsVariogram:
    """Result of :func:`gps_variogram`.

    Attributes
    ----------
    lags : ndarray (L,), s, the lags asked for
    gamma : ndarray (L,), m², per-axis semivariance of the GPS error at each lag (nan: no pair)
    pairs : ndarray (L,), number of fix pairs used per lag
    """

    lags: FloatArray
    gamma: FloatArray
    pairs: FloatArray

    @property
    def rms_2d(self) -> FloatArray:
        """``sqrt(2 gamma)`` per axis, i.e. the 2-D RMS GPS error a stationary error with this
        semivariance as its sill would have (m)."""
        return np.sqrt(2.0 * self.gamma)


def gps_variogram(
    gps_times: ArrayLike,
    gps_xy: ArrayLike,
    path_xy: ArrayLike,
    lags: ArrayLike,
    *,
    rel_tol: float = 0.1,
    abs_tol: float = 0.2,
) -> GpsVariogram:
    """Semivariogram of the GPS error along time from fix-to-fix consistency with a path.

    Parameters
    ----------
    gps_times : (G,) s, non-decreasing
    gps_xy : (G, 2) m, the fixes
    path_xy : (G, 2) m, the same vehicle point (the antenna) on a locally right path at
        ``gps_times``, in a frame rotated like the fixes' (translation does not matter)
    lags : (L,) s, > 0
    rel_tol, abs_tol : a pair ``(i, j)`` counts for lag ``tau`` when
        ``|t_j - t_i - tau| < max(abs_tol, rel_tol tau)``; ``j`` is the first fix at or after
        ``t_i + tau``.

    Returns
    -------
    GpsVariogram
        ``gamma(tau) = ¼ mean |(g_j - g_i) - (p_j - p_i)|²`` (per axis).
    """
    t, g, p = _inputs(gps_times, gps_xy, path_xy, "gps_variogram")
    lg = _lags(lags, "gps_variogram")
    r = g - p
    gam = np.full(lg.shape, np.nan)
    cnt = np.zeros(lg.shape)
    for k, tau in enumerate(lg):
        i, j = _lag_pairs(t, float(tau), rel_tol, abs_tol)
        cnt[k] = i.size
        if i.size:
            d = r[j] - r[i]
            gam[k] = 0.25 * float(np.mean(np.sum(d * d, axis=1)))
    return GpsVariogram(lg, gam, cnt)


def _lags(lags: ArrayLike, name: str) -> FloatArray:
    lg = np.asarray(lags, dtype=np.float64).reshape(-1)
    if np.any(~np.isfinite(lg)) or np.any(lg <= 0):
        raise InputError(f"{name}: lags must be positive seconds, got {lg}.")
    return lg


def _lag_pairs(
    t: FloatArray, tau: float, rel_tol: float, abs_tol: float
) -> tuple[np.ndarray, np.ndarray]:
    """Fix pairs ``(i, j)``, ``j`` the first fix at or after ``t_i + tau``, kept when
    ``|t_j - t_i - tau| < max(abs_tol, rel_tol tau)``."""
    j = np.searchsorted(t, t + tau)
    i = np.flatnonzero(j < t.shape[0])
    j = j[i]
    ok = np.abs(t[j] - t[i] - tau) < max(abs_tol, rel_tol * tau)
    return i[ok], j[ok]


def gps_autocorrelation(
    gps_times: ArrayLike,
    gps_xy: ArrayLike,
    path_xy: ArrayLike,
    lags: ArrayLike,
    *,
    rel_tol: float = 0.1,
    abs_tol: float = 0.2,
) -> FloatArray:
    """(L,) autocorrelation of the GPS error ``e = g - p`` (centred) at each lag: ``mean(e_i .
    e_j) / mean |e|²`` over the fix pairs of :func:`gps_variogram` (nan: no pair).

    Unlike the semivariogram it needs the path *aligned* to the fixes (``path_xy`` in their
    frame, e.g. by :func:`stemmap.eval.trajectory.align_se2`): the path's own slow drift then
    shows as correlation at long lags.
    """
    t, g, p = _inputs(gps_times, gps_xy, path_xy, "gps_autocorrelation")
    lg = _lags(lags, "gps_autocorrelation")
    e = g - p
    e = e - e.mean(axis=0)
    var = float(np.mean(np.sum(e * e, axis=1)))
    out = np.full(lg.shape, np.nan)
    if var <= 0:
        return out
    for k, tau in enumerate(lg):
        i, j = _lag_pairs(t, float(tau), rel_tol, abs_tol)
        if i.size:
            out[k] = float(np.mean(np.sum(e[i] * e[j], axis=1))) / var
    return out


@dataclass(frozen=True)
class GaussMarkovFit:
    """Result of :func:`fit_gauss_markov`, per axis: ``white_sigma`` (m) the fix noise,
    ``bias_sigma`` (m) the bias's stationary std, ``time_constant`` (s) its correlation time
    (autocovariance ``bias_sigma² exp(-|tau| / time_constant)``)."""

    white_sigma: float
    bias_sigma: float
    time_constant: float


def fit_gauss_markov(variogram: GpsVariogram, max_lag: float = 60.0) -> GaussMarkovFit:
    """First-order Gauss-Markov model of the GPS error fitted to its semivariogram.

    Per axis ``gamma(tau) = s_w² + s_b² (1 - exp(-tau / T))``: ``s_w²`` is the semivariance at
    the shortest lag (the nugget; an upper bound, the bias adds ~``s_b² tau / T`` there), then
    ``s_b², T`` by least squares on the other lags up to ``max_lag`` s (a grid of 600 ``T``
    from 0.5 to 500 s, log-spaced, linear in ``s_b²`` for each). Beyond ``max_lag`` the path's
    own drift enters the semivariogram. Needs at least three finite lags <= ``max_lag``.
    """
    ok = np.isfinite(variogram.gamma) & (variogram.lags <= max_lag)
    lags, gam = variogram.lags[ok], variogram.gamma[ok]
    if lags.size < 3:
        raise InputError(
            f"fit_gauss_markov: need >= 3 lags <= {max_lag} s with fix pairs, got {lags.size}."
        )
    order = np.argsort(lags)
    lags, gam = lags[order], gam[order]
    nug = float(gam[0])
    x, y = lags[1:], gam[1:] - nug
    best = (np.inf, 0.0, 1.0)
    for tc in np.geomspace(0.5, 500.0, 600):
        a = 1.0 - np.exp(-x / tc)
        sb2 = max(float(a @ y) / float(a @ a), 0.0)
        cost = float(np.sum((a * sb2 - y) ** 2))
        if cost < best[0]:
            best = (cost, sb2, float(tc))
    return GaussMarkovFit(float(np.sqrt(max(nug, 0.0))), float(np.sqrt(best[1])), best[2])


@dataclass(frozen=True, eq=False)
class GpsErrorEstimate:
    """Result of :func:`gps_revisit_error`: ``rms_2d`` (m) the per-fix 2-D RMS GPS error (nan
    without revisits), ``pairs`` the revisit pairs used, ``median_disagreement`` (m) the median
    of ``|e_j - e_i|`` over them."""

    rms_2d: float
    pairs: int
    median_disagreement: float

    def __bool__(self) -> bool:
        return self.pairs > 0


def gps_revisit_error(
    gps_times: ArrayLike,
    gps_xy: ArrayLike,
    path_xy: ArrayLike,
    *,
    radius: float = 1.0,
    min_dt: float = 60.0,
    block_s: float = 10.0,
) -> GpsErrorEstimate:
    """Per-fix GPS error from its disagreement with itself where the path revisits a place.

    Pairs of fixes at least ``min_dt`` apart whose path positions lie within ``radius``; one
    pair per (``block_s`` x ``block_s``) block of the two times (the pair with the earliest
    first fix, then the earliest second), so that a long stretch driven twice counts once per
    block and not once per fix pair. ``rms_2d = sqrt(½ mean |d|²)`` with
    ``d = (g_j - g_i) - (p_j - p_i)`` (the path's relative position at a revisit is taken as
    right: check it, e.g. by overlaying the trees seen at both times).
    """
    t, g, p = _inputs(gps_times, gps_xy, path_xy, "gps_revisit_error")
    if radius <= 0 or min_dt < 0 or block_s <= 0:
        raise InputError(
            f"gps_revisit_error: need radius > 0, min_dt >= 0, block_s > 0 (got {radius}, "
            f"{min_dt}, {block_s})."
        )
    pairs = np.asarray(cKDTree(p).query_pairs(radius, output_type="ndarray"), dtype=np.int64)
    pairs = pairs.reshape(-1, 2)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]  # the tree's order is not stable
    i, j = pairs[:, 0], pairs[:, 1]
    far = np.abs(t[j] - t[i]) >= min_dt
    i, j = i[far], j[far]
    if i.size == 0:
        return GpsErrorEstimate(float("nan"), 0, float("nan"))
    lo, hi = np.minimum(t[i], t[j]), np.maximum(t[i], t[j])
    key = np.floor(lo / block_s).astype(np.int64) * (1 << 31) + np.floor(hi / block_s).astype(
        np.int64
    )
    _, first = np.unique(key, return_index=True)
    i, j = i[first], j[first]
    d = (g[j] - g[i]) - (p[j] - p[i])
    e2 = np.sum(d * d, axis=1)
    return GpsErrorEstimate(
        float(np.sqrt(0.5 * np.mean(e2))), int(i.size), float(np.median(np.sqrt(e2)))
    )
