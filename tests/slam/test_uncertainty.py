"""Per-tree uncertainty and confidence (stemmap.slam.uncertainty)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stemmap.errors import ConfigError
from stemmap.slam.uncertainty import (
    DIAMETER_BIAS,
    DIAMETER_RHO,
    DetectionCounts,
    annotate_uncertainty,
    confidence_from_counts,
    detection_confidence,
    diameter_standard_errors,
    run_length_factor,
)


def _rows(
    rng: np.random.Generator, real: np.ndarray, n_frames: int, p_f: float, block: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tree, range, hit) rows: real trees detected with 0.9 - 0.04 * range, false with p_f;
    each outcome repeated ``block`` frames (temporally correlated)."""
    ti, rr, hh = [], [], []
    for j, is_real in enumerate(real):
        r = rng.uniform(2, 14, n_frames // block)
        p = 0.9 - 0.04 * r if is_real else np.full(r.shape, p_f)
        y = rng.random(r.shape) < p
        ti.append(np.full(r.size * block, j))
        rr.append(np.repeat(r, block))
        hh.append(np.repeat(y, block))
    return np.concatenate(ti), np.concatenate(rr), np.concatenate(hh)


def test_confidence_separates_and_is_calibrated(rng: np.random.Generator) -> None:
    real = rng.random(300) < 0.85
    ti, rr, hh = _rows(rng, real, 40, p_f=0.1)
    fit = detection_confidence(ti, rr, hh, real.size)
    assert fit.p_false == pytest.approx(0.1, abs=0.03)
    assert fit.prior_real == pytest.approx(real.mean(), abs=0.05)
    assert fit.run_length == pytest.approx(1.0, abs=0.15)  # independent frames
    c = fit.confidence
    # calibration: among trees given > 0.9, > 0.9 are real; among < 0.1, < 0.1 are real
    assert real[c > 0.9].mean() > 0.9 and real[c < 0.1].mean() < 0.1
    # Brier score far below the prior-only forecast's
    brier = np.mean((c - real) ** 2)
    assert brier < 0.25 * np.mean((real.mean() - real) ** 2)


def test_run_length_tempers_correlated_evidence(rng: np.random.Generator) -> None:
    real = rng.random(200) < 0.85
    ti, rr, hh = _rows(rng, real, 60, p_f=0.1, block=6)
    k = run_length_factor(ti, hh)
    assert 3.0 < k < 9.0  # blocks of 6 identical outcomes
    fit = detection_confidence(ti, rr, hh, real.size)
    assert fit.run_length == pytest.approx(k)
    c = fit.confidence
    assert real[c > 0.9].mean() > 0.9


def test_trees_never_in_view_get_the_prior() -> None:
    fit = detection_confidence(np.array([0, 0, 0, 1, 1]), np.full(5, 3.0), [1, 1, 1, 0, 0], 3)
    assert fit.confidence[2] == pytest.approx(fit.prior_real)


def test_counts_in_chunks_equal_counts_at_once(rng: np.random.Generator) -> None:
    """The bounded-memory path (rows counted a block of frames at a time, as
    annotate_uncertainty does on a long drive) gives exactly the counts of all rows at once,
    and the run-length factor of the rows (runs continue across chunk borders)."""
    real = rng.random(40) < 0.8
    ti, rr, hh = _rows(rng, real, 48, p_f=0.1, block=3)
    order = np.argsort(np.tile(np.arange(48), 40), kind="stable")  # time order, as frames come
    ti, rr, hh = ti[order], rr[order], hh[order]
    whole = DetectionCounts(real.size)
    whole.add(ti, rr, hh)
    parts = DetectionCounts(real.size)
    for a, b in zip([0, 7, 300, 301, 1200], [7, 300, 301, 1200, ti.size], strict=True):
        parts.add(ti[a:b], rr[a:b], hh[a:b])
    assert np.array_equal(parts.trials, whole.trials) and np.array_equal(parts.hits, whole.hits)
    assert np.array_equal(parts.runs, whole.runs)
    assert parts.run_length() == pytest.approx(run_length_factor(ti, hh), rel=1e-12)
    assert whole.trials.sum() == ti.size and whole.hits.sum() == hh.sum()
    a_fit, b_fit = confidence_from_counts(parts), detection_confidence(ti, rr, hh, real.size)
    assert np.array_equal(a_fit.confidence, b_fit.confidence)


def test_counts_equal_the_per_row_em(rng: np.random.Generator) -> None:
    """The EM on counts is the per-row EM (one iteration written out per row here): sums per
    (tree, bin) instead of per row change only the floating-point order."""
    real = rng.random(60) < 0.8
    ti, rr, hh = _rows(rng, real, 30, p_f=0.1)
    fit = detection_confidence(ti, rr, hh, real.size, max_iter=1)
    w0 = np.full(real.size, 0.9)
    bins = np.floor(rr / 2.0).astype(int)
    nb = bins.max() + 1
    num = np.bincount(bins, w0[ti] * hh, minlength=nb)
    den = np.bincount(bins, w0[ti], minlength=nb)
    glob = num.sum() / den.sum()
    pd = np.clip((num + 5 * glob) / (den + 5), 1e-4, 1 - 1e-4)
    pf = min(np.sum(0.1 * hh) / np.sum(np.full(ti.size, 0.1)), 0.9 * pd.min())
    k = run_length_factor(ti, hh)
    # design effect of the overdispersion: weighted median of per-tree moment estimates
    n, h = np.bincount(ti).astype(float), np.bincount(ti, hh.astype(float))
    e, v = np.bincount(ti, pd[bins]), np.bincount(ti, pd[bins] * (1 - pd[bins]))
    rj = np.sort(((h - e) ** 2 / (v * k) - 1) / (n / k - 1))  # equal weights 0.9
    rho = float(np.clip(rj[np.searchsorted(np.arange(1, rj.size + 1), 0.5 * rj.size)], 0, 1))
    assert fit.overdispersion == pytest.approx(rho, rel=1e-9, abs=1e-12)
    t = k * (1 + (n / k - 1) * rho)
    lr = np.bincount(ti, np.where(hh, np.log(pd[bins]), np.log1p(-pd[bins]))) / t + math.log(0.9)
    lf = np.bincount(ti, np.where(hh, math.log(pf), math.log1p(-pf))) / t + math.log1p(-0.9)
    assert fit.confidence == pytest.approx(1 / (1 + np.exp(lf - lr)), rel=1e-9, abs=1e-12)
    assert fit.p_false == pytest.approx(pf, rel=1e-12)


def test_thin_real_trees_seen_often_are_not_called_spurious(rng: np.random.Generator) -> None:
    """Real trees whose detection rate differs from the others' (a thin trunk returns too
    few points at range; here a quarter of the real trees at half the rate) are not called
    spurious with near certainty after hundreds of frames: before the overdispersion
    tempering such trees got 1e-9..1e-35 on the simulator. Spurious landmarks (p_f = 0.05)
    stay below the real ones."""
    real = rng.random(200) < 0.8
    thin = real & (rng.random(200) < 0.25)
    ti, rr, hh = [], [], []
    for j in range(real.size):
        r = rng.uniform(2, 14, 300)
        p = (0.9 - 0.04 * r) * (0.5 if thin[j] else 1.0) if real[j] else np.full(300, 0.05)
        ti.append(np.full(300, j))
        rr.append(r)
        hh.append(rng.random(300) < p)
    fit = detection_confidence(np.concatenate(ti), np.concatenate(rr), np.concatenate(hh), 200)
    c = fit.confidence
    assert fit.overdispersion > 0.0
    # no real tree near 0 (the prior is ~0.8: a thin tree is less sure, not impossible)
    assert c[thin].min() > 0.05
    # the ordering still separates: every spurious landmark below every thick real tree
    assert c[~real].max() < c[real & ~thin].min()
    assert c[~real].mean() < 0.5


def test_diameter_standard_errors() -> None:
    idx = np.array([0, 0, 0, 0, 1, 2, 2, -1])
    d = np.array([0.30, 0.32, 0.28, 0.30, 0.5, 0.2, np.nan, 9.0])
    se, spread, n = diameter_standard_errors(idx, d, 4, rho=0.0)
    s = float(np.std([0.30, 0.32, 0.28, 0.30], ddof=1))
    assert spread[0] == pytest.approx(s) and se[0] == pytest.approx(s / 2)
    assert n.tolist() == [4, 1, 1, 0]
    assert np.isnan(se[1:]).all()  # < 2 finite diameters
    se_r, _, _ = diameter_standard_errors(idx, d, 4, rho=0.5)
    assert se_r[0] == pytest.approx(s / 2 * math.sqrt(1 + 3 * 0.5))
    # the per-trunk bias adds in quadrature and does not average out; n < 2 stays NaN
    se_b, spread_b, _ = diameter_standard_errors(idx, d, 4, rho=0.5, bias=0.03)
    assert se_b[0] == pytest.approx(math.hypot(s / 2 * math.sqrt(1 + 3 * 0.5), 0.03))
    assert spread_b[0] == pytest.approx(s) and np.isnan(se_b[1:]).all()
    for bad in ({"bias": -0.01}, {"bias": math.nan}, {"rho": 1.5}):
        with pytest.raises(ConfigError):
            diameter_standard_errors(idx, d, 4, **bad)


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["fastslam", "isam2"])
def test_every_backend_gets_uncertainty(backend: str) -> None:
    """iSAM2 and FastSLAM used to leave diameter_std empty and confidence at 1."""
    from stemmap.cli._map import _simulated
    from stemmap.slam.base import make_backend

    problem, _ = _simulated(3, 40, 30.0, backend=backend)
    result = make_backend(backend).run(problem)
    sm, rep = annotate_uncertainty(result, problem)
    assert len(sm) == len(result.stem_map)
    dstd = np.array([t.diameter_std for t in sm])
    conf = np.array([t.confidence for t in sm])
    n_ok = np.array([t.n_obs >= 3 for t in sm])
    assert np.isfinite(dstd[n_ok]).mean() > 0.95
    # rho = 1 and the bias b (both set on real trunks): sqrt(spread^2 + b^2), the per-scan
    # spread a few cm on the simulator's cylinders
    fin = dstd[np.isfinite(dstd)]
    assert rep.diameter_bias_m == DIAMETER_BIAS and rep.diameter_rho == DIAMETER_RHO
    assert np.all(fin >= DIAMETER_BIAS) and np.all(fin < math.hypot(DIAMETER_BIAS, 0.05))
    assert np.all((conf >= 0) & (conf <= 1)) and conf.std() > 0
    assert all(np.all(np.isfinite(t.cov)) for t in sm)
    assert 0.8 < rep.associated_fraction <= 1.0
