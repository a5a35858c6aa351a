"""The GNSS-frame track: the path as the GNSS receiver reads it (ours).

A fused GNSS fix disagrees with the tree-consistent path by ``r_i = fix_i - antenna(t_i)``. On
a real receiver most of that is not white noise but a slowly varying error of the receiver's
own solution (multipath, satellite geometry; docs/algorithms/slam.md "GNSS fusion": on
Victoria Park ~1 m with a correlation time of ~18 s). A path held by the trees cannot follow
it, and should not: the map has to stay consistent. But a user driving to a GNSS waypoint with
that same receiver wants the path *as the receiver reads it*. This module estimates the
receiver's error as a first-order Gauss-Markov process (the GNSS error model of loosely coupled
GNSS/INS fusion; Groves, *Principles of GNSS, Inertial, and Multisensor Integrated Navigation
Systems*, 2nd ed. 2013, ch. 14, the first-order Gauss-Markov bias states) and adds it to the
path:

* :func:`fit_gnss_offset_model` -- the model's time constant ``T``, bias std ``s_b`` and white
  fix noise ``s_w`` from the run's own fused fixes: the autocorrelation of their residuals from
  the path (:func:`stemmap.eval.gps_noise.gps_autocorrelation`) fitted with
  ``rho(tau) = s_b² / (s_b² + s_w²) exp(-tau / T)``.
* :func:`gnss_offset` -- the bias ``b(t)`` at the fixes by a Kalman filter (``causal=True``:
  the online estimate, each time from the fixes up to it) or a Kalman filter + Rauch-Tung-
  Striebel smoother (default: the offline estimate, from the fixes on both sides; Rauch, Tung
  & Striebel, AIAA J. 3(8), 1965); :meth:`GnssOffset.at` / :meth:`GnssOffset.std_at` between
  the fixes (the Ornstein-Uhlenbeck bridge).
* :func:`gnss_frame_trajectory` -- ``path + b(t)``, headings kept.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from stemmap.errors import InputError
from stemmap.types import FloatArray, Trajectory

if TYPE_CHECKING:
    from stemmap.slam.gnss import GnssFixes

__all__ = [
    "GnssOffset",
    "GnssOffsetFilter",
    "GnssOffsetModel",
    "fit_gnss_offset_model",
    "gnss_frame_trajectory",
    "gnss_offset",
]

log = logging.getLogger(__name__)

#: fewest fixes inside the run :func:`fit_gnss_offset_model` estimates a model from
MIN_FIXES = 30
#: fewest fix pairs at a lag for the lag to enter the fit
MIN_PAIRS = 10


@dataclass(frozen=True)
class GnssOffsetModel:
    """First-order Gauss-Markov model of the fixes' offset from a path (per axis).

    Attributes
    ----------
    time_constant : float, s, the bias's correlation time ``T``
    bias_sigma : float, m, its stationary std ``s_b``
    white_sigma : float, m, the white fix noise ``s_w``
    n_fixes : int, fixes the model was estimated from
    lags : tuple of float, s, lags of the fitted autocorrelation
    autocorrelation : tuple of float, its value at ``lags`` (nan: no pair)
    resolved : bool, False when ``T`` is longer than a quarter of the fixes' time span (the
        run is too short to see the bias decorrelate; the track then follows the fixes as a
        slowly varying offset, which is still right, but ``T`` itself is uncertain)
    autocorrelation_time_constant : float, s, ``T`` of the exponential fitted to the
        autocorrelation alone (the likelihood's starting point; None: not fitted)
    """

    time_constant: float
    bias_sigma: float
    white_sigma: float
    n_fixes: int
    lags: tuple[float, ...] = ()
    autocorrelation: tuple[float, ...] = ()
    resolved: bool = True
    autocorrelation_time_constant: float | None = None

    def to_dict(self) -> dict[str, object]:
        """JSON-ready record (metrics.json ``gnss_track.model``)."""
        return {
            "time_constant_s": round(self.time_constant, 3),
            "bias_sigma_per_axis_m": round(self.bias_sigma, 4),
            "white_sigma_per_axis_m": round(self.white_sigma, 4),
            "n_fixes": self.n_fixes,
            "lags_s": [round(v, 3) for v in self.lags],
            "autocorrelation": [
                round(v, 4) if math.isfinite(v) else None for v in self.autocorrelation
            ],
            "time_constant_resolved": self.resolved,
            "estimator": "maximum likelihood (Kalman filter innovations), started from the "
            "exponential fitted to the autocorrelation",
            "autocorrelation_fit_time_constant_s": (
                None
                if self.autocorrelation_time_constant is None
                else round(self.autocorrelation_time_constant, 3)
            ),
        }


def _residuals(trajectory: Trajectory, fixes: GnssFixes) -> tuple[FloatArray, FloatArray]:
    """Times (M,) and residuals ``fix - antenna`` (M, 2) of the fixes inside the path's span."""
    from stemmap.eval.trajectory import point_track

    use = (fixes.times >= trajectory.times[0]) & (fixes.times <= trajectory.times[-1])
    t = np.asarray(fixes.times[use], dtype=np.float64)
    return t, fixes.xy[use] - point_track(trajectory, t, fixes.lever_arm)


def _autocorrelation_fit(
    t: FloatArray, r: FloatArray, dt: float, span: float
) -> tuple[float, float | None, FloatArray, FloatArray]:
    """``(c, T)`` of ``rho(tau) = c exp(-tau / T)`` fitted to the residuals' autocorrelation
    (:func:`stemmap.eval.gps_noise.gps_autocorrelation`, pairs within 10 % of the lag) at
    multiples 1, 2, 3, 4, 6, 8, 12, ... of the median fix interval ``dt``, least squares
    weighted by each lag's pair count (``T`` on a log grid from ``dt / 4`` to 20x the span,
    ``c`` in closed form in [0, 1]); the window of lags starts at a quarter of the span and is
    set to ``3 T`` (within [8 dt, span / 4]) twice. Also returns the lags and autocorrelation
    of the last pass; ``T`` None when fewer than 3 lags have 10 fix pairs."""
    from stemmap.eval.gps_noise import gps_autocorrelation, gps_variogram

    base = np.array([1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512])
    window, c = 0.25 * span, 0.8
    tc: float | None = None
    lags = rho = np.zeros(0)
    for _ in range(3):
        lags = dt * base[dt * base <= max(window, dt)]
        rho = gps_autocorrelation(t, r, np.zeros_like(r), lags)
        cnt = gps_variogram(t, r, np.zeros_like(r), lags).pairs
        ok = np.isfinite(rho) & (cnt >= MIN_PAIRS)
        if ok.sum() < 3:
            break
        x, y, w = lags[ok], rho[ok], cnt[ok]
        best = (np.inf, c, 10.0 * dt)
        for tg in np.geomspace(0.25 * dt, 20.0 * span, 400):
            a = np.exp(-x / tg)
            cg = float(np.clip(np.sum(w * a * y) / np.sum(w * a * a), 0.0, 1.0))
            cost = float(np.sum(w * (cg * a - y) ** 2))
            if cost < best[0]:
                best = (cost, cg, float(tg))
        _, c, tc = best
        window = float(np.clip(3.0 * tc, 8.0 * dt, 0.25 * span))
    return c, tc, lags, rho


def _gm_nll(theta: FloatArray, gaps: FloatArray, r: FloatArray) -> float:
    """Negative log-likelihood (constants dropped) of residuals ``r`` (M, 2) under the
    Gauss-Markov + white model with ``theta = log(T, s_b, s_w)``, by the Kalman filter's
    prediction-error decomposition (both axes, independent, same model); ``gaps`` (M,) the time
    since the previous fix (the first ignored)."""
    tc, sb, sw = (math.exp(float(v)) for v in theta)
    p0, w2 = sb * sb, sw * sw + 1e-12
    mx = my = 0.0
    p, nll = p0, 0.0
    phis = np.exp(-gaps / tc)
    for i in range(r.shape[0]):
        if i:
            ph = float(phis[i])
            mx, my = ph * mx, ph * my
            p = ph * ph * p + p0 * (1.0 - ph * ph)
        s = p + w2
        vx, vy = float(r[i, 0]) - mx, float(r[i, 1]) - my
        nll += 0.5 * (vx * vx + vy * vy) / s + math.log(s)
        k = p / s
        mx, my, p = mx + k * vx, my + k * vy, (1.0 - k) * p
    return nll


def fit_gnss_offset_model(
    trajectory: Trajectory,
    fixes: GnssFixes,
    *,
    min_fixes: int = MIN_FIXES,
) -> GnssOffsetModel:
    """Estimate the Gauss-Markov model of the fixes' offset from ``trajectory`` (module docs).

    The residuals ``r_i = fix_i - antenna(t_i)`` of the fixes inside the trajectory's span are
    centred (their mean is the path's frame offset from the fixes, not part of the receiver's
    varying error) and modelled per axis as ``b(t_i) + w_i``: ``b`` a first-order Gauss-Markov
    process (time constant ``T``, stationary std ``s_b``), ``w`` white (``s_w``), i.e. variance
    ``s_b² + s_w²`` and autocorrelation ``rho(tau) = s_b² / (s_b² + s_w²) exp(-tau / T)`` at
    ``tau > 0``.

    1. The autocorrelation is measured at multiples of the median fix interval and
       ``rho(tau)`` fitted to it (the starting point, and the record's ``autocorrelation``).
    2. ``(T, s_b, s_w)`` by **maximum likelihood**: the exact Gaussian likelihood of the
       irregularly spaced residuals from the Kalman filter's innovations (prediction-error
       decomposition; Harvey, *Forecasting, Structural Time Series Models and the Kalman
       Filter*, 1989, ch. 3.4), Nelder-Mead on the logarithms from the autocorrelation fit and
       from ``T = 10 dt``. Why not the autocorrelation fit alone: the fixes' own spacing hides
       the short lags (fused fixes 2 s apart on Victoria Park), so ``s_w`` comes from
       extrapolating ``rho`` to 0 and a single exponential fitted over all lags can trade it
       for a long ``T``; on Victoria Park's first half the fit gave T = 96 s, s_w = 0.43 m and
       a held-out second-half track of 0.74 m, the likelihood T = 29 s, s_w ~ 0 and 0.36 m
       (docs/algorithms/slam.md "GNSS-frame track"). The likelihood scores the model where
       the track uses it: predicting the next fix from the earlier ones.

    Parameters
    ----------
    trajectory : Trajectory, the path (in the fixes' frame; the fused run's own path)
    fixes : GnssFixes, the fixes fused into it
    min_fixes : int, fewest fixes inside the path's span to estimate from

    Returns
    -------
    GnssOffsetModel
        ``resolved`` False (and a warning logged) when ``T`` exceeds a quarter of the fixes'
        span.

    Raises
    ------
    InputError
        Fewer than ``min_fixes`` fixes inside the path's span, or all at one time.
    """
    from scipy.optimize import minimize

    t, r = _residuals(trajectory, fixes)
    n = int(t.shape[0])
    if n < min_fixes:
        raise InputError(
            f"GNSS offset model: {n} fixes inside the run, need at least {min_fixes} to estimate "
            "the GNSS error's time constant and size from them; give more fixes (a longer run "
            "or a higher fix rate)."
        )
    gaps = np.diff(t, prepend=t[0])
    pos = gaps[gaps > 0]
    dt = float(np.median(pos)) if pos.size else 0.0
    span = float(t[-1] - t[0])
    if not (dt > 0 and span > 0):
        raise InputError("GNSS offset model: the fixes inside the run share one time.")
    e = r - r.mean(axis=0)
    var_axis = max(0.5 * float(np.mean(np.sum(e * e, axis=1))), 1e-12)
    c_ac, tc_ac, lags, rho = _autocorrelation_fit(t, e, dt, span)
    lo, hi = math.log(0.25 * dt), math.log(20.0 * span)

    def cost(theta: FloatArray) -> float:
        th = np.array(theta, dtype=np.float64)
        th[0] = min(max(th[0], lo), hi)
        return _gm_nll(th, gaps, e)

    best = None
    starts = [(10.0 * dt, 0.8)] + ([(tc_ac, c_ac)] if tc_ac is not None else [])
    for t0, c0 in starts:
        x0 = np.log(
            [t0, math.sqrt(max(c0, 0.05) * var_axis), math.sqrt(max(1 - c0, 0.05) * var_axis)]
        )
        res = minimize(cost, x0, method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-4})
        if best is None or res.fun < best.fun:
            best = res
    assert best is not None
    tc = math.exp(min(max(float(best.x[0]), lo), hi))
    sb, sw = math.exp(float(best.x[1])), math.exp(float(best.x[2]))
    resolved = tc <= 0.25 * span
    if not resolved:
        log.warning(
            "GNSS offset model: fitted time constant %.1f s exceeds a quarter of the fixes' "
            "span (%.1f s); the run is too short to resolve it",
            tc,
            span,
        )
    return GnssOffsetModel(
        time_constant=tc,
        bias_sigma=sb,
        white_sigma=sw,
        n_fixes=n,
        lags=tuple(float(v) for v in lags),
        autocorrelation=tuple(float(v) for v in rho),
        resolved=resolved,
        autocorrelation_time_constant=tc_ac,
    )


@dataclass(frozen=True, eq=False)
class GnssOffset:
    """The fixes' slowly varying offset from a trajectory (from :func:`gnss_offset`).

    times : (M,) s, the fixes' times; offset : (M, 2) m, the estimated ``fix - antenna`` bias
    there (smoothed, or filtered when ``causal``); std : (M,) m, its 1-sigma per axis;
    time_constant : s, the first-order Gauss-Markov model's correlation time (None: a random
    walk); prior_sigma : m, the Gauss-Markov bias's stationary std (the random walk's start
    std); walk_sigma : m/sqrt(s), the random walk's intensity; cross : (M-1,) m², the smoothed
    covariance between consecutive fixes' bias (RTS lag-one covariance; None: not known, the
    interpolated std then counts the two ends as independent); causal : the filter estimate
    (between fixes only the fix before counts).
    """

    times: FloatArray
    offset: FloatArray
    std: FloatArray
    time_constant: float | None = None
    prior_sigma: float = 3.0
    walk_sigma: float = 1.0
    cross: FloatArray | None = None
    causal: bool = False

    def _ends(self, t: FloatArray) -> tuple[np.ndarray, FloatArray, FloatArray, FloatArray]:
        """Per ``t``: index ``k`` of the fix at or before it (clipped to [0, M-2]; 0 when
        M = 1), time ``c`` since fix ``k``, ``a`` to fix ``k + 1``, and ``d = c + a``."""
        tf = self.times
        m = tf.shape[0]
        k = np.clip(np.searchsorted(tf, t, side="right") - 1, 0, max(m - 2, 0))
        if m == 1:
            z = np.zeros_like(t)
            return k, z, z, z
        c = np.clip(t - tf[k], 0.0, None)
        a = np.clip(tf[k + 1] - t, 0.0, None)
        return k, c, a, np.maximum(tf[k + 1] - tf[k], 1e-12)

    def _decay(self, dt: FloatArray) -> FloatArray:
        """Mean carried over ``dt`` >= 0 s: ``exp(-dt / T)`` (Gauss-Markov) or 1 (walk)."""
        if self.time_constant is None:
            return np.ones_like(dt)
        return np.exp(-dt / float(self.time_constant))

    def _grow(self, var: FloatArray, dt: FloatArray) -> FloatArray:
        """Variance carried over ``dt`` >= 0 s from ``var`` (the model's prediction step)."""
        if self.time_constant is None:
            return var + self.walk_sigma**2 * dt
        phi2 = np.exp(-2.0 * dt / float(self.time_constant))
        return phi2 * var + self.prior_sigma**2 * (1.0 - phi2)

    def _bridge(self, c: FloatArray, a: FloatArray, d: FloatArray) -> tuple[FloatArray, ...]:
        """Weights ``w0, w1`` of the bias at the fixes before / after and the variance of the
        bias given both (the Ornstein-Uhlenbeck or Brownian bridge)."""
        if self.time_constant is None:
            return a / d, c / d, self.walk_sigma**2 * c * a / d
        tau = float(self.time_constant)
        # sinh(x)/sinh(d) with exp(-...) only: no overflow for long outages
        den = -np.expm1(-2.0 * d / tau)

        def ratio(x: FloatArray) -> FloatArray:
            return np.asarray((np.exp((x - d) / tau) - np.exp((-x - d) / tau)) / den)

        w0, w1 = ratio(np.minimum(a, d)), ratio(np.minimum(c, d))
        var = self.prior_sigma**2 * np.expm1(-2.0 * c / tau) * np.expm1(-2.0 * a / tau) / den
        return w0, w1, var

    def _moments(self, times: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Mean (N, 2) and per-axis variance (N,) of the bias at ``times``."""
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        tf, b, p = self.times, self.offset, np.asarray(self.std) ** 2
        lo, hi = t < tf[0], t > tf[-1]
        if self.causal:  # the fix at or before t, carried forward; the prior before any fix
            k = np.clip(np.searchsorted(tf, t, side="right") - 1, 0, tf.shape[0] - 1)
            dt = np.clip(t - tf[k], 0.0, None)
            mean = b[k] * self._decay(dt)[:, None]
            var = self._grow(p[k], dt)
            mean[lo] = 0.0
            var[lo] = self.prior_sigma**2
            return mean, var
        k, c, a, d = self._ends(t)
        if tf.shape[0] == 1:
            dt = np.abs(t - tf[0])
            return b[0] * self._decay(dt)[:, None], self._grow(np.full(dt.shape, p[0]), dt)
        else:
            w0, w1, bv = self._bridge(c, a, d)
            x = np.zeros(tf.shape[0] - 1) if self.cross is None else np.asarray(self.cross)
            mean = w0[:, None] * b[k] + w1[:, None] * b[k + 1]
            var = bv + w0**2 * p[k] + w1**2 * p[k + 1] + 2.0 * w0 * w1 * x[k]
        for m, j in ((lo, 0), (hi, -1)):  # outside the fixes: carried from the end fix
            dt = np.abs(t[m] - tf[j])
            mean[m] = b[j] * self._decay(dt)[:, None]
            var[m] = self._grow(np.full(dt.shape, p[j]), dt)
        return mean, var

    def at(self, times: ArrayLike) -> FloatArray:
        """(N, 2) offset at ``times``.

        Smoothed (default): between fixes at ``t0``, ``t1`` the bridge mean, ``E[b(t) | b0,
        b1]`` -- exact for the smoothed mean since no fix lies in between: random walk linear;
        Gauss-Markov with time constant ``T`` ``b0 sinh((t1 - t)/T) / sinh(Δ/T) + b1 sinh((t -
        t0)/T) / sinh(Δ/T)`` (linear for ``Δ << T``). Outside the fixes' span the end fix's
        offset, held (random walk) or decaying as ``exp(-|t - t_end| / T)`` towards 0 (the
        path's own frame). Causal: the offset of the last fix at or before ``t``, carried
        forward the same way; 0 before the first fix.
        """
        return self._moments(times)[0]

    def std_at(self, times: ArrayLike) -> FloatArray:
        """(N,) 1-sigma per axis (m) of :meth:`at`: the bridge variance plus the end fixes'
        (smoothed: with their lag-one covariance ``cross``), or the filtered variance grown
        by the model since the last fix (causal)."""
        return np.sqrt(np.maximum(self._moments(times)[1], 0.0))


def gnss_offset(
    trajectory: Trajectory,
    fixes: GnssFixes,
    *,
    walk_sigma: float = 1.0,
    fix_sigma: float = 0.1,
    prior_sigma: float = 3.0,
    time_constant: float | None = None,
    model: GnssOffsetModel | None = None,
    causal: bool = False,
) -> GnssOffset:
    """Estimate the fixes' offset from ``trajectory`` as a GNSS bias: a 2-D random walk or a
    first-order Gauss-Markov process (as in loosely coupled GNSS/INS fusion).

    ``r_i = fix_i - antenna(t_i)`` (antenna = the lever-arm point of the trajectory) is modelled
    as ``r_i = b(t_i) + w_i``, ``w_i`` white with std ``fix_sigma`` (m), and ``b``:

    * ``time_constant=None``: a random walk of intensity ``walk_sigma`` (m/sqrt(s)), start
      ``N(0, prior_sigma²)``. A long outage lets the variance grow by ``walk_sigma² Δt``: a
      jump after it is followed.
    * ``time_constant=T`` (s): a first-order Gauss-Markov (Ornstein-Uhlenbeck) process with
      stationary std ``prior_sigma`` per axis, ``b(t+Δ) = φ b(t) + η``, ``φ = exp(-Δ/T)``,
      ``var η = prior_sigma² (1 - φ²)``, i.e. autocovariance ``prior_sigma² exp(-|τ|/T)``
      (``walk_sigma`` is not used). Across a long outage the bias forgets towards 0 (the
      trajectory's own frame) instead of holding the last offset.
    * ``model`` (from :func:`fit_gnss_offset_model`): the Gauss-Markov process with its
      ``time_constant``, ``bias_sigma`` (as ``prior_sigma``) and ``white_sigma`` (as
      ``fix_sigma``, at least 1 mm); the three keywords are then ignored.

    A Kalman filter per axis (the model is isotropic) gives ``b`` at each fix from the fixes up
    to it (``causal=True``: what a machine online can know); by default a Rauch-Tung-Striebel
    smoother then uses the fixes on both sides (the offline product: between two fixes the
    smoothed bias interpolates, the filtered one can only hold or decay the last fix's). The
    random-walk defaults are the 2-fold CV choice inside the fused fixes on Victoria Park
    (every 10th screened fix, ~2 s apart; benchmarks/slam_field.py).

    Why: on Victoria Park the GPS error is a slowly varying offset (~1 m RMS, correlation time
    ~18 s, docs/algorithms/slam.md "GNSS fusion"). A path held by the trees cannot follow it;
    ``trajectory + b`` (:func:`gnss_frame_trajectory`) is the track *as the GNSS reports it*,
    not a better position of the vehicle.
    """
    if model is not None:
        time_constant = model.time_constant
        prior_sigma = max(model.bias_sigma, 1e-3)
        fix_sigma = max(model.white_sigma, 1e-3)
    for name, v in (("walk_sigma", walk_sigma), ("fix_sigma", fix_sigma)):
        if not (math.isfinite(v) and v > 0):
            raise InputError(f"gnss_offset: {name} must be > 0 (m), got {v}.")
    if not (math.isfinite(prior_sigma) and prior_sigma > 0):
        raise InputError(f"gnss_offset: prior_sigma must be > 0 (m), got {prior_sigma}.")
    if time_constant is not None and not (math.isfinite(time_constant) and time_constant > 0):
        raise InputError(
            f"gnss_offset: time_constant must be > 0 (s) or None, got {time_constant}."
        )
    t, r = _residuals(trajectory, fixes)
    n = t.shape[0]
    if n == 0:
        raise InputError("gnss_offset: no fix inside the trajectory's time span.")
    m, p = np.zeros((n, 2)), np.zeros(n)
    mp, pp = np.zeros((n, 2)), np.zeros(n)
    ph = np.ones(n)  # transition factor from fix i-1 to fix i (1 for a random walk)
    q2, w2, p0 = walk_sigma**2, fix_sigma**2, prior_sigma**2
    for i in range(n):
        if i == 0:
            mp[i], pp[i] = 0.0, p0
        else:
            dt = t[i] - t[i - 1]
            if time_constant is None:
                mp[i], pp[i] = m[i - 1], p[i - 1] + q2 * dt
            else:
                ph[i] = math.exp(-dt / time_constant)
                mp[i] = ph[i] * m[i - 1]
                pp[i] = ph[i] ** 2 * p[i - 1] + p0 * (1.0 - ph[i] ** 2)
        k = pp[i] / (pp[i] + w2)
        m[i] = mp[i] + k * (r[i] - mp[i])
        p[i] = (1.0 - k) * pp[i]
    if causal:
        return GnssOffset(
            t, m, np.sqrt(np.maximum(p, 0.0)), time_constant, prior_sigma, walk_sigma, causal=True
        )
    cross = np.zeros(max(n - 1, 0))
    for i in range(n - 2, -1, -1):
        c = p[i] * ph[i + 1] / pp[i + 1] if pp[i + 1] > 0 else 0.0
        m[i] = m[i] + c * (m[i + 1] - mp[i + 1])
        p[i] = p[i] + c * c * (p[i + 1] - pp[i + 1])
        cross[i] = c * p[i + 1]  # P_{i,i+1|N} = C_i P_{i+1|N} (p[i + 1] already smoothed)
    return GnssOffset(
        t, m, np.sqrt(np.maximum(p, 0.0)), time_constant, prior_sigma, walk_sigma, cross=cross
    )


class GnssOffsetFilter:
    """The causal offset online, one fix at a time (the forward pass of
    :func:`gnss_offset` with ``causal=True`` and ``model``; the same numbers).

    ``update(t, residual)`` takes a fix's ``fix - antenna`` (m) at time ``t`` (s, not
    decreasing); ``at(t)`` gives the offset (2,) and its per-axis std (m) at ``t`` from the
    fixes so far: the prior (0, ``bias_sigma``) before any fix, then the last filtered value
    decayed by ``exp(-(t - t_k) / T)``. Used by :class:`stemmap.slam.online.OnlineMapper`
    (``pose_gnss``).
    """

    def __init__(self, model: GnssOffsetModel) -> None:
        self.model = model
        self._sb = max(model.bias_sigma, 1e-3)
        self._w2 = max(model.white_sigma, 1e-3) ** 2
        self._last: GnssOffset | None = None

    def _state(self, t: float) -> tuple[FloatArray, float]:
        if self._last is None:
            return np.zeros(2), self._sb**2
        mean, var = self._last._moments([t])
        return mean[0], float(var[0])

    def update(self, t: float, residual: ArrayLike) -> None:
        """Fuse one fix's residual (Kalman update per axis, white noise ``white_sigma``)."""
        if self._last is not None and t < float(self._last.times[0]):
            raise InputError(f"GnssOffsetFilter: fix at {t} s is before the last one.")
        mp, pp = self._state(t)
        k = pp / (pp + self._w2)
        m = mp + k * (np.asarray(residual, dtype=np.float64).reshape(2) - mp)
        self._last = GnssOffset(
            np.array([float(t)]), m[None], np.array([math.sqrt((1.0 - k) * pp)]),
            time_constant=self.model.time_constant, prior_sigma=self._sb, causal=True,
        )  # fmt: skip

    @property
    def last_time(self) -> float:
        """Time (s) of the last fix fused (-inf before any)."""
        return -math.inf if self._last is None else float(self._last.times[0])

    def at(self, t: float) -> tuple[FloatArray, float]:
        """Offset (2,) m and its per-axis 1-sigma (m) at ``t`` from the fixes so far."""
        mean, var = self._state(float(t))
        return mean, math.sqrt(max(var, 0.0))


def gnss_frame_trajectory(trajectory: Trajectory, offset: GnssOffset) -> Trajectory:
    """``trajectory`` shifted at every pose by the fixes' estimated offset (headings kept): the
    vehicle track in the frame the GNSS reports at each moment (:func:`gnss_offset`)."""
    poses = np.array(trajectory.poses, dtype=np.float64)
    poses[:, :2] += offset.at(trajectory.times)
    return Trajectory(trajectory.times, poses, frame=trajectory.frame)
