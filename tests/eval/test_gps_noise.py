"""GPS self-error estimates (stemmap.eval.gps_noise) on a simulated GPS with a known error."""

from __future__ import annotations

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.eval.gps_noise import gps_revisit_error, gps_variogram


def _laps(n_laps: int = 6, rate: float = 5.0, seed: int = 0):
    """A 60 x 40 m rectangle driven ``n_laps`` times at 3 m/s; a GPS with a piecewise-constant
    bias (new N(0, 0.8² I) every 5-20 s, as between outages) + white N(0, 0.1² I)."""
    rng = np.random.default_rng(seed)
    per = 200.0
    s = np.arange(0.0, n_laps * per * (1.0 / 3.0) * 3.0, 3.0 / rate) % per  # arc length
    t = np.arange(s.size) / rate
    corners = np.array([[0, 0], [60, 0], [60, 40], [0, 40], [0, 0]], float)
    seg = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(corners, axis=0).T))))
    k = np.clip(np.searchsorted(seg, s, side="right") - 1, 0, 3)
    f = ((s - seg[k]) / (seg[k + 1] - seg[k]))[:, None]
    truth = corners[k] * (1 - f) + corners[k + 1] * f
    bias = np.zeros_like(truth)
    i = 0
    while i < t.size:
        n = int(rng.uniform(5, 20) * rate)
        bias[i : i + n] = rng.normal(0.0, 0.8, 2)
        i += n
    gps = truth + bias + rng.normal(0.0, 0.1, truth.shape)
    sigma_2d = float(np.sqrt(np.mean(np.sum((gps - truth) ** 2, axis=1))))
    return t, gps, truth, sigma_2d


def test_revisit_error_recovers_the_gps_error() -> None:
    t, gps, truth, sigma = _laps()
    est = gps_revisit_error(t, gps, truth)
    assert est and est.pairs > 50
    # ~0.8 * sqrt(2) + white: the estimate is within 15 % (a few hundred independent pairs)
    assert est.rms_2d == pytest.approx(sigma, rel=0.15)
    # only the path's displacements count: a shifted frame gives the same estimate (up to the
    # pairs that sit exactly at the radius on this regular grid of positions)
    shifted = gps_revisit_error(t, gps, truth + np.array([100.0, -50.0]))
    assert shifted.rms_2d == pytest.approx(est.rms_2d, rel=0.02)


def test_variogram_white_at_short_lags_and_sill_at_long_ones() -> None:
    t, gps, truth, sigma = _laps(seed=1)
    vg = gps_variogram(t, gps, truth + np.array([3.0, 4.0]), [0.2, 60.0, 120.0])
    assert np.all(vg.pairs > 100)
    # short lag: mostly within one bias segment -> the white noise (0.1 m per axis) and a few jumps
    assert vg.rms_2d[0] < 0.35 * sigma
    # long lags: independent biases -> the 2-D RMS of the error
    assert vg.rms_2d[1:] == pytest.approx(sigma, rel=0.15)
    # the path's displacements must be in the fixes' rotation: a rotated path is inconsistent
    c, s_ = np.cos(0.3), np.sin(0.3)
    rot = gps_variogram(t, gps, truth @ np.array([[c, -s_], [s_, c]]).T, [60.0])
    assert rot.rms_2d[0] > 2 * sigma


def test_no_revisits_and_bad_inputs() -> None:
    t = np.arange(100.0)
    xy = np.column_stack((3.0 * t, np.zeros_like(t)))
    est = gps_revisit_error(t, xy, xy)
    assert not est and est.pairs == 0 and np.isnan(est.rms_2d)
    with pytest.raises(InputError):
        gps_variogram(t, xy, xy[:-1], [1.0])
    with pytest.raises(InputError):
        gps_variogram(t, xy, xy, [0.0])
    with pytest.raises(InputError):
        gps_revisit_error(t[::-1], xy, xy)


def _gauss_markov_gps(seed: int, s_w: float, s_b: float, tc: float, dur: float = 4000.0):
    """5 Hz fixes of a still antenna at the origin: a first-order Gauss-Markov bias (stationary
    std ``s_b`` per axis, time constant ``tc``; exact discretisation) + white ``s_w``."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, dur, 0.2)
    phi = np.exp(-0.2 / tc)
    b = np.zeros((t.size, 2))
    b[0] = rng.normal(0.0, s_b, 2)
    eta = rng.normal(0.0, s_b * np.sqrt(1.0 - phi**2), b.shape)
    for i in range(1, t.size):
        b[i] = phi * b[i - 1] + eta[i]
    return t, b + rng.normal(0.0, s_w, b.shape)


def test_gauss_markov_fit_and_autocorrelation_recover_the_model() -> None:
    """A simulated Gauss-Markov GPS error (white 0.1 m, bias 0.7 m, T = 20 s per axis, 10,000 s
    = 500 correlation times): the fit from the semivariogram recovers the bias sigma within
    10 % and T within 25 % (over 8 seeds the spread was 2 % and 12 %: T trades off against
    the sill seen only up to 3 T); the nugget is the white noise plus the bias's growth over
    the shortest lag (sqrt(0.01 + 0.49 x 0.01) = 0.122 m). The autocorrelation at lag T is
    exp(-1) x 0.49 / 0.50 = 0.36 (seen 0.33-0.38)."""
    from stemmap.eval.gps_noise import fit_gauss_markov, gps_autocorrelation

    for seed in (0, 1):
        t, gps = _gauss_markov_gps(seed, 0.1, 0.7, 20.0, dur=10000.0)
        path = np.zeros_like(gps)
        lags = [0.2, 0.5, 1.0, 2.0, 4.0, 8.0, 15.0, 30.0, 60.0]
        fit = fit_gauss_markov(gps_variogram(t, gps, path, lags))
        assert fit.bias_sigma == pytest.approx(0.7, rel=0.1)
        assert fit.time_constant == pytest.approx(20.0, rel=0.25)
        assert 0.1 <= fit.white_sigma <= 0.13
        ac = gps_autocorrelation(t, gps, path, [0.2, 20.0, 200.0])
        assert ac[0] > 0.9
        assert ac[1] == pytest.approx(0.36, abs=0.08)
        assert abs(ac[2]) < 0.12  # 10 T apart: independent (exp(-10) ~ 0; seen |.| <= 0.06)
    with pytest.raises(InputError, match="3 lags"):
        fit_gauss_markov(gps_variogram(t, gps, path, [0.2, 100.0]))
    with pytest.raises(InputError):
        gps_autocorrelation(t, gps, path, [-1.0])
