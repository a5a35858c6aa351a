"""The batch's range-noise estimate by the biweight midvariance (``batch_noise_scale``; issue 11,
Dec 5, "The batch's noise from few triples")."""

import math

import numpy as np
import pytest
from tests.scan.test_scan_noise_pool import random_range_batch

from stemmap.errors import ConfigError
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.plausibility import biweight_scale, scan_noise
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import cast_rays
from stemmap.types import ScanBatch

ANG = np.radians(np.arange(-60.0, 60.0 + 1e-9, 1.0))


def _second_differences(n, rng, sigma=1.0):
    """Second differences of ``n + 2`` i.i.d. Gaussian ranges over sqrt(6): unit scale, each
    correlated with its neighbours as the triples of one run are."""
    return np.diff(rng.normal(0.0, sigma, n + 2), 2) / math.sqrt(6.0)


def _mad(v):
    return 1.4826 * float(np.median(np.abs(v - np.median(v))))


def test_biweight_scale_is_consistent_for_gaussian_noise():
    # the raw biweight reads 1.046 sigma at c = 6; divided out, it estimates sigma (200 000
    # values: the estimate's relative std is ~0.2 %, so 1 % is five of them)
    rng = np.random.default_rng(1)
    assert biweight_scale(rng.normal(0.0, 0.03, 200_000)) == pytest.approx(0.03, rel=0.01)
    assert biweight_scale(_second_differences(200_000, rng)) == pytest.approx(1.0, rel=0.01)


def test_biweight_scale_has_less_sampling_spread_than_the_mad_on_few_triples():
    # 21 triples (the TreeLS pine batch at 1 deg): 2 000 draws; the biweight's relative std
    # is 0.23-0.24, the MAD's 0.30-0.31 (a 25 % narrower spread; 0.85 leaves 3 sigma of the
    # Monte Carlo's own error), and neither is biased by more than 5 %
    rng = np.random.default_rng(2)
    draws = [_second_differences(21, rng) for _ in range(2000)]
    bi = np.array([biweight_scale(v) for v in draws])
    mad = np.array([_mad(v) for v in draws])
    assert np.std(bi) < 0.85 * np.std(mad)
    assert np.median(bi) == pytest.approx(1.0, abs=0.05)
    assert np.median(mad) == pytest.approx(1.0, abs=0.05)


def test_biweight_scale_ignores_a_minority_of_gross_values():
    # a fifth of the triples 10-30 sigma off (bark flakes, a surface's silhouette curvature):
    # the biweight reads the rest, the standard deviation does not
    rng = np.random.default_rng(3)
    v = _second_differences(400, rng)
    v[::5] += rng.choice([-1.0, 1.0], 80) * rng.uniform(10.0, 30.0, 80)
    assert biweight_scale(v) == pytest.approx(1.0, rel=0.2)
    assert np.std(v) > 4.0


def test_biweight_scale_of_constant_values_is_zero():
    assert biweight_scale(np.full(20, 0.004)) == 0.0


def _scan(trees, sigma, rng):
    xy = np.array([t[:2] for t in trees]).reshape(-1, 2)
    r, _ = cast_rays(np.zeros(2), ANG, Stand(xy, np.array([2 * t[2] for t in trees])), 50.0)
    return np.where(np.isfinite(r), r + rng.normal(0, sigma, r.shape), np.inf)


def _single_tree(sigma, rng, n=20):
    """``n`` 1-degree scans of one 26 cm trunk at 1.5-2.9 m (a single tree seen from around it,
    as TreeLS pine): 1-6 interior triples a scan, about 60 in the batch."""
    return np.stack(
        [_scan([(1.5 + 0.15 * (k % 10), 0.2 * np.sin(k), 0.13)], sigma, rng) for k in range(n)]
    )


def test_the_batch_estimate_reads_the_noise_of_a_single_tree_batch():
    # over 100 batches of a single tree with 3 cm of noise, the biweight's estimate lies
    # nearer the truth: its 10-90 % band is narrower than the MAD's, both centred on 3 cm
    rng = np.random.default_rng(4)
    est = {"mad": [], "biweight": []}
    for _ in range(100):
        r = _single_tree(0.03, rng)
        assert np.all(scan_noise(r, 0.2) == 0.0)  # no scan has its own estimate
        for scale in est:
            est[scale].append(scan_noise(r, 0.2, 0.006, batch_min=0.0, batch_scale=scale)[0])
    band = {k: np.percentile(v, [10, 90]) for k, v in est.items()}
    assert np.diff(band["biweight"])[0] < 0.85 * np.diff(band["mad"])[0], band
    for v in est.values():
        assert np.median(v) == pytest.approx(0.03, rel=0.1)


def test_scans_with_their_own_estimate_keep_the_mad():
    rng = np.random.default_rng(5)
    stand = [(3.0 + 1.2 * k, -4.0 + k, 0.25 + 0.05 * k) for k in range(6)]
    ang = np.radians(np.arange(-60.0, 60.0 + 1e-9, 0.25))
    xy = np.array([t[:2] for t in stand])
    r0, _ = cast_rays(np.zeros(2), ang, Stand(xy, np.array([2 * t[2] for t in stand])), 50.0)
    own_scans = np.stack([r0 + rng.normal(0, 0.03, r0.shape) for _ in range(3)])
    r = np.full((23, max(own_scans.shape[1], ANG.size)), np.inf)
    r[:3, : own_scans.shape[1]] = own_scans
    r[3:, : ANG.size] = _single_tree(0.03, rng)
    own = scan_noise(r, 0.2)
    assert np.all(own[:3] > 0) and np.all(own[3:] == 0)
    got = scan_noise(r, 0.2, batch_min=0.0, batch_scale="biweight")
    np.testing.assert_array_equal(got[:3], own[:3])
    assert np.all(got[3:] == got[3]) and got[3] != scan_noise(r, 0.2, batch_min=0.0)[3]


def test_compiled_biweight_batch_noise_equals_numpy():
    from stemmap.scan._fast_robust import _batch_scan_noise

    rng = np.random.default_rng(12)
    changed = 0
    for _ in range(200):
        r, n, jump, surface = random_range_batch(rng)
        fov = np.ones(n, dtype=np.bool_)
        for pool in (False, True):
            for floor in (np.inf, 0.0, 0.02):
                got = _batch_scan_noise(r, fov, 0.0, np.inf, jump, surface, pool, floor, None, True)
                ref = scan_noise(
                    r, jump, surface, pool=pool, batch_min=floor, batch_scale="biweight"
                )
                np.testing.assert_array_equal(got, ref)
                changed += bool(
                    np.any(ref != scan_noise(r, jump, surface, pool=pool, batch_min=floor))
                )
    assert changed > 50, changed


@pytest.mark.parametrize(
    "option",
    [
        {"batch_noise_scale": "biweight"},
        {"batch_noise_scale": "biweight", "scan_noise_batch": 2.0},
    ],
)
def test_the_compiled_detector_equals_numpy_with_the_biweight(option):
    # the preset's step split reads the batch's estimate (step_noise_pool="batch"); with
    # scan_noise_batch the RMS test too: both paths read the same biweight estimate
    rng = np.random.default_rng(8)
    r = _single_tree(0.03, rng)
    b = ScanBatch(
        r, np.arange(r.shape[0], dtype=float), float(ANG[0]), float(ANG[1] - ANG[0]), range_max=50.0
    )
    det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **option))
    assert det._compiled(None, None)
    args = (b.ranges, b.times, b.angle_min, b.angle_increment, b.range_min, b.range_max)
    fast = det._run_compiled(*args, b.frame)
    ref = det._run_numpy(*args, b.frame, None, None)
    np.testing.assert_array_equal(fast.index, ref.index)
    np.testing.assert_allclose(fast.radii, ref.radii, rtol=1e-9, atol=1e-15)
    assert len(fast) > 0


def test_batch_noise_scale_is_validated():
    with pytest.raises(ConfigError, match="batch_noise_scale"):
        DetectorConfig(batch_noise_scale="std")  # type: ignore[arg-type]
