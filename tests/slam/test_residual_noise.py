"""The detection noise measured from a run's residuals (``stemmap.slam.residual_noise``) and the
EKF's ``noise_from_residuals``: a known simulated detection noise is recovered, white and
correlated."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _synthetic import loop_problem  # tests/slam is on sys.path (pytest rootdir-less mode)

from stemmap.errors import ConfigError
from stemmap.slam.ekf import EkfSlam
from stemmap.slam.residual_noise import residual_noise


def _ar1_residuals(rho: float, sigma: tuple[float, float], seed: int = 0):
    """200 trees, each seen in 60 consecutive frames with AR(1) errors of correlation ``rho``
    per frame and std ``sigma`` (range, bearing); one frame in ten missed."""
    rng = np.random.default_rng(seed)
    fr, lm, ee = [], [], []
    for j in range(200):
        e = np.empty((60, 2))
        e[0] = rng.normal(0.0, sigma)
        for k in range(1, 60):
            e[k] = rho * e[k - 1] + math.sqrt(1 - rho**2) * rng.normal(0.0, sigma)
        seen = rng.uniform(size=60) > 0.1
        f0 = int(rng.integers(0, 5000))
        fr.append(f0 + np.flatnonzero(seen))
        lm.append(np.full(int(seen.sum()), j))
        ee.append(e[seen])
    return np.concatenate(fr), np.concatenate(lm), np.concatenate(ee)


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.8])
def test_long_run_noise_of_correlated_errors(rho):
    # AR(1): the long-run variance is s² (1 + rho) / (1 - rho); the Bartlett window (K = 50)
    # is 50x the correlation length at 0.8 (its weights bias the sum by ~ -2 / (K (1 - rho)),
    # 2-10 %), and 12,000 errors in 200 series of 60 give the sum a sampling error of ~15 %
    # at 0.8 (the series are short: each tree's 60 errors hold ~6 independent blocks); the
    # std, not the variance, is compared, so 12 % on it covers both
    sigma = (0.1, math.radians(0.5))
    fr, lm, e = _ar1_residuals(rho, sigma)
    r = residual_noise(fr, lm, e)
    want = math.sqrt((1 + rho) / (1 - rho))
    for c in (0, 1):
        assert r.sigma[c] == pytest.approx(sigma[c], rel=0.06)  # MAD of 12,000: ~1 %
        assert r.sigma_long_run[c] / r.sigma[c] == pytest.approx(want, rel=0.12)
        assert r.rho[c][0] == pytest.approx(rho, abs=0.05)


def test_gross_errors_are_not_noise():
    fr, lm, e = _ar1_residuals(0.0, (0.1, 0.01), seed=1)
    e = e.copy()
    e[::50] += 5.0  # 2 % wrong associations, metres off
    r = residual_noise(fr, lm, e)
    assert r.removed >= e.shape[0] // 50
    assert r.sigma[0] == pytest.approx(0.1, rel=0.06)
    assert r.sigma_long_run[0] == pytest.approx(0.1, rel=0.12)


@pytest.mark.parametrize(
    ("sigma_r", "sigma_b_deg", "update"),
    [(0.05, 0.3, "compressed"), (0.15, 0.8, "compressed"), (0.05, 0.3, "full")],
)
def test_ekf_residuals_recover_the_simulated_detection_noise(sigma_r, sigma_b_deg, update):
    # white detection noise on a simulated loop (odometry biased and noisy): the residuals of
    # the EKF's associated detections at its smoothed path against its map are the noise up to
    # the fit (each tree seen ~100 times, the path by several trees a frame: a few % smaller),
    # measured 0.283-0.294 deg / 0.050 m and 0.75-0.78 deg / 0.149-0.151 m on seeds 0-1; 10 %
    # covers that. The long-run std of white noise is the std, up to the path's own slowly
    # varying error, which the residuals share (0.068 m / 0.38 deg at 0.05 m / 0.3 deg,
    # seed 0): within 1.5x
    problem, *_ = loop_problem(0, laps=1.2, sigma_r=sigma_r, sigma_b=math.radians(sigma_b_deg))
    st = EkfSlam(update=update).run(problem).stats
    sb = math.radians(sigma_b_deg)
    assert st["residual_sigma_range"] == pytest.approx(sigma_r, rel=0.1)
    assert st["residual_sigma_bearing"] == pytest.approx(sb, rel=0.1)
    assert 0.9 * sigma_r <= st["residual_sigma_range_long_run"] <= 1.5 * sigma_r
    assert 0.9 * sb <= st["residual_sigma_bearing_long_run"] <= 1.5 * sb


def test_noise_from_residuals_raises_a_too_small_noise_to_the_measured_one():
    problem, *_ = loop_problem(1, laps=1.2, sigma_r=0.05, sigma_b=math.radians(0.3))
    small = {"sigma_range": 0.02, "sigma_bearing": math.radians(0.1)}
    first = EkfSlam(**small).run(problem)
    res = EkfSlam(**small, noise_from_residuals=True).run(problem)
    st = res.stats
    # the second run used the first run's long-run noise (both above the configured values)
    assert st["noise_from_residuals_sigma_range"] == first.stats["residual_sigma_range_long_run"]
    assert (
        st["noise_from_residuals_sigma_bearing"] == first.stats["residual_sigma_bearing_long_run"]
    )
    assert st["noise_from_residuals_sigma_range"] > small["sigma_range"]
    assert st["noise_from_residuals_sigma_bearing"] > small["sigma_bearing"]
    again = EkfSlam(
        sigma_range=st["noise_from_residuals_sigma_range"],
        sigma_bearing=st["noise_from_residuals_sigma_bearing"],
    ).run(problem)
    np.testing.assert_allclose(res.trajectory.poses, again.trajectory.poses)
    np.testing.assert_allclose(res.pose_covs, again.pose_covs)


def test_noise_from_residuals_keeps_a_larger_configured_noise():
    # the default 0.3 m / 1 deg is above the measured 0.05 m / 0.3 deg: nothing is re-run
    problem, *_ = loop_problem(1, laps=1.2, sigma_r=0.05, sigma_b=math.radians(0.3))
    plain = EkfSlam().run(problem)
    res = EkfSlam(noise_from_residuals=True).run(problem)
    assert res.stats["noise_from_residuals_sigma_range"] == 0.3
    assert res.stats["noise_from_residuals_sigma_bearing"] == math.radians(1.0)
    np.testing.assert_array_equal(res.trajectory.poses, plain.trajectory.poses)
    np.testing.assert_array_equal(res.pose_covs, plain.pose_covs)


def test_noise_from_residuals_needs_the_smoother():
    with pytest.raises(ConfigError, match="smooth"):
        EkfSlam(noise_from_residuals=True, smooth=False)


def test_exact_residuals_have_no_noise_to_measure():
    fr, lm, e = _ar1_residuals(0.0, (0.1, 0.01), seed=2)
    with pytest.raises(ValueError, match="scatter"):
        residual_noise(fr, lm, np.zeros_like(e))
