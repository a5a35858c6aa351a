"""The averaging (SICK-class) scanners' DBH standard error (``dbh_sd_footprint``; issue 11,
Dec 6, "Averaging DBH standard error" in docs/algorithms/scan-detection.md).

The reported radius variance gains the outline's ``(dbh_sd_outline / 2)^2`` and a share of the
footprint's width at the trunk, and the centre-radius covariance the same two errors carried
with the centre's along-sight terms; every detection, and the centre block, stay as they were.
The scene: the 20 cm disc of ``test_max_dbh_sd`` seen by the virtual averaging scanner from 2.5
and 9 m, 3 cm of noise."""

import math

import numpy as np
import pytest
from tests.scan.test_max_dbh_sd import _batch

from stemmap.errors import ConfigError
from stemmap.scan._centre_cov import averaging_centre_covs, averaging_report
from stemmap.scan.detect import DetectorConfig, ScanTrunkDetector

H = 0.6  # the radius std per footprint width
FIELDS = ("centers", "radii", "n_points", "arc_deg", "widths", "quality", "index", "times")


def _det(**extra) -> ScanTrunkDetector:
    return ScanTrunkDetector(DetectorConfig.preset("stemmap", **extra))


def _sight(centers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.hypot(centers[:, 0], centers[:, 1])
    return centers / d[:, None], d


def test_off_in_the_dataclass_on_in_the_preset_and_bad_values_refused():
    assert DetectorConfig().dbh_sd_footprint == 0.0
    assert DetectorConfig.preset("stemmap").dbh_sd_footprint == pytest.approx(0.6)
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="dbh_sd_footprint"):
            DetectorConfig(dbh_sd_footprint=bad)


def test_the_radius_terms_are_the_two_causes_of_the_centre_terms():
    rng = np.random.default_rng(7)
    a = rng.normal(size=(8, 3, 3))
    covs = 1e-4 * (a @ a.transpose(0, 2, 1) + 0.1 * np.eye(3))
    centers = rng.normal(size=(8, 2)) * 6.0
    outline, f, theta, c, ro, h = 0.0085, 0.7, math.radians(0.25), 0.006, 0.0065, H
    centre = averaging_centre_covs(covs, centers, outline, f, theta, c)
    out = averaging_centre_covs(covs, centers, outline, f, theta, c, ro, h)
    u, d = _sight(centers)
    wd = theta * d
    # the centre block is the centre terms' alone
    assert np.array_equal(out[:, :2, :2], centre[:, :2, :2])
    # C_rr: the outline's radius std and h of the footprint's width, in quadrature
    assert np.allclose(out[:, 2, 2], covs[:, 2, 2] + ro**2 + (h * wd) ** 2, rtol=1e-12)
    # centre-radius: each cause's centre term times its radius term, along the line of sight
    cross = (outline * ro + f * h * wd * wd)[:, None] * u
    assert np.allclose(out[:, :2, 2], covs[:, :2, 2] + cross, rtol=1e-12, atol=1e-18)
    assert np.array_equal(out[:, 2, :2], out[:, :2, 2])
    # the addition is v1 v1^T + v2 v2^T + c^2 w w^T: positive semi-definite
    assert np.all(np.linalg.eigvalsh(out - covs) > -1e-15)
    assert np.all(np.linalg.eigvalsh(out) > 0)
    # the radius alone (centre terms off): C_rr grows, the centre-radius entries stay
    alone = averaging_centre_covs(covs, centers, 0.0, 0.0, theta, 0.0, ro, h)
    assert np.array_equal(alone[:, :2, :], covs[:, :2, :])
    assert np.allclose(alone[:, 2, 2], covs[:, 2, 2] + ro**2 + (h * wd) ** 2, rtol=1e-12)


@pytest.mark.parametrize("numpy_path", [False, True])
def test_the_dbh_sd_grows_with_the_footprint_and_the_detections_stay(numpy_path):
    # numpy_path: a finite behind_sigmas takes the numpy pipeline (same option on and off)
    path = {"behind_sigmas": 3.0} if numpy_path else {}
    cfg = DetectorConfig.preset("stemmap", **path)
    assert ScanTrunkDetector(cfg)._compiled(None, None) is not numpy_path
    theta = math.radians(cfg.beam_divergence_deg)
    ro = 0.5 * cfg.dbh_sd_outline
    added = {}
    for dist in (2.5, 9.0):
        batch, _ = _batch(dist, "averaging")
        on = _det(**path, dbh_sd_footprint=H).detect_batch(batch)
        off = _det(**path, dbh_sd_footprint=0.0).detect_batch(batch)
        assert len(on) == len(off) > 0
        for name in FIELDS:  # the same detections: positions, diameters, accept / reject
            assert np.array_equal(getattr(on, name), getattr(off, name)), name
        assert np.array_equal(on.covs[:, :2, :2], off.covs[:, :2, :2])  # the centre block
        u, d = _sight(on.centers)
        grow = on.covs[:, 2, 2] - off.covs[:, 2, 2]
        assert np.allclose(grow, ro**2 + (H * theta * d) ** 2, rtol=1e-9, atol=1e-15)
        # the centre-radius entries gain the shared causes along the line of sight
        outline = 0.5 * cfg.centre_sd_along * cfg.dbh_sd_outline
        cross = np.einsum("ki,ki->k", u, on.covs[:, :2, 2] - off.covs[:, :2, 2])
        want = outline * ro + cfg.centre_sd_footprint * H * (theta * d) ** 2
        assert np.allclose(cross, want, rtol=1e-9, atol=1e-15)
        assert np.all(np.linalg.eigvalsh(on.covs) > 0)
        added[dist] = float(np.median(np.sqrt(grow)))
    # the footprint's share grows with range (1.1 / 3.9 cm of footprint at 2.5 / 9 m): the
    # added radius std sqrt(0.65^2 + (0.6 w)^2) cm, 0.94 cm at 2.5 m and 2.42 cm at 9 m
    assert added[9.0] > 2.0 * added[2.5]


def test_off_returns_the_fit_covariance_and_a_first_echo_scanner_is_not_touched():
    rng = np.random.default_rng(3)
    centers = rng.normal(size=(4, 2)) * 5.0
    covs = np.tile(1e-4 * np.eye(3), (4, 1, 1))
    off = {"centre_sd_footprint": 0.0, "centre_sd_across_averaging": 0.0, "dbh_sd_footprint": 0}
    assert averaging_report(DetectorConfig.preset("stemmap", **off), centers, covs) is covs
    radius = DetectorConfig.preset("stemmap", **{**off, "dbh_sd_footprint": H})
    rep = averaging_report(radius, centers, covs)
    assert np.array_equal(rep[:, :2, :], covs[:, :2, :]) and np.all(rep[:, 2, 2] > covs[:, 2, 2])
    near, _ = _batch(2.5)
    foot = {"beam_footprint_deg": 0.25}
    a = _det(**foot, dbh_sd_footprint=H).detect_batch(near)
    b = _det(**foot, dbh_sd_footprint=0.0).detect_batch(near)
    assert len(a) > 0 and np.array_equal(a.covs, b.covs)
