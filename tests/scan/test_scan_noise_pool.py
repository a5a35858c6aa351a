"""The batch's shared range-noise estimate for scans without their own (``scan_noise_pool``;
issue 11, sixteenth round)."""

import numpy as np
import pytest

from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.plausibility import scan_noise
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import cast_rays
from stemmap.types import ScanBatch

ANG = np.radians(np.arange(-60.0, 60.0 + 1e-9, 0.5))


def _scan(trees, sigma, rng):
    xy = np.array([t[:2] for t in trees]).reshape(-1, 2)
    r, _ = cast_rays(np.zeros(2), ANG, Stand(xy, np.array([2 * t[2] for t in trees])), 50.0)
    return np.where(np.isfinite(r), r + rng.normal(0, sigma, r.shape), np.inf)


def _sparse_scans(sigma, rng, n=20):
    """``n`` 0.5-degree scans of two 30-40 cm trunks at 4.5-6 m: 6-9 returns, 3-6 interior
    triples each, too few for a scan's own estimate."""
    return np.stack(
        [
            _scan([(4.5 + 0.05 * k, -1.0 + 0.1 * np.sin(k), 0.15), (6.0, 1.5, 0.2)], sigma, rng)
            for k in range(n)
        ]
    )


def _single_tree_scans(sigma, rng, n=20):
    """``n`` 0.5-degree scans of one 60 cm trunk at 2-2.8 m: >= 20 interior triples in one run per
    scan, enough triples but one surface (the breakdown rule: no estimate of its own)."""
    return np.stack([_scan([(2.0 + 0.04 * k, 0.3 * np.sin(k), 0.3)], sigma, rng) for k in range(n)])


def _stand(sigma, rng):
    return _scan([(3.0 + 1.2 * k, -4.0 + k, 0.25 + 0.05 * k) for k in range(6)], sigma, rng)


def _batch(r):
    return ScanBatch(
        r, np.arange(r.shape[0], dtype=float), float(ANG[0]), float(ANG[1] - ANG[0]), range_max=50.0
    )


def test_pooled_noise_reads_the_sensor_noise_where_no_scan_has_its_own():
    rng = np.random.default_rng(5)
    r = _sparse_scans(0.03, rng)
    assert np.all(scan_noise(r, 0.2) == 0.0)  # too few triples per scan: no estimate
    pooled = scan_noise(r, 0.2, pool=True)
    assert np.all(pooled == pooled[0])  # one shared estimate
    # 20 scans x 3-6 interior triples: a MAD scale of ~90 values, ~12 % relative std
    assert pooled[0] == pytest.approx(0.03, rel=0.3)


def test_scans_with_their_own_estimate_keep_it():
    rng = np.random.default_rng(6)
    r = np.vstack([np.stack([_stand(0.01, rng) for _ in range(4)]), _sparse_scans(0.03, rng)])
    own = scan_noise(r, 0.2)
    pooled = scan_noise(r, 0.2, pool=True)
    assert np.all(own[:4] > 0) and np.all(own[4:] == 0)
    np.testing.assert_array_equal(pooled[:4], own[:4])
    # the lacking scans share only their own triples: the 3 cm of the sparse scans
    assert pooled[4] == pytest.approx(0.03, rel=0.3)
    # the missing value stays where the pool has no estimate either
    assert np.isnan(scan_noise(r[4:5], 0.2, missing=np.nan, pool=True)[0])


def test_the_pool_keeps_the_breakdown_rule():
    rng = np.random.default_rng(7)
    # one lacking scan: its union is its own few triples, still no estimate
    assert scan_noise(_sparse_scans(0.03, rng, n=1), 0.2, pool=True)[0] == 0.0
    # scans with enough triples on one surface (one tree seen from many sides) are not
    # pooled: one object would decide the estimate again (its bark read as noise)
    one = _single_tree_scans(0.03, rng)
    assert np.all(scan_noise(one, 0.2, pool=True) == 0.0)


def random_range_batch(rng):
    """A random batch for the compiled-vs-numpy noise checks: 1-11 scans of 0-119 beams, a
    random walk in range with 1 or 3 cm noise, 0-30 % of the returns NaN or +-inf, and a random
    jump threshold and surface roughness. Returns (ranges, n_beams, jump, surface)."""
    s, n = int(rng.integers(1, 12)), int(rng.integers(0, 120))
    r = 5.0 + np.cumsum(rng.normal(0.0, rng.choice([0.01, 0.05, 0.15]), (s, n)), axis=1)
    r += rng.normal(0.0, rng.choice([0.01, 0.03]), (s, n))
    cut = rng.random((s, n)) < rng.choice([0.0, 0.1, 0.3])
    r[cut] = rng.choice([np.nan, np.inf, -np.inf], int(cut.sum()))
    return r, n, float(rng.choice([0.05, 0.2])), float(rng.choice([0.0, 0.006]))


def test_compiled_pooled_noise_equals_numpy():
    # the pool, the batch (scan_noise_batch: floors inf = off, 0, 2 cm) and both together
    from stemmap.scan._fast_robust import _batch_scan_noise

    rng = np.random.default_rng(12)
    changed = {"pool": 0, "batch": 0}
    for _ in range(300):
        r, n, jump, surface = random_range_batch(rng)
        own = scan_noise(r, jump, surface)
        fov = np.ones(n, dtype=np.bool_)
        for pool in (False, True):
            for floor in (np.inf, 0.0, 0.02):
                own_out = np.full(r.shape[0], -1.0)
                got = _batch_scan_noise(r, fov, 0.0, np.inf, jump, surface, pool, floor, own_out)
                ref = scan_noise(r, jump, surface, pool=pool, batch_min=floor)
                np.testing.assert_array_equal(got, ref)
                # every scan's own estimate before pooling: the unpooled statistic, bit for
                # bit (the detector kernel reads its scan noise there with the step split)
                np.testing.assert_array_equal(own_out, own)
                if floor == np.inf:
                    changed["pool"] += bool(pool and np.any(ref != own))
                else:
                    changed["batch"] += bool(np.any(ref != scan_noise(r, jump, surface, pool=pool)))
    assert changed["pool"] > 20 and changed["batch"] > 50, changed


@pytest.mark.parametrize("option", [{"scan_noise_pool": True}, {"scan_noise_batch": 2.0}])
def test_the_detector_finds_noisy_sparse_trunks_with_the_shared_noise_on_both_paths(option):
    # 3 cm noise, sigma configured 1 cm: without an estimate the RMS test (2 sigma + bark)
    # rejects most views of the trunks; with the batch's shared estimate (the pool of the
    # sparse scans, or every scan's with scan_noise_batch) it does not
    rng = np.random.default_rng(8)
    b = _batch(_sparse_scans(0.03, rng))
    found = []
    for overrides in ({}, option):
        det = ScanTrunkDetector(DetectorConfig.preset("stemmap", **overrides))
        args = (b.ranges, b.times, b.angle_min, b.angle_increment, b.range_min, b.range_max)
        fast = det._run_compiled(*args, b.frame)
        ref = det._run_numpy(*args, b.frame, None, None)
        np.testing.assert_array_equal(fast.index, ref.index)
        np.testing.assert_allclose(fast.radii, ref.radii, rtol=1e-9, atol=1e-15)
        found.append(len(fast))
    assert found[1] >= found[0] + 8, found  # of 40 trunk views


# ``scan_noise_batch`` (issue 11, Dec 4, "Range noise on sparse scans"): scans without an
# estimate take the one over every scan's triples, where it is at least a floor


def test_batch_noise_reads_the_sensor_noise_for_sparse_and_single_surface_scans():
    rng = np.random.default_rng(21)
    sparse = _sparse_scans(0.03, rng)
    one = _single_tree_scans(0.03, rng)
    for r in (sparse, one):
        assert np.all(scan_noise(r, 0.2) == 0.0)  # no scan has its own estimate
        got = scan_noise(r, 0.2, batch_min=0.02)
        assert np.all(got == got[0])  # one shared estimate
        # 20 scans x 3-30 interior triples: a MAD scale of >= 90 values, ~12 % relative std
        assert got[0] == pytest.approx(0.03, rel=0.3)
    # single-surface scans are left out of the pool (one tree would decide it), not of the
    # batch: over 20 scans no run holds half the triples, and the floor guards the bark
    assert np.all(scan_noise(one, 0.2, pool=True) == 0.0)


def test_batch_noise_below_the_floor_changes_nothing():
    rng = np.random.default_rng(22)
    for sigma in (0.0, 0.01):  # a scanner as quiet as configured (1 cm), or quieter
        r = np.vstack([_sparse_scans(sigma, rng), _single_tree_scans(sigma, rng)])
        np.testing.assert_array_equal(scan_noise(r, 0.2, batch_min=0.02), scan_noise(r, 0.2))
        np.testing.assert_array_equal(
            scan_noise(r, 0.2, missing=np.nan, batch_min=0.02),
            scan_noise(r, 0.2, missing=np.nan),
        )


def test_scans_with_their_own_estimate_keep_it_under_the_batch():
    rng = np.random.default_rng(23)
    r = np.vstack([np.stack([_stand(0.03, rng) for _ in range(4)]), _sparse_scans(0.03, rng)])
    own = scan_noise(r, 0.2)
    got = scan_noise(r, 0.2, batch_min=0.02)
    assert np.all(own[:4] > 0) and np.all(own[4:] == 0)
    np.testing.assert_array_equal(got[:4], own[:4])
    assert np.all(got[4:] == got[4]) and got[4] == pytest.approx(0.03, rel=0.3)


def test_batch_noise_setting_is_checked():
    from stemmap.errors import ConfigError

    for bad in (0.5, -1.0, float("inf"), float("nan")):
        with pytest.raises(ConfigError, match="scan_noise_batch"):
            DetectorConfig.preset("stemmap", scan_noise_batch=bad)
    assert DetectorConfig.preset("stemmap").scan_noise_batch_min() == np.inf
    on = DetectorConfig.preset("stemmap", scan_noise_batch=2.0)
    assert on.scan_noise_batch_min() == pytest.approx(2.0 * on.sigma)
