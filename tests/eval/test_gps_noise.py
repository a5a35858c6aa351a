"""GPS self-error estimates (stemmap.eval.gps_noise) on a simulated GPS with a known error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import InputError
from stemmap.eval.gps_noise import (
    GpsVariogram,
    fit_gauss_markov,
    gps_autocorrelation,
    gps_revisit_error,
    gps_variogram,
)


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


# --- hand-built cases: exact values, limits and messages ---------------------------------------


@pytest.mark.parametrize("fn", [gps_variogram, gps_autocorrelation, gps_revisit_error])
def test_input_checks_name_the_function_and_every_count(fn) -> None:
    name = fn.__name__
    args = () if fn is gps_revisit_error else ([1.0],)
    with pytest.raises(
        InputError,
        match=rf"^{name}: 3 times, 4 fixes and 5 path positions must all match "
        r"\(the path at the fix times\)\.$",
    ):
        fn(np.arange(3.0), np.zeros((4, 2)), np.zeros((5, 2)), *args)
    with pytest.raises(InputError, match=rf"^{name}: fix times must not decrease\.$"):
        fn([1.0, 0.0], np.zeros((2, 2)), np.zeros((2, 2)), *args)  # two fixes are enough
    fn([0.0, 0.0, 1.0], np.zeros((3, 2)), np.zeros((3, 2)), *args)  # equal times are allowed
    if fn is not gps_revisit_error:
        for bad in (0.0, -1.0, math.nan, math.inf):
            with pytest.raises(InputError, match=rf"^{name}: lags must be positive seconds, got "):
                fn(np.arange(3.0), np.zeros((3, 2)), np.zeros((3, 2)), [1.0, bad])


def test_variogram_exact_value_and_the_pair_rule() -> None:
    """``gamma = 1/4 mean |(g_j - g_i) - (p_j - p_i)|^2`` over pairs ``|t_j - t_i - tau| <
    max(abs_tol, rel_tol tau)``, ``j`` the first fix at or after ``t_i + tau`` (defaults 0.2 s
    and 10 %)."""
    t = np.arange(4.0)
    path = np.array([[0.0, 0.0], [3.0, 0.0], [6.0, 1.0], [9.0, 1.0]]) + np.array([100.0, -40.0])
    err = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 2.0], [1.0, 2.0]])
    vg = gps_variogram(t, path + err, path, [1.0, 3.0, 10.0])
    # lag 1: |d|^2 = 1, 4, 0; lag 3: |(1, 2)|^2 = 5; lag 10: no pair
    np.testing.assert_allclose(vg.gamma[:2], [5.0 / 12.0, 5.0 / 4.0])
    assert np.isnan(vg.gamma[2]) and vg.gamma.dtype == np.float64
    np.testing.assert_array_equal(vg.pairs, [3, 1, 0])
    np.testing.assert_allclose(vg.rms_2d[:2], np.sqrt(2.0 * vg.gamma[:2]))
    np.testing.assert_array_equal(vg.lags, [1.0, 3.0, 10.0])

    def n_pairs(times, tau, **kw):
        z = np.zeros((len(times), 2))
        return int(gps_variogram(times, z, z, [tau], **kw).pairs[0])

    assert n_pairs([0.0, 1.25], 1.0) == 0  # 0.25 s off: beyond the default 0.2 s
    assert n_pairs([0.0, 1.1875], 1.0) == 1
    assert n_pairs([0.0, 1.25], 1.0, abs_tol=0.25) == 0  # strictly inside the tolerance
    assert n_pairs([0.0, 1.25], 1.0, abs_tol=0.3) == 1
    assert n_pairs([0.0, 10.5], 10.0) == 1  # 10 % of 10 s = 1 s > 0.2 s
    assert n_pairs([0.0, 11.5], 10.0) == 0
    assert n_pairs([0.0, 11.5], 10.0, rel_tol=0.2) == 1
    # j is the first fix at or after t_i + tau, even when a later one is as close
    e = np.array([[0.0, 0.0], [0.0, 0.0], [2.0, 0.0], [0.0, 0.0]])
    one = gps_variogram([0.0, 0.9, 1.0, 1.1], e, np.zeros((4, 2)), [1.0])
    assert one.pairs[0] == 1 and one.gamma[0] == pytest.approx(1.0)


def test_autocorrelation_exact_values() -> None:
    """``mean(e_i . e_j) / mean |e|^2`` of the centred error ``e = g - p`` (each axis centred
    on its own mean); NaN for a lag without pairs and for an error without variance."""
    t = np.arange(4.0)
    path = np.array([[0.0, 0.0], [3.0, 0.0], [6.0, 1.0], [9.0, 1.0]])
    u = np.array([[0.1, 0.0], [0.1, 0.0], [-0.1, 0.0], [-0.1, 0.0]])  # variance 0.01 m^2
    gps = path + u + np.array([5.0, -3.0])  # a constant offset, other on each axis
    ac = gps_autocorrelation(t, gps, path, [1.0, 2.0, 3.0, 10.0])
    assert ac.dtype == np.float64
    np.testing.assert_allclose(ac[:3], [1.0 / 3.0, -1.0, -1.0])
    assert np.isnan(ac[3])
    flat = gps_autocorrelation(t, path + np.array([5.0, -3.0]), path, [1.0, 2.0])  # no variance
    assert flat.dtype == np.float64 and np.all(np.isnan(flat))
    # the pair rule of gps_variogram, with its defaults (0.2 s, 10 %)
    two = np.array([[0.0, 0.0], [1.0, 0.0]])
    z = np.zeros((2, 2))
    assert gps_autocorrelation([0.0, 1.1875], two, z, [1.0])[0] == pytest.approx(-1.0)
    far = gps_autocorrelation([0.0, 1.25], two, z, [1.0])
    assert far.shape == (1,) and np.isnan(far[0])
    assert gps_autocorrelation([0.0, 10.5], two, z, [10.0])[0] == pytest.approx(-1.0)
    assert np.isnan(gps_autocorrelation([0.0, 11.5], two, z, [10.0])[0])


def _gm_grid() -> np.ndarray:
    return np.geomspace(0.5, 500.0, 600)  # the documented grid of T


def _gm_variogram(lags, nug: float, sb2: float, tc: float) -> GpsVariogram:
    """A semivariogram that is exactly the fitted model: the nugget at the first lag, then
    ``nug + sb2 (1 - exp(-tau / T))``."""
    lg = np.asarray(lags, dtype=float)
    gam = nug + sb2 * (1.0 - np.exp(-lg / tc))
    gam[0] = nug
    return GpsVariogram(lg, gam, np.ones_like(lg))


def test_gauss_markov_fit_is_exact_on_its_own_model() -> None:
    for k in (40, 250, 480):
        tc = float(_gm_grid()[k])
        vg = _gm_variogram([0.2, 1.0, 2.0, 5.0, 10.0, 20.0, 40.0, 60.0], 0.01, 0.49, tc)
        fit = fit_gauss_markov(vg)
        assert fit.time_constant == pytest.approx(tc, rel=1e-12)
        assert fit.bias_sigma == pytest.approx(0.7, rel=1e-9)
        assert fit.white_sigma == pytest.approx(0.1, rel=1e-12)
    tc = float(_gm_grid()[250])
    base = _gm_variogram([0.2, 1.0, 2.0, 5.0, 10.0, 20.0, 40.0, 60.0], 0.01, 0.49, tc)
    # lags beyond max_lag (default 60 s) and lags without pairs (NaN) are left out
    lags = np.concatenate((base.lags, [61.0, 30.0]))
    gam = np.concatenate((base.gamma, [50.0, np.nan]))
    fit = fit_gauss_markov(GpsVariogram(lags, gam, np.ones(lags.size)))
    assert fit.time_constant == pytest.approx(tc, rel=1e-12)
    assert fit.bias_sigma == pytest.approx(0.7, rel=1e-9)
    wide = fit_gauss_markov(GpsVariogram(lags, gam, np.ones(lags.size)), max_lag=61.0)
    assert wide.bias_sigma > 1.0  # the 61-s lag now counts
    # the lags may come in any order: the nugget is the shortest
    rev = GpsVariogram(base.lags[::-1], base.gamma[::-1], base.pairs)
    assert fit_gauss_markov(rev) == fit_gauss_markov(base)
    # a semivariogram that does not grow: no bias
    flat = fit_gauss_markov(GpsVariogram(base.lags, np.full(8, 0.04), base.pairs))
    assert flat.bias_sigma == 0.0 and flat.white_sigma == pytest.approx(0.2)


def test_gauss_markov_fit_needs_three_lags_up_to_max_lag() -> None:
    tc = float(_gm_grid()[250])
    three = fit_gauss_markov(_gm_variogram([0.2, 10.0, 60.0], 0.01, 0.49, tc))  # 60 s counts
    assert three.time_constant == pytest.approx(tc, rel=1e-6)
    with pytest.raises(
        InputError, match=r"^fit_gauss_markov: need >= 3 lags <= 60\.0 s with fix pairs, got 2\.$"
    ):
        fit_gauss_markov(_gm_variogram([0.2, 10.0, 60.5], 0.01, 0.49, tc))


def _revisits(t, p, e):
    p = np.asarray(p, dtype=float)
    return np.asarray(t, dtype=float), p + np.asarray(e, dtype=float), p


def test_revisit_error_exact_value_and_default_limits() -> None:
    """One pair 0.9 m apart and exactly 60 s apart counts (``radius`` 1 m, ``min_dt`` 60 s,
    inclusive); a pair 1.5 m apart does not."""
    t, g, p = _revisits(
        [0.0, 60.0, 200.0, 300.0],
        [[0.0, 0.0], [0.9, 0.0], [50.0, 0.0], [51.5, 0.0]],
        [[0.0, 0.0], [0.3, 0.4], [0.0, 0.0], [1.0, 1.0]],
    )
    est = gps_revisit_error(t, g, p)
    assert est and est.pairs == 1
    assert est.rms_2d == pytest.approx(math.sqrt(0.5 * 0.25))  # |d| = 0.5 m
    assert est.median_disagreement == pytest.approx(0.5)
    two = gps_revisit_error(t, g, p, radius=2.0)
    assert two.pairs == 2
    assert two.rms_2d == pytest.approx(math.sqrt(0.5 * (0.25 + 2.0) / 2))
    assert two.median_disagreement == pytest.approx((0.5 + math.sqrt(2.0)) / 2)
    assert gps_revisit_error(t, g, p, min_dt=60.5).pairs == 0
    none = gps_revisit_error(t, g, p, min_dt=500.0)
    assert not none and math.isnan(none.rms_2d) and math.isnan(none.median_disagreement)


def test_revisit_error_one_pair_per_time_block() -> None:
    """Two revisit pairs whose first times share a 10-s block and whose second times share one
    count once: the pair with the earliest first fix. Blocks are ``block_s`` wide (default 10 s)."""
    # fixes 0, 1 at 0 and 0.5 s; fix 2 revisits fix 1's place, fix 3 fix 0's place
    p = [[0.0, 0.0], [10.0, 0.0], [10.0, 0.2], [0.0, 0.2]]
    e = [[0.0, 0.0], [0.0, 0.0], [0.0, 0.6], [0.0, 0.2]]
    t, g, pp = _revisits([0.0, 0.5, 100.0, 100.5], p, e)
    est = gps_revisit_error(t, g, pp)
    assert est.pairs == 1 and est.median_disagreement == pytest.approx(0.2)  # the pair (0, 3)
    assert gps_revisit_error(t, g, pp, block_s=0.5).pairs == 2
    # first times 9.5 and 10.5 s: two 10-s blocks (one 11-s block)
    t2, g2, p2 = _revisits([9.5, 10.5, 110.5, 111.5], p, e)
    assert gps_revisit_error(t2, g2, p2).pairs == 2
    assert gps_revisit_error(t2, g2, p2, block_s=11.0).pairs == 1


def test_revisit_error_argument_limits() -> None:
    t, g, p = _revisits([0.0, 60.0], [[0.0, 0.0], [0.5, 0.0]], [[0.0, 0.0], [0.3, 0.4]])
    msg = r"^gps_revisit_error: need radius > 0, min_dt >= 0, block_s > 0 \(got "
    for kw in ({"radius": 0.0}, {"min_dt": -1.0}, {"block_s": 0.0}, {"radius": -1.0}):
        with pytest.raises(InputError, match=msg):
            gps_revisit_error(t, g, p, **kw)
    with pytest.raises(InputError, match=r"\(got 1\.0, -1\.0, 10\.0\)\.$"):
        gps_revisit_error(t, g, p, min_dt=-1.0)
    for kw in ({"min_dt": 0.0}, {"min_dt": 0.5}, {"block_s": 0.5}, {"radius": 0.6}):
        assert gps_revisit_error(t, g, p, **kw).pairs == 1


def test_revisit_blocks_hold_for_absolute_times() -> None:
    """GPS logs carry absolute times (UNIX or GPS-week seconds, ~1.7e9 s): shifting every time
    by a whole number of blocks keeps the pairs apart exactly as from t = 0 (the block key of
    two ~1.7e8 block numbers must not lose either to rounding)."""
    p = [[0.0, 0.0], [10.0, 0.0], [0.0, 0.2], [10.0, 0.2]]  # fix 2 revisits 0, fix 3 revisits 1
    e = [[0.0, 0.0], [0.0, 0.0], [0.0, 0.6], [0.0, 0.2]]
    q = [[0.0, 0.0], [10.0, 0.0], [10.0, 0.2], [0.0, 0.2]]  # fix 2 revisits 1, fix 3 revisits 0
    cases = (
        ([9.5, 9.6, 110.5, 120.5], p),  # one first block, two second blocks
        ([9.5, 10.5, 110.5, 111.5], q),  # two first blocks, one second block
    )
    for times, pos in cases:
        t, g, pp = _revisits(times, pos, e)
        ref = gps_revisit_error(t, g, pp)
        assert ref.pairs == 2
        for t0 in (1.7e9, 1.4e9 + 10.0):
            got = gps_revisit_error(t + t0, g, pp)
            assert (got.pairs, got.rms_2d) == (ref.pairs, pytest.approx(ref.rms_2d))
