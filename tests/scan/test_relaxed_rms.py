"""The relaxed RMS tests of issue 11's twelfth round: a candidate's own noise from its fit
residuals (``rms_noise_from_fit``) and smooth lobed outlines (``lobe_roughness``)."""

from dataclasses import replace

import numpy as np
import pytest

from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector
from stemmap.scan.plausibility import (
    REASONS,
    SMOOTH_MIN_POINTS,
    own_noise,
    residual_smoothness,
    scan_noise,
)
from stemmap.scan.segment import ScanPoints, Segments
from stemmap.sim.forest import Stand
from stemmap.sim.scanner import cast_rays
from stemmap.types import ScanBatch

ANG = np.radians(np.arange(-60.0, 60.0 + 1e-9, 0.5))


def _arc(radius, rng, noise=0.0, lobe=0.0, k=4, n=40, rng_m=3.0):
    """One segment: ``n`` returns over the front half of a circle of ``radius`` at ``rng_m``,
    radial noise ``noise`` and a lobe of relative amplitude ``lobe`` with ``k`` lobes."""
    phi = np.pi + np.linspace(-1.2, 1.2, n)  # the side facing the sensor at the origin
    rad = radius * (1.0 + lobe * np.cos(k * phi)) + rng.normal(0.0, noise, n)
    x, y = rng_m + rad * np.cos(phi), rad * np.sin(phi)
    order = np.argsort(np.arctan2(y, x))
    x, y = x[order], y[order]
    pts = ScanPoints(
        np.zeros(n, dtype=np.int64),
        np.arange(n),
        np.hypot(x, y),
        x,
        y,
        1,
        n,
        0.01,
    )
    f = np.zeros(1, dtype=bool)
    seg = Segments(pts, np.array([0]), np.array([n]), np.zeros(1, dtype=np.int64), f, f, f, f)
    return seg, np.array([[rng_m, 0.0]]), np.array([radius])


@pytest.mark.parametrize("noise", [0.01, 0.03])
def test_residual_smoothness_reads_white_noise(noise):
    rng = np.random.default_rng(1)
    est = [residual_smoothness(*_arc(0.3, rng, noise=noise))[0] for _ in range(40)]
    # the MAD scale of ~38 second differences: ~20 % relative std per segment
    assert np.mean(est) == pytest.approx(noise, rel=0.12)


def test_residual_smoothness_ignores_smooth_lobes_but_not_scatter():
    rng = np.random.default_rng(2)
    seg, c, r = _arc(0.3, rng, lobe=0.08, k=4)
    resid = np.hypot(seg.points.x - c[0, 0], seg.points.y - c[0, 1]) - r[0]
    rms = float(np.sqrt(np.mean(resid**2)))
    assert rms > 0.015  # the lobes: ~8 % of 30 cm RMS
    assert residual_smoothness(seg, c, r)[0] < 0.05 * rms
    # too few returns: not measured
    short = _arc(0.3, rng, noise=0.01, n=SMOOTH_MIN_POINTS - 1)
    assert np.isnan(residual_smoothness(*short)[0])


def _noisy_single_tree(noise, seed, n_scans=12):
    """Scans of one 40 cm trunk at 3-6 m and nothing else (a segmented single tree): the scan
    has no noise estimate of its own (one surface)."""
    rng = np.random.default_rng(seed)
    out = []
    for s in range(n_scans):
        stand = Stand(np.array([[3.0 + 0.25 * s, 0.3]]), np.array([0.4]))
        r, _ = cast_rays(np.zeros(2), ANG, stand, 50.0)
        out.append(np.where(np.isfinite(r), r + rng.normal(0, noise, r.shape), np.inf))
    r = np.stack(out)
    inc = float(ANG[1] - ANG[0])
    return ScanBatch(r, np.arange(n_scans, dtype=float), float(ANG[0]), inc, range_max=50.0)


@pytest.mark.parametrize("seed", [3, 4])
def test_own_noise_keeps_a_noisy_single_tree_the_rms_test_rejects(seed):
    b = _noisy_single_tree(0.04, seed)
    assert np.all(np.isnan(scan_noise(b.ranges, 0.2, 0.006, missing=np.nan)))
    base = ScanTrunkDetector(DetectorConfig.preset("stemmap"))
    own = ScanTrunkDetector(DetectorConfig.preset("stemmap", rms_noise_from_fit=5.0))
    assert not own._compiled(None, None)  # numpy path only
    # 4 cm of noise read against sigma = 1 cm (seeds 3 / 4: 9 / 8 of 12 views)
    assert base.rejected(b)["reason"].count("rms") >= 6
    n_base, got = len(base.detect_batch(b)), own.detect_batch(b)
    assert len(got) >= n_base + 5  # seeds 3 / 4: 3 -> 11, 4 -> 10
    assert np.all(np.abs(got.radii - 0.2) < 0.03)


def test_own_noise_changes_nothing_where_the_scan_measured_its_noise():
    # three rough objects (4 cm of scatter) in front of a wall the scan measures its 1 cm of
    # noise on: rougher than the scan's own noise, they stay rejected
    rng = np.random.default_rng(5)
    stand = Stand(np.array([[3.5, -2.0], [3.5, 0.3], [3.5, 2.5]]), np.array([0.4, 0.4, 0.4]))
    trunks = cast_rays(np.zeros(2), ANG, stand, 50.0)[0]
    wall = 6.0 / np.cos(ANG)  # a wall 6 m ahead behind them
    rough = np.isfinite(trunks)
    r = np.stack([np.where(rough, trunks, wall) for _ in range(6)])
    r = r + rng.normal(0, 1.0, r.shape) * np.where(rough, 0.04, 0.01)
    inc = float(ANG[1] - ANG[0])
    b = ScanBatch(r, np.arange(6, dtype=float), float(ANG[0]), inc, range_max=50.0)
    assert np.all(scan_noise(b.ranges, 0.2, 0.006, missing=np.nan) < 0.015)
    own = DetectorConfig.preset("stemmap", rms_noise_from_fit=5.0)
    base = ScanTrunkDetector(DetectorConfig.preset("stemmap"))
    assert base.rejected(b)["reason"].count("rms") >= 6
    a, o = base.detect_batch(b), ScanTrunkDetector(own).detect_batch(b)
    np.testing.assert_allclose(o.centers, a.centers, rtol=1e-9)
    np.testing.assert_allclose(o.radii, a.radii, rtol=1e-9)


def test_own_noise_applies_only_where_the_scan_has_no_estimate_and_below_the_cap():
    cfg = DetectorConfig.preset("stemmap", rms_noise_from_fit=3.0)
    rng = np.random.default_rng(4)
    seg, _, _ = _arc(0.3, rng, noise=0.02)
    sigma = np.array([0.01])

    def with_noise(v):
        return replace(seg, points=replace(seg.points, noise=np.array([v])))

    # no estimate of the scan's own: the candidate's; a scan that measured 1.2 cm: sigma
    assert own_noise(cfg, with_noise(np.nan), sigma, np.array([0.025]))[0] == 0.025
    assert own_noise(cfg, with_noise(0.012), sigma, np.array([0.025]))[0] == 0.01
    # rougher than the cap (3 sigma): a rock or a bush, the sensor's sigma stands
    assert own_noise(cfg, with_noise(np.nan), sigma, np.array([0.035]))[0] == 0.01
    # smoother than sigma: sigma
    assert own_noise(cfg, with_noise(np.nan), sigma, np.array([0.005]))[0] == 0.01


def test_relaxed_rms_keeps_the_silhouette_no_wider_than_the_circle():
    from stemmap.scan.plausibility import fit_reasons

    cfg = DetectorConfig.preset("stemmap", rms_noise_from_fit=5.0)
    one = np.ones(1)
    args = {
        "centers": np.array([[3.0, 0.0]]),
        "fit_ok": np.ones(1, dtype=bool),
        "mean_r": 2.8 * one,
        "rms": 0.04 * one,  # fails 2 x sqrt(1^2 + (3 % x 20)^2) cm, passes 1.5 x own 3 cm
        "sigma": 0.01 * one,
        "own": 0.03 * one,
    }
    ok = fit_reasons(cfg, radii=0.2 * one, sil_width=0.38 * one, **args)
    assert REASONS[ok[0]] == "kept"
    wide = fit_reasons(cfg, radii=0.2 * one, sil_width=0.55 * one, **args)
    assert REASONS[wide[0]] == "rms"  # a 55 cm silhouette on a 40 cm circle
    plain = fit_reasons(cfg, radii=0.2 * one, sil_width=0.38 * one, **{**args, "own": None})
    assert REASONS[plain[0]] == "rms"


def test_config_checks_the_relaxed_rms_options():
    for bad in (
        {"rms_noise_from_fit": 0.5},
        {"rms_own_sigmas": 0.0},
        {"lobe_roughness": -0.1},
        {"lobe_smooth_sigmas": 0.0},
    ):
        with pytest.raises(Exception, match=next(iter(bad))):
            DetectorConfig(**bad)
