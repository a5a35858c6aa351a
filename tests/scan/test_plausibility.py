"""Rejection reasons, the data-driven noise scale and the robust residual scale (issue 11)."""

import math

import numpy as np
import pytest

from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.plausibility import REASONS, range_roughness, robust_residual_scale
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import cast_rays
from stemmap.types import ScanBatch

ANG = np.radians(np.arange(-60.0, 60.0 + 1e-9, 0.1))


def _ranges(trees, angles=ANG):
    xy = np.array([t[:2] for t in trees]).reshape(-1, 2)
    r, _ = cast_rays(np.zeros(2), angles, Stand(xy, np.array([2 * t[2] for t in trees])), 50.0)
    return r


def _batch(r, angles=ANG):
    r = np.atleast_2d(r)
    inc = float(angles[1] - angles[0])
    return ScanBatch(r, np.arange(r.shape[0], dtype=float), float(angles[0]), inc, range_max=50.0)


def _segments(r, **cfg):
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg))
    b = _batch(r)
    return det.candidates(b.ranges, b.angle_min, b.angle_increment, 0.0, 50.0)


@pytest.mark.parametrize("sigma", [0.005, 0.01, 0.03])
def test_range_roughness_estimates_the_noise_of_a_trunk_arc(sigma):
    # a 1 m trunk at 4 m seen over ~14 deg at 0.1 deg: ~140 returns; the std of a MAD-based
    # scale from ~140 second differences is ~10 % (1.65 / sqrt(n) relative, correlated
    # differences add a little), so +-25 % is > 2.5 std
    rng = np.random.default_rng(3)
    r = _ranges([(4.0, 0.0, 0.5)])
    est = []
    for _ in range(5):
        noisy = np.where(np.isfinite(r), r + rng.normal(0, sigma, r.shape), np.inf)
        segs = _segments(noisy, max_jump=0.3, sigma=sigma)
        big = int(np.argmax(segs.counts))
        est.append(range_roughness(segs)[big])
    assert np.mean(est) == pytest.approx(sigma, rel=0.25)
    # noise-free: only the arc's curvature, far below a sensor's noise
    segs = _segments(r)
    assert range_roughness(segs).max() < 0.001


def test_robust_residual_scale_ignores_a_few_returns_off_the_circle():
    rng = np.random.default_rng(5)
    r = _ranges([(3.0, 0.0, 0.3)])
    hit = np.flatnonzero(np.isfinite(r))
    noisy = r.copy()
    noisy[hit] += rng.normal(0, 0.01, hit.size)
    spikes = hit[5:-5:10]  # every 10th return 3 cm nearer (bark ridges, stubs)
    noisy[spikes] -= 0.03
    segs = _segments(noisy, max_jump=0.3)
    big = int(np.argmax(segs.counts))
    sub = segs.select(np.arange(len(segs)) == big)
    centre = np.array([[3.0, 0.0]])
    scale = robust_residual_scale(sub, centre, np.array([0.3]))[0]
    p = sub.points
    rms = float(np.sqrt(np.mean((np.hypot(p.x - 3.0, p.y) - 0.3) ** 2)))
    # 1.4826 x median |res| of N(0, 1 cm) is 1 cm; 10 % of the returns 3 cm off move the
    # median by ~0.1 sigma but the RMS by sqrt(0.1 x 9 + 1) ~ 1.4x
    assert scale == pytest.approx(0.01, rel=0.3)
    assert rms > 1.25 * scale


def test_every_candidate_is_either_detected_or_rejected_with_one_reason():
    rng = np.random.default_rng(2)
    a = ANG
    trees = [(3.0, 0.0, 0.15), (5.0, -2.0, 0.3), (6.0, 1.5, 0.1)]
    r = _ranges(trees)
    # a bush: scattered returns at ~4 m around 30 deg, and a wall at x = 8 m
    bush = (a > math.radians(25)) & (a < math.radians(35))
    r[bush] = 4.0 + rng.uniform(-0.3, 0.3, bush.sum())
    wall = (a > math.radians(-55)) & (a < math.radians(-40))
    r[wall] = 8.0 / np.cos(a[wall])
    b = _batch(np.vstack([r, r + rng.normal(0, 0.01, r.shape)]))
    for cfg in ({}, {"fit_method": "kasa"}, {"sigma_from_data": True, "rms_robust": True}):
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **cfg))
        obs = det.detect_batch(b)
        rej = det.rejected(b)
        all_segs, _, _ = det._candidates(
            b.ranges, b.angle_min, b.angle_increment, 0.0, 50.0, apply_filters=False
        )
        assert len(obs) + len(rej["reason"]) == len(all_segs)
        assert set(rej["reason"]) <= set(REASONS[1:])
        # the three trunks are kept in both scans; the wall and the bush are rejected
        assert len(obs) == 6
        assert {"depth", "straight"} & set(rej["reason"])


def test_config_checks_the_roughness_cap():
    with pytest.raises(Exception, match="roughness_max_factor"):
        DetectorConfig(roughness_max_factor=0.5)


def test_rms_limit_adds_relative_bark_roughness_in_quadrature():
    from stemmap.scan.plausibility import rms_limit

    sigma = np.array([0.01, 0.01])
    radii = np.array([0.1, 0.4])
    plain = DetectorConfig.preset("stemmap", bark_roughness=0.0)
    np.testing.assert_array_equal(rms_limit(plain, sigma, radii), 2.0 * sigma)
    bark = DetectorConfig.preset("stemmap", bark_roughness=0.05)
    np.testing.assert_allclose(
        rms_limit(bark, sigma, radii), 2.0 * np.sqrt(0.01**2 + (0.05 * radii) ** 2)
    )
    with pytest.raises(Exception, match="bark_roughness"):
        DetectorConfig.preset("stemmap", bark_roughness=-0.1)
